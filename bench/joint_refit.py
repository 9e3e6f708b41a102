"""The joint pose's Cauchy refit against least squares on the same inliers: an error-free
city, judged against the true poses, both in the same run.

The joint pose (``vision.joint``) refines one pose on the union of the consistent
entries' inliers; a Cauchy refit follows the least-squares rounds
(``JointConfig.cauchy_scale_sigmas`` / ``cauchy_rounds``, ``pnp.robust_refit``). This
bench localizes every query frame of a city generated without any recording error (exact geometry,
calibration, poses and signals: its written poses are the true ones) twice, without a
prior: with the refit and with ``cauchy_rounds=0`` (the baseline, least squares
alone). Printed: the joint pose's position and heading error on the frames where both
passes give one (median, mean, 90th percentile), and each pass's localize CPU time per
frame (p50, one thread). Writes bench/results/joint_refit.json.
Usage: python -m bench.joint_refit [--size medium] [--frames 150] [--seed 8807]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"
RUNS = ("map", "query")


def error_free_city(root: Path, size: str, frames: int, seed: int) -> dict:
    """Generate (or reuse) the city without recording errors; its runs' sequence ids."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.recording import RecordingErrors

    if not (root / "dataset.json").exists():
        print(f"generating an error-free {size} city into {root} ...", flush=True)
        config = GenerateConfig(
            size=size,
            seed=seed,
            runs=RUNS,
            max_frames=frames,
            errors=RecordingErrors.none(),
            workers=2,
        )
        generate_dataset(config, root)
    meta = json.loads((root / "dataset.json").read_text())
    return {s["run"]: s["id"] for s in meta["sequences"]}


def joint_pass(memory, query, config) -> tuple[dict[int, tuple[float, float]], list[float]]:
    """Per query frame index, the joint pose's (position m, |heading| rad) error against the
    frame's pose; and the localize CPU time (ms) of every frame."""
    from bench.lab.evaluation import localize_globally
    from monoloc.core.geometry import wrap_angle

    errors, cpu_ms = {}, []
    for frame in localize_globally(memory, query, config, np.random.default_rng(1)):
        cpu_ms.append(frame.cpu_ms)
        if frame.result.joint is not None:
            d = frame.result.joint.pose_world - frame.truth_world
            errors[frame.index] = (float(np.hypot(d[0], d[1])), abs(float(wrap_angle(d[2]))))
    return errors, cpu_ms


def summary(errors: np.ndarray, cpu_ms: list[float]) -> dict:
    position_mm = errors[:, 0] * 1e3
    return {
        "position_median_mm": float(np.median(position_mm)),
        "position_mean_mm": float(np.mean(position_mm)),
        "position_p90_mm": float(np.percentile(position_mm, 90)),
        "heading_median_deg": float(np.degrees(np.median(errors[:, 1]))),
        "localize_cpu_ms_p50": float(np.median(cpu_ms)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="medium")
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--seed", type=int, default=8807)
    parser.add_argument("--data", type=Path, default=Path(__file__).parent / "data")
    args = parser.parse_args()
    from monoloc.server.settings import Settings
    from monoloc.server.threads import limit_threads

    # one thread per library, as the server runs a query (its defaults, set explicitly)
    limiter = limit_threads(Settings(cv_threads=1, faiss_threads=1))  # noqa: F841 (held)
    from bench.lab.evaluation import MemoryMap
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.localize import LocalizeConfig, PoseConfig
    from monoloc.server.vision.joint import JointConfig
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    root = args.data / f"urban_{args.size}_{args.frames}_s{args.seed}_error_free"
    ids = error_free_city(root, args.size, args.frames, args.seed)
    vocab = load_default_vocabulary()
    memory = MemoryMap.empty(vocab)
    memory.add_run(read_kitti_sequence(root, ids["map"]))
    query = read_kitti_sequence(root, ids["query"])
    configs = {
        "least squares (baseline)": LocalizeConfig(
            poses=PoseConfig(joint=JointConfig(cauchy_rounds=0))
        ),
        "Cauchy refit (default)": LocalizeConfig(),
    }
    passes = {}
    for name, config in configs.items():
        print(f"localizing {len(query.frames)} query frames: {name} ...", flush=True)
        passes[name] = joint_pass(memory, query, config)
    both = sorted(set.intersection(*(set(errors) for errors, _ in passes.values())))
    if not both:
        raise SystemExit("no frame has a joint pose in both passes: nothing to compare")
    rows = {
        name: summary(np.array([errors[i] for i in both]), cpu_ms)
        for name, (errors, cpu_ms) in passes.items()
    }
    print(
        f"\njoint pose against the true pose, {len(both)} of {len(query.frames)} frames "
        f"(error-free {args.size} city, seed {args.seed}):"
    )
    print(f"  {'':<26}{'median mm':>10}{'mean mm':>9}{'p90 mm':>8}{'head deg':>9}{'CPU ms':>8}")
    for name, r in rows.items():
        print(
            f"  {name:<26}{r['position_median_mm']:>10.2f}{r['position_mean_mm']:>9.2f}"
            f"{r['position_p90_mm']:>8.2f}{r['heading_median_deg']:>9.3f}"
            f"{r['localize_cpu_ms_p50']:>8.2f}"
        )
    base, refit = rows["least squares (baseline)"], rows["Cauchy refit (default)"]
    ratio = refit["position_median_mm"] / base["position_median_mm"]
    print(f"  Cauchy refit / least squares, median position error: {ratio:.2f}x")
    RESULTS.mkdir(exist_ok=True)
    out = {
        "dataset": root.name,
        "frames": len(query.frames),
        "frames_compared": len(both),
        "rows": rows,
        "median_ratio": ratio,
    }
    (RESULTS / "joint_refit.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {RESULTS / 'joint_refit.json'}")


if __name__ == "__main__":
    main()
