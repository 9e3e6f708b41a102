"""Does a measurement model calibrated on one street transfer to another? (issue 47)

A matrix of training environments x test environments. A training environment is a
``train`` run generated on its own (its poses in its own world frame, as a KITTI
sequence's): the city's training loop as the sim drives it by default, a short straight
street of another district under another exposure and palette, a straight highway at
25-30 m/s recorded at 5 Hz. A test environment is a city's ``map`` (entries thinned to
one every ``spacing_m``) and ``query`` runs. Per cell, in the same run:

- the filter's position RMSE with each model of ``VARIANTS`` (the model calibrated on the
  training environment, then transformed: "calibrated" itself, "default" the
  uncalibrated ``MeasurementModel()``, "vehicle frame", "relative e_vlad");
- the RMSE of the frames' own joint poses (each query frame localized without a prior:
  its joint pose, else its likeliest (most-inlier) hypothesis), per test environment;
- the calibration's e_vlad mean / std (mu2[0], Sigma2[0, 0]) beside the e_vlad of the
  test map's accepted hypotheses.

Goal per cell: the calibrated filter within 1.2x its joint poses' RMSE and never worse
than the default model. Writes bench/results/transfer.json.
Usage: python -m bench.transfer [--size small] [--frames 120] [--scale 1.0] [--data bench/data]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from bench.accuracy import RESULTS, calibrate_on, limit_threads, sequence_of
from monoloc.core.measurement import MeasurementModel
from monoloc.sim.generate import GenerateConfig
from monoloc.sim.urban.city import CityConfig
from monoloc.sim.urban.runs import TrainRunConfig

GOAL_JOINT_RATIO = 1.2

# A model variant: the calibrated model in, the model the filter runs with out.
VARIANTS: dict[str, Callable[[MeasurementModel], MeasurementModel]] = {
    "calibrated": lambda model: model,
    "default": lambda model: MeasurementModel(),
    "vehicle frame": lambda model: replace(model, retrieval_frame="vehicle"),
    # the relative-e_vlad retrieval term (MeasurementModel.vlad_evidence); further retrieval
    # terms plug in here as one more entry
    "relative e_vlad": lambda model: replace(model, vlad_evidence="relative"),
}


@dataclass(frozen=True)
class TrainEnv:
    """A training run generated alone: the city's seed, its training-run options and the
    training district's layout (``CityConfig.train_blocks``, ``train_seed``)."""

    seed: int
    run: TrainRunConfig | None = None
    train_blocks: tuple[int, int] = (2, 2)
    train_seed: int | None = None

    def generate_config(self, frames: int, scale: float) -> GenerateConfig:
        city = replace(
            CityConfig.preset("small"), train_blocks=self.train_blocks, train_seed=self.train_seed
        )
        return GenerateConfig(
            seed=self.seed,
            runs=("train",),
            max_frames=frames,
            image_scale=scale,
            city=city,
            train_run=self.run,
            workers=2,
        )


@dataclass(frozen=True)
class TestEnv:
    """A city's map and query runs; the map holds an entry every ``spacing_m``."""

    seed: int
    spacing_m: float
    size: str = "small"
    config: dict = field(default_factory=dict)  # further GenerateConfig fields

    def generate_config(self, frames: int, scale: float) -> GenerateConfig:
        return GenerateConfig(
            size=self.size,
            seed=self.seed,
            runs=("map", "query"),
            max_frames=frames,
            image_scale=scale,
            workers=2,
            **self.config,
        )


TRAIN_ENVS = {
    # the sim as before: the test city's own training district, driven in loops, by day
    "own city's training loop": TrainEnv(seed=4721),
    "short straight street, other district, -1 EV, other palette": TrainEnv(
        seed=4721,
        run=TrainRunConfig(route="straight", length_m=120.0, exposure_ev=-1.0, material_gain=0.3),
        train_seed=9001,
    ),
    "highway: straight, 25-30 m/s, 5 Hz": TrainEnv(
        seed=4721,
        run=TrainRunConfig(route="straight", speed_mps=(25.0, 30.0), frame_period_s=0.2),
        train_blocks=(6, 1),
        train_seed=9002,
    ),
}
TEST_ENVS = {
    "city 4721, entry every 1 m": TestEnv(seed=4721, spacing_m=1.0),
    "city 5303, entry every 2.5 m": TestEnv(seed=5303, spacing_m=2.5),
}


def ensure(root: Path, config: GenerateConfig) -> None:
    from monoloc.sim.generate import generate_dataset

    if (root / "dataset.json").exists():
        return
    print(f"generating {root.name} ...", flush=True)
    t0 = time.time()
    generate_dataset(config, root)
    print(f"  done in {time.time() - t0:.0f} s", flush=True)


def thinned(seq, spacing_m: float):
    """``seq`` (a KittiSequence) with a frame every ``spacing_m`` of camera travel."""
    xyz = np.array([f.T_world_from_cam[:3, 3] for f in seq.frames])
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])
    keep, next_m = [], 0.0
    for frame, s in zip(seq.frames, travelled, strict=True):
        if s >= next_m:
            keep.append(frame)
            next_m = s + spacing_m
    return replace(seq, frames=keep)


def rmse(estimates: np.ndarray, truth: np.ndarray) -> float | None:
    """Planar position RMSE (m) over the frames with an estimate; None without any."""
    ok = np.isfinite(estimates[:, 0])
    if not ok.any():
        return None
    return float(np.sqrt(np.mean(np.sum((estimates[ok, :2] - truth[ok, :2]) ** 2, axis=1))))


def per_frame_poses(memory, query) -> dict:
    """Every query frame without a prior: its joint pose (else its likeliest hypothesis)
    and the e_vlad of its accepted per-entry hypotheses."""
    from bench.lab.evaluation import localize_globally
    from monoloc.server.localize import LocalizeConfig

    n = len(query.frames)
    poses, truth, e_vlad = np.full((n, 3), np.nan), np.zeros((n, 3)), []
    for g in localize_globally(memory, query, LocalizeConfig(), np.random.default_rng(1)):
        truth[g.index] = g.truth_world
        chosen = g.result.joint or g.result.best
        if chosen is not None:
            poses[g.index] = chosen.pose_world
        e_vlad += [h.e_vlad for h in g.result.hypotheses if not h.joint]
    return {
        "joint_rmse_m": rmse(poses, truth),
        "coverage": float(np.mean(np.isfinite(poses[:, 0]))),
        "e_vlad": [float(np.mean(e_vlad)), float(np.std(e_vlad))] if e_vlad else None,
    }


def calibration_summary(calibration) -> dict:
    model = calibration.model
    return {
        "used": calibration.provenance.get("used"),
        "e_vlad": [float(model.mu2[0]), math.sqrt(float(model.Sigma2[0, 0]))],
        "offset_std_m": [math.sqrt(float(model.Sigma2[i, i])) for i in (1, 2)],
    }


def cell_goal(filter_rmse: dict, joint_rmse: float | None) -> dict:
    """Per variant: within 1.2x the joint poses' RMSE and not worse than the default."""
    default = filter_rmse.get("default")
    out = {}
    for name, value in filter_rmse.items():
        within = value is not None and joint_rmse is not None
        out[name] = bool(
            within
            and value <= GOAL_JOINT_RATIO * joint_rmse
            and (default is None or value <= default)
        )
    return out


def run(args) -> dict:
    from bench.lab.evaluation import MemoryMap, evaluate_run
    from monoloc.client.replay import read_kitti_run, rig_lever_arm_m
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    vocab = load_default_vocabulary()
    data = args.data / "transfer"
    tag = f"{args.frames}f_x{args.scale:g}"
    trains = {}
    for name, env in TRAIN_ENVS.items():
        root = data / f"train_{_slug(name)}_{env.seed}_{tag}"
        ensure(root, env.generate_config(args.frames, args.scale))
        meta = json.loads((root / "dataset.json").read_text())
        seq_id = sequence_of(meta, "train")
        t0 = time.time()
        calibration = calibrate_on(read_kitti_sequence(root, seq_id), vocab)
        trains[name] = (calibration, meta)
        summary = calibration_summary(calibration)
        print(
            f"{name}: calibrated on {summary['used']} hypotheses in {time.time() - t0:.0f} s; "
            f"e_vlad {summary['e_vlad'][0]:.3f} +- {summary['e_vlad'][1]:.3f}, offsets std "
            f"{summary['offset_std_m'][0]:.2f} / {summary['offset_std_m'][1]:.2f} m",
            flush=True,
        )
    out = {
        "frames_per_run": args.frames,
        "image_scale": args.scale,
        "goal": f"filter <= {GOAL_JOINT_RATIO}x its joint poses' RMSE and <= the default model",
        "train": {},
        "test": {},
        "cells": [],
    }
    for name, (calibration, meta) in trains.items():
        train_seq = meta["sequences"][0]
        out["train"][name] = {
            **calibration_summary(calibration),
            "frames": train_seq["frames"],
            "route_length_m": train_seq["route_length_m"],
            "options": train_seq.get("train_run"),
        }
    for test_name, env in TEST_ENVS.items():
        env = replace(env, size=args.size)
        root = data / f"test_{env.seed}_{env.size}_{tag}"
        ensure(root, env.generate_config(args.frames, args.scale))
        meta = json.loads((root / "dataset.json").read_text())
        memory = MemoryMap.empty(vocab)
        map_seq = thinned(read_kitti_sequence(root, sequence_of(meta, "map")), env.spacing_m)
        memory.add_run(map_seq)
        query_id = sequence_of(meta, "query")
        query = read_kitti_sequence(root, query_id)
        signals = read_kitti_run(root, query_id).signals
        # the sim rig's camera lever arm (a straight training street cannot fit one)
        lever = rig_lever_arm_m(root) or 0.0
        t0 = time.time()
        frames = per_frame_poses(memory, query)
        out["test"][test_name] = {**frames, "map_entries": len(memory.refs)}
        print(
            f"\n{test_name}: {len(memory.refs)} entries; joint poses RMSE "
            f"{_m(frames['joint_rmse_m'])} ({time.time() - t0:.0f} s), e_vlad of accepted "
            f"hypotheses {_pm(frames['e_vlad'])}",
            flush=True,
        )
        for train_name, (calibration, _) in trains.items():
            filter_rmse = {}
            for variant, transform in VARIANTS.items():
                model = transform(calibration.model)
                result = evaluate_run(
                    memory, query, signals, model, lever_arm_m=lever, variants=("full",)
                )
                filter_rmse[variant] = result.metrics["full"].position_rmse_m
                if not math.isfinite(filter_rmse[variant]):
                    filter_rmse[variant] = None
            cell = {
                "train": train_name,
                "test": test_name,
                "filter_rmse_m": filter_rmse,
                "joint_rmse_m": frames["joint_rmse_m"],
                "meets_goal": cell_goal(filter_rmse, frames["joint_rmse_m"]),
            }
            out["cells"].append(cell)
            print_cell(cell, out["train"][train_name]["e_vlad"], frames["e_vlad"])
    return out


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name.split(":")[0].split(",")[0]).strip("_")


def _m(x) -> str:
    return "-" if x is None else f"{x:.3f} m"


def _pm(pair) -> str:
    return "-" if pair is None else f"{pair[0]:.3f} +- {pair[1]:.3f}"


def print_cell(cell: dict, train_vlad, test_vlad) -> None:
    joint = cell["joint_rmse_m"]
    parts = []
    for variant, value in cell["filter_rmse_m"].items():
        ratio = "" if value is None or not joint else f" ({value / joint:.1f}x)"
        mark = "ok" if cell["meets_goal"][variant] else "FAIL"
        parts.append(f"{variant} {_m(value)}{ratio} {mark}")
    print(
        f"  train {cell['train']!r}: e_vlad {_pm(train_vlad)} vs test {_pm(test_vlad)}\n"
        f"    joint poses {_m(joint)}; filter: " + "; ".join(parts),
        flush=True,
    )


def print_matrix(out: dict) -> None:
    print(f"\ngoal: {out['goal']} (calibrated model)")
    tests = list(out["test"])
    print(f"{'train / test':<62}" + "".join(f"{t:>36}" for t in tests))
    for train in out["train"]:
        row = f"{train:<62}"
        for test in tests:
            cell = next(c for c in out["cells"] if c["train"] == train and c["test"] == test)
            value, joint = cell["filter_rmse_m"]["calibrated"], cell["joint_rmse_m"]
            default = cell["filter_rmse_m"]["default"]
            mark = "ok" if cell["meets_goal"]["calibrated"] else "FAIL"
            text = f"{_m(value)} / j {_m(joint)} / d {_m(default)} {mark}"
            row += f"{text:>36}"
        print(row)
    failing = [c for c in out["cells"] if not c["meets_goal"]["calibrated"]]
    n = len(out["cells"])
    print(f"cells failing the goal with the calibrated model: {len(failing)} of {n}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--size", default="small", help="the test cities' size preset")
    parser.add_argument("--frames", type=int, default=120, help="frames per run")
    parser.add_argument("--scale", type=float, default=1.0, help="image scale of the renders")
    parser.add_argument("--data", type=Path, default=Path(__file__).parent / "data")
    args = parser.parse_args()
    limit_threads()
    t0 = time.time()
    out = run(args)
    print_matrix(out)
    out["seconds"] = round(time.time() - t0)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "transfer.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {RESULTS / 'transfer.json'}")


if __name__ == "__main__":
    main()
