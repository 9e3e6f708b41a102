"""`monoloc drive --lever-arm-from`: a run without poses to fit on is one line and exit 1,
before any server is contacted."""

from __future__ import annotations

import sys

import pytest

from monoloc import cli


def test_lever_arm_from_a_run_without_poses_is_one_line(tmp_path, monkeypatch, capsys):
    seq = tmp_path / "sequences" / "00"
    (seq / "image_0").mkdir(parents=True)
    for i in range(3):
        (seq / "image_0" / f"{i:06d}.png").write_bytes(b"")
    (seq / "times.txt").write_text("0.0\n0.1\n0.2\n")
    (seq / "vehicle.txt").write_text("0.0 5.0 0.1\n0.1 5.0 0.1\n0.2 5.0 0.1\n")
    argv = ["drive", str(seq), "--map", "m", "--key", "k", "--lever-arm-from", str(seq)]
    monkeypatch.setattr(sys, "argv", ["monoloc", *argv])
    with pytest.raises(SystemExit) as exited:
        cli.main()
    err = capsys.readouterr().err.strip().splitlines()
    assert exited.value.code == 1
    assert len(err) == 1 and "has no poses to fit a lever arm on" in err[0], err
