"""MONOLOC_LOCALIZE_REFINE=false switches a server's refit by projection off (to compare
both on a fleet's own data): the same entries give hypotheses either way, and with the
refit (the default) each keeps at least as many inliers."""

from __future__ import annotations

from e2e_helpers import QUERY_SEQ, localize_frames, localize_frames_on_copy

from monoloc.client.replay import read_run

FRAMES = (4, 8, 12, 16, 20)


def test_setting_reads_the_environment(monkeypatch, tmp_path):
    from monoloc.server.calibrate import server_calibration_config
    from monoloc.server.settings import Settings

    assert Settings(data_dir=tmp_path).localize_refine is True
    monkeypatch.setenv("MONOLOC_LOCALIZE_REFINE", "false")
    assert Settings(data_dir=tmp_path).localize_refine is False
    # a calibration job fits its model on the hypotheses the server sends
    assert server_calibration_config(10, False).strategy.refine is None
    assert server_calibration_config(10, True).strategy.refine is not None
    assert server_calibration_config(7, True).k == 7


def _inliers(answer) -> dict[int, int]:
    return {h["entry_id"]: h["n_inliers"] for h in answer.raw["hypotheses"] if not h["joint"]}


def test_the_refit_keeps_the_entries_and_adds_inliers(live_map, tmp_path):
    run = read_run(live_map.dataset, QUERY_SEQ)
    images = [run.image_paths[f].read_bytes() for f in FRAMES]
    refined = localize_frames(live_map.url, live_map.keys.localize, live_map.map_id, images, 5)
    plain = localize_frames_on_copy(live_map, tmp_path / "data", images, 5, localize_refine=False)
    gained = 0
    for r, p in zip(refined, plain, strict=True):
        with_refit, without = _inliers(r), _inliers(p)
        assert with_refit.keys() == without.keys()
        assert all(with_refit[e] >= without[e] for e in without)
        gained += sum(with_refit[e] > without[e] for e in without)
    # measured when written: all 17 entries of these frames gained inliers
    assert gained >= 0.5 * sum(len(_inliers(p)) for p in plain)
