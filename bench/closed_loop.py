"""The closed-loop study (issues 16 and 51; docs/method.md section 10, the paper's indoor
closed loop).

Starts a map server, maps the track (indoor: the 1:10 track's centre line; urban: the
lane centre of the city's map route) with laps recorded by the sim's own vehicle,
calibrates on a training lap, then drives the query laps three ways: open loop (the
controller on the ground truth: the baseline, measured in this run), closed loop on the
centre-line map, and closed loop after adding oscillating off-center laps.

Indoor (the default) is the seeded study (``monoloc.sim.closed_loop_seeded``): every case
driven with ``--seeds`` seeds by each of ``--controllers`` (pid, mpc) on one map; every
metric with its bootstrap CI over seeds, the paper's two claims as paired permutation
tests, the known-feature share against the tracking error, the open loop's share of
frames within 0.06 / 0.1 m beside the paper's (judged against the tracker's record of each
drive, as the paper judged against its Vive). Writes bench/results/closed_loop_indoor.json
(after every drive, ``complete`` false until the end) and
bench/results/closed_loop_indoor_{errors,per_seed,known_vs_lateral,...}.png.

Urban is one seed: the city route is no loop, "laps" is the share of the route driven,
and each case drives that share ``--passes`` times from its start (fresh filter each
pass; the figures pool the passes).

Usage: python -m bench.closed_loop [--scenario indoor|urban] [--seeds 10]
    [--controllers pid,mpc] [--mpc-seeds N] [--cases open,closed,closed+offcenter]
    [--name closed_loop_indoor] [--laps N] [--passes N] [--size small]
(``--name``: the indoor results' file stem, so that a partial run does not overwrite the
study's files.)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path

RESULTS = Path(__file__).parent / "results"
GOAL_RMSE_RATIO = 1.5
# The round trips of the indoor study on an unloaded machine (2026-12-01, 680 frames a
# case: p50 23 ms, p95 33 ms): drawn uniformly, so that a study on busy shared cores
# measures the loop, not the load (there the server's answers took 4x a frame period).
NOMINAL_LATENCY_MS = tuple(float(v) for v in range(20, 34))


def print_table(cases: dict) -> None:
    head = (
        f"{'case':<18}{'frames':>7}{'RMSE cm':>8}{'p95 cm':>8}{'max cm':>8}{'spikes':>7}"
        f"{'lat RMSE cm':>12}{'lat max cm':>11}{'lane dep':>9}{'hyp %':>7}{'corr':>7}"
        f"{'DR int':>7}{'known %':>8}"
    )
    print(head)
    for name, m in cases.items():
        corr = m["corr_tracking_vs_loc_error"]
        print(
            f"{name:<18}{m['frames']:>7}{100 * m['loc_rmse_m']:>8.2f}{100 * m['loc_p95_m']:>8.2f}"
            f"{100 * m['loc_max_m']:>8.2f}{m.get('spikes', 0):>7}"
            f"{100 * m['lateral_rmse_m']:>12.2f}{100 * m['lateral_max_m']:>11.2f}"
            f"{m['lane_departures']:>9}{100 * m['hypotheses_share']:>6.0f}%"
            f"{(corr if corr is not None else float('nan')):>7.2f}"
            f"{m['dead_reckoning_intervals']:>7}{100 * m['known_share_mean']:>7.0f}%"
        )


def goals(summary: dict) -> dict:
    cases = summary["cases"]
    base, closed, aug = cases["open"], cases["closed"], cases["closed+offcenter"]
    ratio = aug["loc_rmse_m"] / base["loc_rmse_m"]
    out = {
        "augmented_inside_lane": aug["lane_departures"] == 0,
        "augmented_rmse_over_open": ratio,
        "augmented_rmse_within_1_5x": ratio <= GOAL_RMSE_RATIO,
        "spikes_centre_map": closed["spikes"],
        "spikes_augmented_map": aug["spikes"],
        "augmentation_removes_spikes": closed["spikes"] > 0 and aug["spikes"] == 0,
    }
    print(
        f"goal: augmented map keeps every lap in the lane: "
        f"{'met' if out['augmented_inside_lane'] else 'MISSED'} "
        f"({aug['lane_departures']} departures, lateral max {100 * aug['lateral_max_m']:.1f} cm "
        f"of {100 * aug['lane_half_width_m']:.0f} cm)"
    )
    print(
        f"goal: augmented RMSE within {GOAL_RMSE_RATIO}x of open loop: "
        f"{'met' if out['augmented_rmse_within_1_5x'] else 'MISSED'} ({ratio:.2f}x; "
        f"baseline open loop {100 * base['loc_rmse_m']:.2f} cm measured in this run)"
    )
    open_spikes = base["spikes"]
    if out["augmentation_removes_spikes"]:
        print(
            f"the centre-line map shows {closed['spikes']} error spike(s) (> 3x the open-loop "
            f"p95) in closed loop (open loop: {open_spikes}); the augmented map none"
        )
    else:
        print(
            f"NOT reproduced: error spikes (> {100 * closed['spike_threshold_m']:.1f} cm = 3x "
            f"the open-loop p95, after the filter's first second): open loop {open_spikes}, "
            f"closed loop on the centre-line map {closed['spikes']}, after augmentation "
            f"{aug['spikes']}."
        )
        if closed["spikes"] <= open_spikes:
            print(
                "  Why: closing the loop adds no spikes here, so the feedback loop does not "
                f"start: the PID holds the car within {100 * closed['lateral_max_m']:.1f} cm "
                "of the centre line on the estimate, the camera sees what the centre-line "
                f"map holds (inlier share {100 * closed['known_share_mean']:.0f} % vs "
                f"{100 * base['known_share_mean']:.0f} % open loop), and the spikes that do "
                "occur happen open loop too (places where few features match, not steering)."
            )
        else:
            print(
                "  Closing the loop adds spikes; the off-center laps reduce them but do not "
                "remove them all."
            )
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scenario", default="indoor", choices=("indoor", "urban"))
    parser.add_argument("--laps", type=float, default=None, help="indoor 1, urban 0.25")
    parser.add_argument("--passes", type=int, default=None, help="drives per case (urban): 3")
    parser.add_argument("--seeds", type=int, default=10, help="indoor: seeds 0..N-1 per case")
    parser.add_argument("--controllers", default="pid,mpc", help="indoor: pid, mpc or both")
    parser.add_argument(
        "--latency",
        default="nominal",
        choices=("nominal", "measured"),
        help="indoor: answers' delays drawn from NOMINAL_LATENCY_MS, or the measured round trips",
    )
    parser.add_argument(
        "--mpc-seeds", type=int, default=None, help="indoor: the MPC drives only the first N seeds"
    )
    parser.add_argument(
        "--cases", default=None, help="indoor: among open,closed,closed+offcenter (default all)"
    )
    parser.add_argument(
        "--name", default="closed_loop_indoor", help="indoor: results file stem in bench/results"
    )
    parser.add_argument("--size", default="small")
    parser.add_argument("--seed", type=int, default=0, help="the world's (and the map's) seed")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if args.scenario == "indoor":
        seeded_main(args)
        return

    from monoloc.client.api import MonolocClient
    from monoloc.sim.closed_loop_plots import plot_cases
    from monoloc.sim.closed_loop_study import StudyConfig, run_study, serving
    from monoloc.sim.closed_loop_world import WorldSpec, build_loop_world

    started = time.time()
    out = args.out or Path(f"out/closed_loop_bench_{args.scenario}")
    world = build_loop_world(WorldSpec(args.scenario, args.size, args.seed))
    # a share of the route: map, off-center and query drives cover the same stretch
    laps = args.laps or 0.25
    passes = args.passes or 3
    study = StudyConfig(
        laps=laps,
        map_laps=laps,
        offcenter_laps=laps,
        train_laps=0.15,
        seed=args.seed,
        passes=passes,
    )

    def log(text: str) -> None:
        print(f"[{time.time() - started:5.0f} s] {text}", flush=True)

    with serving(out) as (url, key):
        with MonolocClient(url, key, timeout_s=120.0) as client:
            summary = run_study(client, world, study, out, log=log)
    results = summary.pop("_results")
    print(
        f"{args.scenario} ({args.size}, seed {args.seed}), {laps:g} laps x {passes} pass(es) "
        "per case:"
    )
    print_table(summary["cases"])
    summary["goals"] = goals(summary)
    RESULTS.mkdir(exist_ok=True)
    plots = plot_cases(
        results,
        RESULTS,
        prefix=f"closed_loop_{args.scenario}",
        reference_xy=world.reference_path(min(laps, 1.0)).xy,
        spike_threshold_m=summary["cases"]["open"].get("spike_threshold_m"),
    )
    summary["plots"] = _relative(plots)
    summary["total_s"] = time.time() - started
    path = RESULTS / f"closed_loop_{args.scenario}.json"
    path.write_text(json.dumps(summary, indent=2, default=float) + "\n")
    print(f"wrote {path} and {len(plots)} plots ({summary['total_s']:.0f} s)")


# What the study's figures depend on: a drive run on other code is not comparable.
CODE_PATHS = ("sim", "client", "server", "monoloc", "bench/closed_loop.py")


def code_version() -> dict:
    """The commit the study runs on and whether CODE_PATHS differ from it (None outside a
    git checkout)."""
    root = Path(__file__).resolve().parent.parent

    def git(*cmd: str) -> str | None:
        try:
            done = subprocess.run(
                ["git", "-C", str(root), *cmd], capture_output=True, text=True, timeout=30
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.rstrip("\n") if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    # porcelain lines are "XY path": two status columns and a space
    changed = git("status", "--porcelain", "--", *CODE_PATHS)
    return {
        "commit": commit,
        "changed_paths": None if changed is None else [ln[3:] for ln in changed.splitlines()],
    }


def _relative(plots) -> list[str]:
    """Plot paths relative to the repository: a results file names no path outside it."""
    root = Path(__file__).resolve().parent.parent
    return [
        str(Path(p).resolve().relative_to(root))
        if Path(p).resolve().is_relative_to(root)
        else Path(p).name
        for p in plots
    ]


def seeded_main(args) -> None:
    """The indoor seeded study (see the module docstring)."""
    from monoloc.client.api import MonolocClient
    from monoloc.sim.closed_loop_plots import plot_cases, plot_seeded
    from monoloc.sim.closed_loop_seeded import SeededStudyConfig, run_seeded_study, summarize
    from monoloc.sim.closed_loop_study import StudyConfig, serving
    from monoloc.sim.closed_loop_world import WorldSpec, build_loop_world

    started = time.time()
    out = args.out or Path("out/closed_loop_bench_indoor")
    world = build_loop_world(WorldSpec("indoor", args.size, args.seed))
    laps = args.laps or 1.0
    cases = {} if args.cases is None else {"cases": tuple(args.cases.split(","))}
    config = SeededStudyConfig(
        seeds=tuple(range(args.seeds)),
        controllers=tuple(c.strip() for c in args.controllers.split(",") if c.strip()),
        max_seeds=() if args.mpc_seeds is None else (("mpc", args.mpc_seeds),),
        latency_ms=NOMINAL_LATENCY_MS if args.latency == "nominal" else None,
        study=StudyConfig(laps=laps, offcenter_laps=1.0, train_laps=1.0, seed=args.seed, **cases),
        map_seed=args.seed,
    )
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{args.name}.json"
    planned = sum(len(config.seeds_of(c)) for c in config.controllers) * len(config.study.cases)
    header = {
        "scenario": "indoor",
        "size": args.size,
        "world_seed": args.seed,
        "laps_per_drive": laps,
        "seeds": {c: list(config.seeds_of(c)) for c in config.controllers},
        "controllers": list(config.controllers),
        "drives_planned": planned,
        "latency": args.latency,
        "code": code_version(),
    }

    def log(text: str) -> None:
        print(f"[{time.time() - started:5.0f} s] {text}", flush=True)

    def save(drives, info=None, complete=False, plots=()) -> dict:
        summary = summarize(drives, config.stats)
        data = {
            **header,
            "complete": complete,
            "drives_done": len(drives),
            "map": info or {},
            # flat means per case/controller (bench.report's table)
            "cases": {
                name: {k: v["mean"] for k, v in c.items() if isinstance(v, dict)}
                for name, c in summary["cases"].items()
            },
            "seeded": summary,
            "drives": [
                {"case": d.case, "controller": d.controller, "seed": d.seed, **d.metrics}
                for d in drives
            ],
            "plots": _relative(plots),
            "total_s": time.time() - started,
        }
        path.write_text(json.dumps(data, indent=2, default=float) + "\n")
        save_series(drives, out / f"{args.name}_frames.npz")
        return data

    with serving(out) as (url, key):
        with MonolocClient(url, key, timeout_s=120.0) as client:
            info, drives = run_seeded_study(
                client, world, config, out, log=log, on_drive=lambda d: save(d)
            )
    plots = []
    for controller in config.controllers:
        kept = {d.case: d.result for d in drives if d.controller == controller and d.result}
        if kept:
            plots += plot_cases(
                kept,
                RESULTS,
                prefix=f"{args.name}_{controller}",
                reference_xy=world.reference_path(min(laps, 1.0)).xy,
            )
    summary = summarize(drives, config.stats)
    plots += plot_seeded(drives, summary, RESULTS, args.name)
    data = save(drives, info, complete=True, plots=plots)
    print_seeded(data)
    print(f"wrote {path} and {len(plots)} plots ({data['total_s']:.0f} s)")


SERIES = ("t_s", "s_m", "loc_error_m", "lateral_m", "heading_rad", "known_share", "n_hypotheses")


def save_series(drives, path: Path) -> None:
    """Every drive's per-frame series (``case/controller/seed/name`` arrays) in one npz,
    beside the drive outputs (not in bench/results: ~100 frames x 7 series a drive), so
    that the study's statistics can be recomputed without driving again."""
    import numpy as np

    arrays = {
        f"{d.case}/{d.controller}/{d.seed}/{name}": np.asarray(getattr(d, name))
        for d in drives
        for name in SERIES
        if getattr(d, name) is not None
    }
    np.savez_compressed(path, **arrays)


def _ci(v: dict, scale: float = 100.0, digits: int = 2) -> str:
    if v.get("mean") is None:
        return "-"
    mean, lo, hi = (scale * v[k] for k in ("mean", "lo", "hi"))
    return f"{mean:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def print_seeded(data: dict) -> None:
    """The seeded study's tables: per case and controller the means with 95 % CIs, the
    open loop beside the paper, the claims' tests, the mechanism."""
    s = data["seeded"]
    print(f"indoor seeded study: {data['drives_done']} drives ({s['ci']})")
    print(f"{'case/controller':<24}{'RMSE cm':>22}{'max cm':>22}{'< 6 cm %':>20}"
          f"{'lat RMSE cm':>22}{'spikes':>18}{'known %':>20}")  # fmt: skip
    for name, c in s["cases"].items():
        print(
            f"{name:<24}{_ci(c['loc_rmse_m']):>22}{_ci(c['loc_max_m']):>22}"
            f"{_ci(c['within_0_06'], 100, 1):>20}{_ci(c['lateral_rmse_m']):>22}"
            f"{_ci(c['spikes'], 1, 1):>18}{_ci(c['known_share_sent_mean'], 100, 1):>20}"
        )
    for name, c in s["cases"].items():
        if name.startswith("open/"):
            print(
                f"open loop ({name}): {_ci(c['within_0_06'], 100, 1)} % of frames < 0.06 m "
                f"(paper ~92 %), {_ci(c['within_0_1'], 100, 1)} % < 0.1 m (paper 100 %)"
            )
    for controller, claims in s["claims"].items():
        for claim, t in claims.items():
            if not t.get("seeds"):
                continue
            r = t["loc_rmse_m"]
            print(
                f"{controller}: {claim}: RMSE {t['worse']} - {t['better']} = "
                f"{100 * r['mean_diff']:+.3f} cm [{100 * r['lo']:+.3f}, {100 * r['hi']:+.3f}], "
                f"{r['n_positive']}/{r['n']} seeds, p = {r['p']:.3f}; max: p = "
                f"{t['loc_max_m']['p']:.3f}; spikes: p = {t['spikes']['p']:.3f} -> "
                f"{'supported' if t['supported'] else 'NOT supported'} (p < 0.05 on RMSE)"
            )
    for controller, cases in s["mechanism"].items():
        for case, m in cases.items():
            parts = []
            for name, r in m.items():
                if r.get("r") is None:
                    continue
                ci = "" if r.get("lo") is None else f" [{r['lo']:.2f}, {r['hi']:.2f}]"
                slope = ""
                if name == "known_resid_vs_lateral" and r.get("slope_lo") is not None:
                    # share per m -> percentage points per cm
                    slope = (
                        f" (slope {r['slope']:+.2f} [{r['slope_lo']:+.2f}, "
                        f"{r['slope_hi']:+.2f}] points/cm)"
                    )
                parts.append(f"{name} r = {r['r']:.2f}{ci}{slope}")
            print(f"mechanism {controller} {case}: " + "; ".join(parts))
    for case, tests in s.get("controllers", {}).items():
        if case == "note":
            continue
        r = tests["loc_rmse_m"]
        lat = tests["lateral_rmse_m"]
        if r.get("n"):
            print(
                f"pid - mpc, {case}: RMSE {100 * r['mean_diff']:+.3f} cm (p = {r['p']:.3f}), "
                f"lateral RMSE {100 * lat['mean_diff']:+.3f} cm (p = {lat['p']:.3f})"
            )


if __name__ == "__main__":
    main()
