"""The MPC's solve time per step on one core, against the 100 ms a 10 Hz controller has,
with the PID's time per command as the baseline measured in the same run.

The indoor 1:10 car drives ``--laps`` of the small track's centre line on a believed pose
that is the truth plus a localization-like error (a random walk of ``--pose-noise-m``
per frame, re-centred whenever an estimate would arrive), while the quality handed to
the MPC alternates between sure and lost every ``--quality-period-s`` (so the view term
switches on and off, as on the featureless stretch). Both controllers drive the same
lap; per MPC solve the wall and CPU time (p50 / p99 / max), the SQP's failures, and
each controller's wall and CPU time per command and lateral tracking error on the truth
are reported, with the load average before and after each drive (other processes
stretch the wall times, not the CPU times). The process is pinned to one core
(``os.sched_setaffinity``). Writes bench/results/mpc.json.

``--closed-loop``: also short closed-loop drives through a map server started here (the
small indoor track mapped by one centre-line lap, the measurement model calibrated on
``--train-laps``), PID and MPC on the same map and query lap, one drive each per seed of
``--drive-seeds``, every answer delayed by ``--latency-ms`` (a fixed delay below the
frame period, so that the load of the machine does not decide which frames are sent);
their localization and tracking errors side by side under "closed_loop", per seed and
their means (the server and the drives share the cores: the solve-time figures come
from the first part). Without it, the JSON keeps the last run's "closed_loop" (dated).

    python -m bench.mpc --laps 2
    python -m bench.mpc --closed-loop --drive-laps 0.5 --drive-seeds 3
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path

import numpy as np

from monoloc.sim.closed_loop import make_controller
from monoloc.sim.closed_loop_world import IndoorLoopWorld, WorldSpec, build_loop_world
from monoloc.sim.control import step_bicycle, tracking_error
from monoloc.sim.mpc import LocalizationQuality, MpcController

RESULTS = Path(__file__).parent / "results"
BUDGET_MS = 100.0  # one period of a 10 Hz controller
SURE = LocalizationQuality(0.003, math.radians(0.3), 0.55)
LOST = LocalizationQuality(0.03, math.radians(3.0), 0.0)


def drive(world, name: str, laps: float, pose_noise_m: float, quality_period_s: float, rng):
    """One drive of ``laps``: (per-command wall times s, per-command CPU times s, solve
    wall times s, solve CPU times s (both empty for the PID), lateral errors on the truth
    m, solver failures)."""
    path = world.reference_path(laps)
    controller = make_controller(name, world, path)
    state = world.start_state(path)
    dt, frame_s = world.dt_s, 1.0 / world.frame_rate_hz
    offset = np.zeros(3)
    command_s, command_cpu_s, lateral = [], [], []
    t, next_frame, hint = 0.0, 0.0, 0
    while not controller.at_end:
        if t >= next_frame:
            # The believed pose's error walks between estimates, as the filter's does.
            offset += rng.normal(scale=[pose_noise_m, pose_noise_m, pose_noise_m / 0.5])
            offset *= 0.8
            next_frame += frame_s
            if isinstance(controller, MpcController):
                lost = int(t / quality_period_s) % 2 == 1
                controller.set_quality(LOST if lost else SURE)
        started, started_cpu = time.perf_counter(), time.thread_time()
        command, _ = controller.command(
            t,
            state.x_m + offset[0],
            state.y_m + offset[1],
            state.yaw_rad + offset[2],
            state.speed_mps,
            dt,
        )
        command_s.append(time.perf_counter() - started)
        command_cpu_s.append(time.thread_time() - started_cpu)
        err = tracking_error(path, state.x_m, state.y_m, state.yaw_rad, hint)
        hint = err.index
        lateral.append(err.lateral_m)
        state = step_bicycle(state, command, world.bicycle, dt)
        t += dt
        if hint >= len(path.s_m) - 2:
            break
    is_mpc = isinstance(controller, MpcController)
    solves = controller.solve_times_s if is_mpc else []
    solves_cpu = controller.solve_cpu_s if is_mpc else []
    failures = controller.failed_solves if is_mpc else 0
    return (
        np.array(command_s),
        np.array(command_cpu_s),
        np.array(solves),
        np.array(solves_cpu),
        np.array(lateral),
        failures,
    )


def _ms(values_s: np.ndarray) -> dict:
    ms = 1e3 * values_s
    return {
        "p50_ms": float(np.percentile(ms, 50)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(np.max(ms)),
        "n": len(ms),
    }


CLOSED_LOOP_FIGURES = (
    "frames",
    "loc_rmse_m",
    "loc_p95_m",
    "loc_max_m",
    "lateral_rmse_m",
    "lateral_max_m",
    "heading_rmse_deg",
    "lane_departures",
    "hypotheses_share",
    "known_share_mean",
    "dead_reckoning_intervals",
    "frames_not_sent",
    "wall_s",
)


def closed_loop(
    seed: int,
    drive_laps: float,
    train_laps: float,
    frames: int | None,
    out_dir: Path,
    drive_seeds: int = 1,
    latency_ms: float = 30.0,
) -> dict:
    """PID and MPC, closed-loop drives on the same fresh map (see the module docstring):
    per controller and seed the loop's figures (and the MPC's quality q), and the means
    over the seeds."""
    from dataclasses import replace

    from monoloc.client.api import MonolocClient
    from monoloc.sim.closed_loop_metrics import loop_metrics
    from monoloc.sim.closed_loop_study import StudyConfig, build_map, drive_case, serving

    world = build_loop_world(WorldSpec("indoor", "small", seed))
    study = StudyConfig(
        laps=drive_laps,
        map_laps=1.0,
        offcenter_laps=0.0,
        train_laps=train_laps,
        max_frames=frames,
        seed=seed,
        cases=("closed",),
    )
    out: dict = {
        "date": time.strftime("%Y-%m-%d"),
        "drive_laps": drive_laps,
        "train_laps": train_laps,
        "max_frames": frames,
        "latency_ms": latency_ms,
        "drive_seeds": [seed + k for k in range(drive_seeds)],
        "per_seed": {"pid": [], "mpc": []},
    }
    with serving(out_dir) as (url, key):
        with MonolocClient(url, key, timeout_s=120.0) as client:
            started = time.perf_counter()
            map_id, info = build_map(client, world, study, out_dir, log=print)
            out["map"] = {"map_frames": info.get("map_frames"), "s": time.perf_counter() - started}
            for drive_seed in out["drive_seeds"]:
                for name in ("pid", "mpc"):
                    result = drive_case(
                        client,
                        map_id,
                        world,
                        "closed",
                        replace(study, seed=drive_seed),
                        (latency_ms,),
                        controller=name,
                    )
                    metrics = loop_metrics(result)
                    row = {k: metrics[k] for k in CLOSED_LOOP_FIGURES if k in metrics}
                    row["seed"] = drive_seed
                    std = result.frames["filter_std"]
                    row["filter_position_std_median_m"] = float(np.nanmedian(std[:, 0]))
                    row["filter_yaw_std_median_deg"] = float(np.degrees(np.nanmedian(std[:, 1])))
                    if name == "mpc":
                        q = result.frames["mpc_quality"]
                        row["mpc_quality_mean"] = float(np.nanmean(q))
                        row["mpc_quality_min"] = float(np.nanmin(q))
                    out["per_seed"][name].append(row)
                    print(f"  seed {drive_seed} {name}: {json.dumps(row, default=float)}")
    for name, rows in out["per_seed"].items():
        out[name] = {
            k: float(np.mean([r[k] for r in rows]))
            for k in rows[0]
            if k != "seed" and isinstance(rows[0][k], (int, float))
        }
    return out


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--laps", type=float, default=2.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pose-noise-m", type=float, default=0.003)
    parser.add_argument("--quality-period-s", type=float, default=3.0)
    parser.add_argument("--core", type=int, default=None, help="CPU to pin to (default: last)")
    parser.add_argument("--closed-loop", action="store_true", help="also drive PID and MPC")
    parser.add_argument("--drive-laps", type=float, default=0.5)
    parser.add_argument("--train-laps", type=float, default=1.5)
    parser.add_argument("--frames", type=int, default=None, help="cap per closed-loop drive")
    parser.add_argument("--drive-seeds", type=int, default=3, help="closed-loop drives each")
    parser.add_argument("--latency-ms", type=float, default=30.0, help="each answer's delay")
    parser.add_argument("--out", type=Path, default=Path("out/bench_mpc"))
    args = parser.parse_args(argv)
    cores = sorted(os.sched_getaffinity(0))
    core = cores[-1] if args.core is None else args.core
    os.sched_setaffinity(0, {core})
    world = IndoorLoopWorld("small", seed=args.seed)
    out: dict = {
        "scenario": "indoor small track, truth + localization-like pose error",
        "laps": args.laps,
        "seed": args.seed,
        "pose_noise_m": args.pose_noise_m,
        "quality_period_s": args.quality_period_s,
        "pinned_core": core,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "budget_ms": BUDGET_MS,
        "date": time.strftime("%Y-%m-%d"),
        "controllers": {},
    }
    for name in ("pid", "mpc"):
        rng = np.random.default_rng([args.seed, 51])
        load_before = os.getloadavg()[0]
        started = time.perf_counter()
        command_s, command_cpu_s, solve_s, solve_cpu_s, lateral, failures = drive(
            world, name, args.laps, args.pose_noise_m, args.quality_period_s, rng
        )
        row = {
            "command": _ms(command_s),
            "command_cpu": _ms(command_cpu_s),
            "load_average_1min": {"before": load_before, "after": os.getloadavg()[0]},
            "lateral_rmse_m": float(np.sqrt(np.mean(lateral**2))),
            "lateral_max_m": float(np.max(np.abs(lateral))),
            "wall_s": time.perf_counter() - started,
        }
        if len(solve_s):
            row["solve"] = _ms(solve_s)
            row["solve_cpu"] = _ms(solve_cpu_s)
            row["solver_failures"] = int(failures)
        out["controllers"][name] = row
    # Other processes on the machine stretch the wall times, not the CPU times.
    out["load_average_1min"] = os.getloadavg()[0]
    mpc = out["controllers"]["mpc"]
    out["meets_budget"] = mpc["solve"]["max_ms"] <= BUDGET_MS
    out["meets_budget_cpu"] = mpc["solve_cpu"]["max_ms"] <= BUDGET_MS
    print(f"{'per step, one core':<34}{'p50 ms':>10}{'p99 ms':>10}{'max ms':>10}{'n':>8}")
    pid = out["controllers"]["pid"]
    for label, row in (
        ("MPC solve (10 Hz re-plan), wall", mpc["solve"]),
        ("MPC solve, CPU time", mpc["solve_cpu"]),
        ("MPC command (every 5 ms step)", mpc["command"]),
        ("MPC command, CPU time", mpc["command_cpu"]),
        ("PID command (baseline), wall", pid["command"]),
        ("PID command, CPU time", pid["command_cpu"]),
    ):
        print(
            f"{label:<34}{row['p50_ms']:>10.3f}{row['p99_ms']:>10.3f}"
            f"{row['max_ms']:>10.3f}{row['n']:>8d}"
        )
    loads = {n: r["load_average_1min"] for n, r in out["controllers"].items()}
    print(
        "load average (1 min) before/after: "
        + ", ".join(f"{n} {v['before']:.1f}/{v['after']:.1f}" for n, v in loads.items())
    )
    print(
        f"budget {BUDGET_MS:.0f} ms per 10 Hz step: wall "
        f"{'met' if out['meets_budget'] else 'MISSED'}, CPU "
        f"{'met' if out['meets_budget_cpu'] else 'MISSED'}; SQP failures "
        f"{mpc['solver_failures']}"
    )
    for name, row in out["controllers"].items():
        print(
            f"{name}: lateral RMSE {1e3 * row['lateral_rmse_m']:.2f} mm, "
            f"max {1e3 * row['lateral_max_m']:.2f} mm on the truth"
        )
    if args.closed_loop:
        os.sched_setaffinity(0, set(cores))  # the server and the drive: every core
        out["closed_loop"] = closed_loop(
            args.seed,
            args.drive_laps,
            args.train_laps,
            args.frames,
            args.out,
            args.drive_seeds,
            args.latency_ms,
        )
        n = args.drive_seeds
        print(f"closed loop, means over {n} seed(s):")
        print(f"{'':<12}{'loc RMSE mm':>12}{'lat RMSE mm':>12}{'lat max mm':>12}")
        for name in ("pid", "mpc"):
            row = out["closed_loop"][name]
            print(
                f"{name:<12}{1e3 * row['loc_rmse_m']:>12.2f}{1e3 * row['lateral_rmse_m']:>12.2f}"
                f"{1e3 * row['lateral_max_m']:>12.2f}"
            )
    RESULTS.mkdir(exist_ok=True)
    previous = RESULTS / "mpc.json"
    if not args.closed_loop and previous.exists():
        # Keep the last closed-loop comparison (its own date says when it ran).
        earlier = json.loads(previous.read_text()).get("closed_loop")
        if earlier is not None:
            out["closed_loop"] = earlier
    (RESULTS / "mpc.json").write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    main()
