"""The waits a full lane gives shed requests, compared without the machine (issue 50, 5).

On the shared 2-core VM, ``bench/load.py``'s 3x / 5x phases of the same code differ
from run to run by more than two wait policies do (the other jobs take 1-1.5 cores). This
model runs the server's own ``Lane`` (``monoloc.server.api.admission``: its capacity, its
service-time average, its booked waits) on simulated time, with vehicles that honour the
waits through the vehicle library's own rule (``monoloc.client.localizer.FrameHold``, one
rng per vehicle) or an earlier one:

- N vehicles at R Hz (N x R = the overload x the lane's capacity), each frame at the
  vehicle's own phase as in ``bench/load.py``; a vehicle that honours the waits sends
  one frame at a time, as the library does (a frame taken while its previous one is
  unanswered is not sent: busy), and not the frames of its hold (held); a sent frame
  finds the lane full (shed, answered at once) or takes a place in it;
- a request holds its place ``--pre-s`` (on average, exponentially distributed) before
  its computation queues (its body read and parsed: 10-37 ms at the median, in a trace
  of the real server on the loaded VM) and ``--post-s`` after it (the answer sent);
- the lane's workers compute in arrival order, each frame the service time +-30 %; with
  ``--stall-s``, the machine computes nothing for that long every ``--stall-every-s``
  (what another job taking the cores does), and the lane's service time follows what
  it sees;
- the policies (``POLICIES``): ``every-frame`` (vehicles that ignore the waits),
  ``before`` (the drain time for every shed, the vehicle back on the first frame after
  it: the system before 2026-12-02), ``drain+jitter`` (the same, the wait jittered),
  ``booked+jitter`` (returns booked one slot apart over up to 60 slots, first frame
  after the jittered wait: 2026-12-02), ``product`` (booked over the lane's default
  ``return_spread_s``, the vehicle's ``FrameHold``: back on the frame nearest the
  jittered wait).

Printed per overload and policy: frames served (share of the lane's capacity), the
workers' time idle while the lane had a place free, sent and shed (multiples of the
capacity), held, busy, the waits given (p50 / p90, share over one frame period). What it
leaves out: the CPU each shed costs the server (0.2-0.4 ms, taken from the computations
on a real machine), so fewer sheds serve no more frames here. Usage:
    python -m bench.shed_model [--overloads 3 5] [--seconds 60] [--stall-s 0 0.3]
                               [--service-s 0.045] [--pre-s 0 0.03] [--post-s 0.005]
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
from monoloc.client.localizer import FrameHold
from monoloc.server.api.admission import Lane, LaneConfig

RESULTS = Path(__file__).parent / "results"


@dataclass(frozen=True)
class Policy:
    """What a shed frame is told and what its vehicle does with it. ``waits``: ``ignored``
    (the vehicle sends every frame), ``drain`` (the lane's drain time for every shed) or
    ``booked`` (``Lane.book_retry_ms`` with the lane's ``return_spread_s``); ``vehicle``:
    ``first-after`` (back on the first frame after the wait, jittered or not) or
    ``nearest`` (the library's ``FrameHold``: jittered, back on the nearest frame)."""

    waits: str
    spread_s: float = math.inf
    vehicle: str = "first-after"
    jitter: bool = False


POLICIES = {
    "every-frame": Policy("ignored"),  # vehicles that send every frame, waits or not
    "before": Policy("drain"),  # the system before 2026-12-02
    "drain+jitter": Policy("drain", jitter=True),  # the vehicle's jitter alone
    "booked+jitter": Policy("booked", jitter=True),  # 2026-12-02: 60 slots, frame after
    # the product: returns spread over the lane's default, the vehicle's FrameHold
    "product": Policy("booked", LaneConfig(1, 0, 1).return_spread_s, "nearest", True),
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
    # a request's place in the lane before its computation queues (its body read and
    # parsed; the mean of an exponential) and after it (the answer sent and read): the
    # lane holds it, no worker does
    pre_s: float = 0.0
    post_s: float = 0.0
    max_in_flight: int = 4  # a vehicle that sends every frame: its connections


FRAME, QUEUED, DONE, ANSWERED = 3, 2, 0, 1  # event kinds; at one instant a place frees first


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
    rule = POLICIES[policy]
    honours = rule.waits != "ignored"
    lane_cfg = LaneConfig(cfg.workers, cfg.queue_depth, 1000, return_spread_s=rule.spread_s)
    lane = Lane("localize", lane_cfg)
    for _ in range(20):  # its service-time average settled at the computations' mean
        lane.record_service_s(cfg.service_s)
    capacity_per_s = cfg.workers / cfg.service_s
    vehicles = max(1, math.ceil(overload * capacity_per_s / cfg.rate_hz))
    period_s = vehicles / (overload * capacity_per_s)
    rng = np.random.default_rng(cfg.seed)
    jitter = [np.random.default_rng(cfg.seed * 1000 + v) for v in range(vehicles)]
    holds = [FrameHold(jitter[v]) for v in range(vehicles)]  # the library's rule
    hold_until_s = [-math.inf] * vehicles  # the first-after rule's
    in_flight = [0] * vehicles
    # (time, kind, vehicle, started): a frame taken, a body read (the request queues for
    # a worker), a computation done, the answer at the vehicle (its place in the lane free)
    events = [(v / vehicles * period_s, FRAME, v, 0.0) for v in range(vehicles)]
    heapq.heapify(events)
    waiting: deque[int] = deque()
    busy = served = shed = held = skipped = 0
    sent_s: list[float] = []
    waits_s: list[float] = []
    idle_free_s = 0.0  # worker-seconds idle while the lane had a place free
    last_s = 0.0

    def start(now_s: float, v: int) -> None:
        duration_s = cfg.service_s * rng.uniform(0.7, 1.3)
        heapq.heappush(events, (_finish_s(now_s, duration_s, cfg), DONE, v, now_s))

    def holding(v: int, now_s: float) -> bool:
        if rule.vehicle == "nearest":
            return not holds[v].send(now_s)
        return now_s < hold_until_s[v]

    while events:
        now_s, kind, v, started_s = heapq.heappop(events)
        if now_s >= cfg.seconds:
            break
        if lane.inside < lane.capacity:
            idle_free_s += (cfg.workers - busy) * (now_s - last_s)
        last_s = now_s
        if kind == DONE:
            served += 1
            lane.record_service_s(now_s - started_s)
            heapq.heappush(events, (now_s + cfg.post_s, ANSWERED, v, 0.0))
            if waiting:
                start(now_s, waiting.popleft())
            else:
                busy -= 1
        elif kind == ANSWERED:
            lane.leave()
            in_flight[v] -= 1
        elif kind == QUEUED:
            if busy < cfg.workers:
                busy += 1
                start(now_s, v)
            else:
                waiting.append(v)
        else:  # a frame
            heapq.heappush(events, (now_s + period_s, FRAME, v, 0.0))
            if honours and holding(v, now_s):
                held += 1
            elif in_flight[v] >= (1 if honours else cfg.max_in_flight):
                skipped += 1  # its previous frame still unanswered (busy)
            elif not lane.try_enter():
                sent_s.append(now_s)
                shed += 1
                ms = lane.book_retry_ms(now_s) if rule.waits == "booked" else lane.retry_after_ms()
                waits_s.append(ms / 1e3)
                if rule.vehicle == "nearest":
                    holds[v].shed(now_s, ms / 1e3)
                else:
                    wait_s = jittered_wait_s(ms / 1e3, jitter[v]) if rule.jitter else ms / 1e3
                    hold_until_s[v] = now_s + wait_s
            else:
                sent_s.append(now_s)
                in_flight[v] += 1
                pre_s = rng.exponential(cfg.pre_s) if cfg.pre_s > 0 else 0.0
                heapq.heappush(events, (now_s + pre_s, QUEUED, v, 0.0))
    per_50ms = np.histogram(sent_s, bins=np.arange(0.0, cfg.seconds + 1e-9, 0.05))[0]
    waits = np.array(waits_s) if waits_s else np.zeros(1)
    return {
        "policy": policy,
        "overload": overload,
        "vehicles": vehicles,
        "served_share": served / cfg.seconds / capacity_per_s,
        "sent_over_capacity": len(sent_s) / cfg.seconds / capacity_per_s,
        "shed_over_capacity": shed / cfg.seconds / capacity_per_s,
        "held": held,
        "busy": skipped,
        "idle_with_free_place_share": idle_free_s / (cfg.workers * cfg.seconds),
        "wait_p50_ms": float(np.percentile(waits, 50)) * 1e3,
        "wait_p90_ms": float(np.percentile(waits, 90)) * 1e3,
        "wait_over_period_share": float(np.mean(waits > period_s)),
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
    parser.add_argument(
        "--pre-s",
        type=float,
        nargs="+",
        default=[0.0, 0.03],
        help="mean time a request holds its place before its computation queues (s)",
    )
    parser.add_argument("--post-s", type=float, default=0.005, help="after it (s)")
    parser.add_argument("--out", type=Path, default=RESULTS / "shed_model.json")
    args = parser.parse_args()
    if args.seconds <= 0 or args.stall_every_s <= max(args.stall_s) or min(args.stall_s) < 0:
        raise SystemExit("error: --seconds > 0 and 0 <= --stall-s < --stall-every-s")
    if min(args.service_s) <= 0 or min(args.pre_s) < 0 or args.post_s < 0:
        raise SystemExit("error: --service-s must be > 0, --pre-s and --post-s >= 0")
    rows = []
    grid = [(a, b, c) for a in args.service_s for b in args.stall_s for c in args.pre_s]
    for service_s, stall_s, pre_s in grid:
        cfg = ModelConfig(
            service_s=service_s,
            seconds=args.seconds,
            stall_s=stall_s,
            stall_every_s=args.stall_every_s,
            pre_s=pre_s,
            post_s=args.post_s,
        )
        for overload in args.overloads:
            for policy in POLICIES:
                row = {"service_s": service_s, "stall_s": stall_s, "pre_s": pre_s}
                row.update(simulate(policy, overload, cfg))
                rows.append(row)
                print(
                    f"service {1000 * service_s:.0f} ms, stall {stall_s:.1f} s / "
                    f"{args.stall_every_s:g} s, place before {1000 * pre_s:.0f} ms, "
                    f"{overload:g}x ({row['vehicles']} vehicles) {policy:13s}: served "
                    f"{100 * row['served_share']:.1f} % of capacity (idle with a place free "
                    f"{100 * row['idle_with_free_place_share']:.1f} %), sent "
                    f"{row['sent_over_capacity']:.2f}x, shed {row['shed_over_capacity']:.2f}x, "
                    f"held {row['held']}, busy {row['busy']}, waits p50 "
                    f"{row['wait_p50_ms']:.0f} / p90 {row['wait_p90_ms']:.0f} ms "
                    f"({100 * row['wait_over_period_share']:.0f} % over a frame period)",
                    flush=True,
                )
    out = {
        "config": asdict(ModelConfig(seconds=args.seconds, post_s=args.post_s)),
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
