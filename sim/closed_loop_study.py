"""The closed-loop study, end to end through a map server (docs/method.md section 10: the
paper's indoor closed-loop result).

1. Mapping laps on the centre line (open loop on the ground truth, camera + depth) are
   recorded in the TUM layout and uploaded as the map's ``map`` run; a training lap in
   the training room (with the steering disturbance, so it leaves the line) calibrates
   the measurement model.
2. Cases: ``open`` (the controller on the ground truth, monoloc only watching), ``closed``
   (the controller on monoloc's estimate, centre-line map), then the oscillating
   off-center laps (the steering disturbance) are uploaded as ``offcenter`` runs (tag
   ``off-center``) and ``closed+offcenter`` drives again.

The server is reached only over HTTP through ``monoloc.client``; ``serving`` starts one
(`monoloc serve` in a child process) when none is given.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monoloc.client.api import MonolocClient
from monoloc.client.motion import MotionConfig
from monoloc.client.particle_filter import FilterConfig
from monoloc.core.errors import InvalidInputError
from monoloc.sim.closed_loop import LoopConfig, LoopResult, run_loop
from monoloc.sim.closed_loop_metrics import SPIKE_FACTOR, loop_metrics
from monoloc.sim.closed_loop_record import make_recorder, run_archive, write_loop_outputs
from monoloc.sim.closed_loop_world import Lap

CASES = ("open", "closed", "closed+offcenter")
QUERY_LAP = Lap(room="main", variant=1, lighting_key=7)  # obstacles moved, other light
MAP_LAP = Lap(room="main", variant=0, lighting_key=1)
TRAIN_LAP = Lap(room="train", variant=0, lighting_key=3)
# The upload route does not derive tags from the run kind (`monoloc map ingest` does):
# the off-center tag is given explicitly.
OFFCENTER = {"kind": "offcenter", "tags": "off-center"}


@dataclass(frozen=True)
class StudyConfig:
    """laps: laps per driven case; map_laps / offcenter_laps / train_laps: laps recorded
    for the map, the augmentation and the calibration (0 train laps: the default
    measurement model); max_frames: cap per drive (short demo laps);
    recorded_latency: draw answer delays from the open-loop case's measured ones;
    passes: drives per case over the same ``laps`` (a route that is no loop is driven
    again from its start, with a fresh filter; the case's figures pool the passes)."""

    laps: float = 2.0
    map_laps: float = 1.0
    offcenter_laps: float = 2.0
    train_laps: float = 1.5
    max_frames: int | None = None
    seed: int = 0
    recorded_latency: bool = False
    cases: tuple[str, ...] = CASES
    passes: int = 1

    def __post_init__(self) -> None:
        bad = [c for c in self.cases if c not in CASES]
        if bad or not self.cases:
            raise InvalidInputError(f"cases must be among {CASES}, got {self.cases}")
        if "closed+offcenter" in self.cases and self.offcenter_laps <= 0:
            raise InvalidInputError("the closed+offcenter case needs offcenter_laps > 0")
        if self.passes < 1:
            raise InvalidInputError(f"passes must be at least 1, got {self.passes}")


@contextmanager
def serving(out_dir: Path, server: str | None = None, key: str | None = None) -> Iterator[tuple]:
    """(base URL, admin key) of ``server``, or of a `monoloc serve` started here with its
    own data folder under ``out_dir`` (stopped on exit)."""
    from monoloc import local_server

    if server:
        if not key:
            raise InvalidInputError("--server needs --key (a map:write or admin key)")
        yield server.rstrip("/"), key
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    port, admin = local_server.free_port(), local_server.new_admin_key()
    # A fresh data folder per start: a folder kept from an earlier run holds that run's
    # bootstrap key, and this start's key would be refused.
    stamp = time.strftime("%Y%m%d-%H%M%S")
    data_dir = out_dir / f"server-{stamp}"
    proc = local_server.start_server(data_dir, port, admin, out_dir / f"server-{stamp}.log")
    try:
        yield f"http://127.0.0.1:{port}", admin
    finally:
        local_server.stop_server(proc)


def filter_config_for(world) -> FilterConfig:
    """The particle filter for the world's vehicle: the camera's lever arm, and motion
    noise bounds a few times the measured signals' errors."""
    e = world.signal_errors
    v = 3.0 * (e.speed_noise_mps + e.speed_bias_mps) + 0.02 * world.reference_speed_mps
    g = 3.0 * (e.yaw_rate_noise_radps + e.yaw_rate_bias_radps) + 0.02
    return FilterConfig(
        motion=MotionConfig(
            speed_noise_mps=(-v, v), yaw_rate_noise_radps=(-g, g), lever_arm_m=world.lever_arm_m
        )
    )


def create_map(client: MonolocClient, world, name: str) -> int:
    k = world.calibrated_intrinsics
    camera = dict(fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy, width_px=k.width_px, height_px=k.height_px)
    return int(
        client.request("POST", "/v1/maps", json={"name": name, "camera": camera}).json()["id"]
    )


def record_lap(world, out_dir: Path, name: str, config: LoopConfig) -> tuple[Path, LoopResult]:
    """Drive and record a mapping lap (open loop, camera + depth) as a TUM run folder."""
    recorder = make_recorder(world, out_dir / name, f"monoloc sim closed-loop {name}")
    result = run_loop(world, config, sink=recorder, with_depth=True)
    return recorder.finish(result), result


def upload(client: MonolocClient, map_id: int, world, run_dir: Path, path: str, **fields) -> dict:
    """Upload a recorded run to ``path`` (runs or calibration jobs); wait for its job."""
    from monoloc import local_server

    archive, described = run_archive(world, run_dir, run_dir.with_suffix(".tar"))
    try:
        answer = local_server.upload_run(client, map_id, archive, path, **described, **fields)
    finally:
        archive.unlink(missing_ok=True)
    job_id = answer["job"]["id"] if "job" in answer else answer["id"]
    return local_server.wait_job(client, job_id, lambda _p: None)


@dataclass
class CaseResult:
    name: str
    result: LoopResult
    metrics: dict


def drive_case(
    client: MonolocClient,
    map_id: int,
    world,
    mode: str,
    study: StudyConfig,
    recorded_latency_ms: tuple[float, ...] | None = None,
    progress: Callable[[int, int], None] | None = None,
    record_dir: Path | None = None,
    seed: int | None = None,
    controller: str = "pid",
) -> LoopResult:
    """The localized drives of the query lap over HTTP (``mode`` open|closed), one per
    ``study.passes`` (concatenated, see ``concat_passes``); with ``record_dir``, each
    pass's frames are also written as a run (``record_dir``, then ``<record_dir>_pass2``,
    ...). ``seed`` (default ``study.seed``) draws the drive's noise; ``controller``
    pid|mpc steers it."""
    from monoloc.client.localizer import HttpLocalizer
    from monoloc.sim.closed_loop import concat_passes

    model, _ = client.measurement_model(map_id)
    results = []
    for index in range(study.passes):
        config = LoopConfig(
            mode=mode,
            laps=study.laps,
            max_frames=study.max_frames,
            lap=QUERY_LAP,
            recorded_latency_ms=recorded_latency_ms,
            seed=(study.seed if seed is None else seed) + 100 + 1000 * index,
            controller=controller,
        )
        recorder = None
        if record_dir is not None:
            run_dir = (
                record_dir
                if index == 0
                else record_dir.with_name(f"{record_dir.name}_pass{index + 1}")
            )
            recorder = make_recorder(world, run_dir, f"monoloc sim closed-loop {mode} drive")
        result = run_loop(
            world,
            config,
            localizer=HttpLocalizer(client, map_id),
            model=model,
            filter_config=filter_config_for(world),
            sink=recorder,
            progress=progress,
        )
        if recorder is not None:
            recorder.finish(result)
        results.append(result)
    return results[0] if len(results) == 1 else concat_passes(results)


def build_map(
    client: MonolocClient, world, study: StudyConfig, out_dir: Path, log=print
) -> tuple[int, dict]:
    """Create a map from centre-line mapping laps (and calibrate it); returns its id and
    what was recorded."""
    map_id = create_map(client, world, f"closed-loop-{world.name}-{time.strftime('%H%M%S')}")
    info: dict = {"map_id": map_id}
    run_dir, lap = record_lap(
        world, out_dir / "runs", "map", LoopConfig(mode="open", laps=study.map_laps, lap=MAP_LAP,
                                                   seed=study.seed + 1)
    )  # fmt: skip
    job = upload(client, map_id, world, run_dir, "/v1/maps/{map_id}/runs", kind="map")
    info["map_frames"] = lap.n_frames
    log(f"  map: {lap.n_frames} centre-line frames ingested (job {job['id']})")
    if study.train_laps > 0:
        train_cfg = LoopConfig(
            mode="open", laps=study.train_laps, disturbance=True, lap=TRAIN_LAP,
            seed=study.seed + 2,
        )  # fmt: skip
        run_dir, lap = record_lap(world, out_dir / "runs", "train", train_cfg)
        upload(client, map_id, world, run_dir, "/v1/maps/{map_id}/calibration/jobs")
        info["train_frames"] = lap.n_frames
        log(f"  calibrated on a {lap.n_frames}-frame training lap")
    return map_id, info


def add_offcenter(client, map_id, world, study: StudyConfig, out_dir: Path, log=print) -> dict:
    """Record the oscillating laps (steering disturbance) and ingest them as off-center."""
    config = LoopConfig(
        mode="open", laps=study.offcenter_laps, disturbance=True, lap=MAP_LAP,
        seed=study.seed + 3,
    )  # fmt: skip
    run_dir, lap = record_lap(world, out_dir / "runs", "offcenter", config)
    upload(client, map_id, world, run_dir, "/v1/maps/{map_id}/runs", **OFFCENTER)
    lateral = np.abs(lap.trace["lateral_m"])
    log(f"  +{lap.n_frames} off-center frames (lateral up to {lateral.max():.3f} m)")
    return {"offcenter_frames": lap.n_frames, "offcenter_lateral_max_m": float(lateral.max())}


def run_study(
    client: MonolocClient,
    world,
    study: StudyConfig,
    out_dir: Path,
    log=print,
    map_id: int | None = None,
) -> dict:
    """Map (unless ``map_id`` is given), then the cases in order; writes every drive's
    outputs under ``out_dir/<case>`` and returns the figures."""
    out_dir = Path(out_dir)
    info: dict = {}
    if map_id is None:
        map_id, info = build_map(client, world, study, out_dir, log)
    cases: dict[str, CaseResult] = {}
    open_p95 = None
    recorded = None
    for name in study.cases:
        if name == "closed+offcenter":
            info.update(add_offcenter(client, map_id, world, study, out_dir, log))
        mode = "open" if name == "open" else "closed"
        log(f"  driving: {name}")
        result = drive_case(
            client,
            map_id,
            world,
            mode,
            study,
            recorded if mode == "closed" else None,
            record_dir=out_dir / name.replace("+", "_") / "run",
        )
        if name == "open":
            lat = result.frames["latency_ms"]
            if study.recorded_latency:
                recorded = tuple(float(v) for v in lat[np.isfinite(lat)])
        metrics = loop_metrics(result)
        if name == "open" and metrics["loc_p95_m"] is not None:
            open_p95 = metrics["loc_p95_m"]
        cases[name] = CaseResult(name, result, metrics)
    for case in cases.values():
        if open_p95 is not None:
            case.metrics = loop_metrics(case.result, SPIKE_FACTOR * open_p95)
        write_loop_outputs(
            case.result, out_dir / case.name.replace("+", "_"), {"case": case.name, **case.metrics}
        )
    return {
        "scenario": world.name,
        "map": {**info, "map_id": map_id},
        "study": {k: v for k, v in vars(study).items()},
        "open_loop_p95_m": open_p95,
        "cases": {name: c.metrics for name, c in cases.items()},
        "_results": {name: c.result for name, c in cases.items()},
    }


def read_latencies(frames_csv: Path) -> tuple[float, ...]:
    """The measured round trips (ms) of an earlier drive's frames.csv."""
    import csv

    try:
        with open(frames_csv, newline="") as fh:
            values = [float(row["latency_ms"]) for row in csv.DictReader(fh)]
    except (OSError, KeyError, ValueError) as exc:
        raise InvalidInputError(f"cannot read latencies from {frames_csv}: {exc}") from exc
    values = [v for v in values if np.isfinite(v)]
    if not values:
        raise InvalidInputError(f"{frames_csv} holds no measured latency")
    return tuple(values)
