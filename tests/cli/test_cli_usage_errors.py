"""Every command answers a usage error with one line naming the command and exit code 2,
never a traceback (typer vendors its own click, which the first wave's check missed)."""

from __future__ import annotations

import sys

import click
import pytest
import typer

from monoloc import cli


def _leaf_commands() -> list[list[str]]:
    """The path (list of names) of every runnable command under ``monoloc``."""
    cli._register()
    root = typer.main.get_command(cli.app)
    found: list[list[str]] = []

    def walk(command, path: list[str]) -> None:
        subcommands = getattr(command, "commands", None)
        if subcommands:
            for name, sub in subcommands.items():
                walk(sub, [*path, name])
        else:
            found.append(path)

    walk(root, [])
    return found


def _run(monkeypatch, capsys, argv: list[str]) -> tuple[int, str]:
    monkeypatch.setattr(sys, "argv", ["monoloc", *argv])
    with pytest.raises(SystemExit) as exited:
        cli.main()
    return exited.value.code, capsys.readouterr().err


COMMANDS = _leaf_commands()


def test_the_walk_finds_every_command_group():
    names = {" ".join(path) for path in COMMANDS}
    assert {"serve", "drive", "localize", "demo", "keys create", "map ingest"} <= names
    assert any(name.startswith("sim ") for name in names)
    assert len(COMMANDS) >= 15


@pytest.mark.parametrize("path", COMMANDS, ids=[" ".join(p) for p in COMMANDS])
def test_an_unknown_option_is_one_line_and_exit_2(path, monkeypatch, capsys):
    code, err = _run(monkeypatch, capsys, [*path, "--no-such-option"])
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"error: monoloc {' '.join(path)}: ")
    assert "--no-such-option" in lines[0]


def test_a_missing_required_option_names_it(monkeypatch, capsys):
    code, err = _run(monkeypatch, capsys, ["keys", "create", "--scope", "admin"])
    assert code == 2
    assert err.strip() == (
        "error: monoloc keys create: Missing option '--name'. (see monoloc keys create --help)"
    )


def test_an_unknown_command_is_one_line(monkeypatch, capsys):
    code, err = _run(monkeypatch, capsys, ["nosuch"])
    assert code == 2
    assert err.strip().splitlines() == [
        "error: monoloc: No such command 'nosuch'. (see monoloc --help)"
    ]


def test_the_exception_class_matched_is_clicks_own_base():
    # If typer stops vendoring click, the class found must still be a ClickException.
    assert cli._CLICK_EXCEPTION.__name__ == "ClickException"
    assert issubclass(typer.BadParameter, cli._CLICK_EXCEPTION)
    assert (
        click.ClickException is cli._CLICK_EXCEPTION or "typer" in cli._CLICK_EXCEPTION.__module__
    )
