"""The closed-loop study (issue 16; docs/method.md section 10, the paper's indoor closed loop).

Starts a map server, maps the track (indoor: the 1:10 track's centre line; urban: the
lane centre of the city's map route) with laps recorded by the sim's own vehicle,
calibrates on a training lap, then drives the query laps three ways: open loop (the
controller on the ground truth: the baseline, measured in this run), closed loop on the
centre-line map, and closed loop after adding oscillating off-center laps. Prints the
table and the goals; writes bench/results/closed_loop_<scenario>.json and
bench/results/closed_loop_<scenario>_{trajectories,errors,loc_vs_tracking}.png.
The city route is no loop: there, "laps" is the share of the route driven, and each case
drives that share ``--passes`` times from its start (fresh filter each pass; the figures
pool the passes).

Usage: python -m bench.closed_loop [--scenario indoor|urban] [--laps N] [--passes N]
    [--size small]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

RESULTS = Path(__file__).parent / "results"
GOAL_RMSE_RATIO = 1.5


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
    parser.add_argument("--laps", type=float, default=None, help="indoor 3, urban 0.25")
    parser.add_argument(
        "--passes", type=int, default=None, help="drives per case: indoor 1, urban 3"
    )
    parser.add_argument("--size", default="small")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    from monoloc.client.api import MonolocClient
    from monoloc.sim.closed_loop_plots import plot_cases
    from monoloc.sim.closed_loop_study import StudyConfig, run_study, serving
    from monoloc.sim.closed_loop_world import WorldSpec, build_loop_world

    started = time.time()
    out = args.out or Path(f"out/closed_loop_bench_{args.scenario}")
    world = build_loop_world(WorldSpec(args.scenario, args.size, args.seed))
    if args.scenario == "indoor":
        laps = args.laps or 3.0
        passes = args.passes or 1
        study = StudyConfig(laps=laps, offcenter_laps=2.0, seed=args.seed, passes=passes)
    else:  # a share of the route: map, off-center and query drives cover the same stretch
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
    # relative to the repository: a results file names no path outside it
    root = Path(__file__).resolve().parent.parent
    summary["plots"] = [
        str(Path(p).resolve().relative_to(root))
        if Path(p).resolve().is_relative_to(root)
        else Path(p).name
        for p in plots
    ]
    summary["total_s"] = time.time() - started
    path = RESULTS / f"closed_loop_{args.scenario}.json"
    path.write_text(json.dumps(summary, indent=2, default=float) + "\n")
    print(f"wrote {path} and {len(plots)} plots ({summary['total_s']:.0f} s)")


if __name__ == "__main__":
    main()
