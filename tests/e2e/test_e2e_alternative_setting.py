"""A server adds the alternative pose (``LocalizeConfig.alternative``) to frames whose
per-entry poses are poorly pinned down, unless MONOLOC_LOCALIZE_ALTERNATIVE=false;
ordinary frames get exactly the answer of a server without it (the same seed)."""

from __future__ import annotations

import numpy as np
from e2e_helpers import QUERY_SEQ, localize_frames, localize_frames_on_copy

from monoloc.client.replay import read_run

FRAMES = (4, 8, 12, 16, 20)


def test_setting_reads_the_environment_and_reaches_the_pipeline(monkeypatch, tmp_path):
    from monoloc.server.api.localizing import localize_config
    from monoloc.server.localize import AlternativeConfig
    from monoloc.server.settings import Settings

    settings = Settings(data_dir=tmp_path)
    assert settings.localize_alternative is True
    strategy = localize_config(settings).pnp_strategy
    assert strategy.alternative == AlternativeConfig() and strategy.covariance
    monkeypatch.setenv("MONOLOC_LOCALIZE_ALTERNATIVE", "false")
    assert Settings(data_dir=tmp_path).localize_alternative is False
    assert localize_config(Settings(data_dir=tmp_path)).pnp_strategy.alternative is None
    # the paper's preset has no pooled PnP, hence no alternative pose
    paper = Settings(data_dir=tmp_path, localize_pipeline="paper")
    assert localize_config(paper).pnp_strategy.alternative is None


def _by_entry(answer) -> dict[tuple[int, str], list[float]]:
    return {
        (h["entry_id"], h["method"]): h["T_world_from_cam"]
        for h in answer.raw["hypotheses"]
        if h["method"] != "alternative"
    }


def test_ordinary_frames_are_answered_as_without_it(live_map, tmp_path):
    run = read_run(live_map.dataset, QUERY_SEQ)
    images = [run.image_paths[f].read_bytes() for f in FRAMES]
    tried = localize_frames(live_map.url, live_map.keys.localize, live_map.map_id, images, 5)
    data_dir = tmp_path / "data"
    plain = localize_frames_on_copy(live_map, data_dir, images, 5, localize_alternative=False)
    assert sum(bool(p.raw["hypotheses"]) for p in plain) >= 3
    for p, t in zip(plain, tried, strict=True):
        ours, theirs = _by_entry(p), _by_entry(t)
        assert ours.keys() == theirs.keys()
        for key, pose in ours.items():
            np.testing.assert_allclose(theirs[key], pose, atol=1e-9)
        for h in t.raw["hypotheses"]:
            if h["method"] == "alternative":
                assert h["pose_covariance"] is not None
