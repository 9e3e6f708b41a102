"""Run ``monoloc ...`` in-process through its real entry point (``monoloc.cli.main``: the
one-line ``error: ...`` and the exit code), without a subprocess's import time."""

from __future__ import annotations

import sys


def run_monoloc(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``monoloc *args``."""
    from monoloc import cli

    capsys.readouterr()
    monkeypatch.setattr(sys, "argv", ["monoloc", *args])
    try:
        cli.main()
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    captured = capsys.readouterr()
    return code, captured.out, captured.err
