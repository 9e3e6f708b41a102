"""The waits a full lane gives shed requests, compared without the machine (issue 50, 5).

On the shared 2-core VM, ``bench/load.py``'s 3x / 5x phases of the same code differ
from run to run by more than two wait policies do (the other jobs take 1-1.5 cores). This
model runs the server's own ``Lane`` (``monoloc.server.api.admission``: its capacity, its
service-time average, its waits) on simulated time, with vehicles that honour the waits
through the vehicle library's own jitter (``monoloc.client.api.jittered_wait_s``, one rng
per vehicle):

- N vehicles at R Hz (N x R = the overload x the lane's capacity), each frame at the
  vehicle's own phase as in ``bench/load.py``; a frame inside the vehicle's hold is not
  sent (held); a sent frame finds the lane full (shed: the vehicle holds for the wait it
  is given, plus its jitter) or enters it;
- the lane's workers compute in arrival order, each frame the service time +-30 %; with
  ``--stall-s``, the machine computes nothing for that long every ``--stall-every-s``
  (what another job taking the cores does), and the lane's service time follows what
  it sees;
- the wait a shed frame is given: ``drain`` (the lane's drain time for every one, the
  server before 2026-12-02) or ``booked`` (``Lane.book_retry_ms``, the product: returns
  booked one service slot apart), and whether the vehicles lengthen it by the library's
  jitter: ``before`` (drain, no jitter: the baseline), ``drain+jitter``,
  ``booked+jitter`` (the product).

Printed per overload and policy: frames served (share of the lane's capacity), sent and
shed (multiples of the capacity), held, and sends per 50 ms (p50 / p99). What it leaves
out: the CPU each shed costs the server (0.2-0.4 ms, taken from the computations on a real
machine), so fewer sheds serve no more frames here. Usage:
    python -m bench.shed_model [--overloads 3 5] [--seconds 60] [--stall-s 0 0.3]
                               [--service-s 0.045]
Writes bench/results/shed_model.json (``--out``).
"""

from __future__ import annotations

import argparse
import heapq
import json
import math
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from monoloc.client.api import jittered_wait_s
from monoloc.server.api.admission import Lane, LaneConfig

RESULTS = Path(__file__).parent / "results"
# (the wait a shed frame is given, whether the vehicle adds the library's jitter)
POLICIES = {
    "before": ("drain", False),  # the system before 2026-12-02
    "drain+jitter": ("drain", True),  # the vehicle's jitter alone
    "booked+jitter": ("booked", True),  # the product
}


@dataclass(frozen=True)
class ModelConfig:
    """The lane and the fleet. Defaults: the bench replica (2 workers, 2 waiting, about
    44 frames/s on a quiet machine), vehicles at 10 Hz."""

    workers: int = 2
    queue_depth: int = 2
    service_s: float = 0.045
    rate_hz: float = 10.0
    seconds: float = 60.0
    stall_s: float = 0.0
    stall_every_s: float = 2.0
    seed: int = 0


def _finish_s(start_s: float, duration_s: float, cfg: ModelConfig) -> float:
    """When a computation of ``duration_s`` started at ``start_s`` ends, stalls included."""
    if cfg.stall_s <= 0:
        return start_s + duration_s
    end_s, t = start_s + duration_s, start_s
    while True:  # each stall [k * every - stall, k * every) the computation overlaps
        stall_at = (math.floor(t / cfg.stall_every_s) + 1) * cfg.stall_every_s - cfg.stall_s
        if stall_at >= end_s:
            return end_s
        end_s += max(0.0, min(cfg.stall_s, stall_at + cfg.stall_s - t))
        t = stall_at + cfg.stall_s


def simulate(policy: str, overload: float, cfg: ModelConfig) -> dict:
    """One run: the fleet offering ``overload`` x the lane's capacity for ``cfg.seconds``."""
    if policy not in POLICIES:
        raise ValueError(f"policy must be one of {list(POLICIES)}, got {policy!r}")
    waits, jittered = POLICIES[policy]
    lane = Lane("localize", LaneConfig(cfg.workers, cfg.queue_depth, default_deadline_ms=1000))
    for _ in range(20):  # its service-time average settled at the computations' mean
        lane.record_service_s(cfg.service_s)
    capacity_per_s = cfg.workers / cfg.service_s
    vehicles = max(1, math.ceil(overload * capacity_per_s / cfg.rate_hz))
    period_s = vehicles / (overload * capacity_per_s)
    rng = np.random.default_rng(cfg.seed)
    jitter = [np.random.default_rng(cfg.seed * 1000 + v) for v in range(vehicles)]
    hold_until_s = [-math.inf] * vehicles
    events = [(v / vehicles * period_s, 0, v, 0.0) for v in range(vehicles)]  # frames
    heapq.heapify(events)
    waiting: deque[float] = deque()
    busy = served = shed = held = 0
    sent_s: list[float] = []

    def start(now_s: float) -> None:
        duration_s = cfg.service_s * rng.uniform(0.7, 1.3)
        heapq.heappush(events, (_finish_s(now_s, duration_s, cfg), 1, -1, now_s))

    while events:
        now_s, kind, v, started_s = heapq.heappop(events)
        if now_s >= cfg.seconds:
            break
        if kind == 1:  # a computation ended
            served += 1
            lane.leave()
            lane.record_service_s(now_s - started_s)
            if waiting:
                waiting.popleft()
                start(now_s)
            else:
                busy -= 1
            continue
        heapq.heappush(events, (now_s + period_s, 0, v, 0.0))
        if now_s < hold_until_s[v]:
            held += 1
            continue
        sent_s.append(now_s)
        if not lane.try_enter():
            shed += 1
            wait_s = (
                lane.retry_after_ms() if waits == "drain" else lane.book_retry_ms(now_s)
            ) / 1e3
            hold_until_s[v] = now_s + (jittered_wait_s(wait_s, jitter[v]) if jittered else wait_s)
            continue
        if busy < cfg.workers:
            busy += 1
            start(now_s)
        else:
            waiting.append(now_s)
    per_50ms = np.histogram(sent_s, bins=np.arange(0.0, cfg.seconds + 1e-9, 0.05))[0]
    return {
        "policy": policy,
        "overload": overload,
        "vehicles": vehicles,
        "served_share": served / cfg.seconds / capacity_per_s,
        "sent_over_capacity": len(sent_s) / cfg.seconds / capacity_per_s,
        "shed_over_capacity": shed / cfg.seconds / capacity_per_s,
        "held": held,
        "sent_per_50ms_p50": float(np.percentile(per_50ms, 50)),
        "sent_per_50ms_p99": float(np.percentile(per_50ms, 99)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--overloads", type=float, nargs="+", default=[3.0, 5.0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--stall-s", type=float, nargs="+", default=[0.0, 0.3])
    parser.add_argument("--stall-every-s", type=float, default=2.0)
    parser.add_argument(
        "--service-s", type=float, nargs="+", default=[0.045], help="one computation (s)"
    )
    parser.add_argument("--out", type=Path, default=RESULTS / "shed_model.json")
    args = parser.parse_args()
    if args.seconds <= 0 or args.stall_every_s <= max(args.stall_s) or min(args.stall_s) < 0:
        raise SystemExit("error: --seconds > 0 and 0 <= --stall-s < --stall-every-s")
    if min(args.service_s) <= 0:
        raise SystemExit("error: --service-s must be > 0")
    rows = []
    for service_s, stall_s in ((a, b) for a in args.service_s for b in args.stall_s):
        cfg = ModelConfig(
            service_s=service_s,
            seconds=args.seconds,
            stall_s=stall_s,
            stall_every_s=args.stall_every_s,
        )
        for overload in args.overloads:
            for policy in POLICIES:
                row = {"service_s": service_s, "stall_s": stall_s}
                row.update(simulate(policy, overload, cfg))
                rows.append(row)
                print(
                    f"service {1000 * service_s:.0f} ms, stall {stall_s:.1f} s / "
                    f"{args.stall_every_s:g} s, {overload:g}x "
                    f"({row['vehicles']} vehicles) {policy:13s}: served "
                    f"{100 * row['served_share']:.0f} % of capacity, sent "
                    f"{row['sent_over_capacity']:.2f}x, shed {row['shed_over_capacity']:.2f}x, "
                    f"held {row['held']}, sent per 50 ms p50 {row['sent_per_50ms_p50']:.0f} / "
                    f"p99 {row['sent_per_50ms_p99']:.0f}",
                    flush=True,
                )
    out = {"config": asdict(ModelConfig(seconds=args.seconds)), "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
