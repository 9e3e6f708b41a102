import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from monoloc.server.storage.migrate import current_revision

REPO = Path(__file__).resolve().parents[3]


def _monoloc_app():
    import monoloc.cli

    if not any(group.name == "db" for group in monoloc.cli.app.registered_groups):
        monoloc.cli._register()
    return monoloc.cli.app


def test_db_upgrade_and_current_through_the_monoloc_app(tmp_path):
    url = f"sqlite:///{tmp_path / 'cli' / 'monoloc.db'}"
    runner = CliRunner()
    app = _monoloc_app()
    result = runner.invoke(app, ["db", "current", "--database-url", url])
    assert result.exit_code == 0, result.output
    assert result.output.startswith("none")
    assert not (tmp_path / "cli" / "monoloc.db").exists()  # looking does not create

    result = runner.invoke(app, ["db", "upgrade", "--database-url", url])
    assert result.exit_code == 0, result.output
    assert "at revision 0010" in result.output
    assert current_revision(url) == "0010"

    result = runner.invoke(app, ["db", "current", "--database-url", url])
    assert result.output.startswith("0010") and "up to date" in result.output


def test_db_upgrade_console_script_uses_settings(tmp_path):
    monoloc = Path(sys.executable).parent / "monoloc"
    env = {"MONOLOC_DATA_DIR": str(tmp_path / "d"), "PATH": "/usr/bin:/bin"}
    done = subprocess.run(
        [str(monoloc), "db", "upgrade"], env=env, cwd=tmp_path, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "d" / "monoloc.db").exists()
    bad = subprocess.run(
        [str(monoloc), "db", "upgrade", "--database-url", "nonsense://"],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 1
    assert bad.stderr.startswith("error:") and len(bad.stderr.strip().splitlines()) == 1
