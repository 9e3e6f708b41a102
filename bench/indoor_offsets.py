"""Known-feature share and localization error against the camera's offset from the
centre line on the indoor closed-loop world (issue 51, deliverable 1's mechanism).

At stations along the track's centre line a map frame is rendered with the RGB-D
sensor's depth (the entry: its ORB keypoints with a 3D point); query frames are rendered
from the same station moved sideways (0, 2, 5, 10, 20 cm) or turned (0, 2, 5, 10 deg),
and ``along_m`` (1.7 cm) ahead: a closed-loop frame falls anywhere between two map frames
6.7 cm apart (mean 1.7 cm from the nearer), and a query rendered exactly at a map pose
would repeat its pixels and score a share no drive sees.
Each query is matched against the station's entry and its two neighbours one map frame
period (at 1 m/s, 15 Hz) before and after, with the product's matching and PnP RANSAC;
the best entry (most inliers) gives the known-feature share (inliers / query features,
as the closed loop's ``frames.csv``) and the position error of its pose. Stations on
the featureless end are skipped (nothing to match there by design).

    python -m bench.indoor_offsets                       # the hard world's defaults
    python -m bench.indoor_offsets --baseline            # and the same without near clutter

Prints a table per world; ``--json`` writes the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

LATERAL_M = (0.0, 0.02, 0.05, 0.10, 0.20)
HEADING_DEG = (0.0, 2.0, 5.0, 10.0)
MAP_SPACING_M = 1.0 / 15.0  # one map frame period at the reference speed


@dataclass(frozen=True)
class OffsetStudyConfig:
    """stations: how many centre-line stations (spread over the lap, the bare end left
    out); neighbours: map frames each side of a station's own that a query may match."""

    stations: int = 8
    neighbours: int = 1
    along_m: float = MAP_SPACING_M / 4
    lateral_m: tuple[float, ...] = LATERAL_M
    heading_deg: tuple[float, ...] = HEADING_DEG
    seed: int = 0


def _cam_pose(world, x_m: float, y_m: float, yaw_rad: float) -> np.ndarray:
    from monoloc.sim.closed_loop import T_world_from_vehicle_flat

    return T_world_from_vehicle_flat(x_m, y_m, yaw_rad) @ world.T_vehicle_from_cam


def _render(world, lighting, T_world_from_cam, rng, with_depth):
    from monoloc.sim.closed_loop_world import Lap

    world.camera_state.reset()  # a still frame: no motion blur, settled exposure
    return world.render(Lap(), lighting, T_world_from_cam, rng, with_depth)


def _entry(world, image, depth_m):
    from monoloc.server.vision.depth import points_from_depth_image
    from monoloc.server.vision.features import extract_features

    features = extract_features(image)
    raw = np.round(np.nan_to_num(depth_m, nan=0.0) * 5000.0).astype(np.uint16)
    points, has = points_from_depth_image(features.keypoints_px, raw, 5000.0, world.intrinsics)
    return features.descriptors[has], points[has]


def _station_poses(world, config: OffsetStudyConfig) -> list[tuple[float, float, float, float]]:
    """(s, x, y, heading) of centre-line stations away from the bare end."""
    path = world.reference_path(1.0)
    bare_x_m = world.config.main_room.size_m[0] / 2 - world.config.main_room.featureless_end_m
    ok = np.flatnonzero(path.xy[:, 0] < bare_x_m - 1.0)
    pick = ok[np.linspace(0, len(ok) - 1, config.stations).round().astype(int)]
    return [(float(path.s_m[i]), *map(float, path.xy[i]), float(path.heading_rad[i])) for i in pick]


def _at(path, s_m: float) -> tuple[float, float, float]:
    i = int(np.clip(np.searchsorted(path.s_m, s_m), 0, len(path.s_m) - 1))
    return float(path.xy[i, 0]), float(path.xy[i, 1]), float(path.heading_rad[i])


def offset_study(world, config: OffsetStudyConfig = OffsetStudyConfig()) -> dict:
    """{"lateral": {offset_m: (share mean, error median m, n)}, "heading": {...}} over the
    stations; every query with its own seeded render noise."""
    from monoloc.server.vision.features import extract_features
    from monoloc.server.vision.matching import match_descriptors
    from monoloc.server.vision.pnp import PnpConfig, estimate_relative_pose
    from monoloc.sim.closed_loop_world import Lap

    path = world.reference_path(1.0)
    lighting = world.lighting(Lap())
    pnp = PnpConfig()
    shares: dict[tuple[str, float], list[float]] = {}
    errors: dict[tuple[str, float], list[float]] = {}
    for k, (s, *_) in enumerate(_station_poses(world, config)):
        entries = []
        for j in range(-config.neighbours, config.neighbours + 1):
            x, y, h = _at(path, s + j * MAP_SPACING_M)
            T_map = _cam_pose(world, x, y, h)
            image, depth = _render(
                world, lighting, T_map, np.random.default_rng([config.seed, k, j + 100, 1]), True
            )
            entries.append((T_map, *_entry(world, image, depth)))
        x, y, h = _at(path, s + config.along_m)
        queries = [
            ("lateral", d, x - d * math.sin(h), y + d * math.cos(h), h) for d in config.lateral_m
        ]
        queries += [("heading", a, x, y, h + math.radians(a)) for a in config.heading_deg]
        for q, (kind, value, qx, qy, qh) in enumerate(queries):
            T_query = _cam_pose(world, qx, qy, qh)
            image, _ = _render(
                world, lighting, T_query, np.random.default_rng([config.seed, k, q, 2]), False
            )
            features = extract_features(image)
            best = (0, math.nan)
            for T_map, desc, points in entries:
                if len(desc) < 6 or len(features) < 6:
                    continue
                pairs = match_descriptors(features.descriptors, desc)
                rel = estimate_relative_pose(
                    features.keypoints_px[pairs[:, 0]], points[pairs[:, 1]], world.intrinsics,
                    pnp, np.random.default_rng([config.seed, k, q, 3]),
                )  # fmt: skip
                if rel.accepted and rel.n_inliers > best[0]:
                    T_est = T_map @ rel.T_ref_from_query
                    best = (rel.n_inliers, float(np.linalg.norm(T_est[:2, 3] - T_query[:2, 3])))
            shares.setdefault((kind, value), []).append(best[0] / max(len(features), 1))
            errors.setdefault((kind, value), []).append(best[1])
    out: dict = {"lateral": {}, "heading": {}}
    for (kind, value), v in shares.items():
        e = np.array(errors[(kind, value)])
        out[kind][value] = (
            float(np.mean(v)),
            float(np.nanmedian(e)) if np.isfinite(e).any() else math.nan,
            int(np.isfinite(e).sum()),
        )
    return out


def _table(name: str, result: dict, n: int) -> str:
    lines = [f"{name}: known share (mean of {n} stations) / median position error / localized"]
    for kind, unit, scale in (("lateral", "cm", 100.0), ("heading", "deg", 1.0)):
        for value, (share, err, ok) in sorted(result[kind].items()):
            lines.append(
                f"  {kind:8s} {value * scale:5.1f} {unit:3s}  share {100 * share:5.1f} %  "
                f"error {100 * err:6.2f} cm  {ok}/{n}"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from monoloc.sim.closed_loop_world import IndoorLoopWorld

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stations", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0, help="the world's seed")
    parser.add_argument("--baseline", action="store_true", help="also without near clutter")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    config = OffsetStudyConfig(stations=args.stations)
    worlds = {"hard world (defaults)": IndoorLoopWorld("small", args.seed)}
    if args.baseline:
        worlds["baseline: no near clutter"] = IndoorLoopWorld(
            "small", args.seed, near_clutter=False
        )
    report = {"config": {"stations": config.stations, "world_seed": args.seed}, "worlds": {}}
    for name, world in worlds.items():
        t0 = time.perf_counter()
        result = offset_study(world, replace(config))
        print(_table(name, result, config.stations), f"({time.perf_counter() - t0:.0f} s)")
        report["worlds"][name] = {k: {str(v): r for v, r in d.items()} for k, d in result.items()}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
