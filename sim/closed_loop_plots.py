"""Figures of closed-loop drives, like the paper's: trajectories against the ground
truth, localization error over time (dead-reckoning intervals shaded: frames without
hypotheses), and localization error against tracking error."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from monoloc.sim.closed_loop import LoopResult
from monoloc.sim.closed_loop_metrics import episodes
from monoloc.sim.closed_loop_record import localization_error_m

COLOURS = {"open": "tab:blue", "closed": "tab:red", "closed+offcenter": "tab:green"}
MARKERS = {"pid": "o", "mpc": "s"}


def plot_cases(
    results: dict[str, LoopResult],
    out_dir: Path,
    prefix: str = "closed_loop",
    reference_xy: np.ndarray | None = None,
    spike_threshold_m: float | None = None,
) -> list[Path]:
    """Three PNGs under ``out_dir``: ``<prefix>_trajectories.png``,
    ``<prefix>_errors.png``, ``<prefix>_loc_vs_tracking.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []

    fig, ax = plt.subplots(figsize=(7, 6))
    if reference_xy is not None:
        ax.plot(*reference_xy.T, color="0.7", lw=1, ls="--", label="reference (centre line)")
    for name, r in results.items():
        c = COLOURS.get(name)
        truth = r.frames["truth_cam"]
        ax.plot(truth[:, 0], truth[:, 1], color=c, lw=1.2, label=f"{name}: true")
        est = r.estimates_world
        ax.plot(est[:, 0], est[:, 1], ".", color=c, ms=2, label=f"{name}: estimate")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(fontsize=7)
    ax.set_title("trajectories (camera) against the ground truth")
    paths.append(_save(fig, out_dir / f"{prefix}_trajectories.png"))

    fig, axes = plt.subplots(len(results), 1, figsize=(9, 2.3 * len(results)), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, (name, r) in zip(axes, results.items(), strict=True):
        t = r.frames["t_s"]
        err = localization_error_m(r)
        ax.plot(t, 100 * err, color=COLOURS.get(name), lw=1)
        ax.plot(t, 100 * np.abs(r.frames["lateral_m"]), color="0.4", lw=0.8, ls=":")
        for a, b in episodes(r.frames["n_hypotheses"] == 0):
            ax.axvspan(t[a], t[min(b, len(t) - 1)], color="orange", alpha=0.25, lw=0)
        if spike_threshold_m is not None:
            ax.axhline(100 * spike_threshold_m, color="k", lw=0.6, ls="--")
        ax.set_ylabel("cm")
        ax.set_title(
            f"{name}: localization error (solid), |lateral tracking error| (dotted); "
            "shaded: dead reckoning (no hypotheses)",
            fontsize=8,
        )
    axes[-1].set_xlabel("time (s)")
    paths.append(_save(fig, out_dir / f"{prefix}_errors.png"))

    fig, ax = plt.subplots(figsize=(6, 5))
    for name, r in results.items():
        err = localization_error_m(r)
        ok = np.isfinite(err)
        ax.scatter(
            100 * np.abs(r.frames["lateral_m"][ok]), 100 * err[ok], s=5,
            color=COLOURS.get(name), label=name, alpha=0.6,
        )  # fmt: skip
    ax.set_xlabel("|lateral tracking error| (cm)")
    ax.set_ylabel("localization error (cm)")
    ax.legend()
    ax.set_title("localization error against tracking error")
    paths.append(_save(fig, out_dir / f"{prefix}_loc_vs_tracking.png"))
    return paths


def plot_seeded(drives, summary: dict, out_dir: Path, prefix: str) -> list[Path]:
    """The seeded study's figures (``monoloc.sim.closed_loop_seeded``): per-seed
    distributions of the localization RMSE, max and lateral RMSE per case and controller
    (lines join one seed's drives), and the known-feature share against |lateral error|
    (every sent frame, binned means; below it, when ``summarize`` set the drives'
    ``known_residual``, the share minus the open loop's at the same place)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    controllers = sorted({d.controller for d in drives})
    cases = [c for c in COLOURS if any(d.case == c for d in drives)]
    paths = []
    metrics = (("loc_rmse_m", "localization RMSE (cm)"), ("loc_max_m", "largest error (cm)"),
               ("lateral_rmse_m", "lateral tracking RMSE (cm)"))  # fmt: skip
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 4.2))
    for ax, (name, label) in zip(np.atleast_1d(axes), metrics, strict=True):
        for ci, controller in enumerate(controllers):
            by_seed: dict[int, list[tuple[float, float]]] = {}
            for k, case in enumerate(cases):
                x0 = k + 0.18 * (ci - (len(controllers) - 1) / 2)
                rows = [d for d in drives if d.case == case and d.controller == controller]
                vals = [100 * d.metrics[name] for d in rows if d.metrics.get(name) is not None]
                jitter = np.linspace(-0.05, 0.05, max(len(vals), 1))[: len(vals)]
                ax.scatter(x0 + jitter, vals, s=14, color=COLOURS[case],
                           marker=MARKERS.get(controller, "o"), alpha=0.8)  # fmt: skip
                if vals:
                    ax.hlines(np.mean(vals), x0 - 0.12, x0 + 0.12, color="k", lw=1.5)
                for d in rows:
                    if d.metrics.get(name) is not None:
                        by_seed.setdefault(d.seed, []).append((x0, 100 * d.metrics[name]))
            for points in by_seed.values():
                xs, ys = zip(*points, strict=True)
                ax.plot(xs, ys, color="0.6", lw=0.4, zorder=0)
        ax.set_xticks(range(len(cases)), cases, fontsize=8)
        ax.set_ylabel(label)
    fig.suptitle(
        "per-seed drives (" + ", ".join(f"{c}: {MARKERS.get(c, 'o')}" for c in controllers)
        + "; bar: mean; lines join a seed)", fontsize=9,
    )  # fmt: skip
    paths.append(_save(fig, out_dir / f"{prefix}_per_seed.png"))

    residuals = any(d.known_residual is not None for d in drives)
    panels = (("known", "known-feature share of the query (%)", "known_vs_lateral"),) + (
        (("resid", "share minus the open loop's at the place (points)", "known_resid_vs_lateral"),)
        if residuals
        else ()
    )
    fig, axes = plt.subplots(len(panels), len(controllers), squeeze=False,
                             figsize=(5.5 * len(controllers), 4.5 * len(panels)))  # fmt: skip
    for row, (kind, ylabel, key) in zip(axes, panels, strict=True):
        for ax, controller in zip(row, controllers, strict=True):
            for case in cases:
                rows = [d for d in drives if d.case == case and d.controller == controller]
                share = [d.known_share if kind == "known" else d.known_residual for d in rows]
                if any(v is None for v in share):
                    continue
                known = np.concatenate(share)
                lateral = np.concatenate([d.lateral_m for d in rows])
                ok = np.isfinite(known)
                ax.scatter(100 * lateral[ok], 100 * known[ok], s=2, alpha=0.15,
                           color=COLOURS[case])  # fmt: skip
                if ok.sum() > 20:
                    centres, means = _binned(lateral[ok], known[ok])
                    r = summary.get("mechanism", {}).get(controller, {}).get(case, {})
                    ax.plot(100 * centres, 100 * means, "-o", color=COLOURS[case], ms=3,
                            label=_r_label(case, r.get(key, {})))  # fmt: skip
            ax.set_xlabel("|lateral tracking error| (cm)")
            ax.set_ylabel(ylabel)
            what = "known features" if kind == "known" else "known features at the same place"
            ax.set_title(f"{controller}: {what} against tracking error", fontsize=9)
            if kind == "resid":
                ax.axhline(0.0, color="0.5", lw=0.6)
            ax.legend(fontsize=7)
    paths.append(_save(fig, out_dir / f"{prefix}_known_vs_lateral.png"))
    return paths


def _binned(x: np.ndarray, y: np.ndarray, n_bins: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Median x and mean y in ``n_bins`` bins of equal counts of x."""
    edges = np.quantile(x, np.linspace(0, 1, n_bins + 1))
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n_bins - 1)
    kept = [b for b in range(n_bins) if (idx == b).any()]
    return (
        np.array([np.median(x[idx == b]) for b in kept]),
        np.array([np.mean(y[idx == b]) for b in kept]),
    )


def _r_label(case: str, r: dict) -> str:
    if r.get("r") is None:
        return case
    if r.get("lo") is None:
        return f"{case}: r = {r['r']:.2f}"
    return f"{case}: r = {r['r']:.2f} [{r['lo']:.2f}, {r['hi']:.2f}]"


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
