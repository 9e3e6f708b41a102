"""The figures of a closed-loop drive: localization error, tracking error, their
correlation (the feedback loop, quantified), spikes, lane departures, dead reckoning."""

from __future__ import annotations

import math

import numpy as np

from monoloc.sim.closed_loop import LoopResult
from monoloc.sim.closed_loop_record import localization_error_m, true_localization_error_m

SPIKE_FACTOR = 3.0
# The filter's first second (initialisation from the first hypotheses) is not a spike.
SETTLE_S = 1.0


def episodes(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index ranges of the runs of True in a (N,) bool array."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _settled(t_s: np.ndarray, has: np.ndarray, pass_index: np.ndarray | None) -> np.ndarray:
    """(N,) bool: at least SETTLE_S after the first estimate of the frame's pass (one
    pass when ``pass_index`` is None)."""
    passes = np.zeros(len(t_s), dtype=np.int64) if pass_index is None else pass_index
    settled = np.zeros(len(t_s), dtype=bool)
    for p in np.unique(passes):
        rows = np.flatnonzero(passes == p)
        estimated = rows[has[rows]]
        if len(estimated):
            settled[rows] = t_s[rows] - t_s[estimated[0]] >= SETTLE_S
    return settled


def _pearson(a: np.ndarray, b: np.ndarray) -> float | None:
    if len(a) < 3 or np.std(a) == 0 or np.std(b) == 0:
        return None
    return float(np.corrcoef(a, b)[0, 1])


def loop_metrics(result: LoopResult, spike_threshold_m: float | None = None) -> dict:
    """Figures of one drive. ``spike_threshold_m``: errors above it count as spikes (the
    study passes 3x the open-loop p95); one spike is one run of consecutive frames above
    it, counted from ``SETTLE_S`` after the filter's first estimate (its initialisation
    is no spike). Lane departures are counted on the integration-rate true trace, once per
    excursion beyond the lane's half width."""
    f = result.frames
    err = localization_error_m(result)
    has = np.isfinite(err)
    e = err[has]
    e_true = true_localization_error_m(result)[has]
    lateral = np.abs(result.trace["lateral_m"])
    out_of_lane = lateral > result.lane_half_width_m
    no_hyp = f["n_hypotheses"] == 0
    period = float(np.median(np.diff(f["t_s"]))) if len(f["t_s"]) > 1 else math.nan
    dr = episodes(no_hyp & (np.arange(len(no_hyp)) > 0))
    lat_sent = f["latency_ms"][np.isfinite(f["latency_ms"])]
    m = {
        "frames": int(result.n_frames),
        "duration_s": float(f["t_s"][-1] - f["t_s"][0]) if result.n_frames else 0.0,
        "estimated_share": float(np.mean(has)),
        "hypotheses_share": float(np.mean(~no_hyp)),
        "loc_rmse_m": float(np.sqrt(np.mean(e**2))) if len(e) else None,
        "loc_p95_m": float(np.percentile(e, 95)) if len(e) else None,
        "loc_max_m": float(np.max(e)) if len(e) else None,
        "loc_rmse_true_m": float(np.sqrt(np.mean(e_true**2))) if len(e_true) else None,
        "lateral_rmse_m": float(np.sqrt(np.mean(lateral**2))),
        "lateral_max_m": float(np.max(lateral)),
        "heading_rmse_deg": float(np.degrees(np.sqrt(np.mean(f["heading_rad"] ** 2)))),
        "lane_half_width_m": float(result.lane_half_width_m),
        "lane_departures": len(episodes(out_of_lane)),
        "dead_reckoning_intervals": len(dr),
        "longest_dead_reckoning_s": float(max((b - a for a, b in dr), default=0) * period),
        "known_share_mean": float(np.mean(result.known_share)),
        "query_features_mean": float(np.mean(f["n_features"])),
        "inliers_mean": float(np.mean(f["n_inliers"])),
        "latency_ms_p50": float(np.percentile(lat_sent, 50)) if len(lat_sent) else None,
        "latency_ms_p95": float(np.percentile(lat_sent, 95)) if len(lat_sent) else None,
        "frames_not_sent": int(np.sum(~f["sent"])),
        "corr_tracking_vs_loc_error": _pearson(np.abs(f["lateral_m"][has]), e),
        "wall_s": float(result.wall_s),
    }
    if spike_threshold_m is not None:
        m["spike_threshold_m"] = float(spike_threshold_m)
        settled = _settled(f["t_s"], has, f.get("pass_index"))
        above = has & settled & (np.nan_to_num(err, nan=0.0) > spike_threshold_m)
        m["spikes"] = len(episodes(above))
    return m
