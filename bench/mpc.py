"""The MPC's solve time per step on one core, against the 100 ms a 10 Hz controller has,
with the PID's time per command as the baseline measured in the same run.

The indoor 1:10 car drives ``--laps`` of the small track's centre line on a believed pose
that is the truth plus a localization-like error (a random walk of ``--pose-noise-m``
per frame, re-centred whenever an estimate would arrive), while the quality handed to
the MPC alternates between sure and lost every ``--quality-period-s`` (so the view term
switches on and off, as on the featureless stretch). Both controllers drive the same
lap; per MPC solve the wall time (p50 / p99 / max), the SQP's failures, and each
controller's time per command and lateral tracking error on the truth are reported.
The process is pinned to one core (``os.sched_setaffinity``). Writes
bench/results/mpc.json.

    python -m bench.mpc --laps 2
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
from monoloc.sim.closed_loop_world import IndoorLoopWorld
from monoloc.sim.control import step_bicycle, tracking_error
from monoloc.sim.mpc import LocalizationQuality, MpcController

RESULTS = Path(__file__).parent / "results"
BUDGET_MS = 100.0  # one period of a 10 Hz controller
SURE = LocalizationQuality(0.003, math.radians(0.3), 0.55)
LOST = LocalizationQuality(0.03, math.radians(3.0), 0.0)


def drive(world, name: str, laps: float, pose_noise_m: float, quality_period_s: float, rng):
    """One drive of ``laps``: (per-command wall times s, solve wall times s, solve CPU
    times s (both empty for the PID), lateral errors on the truth m, solver failures)."""
    path = world.reference_path(laps)
    controller = make_controller(name, world, path)
    state = world.start_state(path)
    dt, frame_s = world.dt_s, 1.0 / world.frame_rate_hz
    offset = np.zeros(3)
    command_s, lateral = [], []
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
        started = time.perf_counter()
        command, _ = controller.command(
            t,
            state.x_m + offset[0],
            state.y_m + offset[1],
            state.yaw_rad + offset[2],
            state.speed_mps,
            dt,
        )
        command_s.append(time.perf_counter() - started)
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


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--laps", type=float, default=2.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pose-noise-m", type=float, default=0.003)
    parser.add_argument("--quality-period-s", type=float, default=3.0)
    parser.add_argument("--core", type=int, default=None, help="CPU to pin to (default: last)")
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
        "machine": f"{platform.system()} {platform.machine()}, {os.cpu_count()} cores",
        "budget_ms": BUDGET_MS,
        "date": time.strftime("%Y-%m-%d"),
        "controllers": {},
    }
    for name in ("pid", "mpc"):
        rng = np.random.default_rng([args.seed, 51])
        started = time.perf_counter()
        command_s, solve_s, solve_cpu_s, lateral, failures = drive(
            world, name, args.laps, args.pose_noise_m, args.quality_period_s, rng
        )
        row = {
            "command": _ms(command_s),
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
    print(f"{'per step, one core':<34}{'p50 ms':>10}{'p99 ms':>10}{'max ms':>10}{'n':>8}")
    for label, row in (
        ("MPC solve (10 Hz re-plan)", mpc["solve"]),
        ("MPC solve, CPU time", mpc["solve_cpu"]),
        ("MPC command (every 5 ms step)", mpc["command"]),
        ("PID command (baseline)", out["controllers"]["pid"]["command"]),
    ):
        print(
            f"{label:<34}{row['p50_ms']:>10.3f}{row['p99_ms']:>10.3f}"
            f"{row['max_ms']:>10.3f}{row['n']:>8d}"
        )
    print(
        f"budget {BUDGET_MS:.0f} ms per 10 Hz step: "
        f"{'met' if out['meets_budget'] else 'MISSED'}; SQP failures {mpc['solver_failures']}"
    )
    for name, row in out["controllers"].items():
        print(
            f"{name}: lateral RMSE {1e3 * row['lateral_rmse_m']:.2f} mm, "
            f"max {1e3 * row['lateral_max_m']:.2f} mm on the truth"
        )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "mpc.json").write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    main()
