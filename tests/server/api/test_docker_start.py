"""CI runs docker/start.sh as a plain process (images cannot be built here): it upgrades
a fresh database, serves /readyz, honours the bootstrap admin key and stops cleanly on
SIGTERM. Also `monoloc keys create` on the same data directory."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
from api_helpers import ADMIN_KEY, free_port

from monoloc.client.api import ServerError, wait_until_ready

REPO = Path(__file__).resolve().parents[3]


def _wait_ready(url: str, process: subprocess.Popen, timeout_s: float = 180.0) -> None:
    try:
        wait_until_ready(url, timeout_s, process)
    except ServerError as exc:
        raise AssertionError(f"{exc}: {process.stderr.read().decode()[-2000:]}") from exc


def test_start_script_serves_readyz_and_stops_on_sigterm(tmp_path):
    port = free_port()
    env = dict(
        os.environ,
        MONOLOC_DATA_DIR=str(tmp_path / "data"),
        MONOLOC_HOST="127.0.0.1",
        MONOLOC_PORT=str(port),
        MONOLOC_PYTHON=sys.executable,
        MONOLOC_BOOTSTRAP_ADMIN_KEY=ADMIN_KEY,
    )
    env.pop("MONOLOC_DATABASE_URL", None)
    process = subprocess.Popen(
        ["sh", str(REPO / "docker" / "start.sh")],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        url = f"http://127.0.0.1:{port}"
        _wait_ready(url, process)
        assert httpx.get(f"{url}/healthz").json() == {"status": "ok"}
        assert httpx.get(f"{url}/v1/maps").status_code == 401
        maps = httpx.get(f"{url}/v1/maps", headers={"X-API-Key": ADMIN_KEY})
        assert maps.status_code == 200 and maps.json() == {"items": []}
        process.send_signal(signal.SIGTERM)  # start.sh exec'd uvicorn: it gets the signal
        _, stderr = process.communicate(timeout=30)
        # uvicorn shuts the app down, then re-raises the signal (exit status -15).
        assert process.returncode in (0, -signal.SIGTERM), stderr
        assert b"Application shutdown complete" in stderr, stderr
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert (tmp_path / "data" / "monoloc.db").is_file()


def test_keys_cli_prints_a_working_key_once(tmp_path):
    from api_helpers import make_settings, open_client

    data_dir = tmp_path / "data"
    cli = [sys.executable, "-m", "monoloc.cli", "keys"]
    made = subprocess.run(
        [*cli, "create", "--scope", "localize", "--name", "car1", "--data-dir", str(data_dir)],
        capture_output=True,
        text=True,
        check=True,
        cwd=REPO,
    )
    key = made.stdout.strip()
    assert key.startswith("mlk_") and "not shown again" in made.stderr
    listed = subprocess.run(
        [*cli, "list", "--data-dir", str(data_dir)],
        capture_output=True,
        text=True,
        check=True,
        cwd=REPO,
    ).stdout
    assert "car1" in listed and key not in listed and key[:12] in listed
    with open_client(make_settings(data_dir, bootstrap_admin_key=None)) as client:
        assert client.get("/v1/maps", headers={"X-API-Key": key}).status_code == 200
        assert client.post("/v1/maps", headers={"X-API-Key": key}, json={}).status_code == 403
    bad = subprocess.run(
        [*cli, "create", "--scope", "root", "--name", "x", "--data-dir", str(data_dir)],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert bad.returncode == 1 and "unknown scope" in bad.stderr
