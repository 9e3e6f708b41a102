"""The closed-loop study with statistical power (issue 51): every case driven with many
seeds on one map, each metric with a bootstrap confidence interval over the seeds, the
paper's two claims as paired tests (by seed), and the feedback mechanism, the share of
known features against the tracking error.

One map serves every drive: centre-line laps (and the calibration lap), then, after
the centre-line cases, the off-center laps are added to it. A seed draws a drive's
render noise, signal errors and filter; drives of one seed in different cases share
them, so cases are compared seed by seed. Controllers (pid, mpc) are one more
dimension: each case is driven by each controller with every seed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.sim.closed_loop import CONTROLLERS, LoopResult
from monoloc.sim.closed_loop_metrics import SETTLE_S, loop_metrics
from monoloc.sim.closed_loop_record import localization_error_m
from monoloc.sim.closed_loop_stats import (
    StatsConfig,
    bootstrap_mean_ci,
    cluster_correlation,
    paired_test,
    pearson,
)
from monoloc.sim.closed_loop_study import (
    CASES,
    StudyConfig,
    add_offcenter,
    build_map,
    drive_case,
)

# The paper's indoor open loop: 100 % of errors below 0.1 m, about 92 % below 0.06 m.
PAPER_WITHIN = {"0.06": 0.92, "0.1": 1.00}
SUMMARY_METRICS = (
    "loc_rmse_m",
    "loc_p95_m",
    "loc_max_m",
    "loc_rmse_true_m",
    "within_0_06",
    "within_0_1",
    "spikes",
    "lateral_rmse_m",
    "lateral_max_m",
    "heading_rmse_deg",
    "lane_departures",
    "hypotheses_share",
    "dead_reckoning_intervals",
    "longest_dead_reckoning_s",
    "known_share_sent_mean",
    "frames_not_sent",
)
# The claims tested on these metrics (larger = worse for every one of them).
CLAIM_METRICS = ("loc_rmse_m", "loc_p95_m", "loc_max_m", "spikes")
# Stations along the drive for the place-controlled mechanism: the known share differs by
# place far more than by offset (0 on the bare end, 70 % in textured turns), and the
# tracking error does too (largest after the bare end), so the pooled correlation mixes
# place and offset. 5 cm: under a map period (6.7 cm), over the drives' spread in
# distance at one station of a 0.4-lap drive with a 3 % speed-scale error (a few cm).
STATION_M = 0.05


@dataclass(frozen=True)
class SeededStudyConfig:
    """seeds: one drive per seed, case and controller; controllers: among pid|mpc;
    max_seeds: per controller, at most this many of the seeds (the first ones; a run
    that cannot afford every seed for every controller); study: laps, map/off-center/
    training laps and the cases (its ``seed`` is unused: the map laps take
    ``map_seed``); latency_ms: every drive draws its answers' delays from these values
    (None: the measured round trips, which on shared cores measure the load); stats: the
    intervals."""

    seeds: tuple[int, ...] = tuple(range(10))
    controllers: tuple[str, ...] = ("pid",)
    max_seeds: tuple[tuple[str, int], ...] = ()
    latency_ms: tuple[float, ...] | None = None
    study: StudyConfig = field(default_factory=lambda: StudyConfig(laps=1.0))
    map_seed: int = 0
    stats: StatsConfig = field(default_factory=StatsConfig)

    def __post_init__(self) -> None:
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise InvalidInputError(f"seeds must be distinct and not empty, got {self.seeds}")
        bad = [c for c in self.controllers if c not in CONTROLLERS]
        if bad or not self.controllers:
            raise InvalidInputError(f"controllers must be among {CONTROLLERS}, got {bad}")
        if any(n < 1 for _, n in self.max_seeds):
            raise InvalidInputError(f"max_seeds must be at least 1, got {self.max_seeds}")

    def seeds_of(self, controller: str) -> tuple[int, ...]:
        """The seeds ``controller`` drives."""
        limit = dict(self.max_seeds).get(controller)
        return self.seeds if limit is None else self.seeds[:limit]


@dataclass
class Drive:
    """One drive: its case, controller, seed, metrics and the per-frame series the
    mechanism needs (all (N,)): time s, localization error m (NaN before an estimate),
    |lateral| m, |heading| rad, known-feature share of sent frames (NaN for frames not
    sent), hypotheses; s_m the distance the car has driven (true path) at each frame;
    known_residual the known share minus the open loop's mean at the same station (set
    by ``summarize``)."""

    case: str
    controller: str
    seed: int
    metrics: dict
    t_s: np.ndarray
    loc_error_m: np.ndarray
    lateral_m: np.ndarray
    heading_rad: np.ndarray
    known_share: np.ndarray
    n_hypotheses: np.ndarray
    result: LoopResult | None = None
    s_m: np.ndarray | None = None
    known_residual: np.ndarray | None = None


def drive_record(case: str, controller: str, seed: int, result: LoopResult, keep: bool) -> Drive:
    """A Drive of ``result`` with its metrics (spikes are counted later, against the
    open loop's p95); ``keep``: hold the full result (for the figures)."""
    f = result.frames
    err = localization_error_m(result)
    sent = f["sent"].astype(bool) & (f["n_features"] > 0)
    known = np.where(sent, result.known_share, np.nan)
    metrics = loop_metrics(result)
    has = np.isfinite(err)
    settled = has & (f["t_s"] - (f["t_s"][has][0] if has.any() else 0.0) >= SETTLE_S)
    e = err[settled]
    metrics["within_0_06"] = float(np.mean(e < 0.06)) if len(e) else None
    metrics["within_0_1"] = float(np.mean(e < 0.1)) if len(e) else None
    metrics["known_share_sent_mean"] = (
        float(np.nanmean(known)) if np.isfinite(known).any() else None
    )
    ok = np.isfinite(known)
    metrics["corr_known_vs_lateral"] = pearson(known[ok], np.abs(f["lateral_m"][ok]))
    metrics["corr_known_vs_heading"] = pearson(known[ok], np.abs(f["heading_rad"][ok]))
    return Drive(
        case,
        controller,
        seed,
        metrics,
        f["t_s"].copy(),
        err,
        np.abs(f["lateral_m"]),
        np.abs(f["heading_rad"]),
        known,
        f["n_hypotheses"].copy(),
        result if keep else None,
        driven_distance_m(f["truth_vehicle"][:, :2]),
    )


def driven_distance_m(xy_m: np.ndarray) -> np.ndarray:
    """(N,) distance along the (N, 2) positions from the first one."""
    step = np.linalg.norm(np.diff(np.asarray(xy_m, float), axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(step)])


def known_share_residuals(drives: list[Drive], station_m: float = STATION_M) -> None:
    """Set each drive's ``known_residual``: its known share minus the mean known share
    of its controller's open-loop drives at the same station (``s_m`` binned by
    ``station_m``); NaN where no open-loop frame was sent there (or without ``s_m``)."""
    for controller in {d.controller for d in drives}:
        rows = [d for d in drives if d.controller == controller]
        opened = [d for d in rows if d.case == "open" and d.s_m is not None]
        if not opened:
            continue
        n_bins = 1 + max(int(np.max(d.s_m) / station_m) for d in rows if d.s_m is not None)
        total, count = np.zeros(n_bins), np.zeros(n_bins)
        for d in opened:
            ok = np.isfinite(d.known_share)
            bins = (d.s_m[ok] / station_m).astype(int)
            np.add.at(total, bins, d.known_share[ok])
            np.add.at(count, bins, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            baseline = np.where(count > 0, total / count, np.nan)
        for d in rows:
            if d.s_m is not None:
                d.known_residual = d.known_share - baseline[(d.s_m / station_m).astype(int)]


def count_spikes(drive: Drive, threshold_m: float) -> int:
    """Runs of frames whose error exceeds ``threshold_m``, from SETTLE_S after the first
    estimate (as ``loop_metrics``)."""
    from monoloc.sim.closed_loop_metrics import episodes

    err = drive.loc_error_m
    has = np.isfinite(err)
    if not has.any():
        return 0
    settled = drive.t_s - drive.t_s[has][0] >= SETTLE_S
    return len(episodes(has & settled & (np.nan_to_num(err, nan=0.0) > threshold_m)))


def run_seeded_study(
    client,
    world,
    config: SeededStudyConfig,
    out_dir: Path,
    log: Callable[[str], None] = print,
    on_drive: Callable[[list[Drive]], None] | None = None,
    keep_seed: int | None = None,
) -> tuple[dict, list[Drive]]:
    """Map, then every (case, controller, seed) drive in the order open, closed, (add the
    off-center laps), closed+offcenter; ``on_drive(drives)`` after each drive (to save
    partial results). ``keep_seed``: keep that seed's full results (default: the first
    seed). Returns the map's info and the drives."""
    study = config.study
    keep_seed = config.seeds[0] if keep_seed is None else keep_seed
    map_id, info = build_map(client, world, _with_seed(study, config.map_seed), out_dir, log)
    info["map_id"] = map_id
    drives: list[Drive] = []
    started = time.perf_counter()
    for case in study.cases:
        if case == "closed+offcenter":
            info.update(
                add_offcenter(
                    client, map_id, world, _with_seed(study, config.map_seed), out_dir, log
                )
            )
        mode = "open" if case == "open" else "closed"
        for controller in config.controllers:
            for seed in config.seeds_of(controller):
                result = drive_case(
                    client, map_id, world, mode, study, config.latency_ms, seed=seed,
                    controller=controller,
                )  # fmt: skip
                drive = drive_record(case, controller, seed, result, seed == keep_seed)
                drives.append(drive)
                m = drive.metrics
                log(
                    f"  {case:<17} {controller} seed {seed}: RMSE "
                    f"{100 * (m['loc_rmse_m'] or 0):.2f} cm, "
                    f"< 6 cm {100 * (m['within_0_06'] or 0):.0f} %, lateral RMSE "
                    f"{100 * m['lateral_rmse_m']:.2f} cm, known "
                    f"{100 * (m['known_share_sent_mean'] or 0):.0f} % "
                    f"({time.perf_counter() - started:.0f} s)"
                )
                if on_drive is not None:
                    on_drive(drives)
    return info, drives


def _with_seed(study: StudyConfig, seed: int) -> StudyConfig:
    from dataclasses import replace

    return replace(study, seed=seed)


def summarize(drives: list[Drive], stats: StatsConfig = StatsConfig(), seed: int = 0) -> dict:
    """The study's figures from its drives: spikes counted against 3x the open loop's
    pooled p95 (per controller), per (case, controller) every SUMMARY_METRICS mean with
    its bootstrap CI over seeds, the paper's claims as paired tests, the mechanism's
    correlations (cluster bootstrap over drives), and PID against MPC."""
    from monoloc.sim.closed_loop_metrics import SPIKE_FACTOR

    rng = np.random.default_rng([seed, 51])
    known_share_residuals(drives)
    controllers = sorted({d.controller for d in drives}, key=CONTROLLERS.index)
    cases = [c for c in CASES if any(d.case == c for d in drives)]
    out: dict = {
        "ci": f"percentile bootstrap over seeds, {stats.resamples} resamples, {stats.level:.0%}",
        "test": "one-sided exact sign-flip permutation test of the mean paired (by seed) "
        "difference",
        "paper_open_loop_within": PAPER_WITHIN,
        "cases": {},
        "claims": {},
        "mechanism": {},
        "controllers": {},
    }
    for controller in controllers:
        open_errors = [
            d.loc_error_m[np.isfinite(d.loc_error_m)]
            for d in drives
            if d.controller == controller and d.case == "open"
        ]
        threshold = None
        if open_errors and sum(len(e) for e in open_errors):
            threshold = SPIKE_FACTOR * float(np.percentile(np.concatenate(open_errors), 95))
        for d in drives:
            if d.controller == controller and threshold is not None:
                d.metrics["spike_threshold_m"] = threshold
                d.metrics["spikes"] = count_spikes(d, threshold)
        for case in cases:
            rows = [d for d in drives if d.controller == controller and d.case == case]
            if not rows:
                continue
            out["cases"][f"{case}/{controller}"] = {
                "seeds": [d.seed for d in rows],
                **{
                    name: {
                        **bootstrap_mean_ci(
                            np.array([_num(d.metrics.get(name)) for d in rows]), rng, stats
                        ),
                        "per_seed": [_num(d.metrics.get(name)) for d in rows],
                    }
                    for name in SUMMARY_METRICS
                },
            }
        out["claims"][controller] = {
            "closed_worse_than_open": _claim(drives, controller, "closed", "open", rng, stats),
            "augmented_better_than_closed": _claim(
                drives, controller, "closed", "closed+offcenter", rng, stats
            ),
        }
        out["mechanism"][controller] = _mechanism(drives, controller, rng, stats)
    if set(controllers) >= {"pid", "mpc"}:
        out["controllers"] = {
            case: {
                name: paired_test(*_paired(drives, case, name, "pid", "mpc"), rng, stats)
                for name in ("loc_rmse_m", "loc_max_m", "lateral_rmse_m", "heading_rmse_deg")
            }
            for case in cases
        }
        out["controllers"]["note"] = "mean_diff = pid - mpc, p: is pid's larger"
    return out


def _num(value) -> float:
    return float("nan") if value is None else float(value)


def _paired(drives, case, metric, controller_a, controller_b):
    """(values of controller_a, of controller_b) in case, aligned by seed."""
    a = {
        d.seed: _num(d.metrics.get(metric))
        for d in drives
        if d.case == case and d.controller == controller_a
    }
    b = {
        d.seed: _num(d.metrics.get(metric))
        for d in drives
        if d.case == case and d.controller == controller_b
    }
    seeds = sorted(set(a) & set(b))
    return np.array([a[s] for s in seeds]), np.array([b[s] for s in seeds])


def _claim(drives, controller, worse_case, better_case, rng, stats) -> dict:
    """Is ``worse_case`` worse than ``better_case`` (by seed), metric by metric."""
    by = {
        case: {d.seed: d for d in drives if d.controller == controller and d.case == case}
        for case in (worse_case, better_case)
    }
    seeds = sorted(set(by[worse_case]) & set(by[better_case]))
    if not seeds:
        return {"seeds": 0}
    out: dict = {"seeds": len(seeds), "worse": worse_case, "better": better_case}
    for name in CLAIM_METRICS:
        a = np.array([_num(by[worse_case][s].metrics.get(name)) for s in seeds])
        b = np.array([_num(by[better_case][s].metrics.get(name)) for s in seeds])
        out[name] = paired_test(a, b, rng, stats)
    out["supported"] = bool(out["loc_rmse_m"]["p"] is not None and out["loc_rmse_m"]["p"] < 0.05)
    return out


def _mechanism(drives, controller, rng, stats) -> dict:
    """Per closed-loop case (and the open loop, where steering ignores the estimate): the
    known-feature share against |lateral| and |heading| tracking error and against the
    localization error, pooled over the drives of that case (frames that were sent and
    had features), with cluster-bootstrap CIs; the same for the known share's residual
    after its place (``known_resid_vs_*``: minus the open loop's mean at the station),
    with the slope (share per m of |lateral|, per rad of |heading|, per m of error)."""
    out = {}
    for case in CASES:
        rows = [d for d in drives if d.controller == controller and d.case == case]
        if not rows:
            continue
        out[case] = {}
        for prefix, share_of in (
            ("known", lambda d: d.known_share),
            ("known_resid", lambda d: d.known_residual),
        ):
            groups = {"lateral": [], "heading": [], "loc_error": []}
            for d in rows:
                share = share_of(d)
                if share is None:
                    continue
                ok = np.isfinite(share)
                groups["lateral"].append((share[ok], d.lateral_m[ok]))
                groups["heading"].append((share[ok], d.heading_rad[ok]))
                ok2 = ok & np.isfinite(d.loc_error_m)
                groups["loc_error"].append((share[ok2], d.loc_error_m[ok2]))
            for name, g in groups.items():
                if g:
                    out[case][f"{prefix}_vs_{name}"] = cluster_correlation(g, rng, stats)
    return out
