"""The seeded closed-loop study's statistics: intervals cover what they should, the
paired test tells a real difference from none, the mechanism's correlation is found
with its cluster interval, and the study's summary tests the paper's claims."""

from __future__ import annotations

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.sim.closed_loop_seeded import Drive, SeededStudyConfig, summarize
from monoloc.sim.closed_loop_stats import (
    StatsConfig,
    bootstrap_mean_ci,
    cluster_correlation,
    paired_test,
)

FAST = StatsConfig(resamples=2000)


def test_bootstrap_interval_covers_the_true_mean_about_as_often_as_stated():
    rng = np.random.default_rng(0)
    hits = 0
    for _ in range(200):
        sample = rng.normal(3.0, 1.0, size=12)
        ci = bootstrap_mean_ci(sample, rng, FAST)
        assert ci["lo"] <= ci["mean"] <= ci["hi"]
        hits += ci["lo"] <= 3.0 <= ci["hi"]
    # Percentile bootstrap with 12 values under-covers a little: 88-97 % of 95 %.
    assert 0.86 < hits / 200 < 0.98
    assert bootstrap_mean_ci(np.array([np.nan]), rng)["mean"] is None


def test_paired_test_finds_a_consistent_difference_and_not_a_symmetric_one():
    rng = np.random.default_rng(1)
    base = rng.normal(1.0, 0.3, size=10)
    worse = base + 0.05 + rng.normal(0, 0.01, size=10)  # every seed worse
    t = paired_test(worse, base, rng, FAST)
    assert t["n_positive"] == 10
    assert t["p"] == pytest.approx(1 / 1024)
    assert t["lo"] > 0
    same = paired_test(base + rng.normal(0, 0.05, size=10), base, rng, FAST)
    assert same["p"] > 0.05
    assert paired_test(worse, worse, rng, FAST)["p"] == 1.0  # no difference at all
    with pytest.raises(InvalidInputError):
        paired_test(base, base[:5], rng)


def test_cluster_correlation_finds_the_relation_and_an_interval_around_it():
    rng = np.random.default_rng(2)
    groups = []
    for _ in range(10):
        x = rng.uniform(0, 1, 80)
        groups.append((x, -0.8 * x + rng.normal(0, 0.2, 80)))
    r = cluster_correlation(groups, rng, FAST)
    assert r["r"] < -0.6 and r["lo"] <= r["r"] <= r["hi"] < 0
    assert r["drives"] == 10 and r["frames"] == 800
    noise = [(rng.uniform(0, 1, 80), rng.normal(0, 1, 80)) for _ in range(10)]
    r0 = cluster_correlation(noise, rng, FAST)
    assert r0["lo"] < 0 < r0["hi"]


def _drive(case: str, seed: int, rmse_m: float, rng) -> Drive:
    n = 60
    err = np.abs(rng.normal(0, rmse_m, n))
    lateral = np.abs(rng.normal(0, 0.01, n))
    known = np.clip(0.5 - 5 * lateral + rng.normal(0, 0.02, n), 0, 1)
    metrics = {
        "loc_rmse_m": float(np.sqrt(np.mean(err**2))),
        "loc_p95_m": float(np.percentile(err, 95)),
        "loc_max_m": float(err.max()),
        "within_0_06": float(np.mean(err < 0.06)),
        "within_0_1": float(np.mean(err < 0.1)),
        "lateral_rmse_m": float(np.sqrt(np.mean(lateral**2))),
        "known_share_sent_mean": float(known.mean()),
    }
    return Drive(
        case, "pid", seed, metrics, np.arange(n) * 0.1, err, lateral, np.zeros(n), known,
        np.ones(n, int),
    )  # fmt: skip


def test_summary_tests_the_papers_claims_by_seed():
    rng = np.random.default_rng(3)
    drives = []
    for seed in range(10):
        drives.append(_drive("open", seed, 0.02, rng))
        drives.append(_drive("closed", seed, 0.04, rng))  # closing the loop doubles it
        drives.append(_drive("closed+offcenter", seed, 0.04, rng))  # augmenting: no help
    s = summarize(drives, FAST)
    claims = s["claims"]["pid"]
    assert claims["closed_worse_than_open"]["supported"]
    assert claims["closed_worse_than_open"]["loc_rmse_m"]["p"] < 0.01
    assert not claims["augmented_better_than_closed"]["supported"]
    rmse = s["cases"]["closed/pid"]["loc_rmse_m"]
    assert rmse["n"] == 10 and rmse["lo"] < rmse["mean"] < rmse["hi"]
    assert s["cases"]["open/pid"]["spikes"]["n"] == 10
    mech = s["mechanism"]["pid"]["closed"]["known_vs_lateral"]
    assert mech["r"] < -0.3 and mech["hi"] < 0


def _placed_drive(case: str, seed: int, offset_effect: float, rng) -> Drive:
    """A drive whose known share is set by the place (s) and, by ``offset_effect`` per m,
    by |lateral|; the lateral error is largest where the share is lowest (as after the
    bare end, closed loop), so the two are correlated through the place alone."""
    n = 120
    s_m = np.linspace(0.0, 3.0, n) + rng.normal(0, 0.005, n)
    place = 0.45 + 0.25 * np.cos(2 * np.pi * s_m / 3.0)
    if case == "open":  # on the truth: a small offset, the same everywhere
        lateral = np.abs(rng.normal(0, 0.002, n))
    else:
        lateral = 0.01 * (1.5 - np.cos(2 * np.pi * s_m / 3.0)) + np.abs(rng.normal(0, 0.01, n))
    known = place - offset_effect * lateral + rng.normal(0, 0.01, n)
    drive = _drive(case, seed, 0.02, rng)
    drive.lateral_m, drive.known_share, drive.s_m = lateral, known, s_m
    drive.t_s, drive.loc_error_m = np.arange(n) / 15, np.full(n, 0.02)
    drive.heading_rad = drive.n_hypotheses = np.zeros(n)
    return drive


@pytest.mark.parametrize("offset_effect", [0.0, 3.0])
def test_mechanism_at_the_same_place_tells_the_offset_from_the_place(offset_effect):
    rng = np.random.default_rng(5)
    drives = [
        _placed_drive(case, seed, offset_effect, rng)
        for seed in range(8)
        for case in ("open", "closed")
    ]
    mech = summarize(drives, FAST)["mechanism"]["pid"]["closed"]
    # pooled over places the share falls with |lateral| either way...
    assert mech["known_vs_lateral"]["hi"] < -0.3
    resid = mech["known_resid_vs_lateral"]
    if offset_effect == 0:  # ...at the same place only when the offset costs features
        assert resid["lo"] < 0 < resid["hi"] and abs(resid["slope"]) < 0.5
    else:
        assert resid["hi"] < 0
        assert resid["slope_lo"] < -offset_effect < resid["slope_hi"]


def test_study_config_refuses_what_it_cannot_drive():
    with pytest.raises(InvalidInputError):
        SeededStudyConfig(seeds=())
    with pytest.raises(InvalidInputError):
        SeededStudyConfig(controllers=("lqr",))
    config = SeededStudyConfig(controllers=("pid", "mpc"), max_seeds=(("mpc", 3),))
    assert config.seeds_of("mpc") == (0, 1, 2) and len(config.seeds_of("pid")) == 10


def test_seeded_figures_are_written(tmp_path):
    import cv2

    from monoloc.sim.closed_loop_plots import plot_seeded

    rng = np.random.default_rng(4)
    drives = [
        _drive(case, seed, rmse, rng)
        for seed in range(4)
        for case, rmse in (("open", 0.01), ("closed", 0.02), ("closed+offcenter", 0.015))
    ]
    paths = plot_seeded(drives, summarize(drives, FAST), tmp_path, "study")
    assert [p.name for p in paths] == ["study_per_seed.png", "study_known_vs_lateral.png"]
    for p in paths:
        image = cv2.imread(str(p))
        assert image is not None and image.shape[0] > 300 and image.std() > 10
    # With the drives' stations the share at the same place gets its own row of panels.
    placed = [_placed_drive(c, seed, 3.0, rng) for seed in range(4) for c in ("open", "closed")]
    two = plot_seeded(placed, summarize(placed, FAST), tmp_path, "placed")[1]
    assert cv2.imread(str(two)).shape[0] > 1.8 * cv2.imread(str(paths[1])).shape[0]
