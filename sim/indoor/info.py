"""The ``dataset.json`` of an indoor dataset: what every run is, in which frames."""

from __future__ import annotations

from dataclasses import asdict

from monoloc.core.formats.tum import DEPTH_SCALE_PER_M
from monoloc.sim.indoor.track import lap_length_m

WORLD_FRAME = (
    "All groundtruth.txt (timestamp tx ty tz qx qy qz qw: T_world_from_cam, camera axes "
    "x right, y down, z forward) share one z-up world: the motion-capture frame, origin on "
    "the floor at the centre of the main room, x along its long side, y left, z up. The "
    "training room (run 'train') lies 60 m along +x and shares nothing visible with it."
)


def _matrix(T) -> list[list[float]]:
    return [[float(v) for v in row] for row in T]


def dataset_info(config, indoor, world, plans) -> dict:
    k = indoor.intrinsics
    return {
        "format": "tum-rgbd",
        "generator": "monoloc sim",
        "scenario": "indoor",
        "size": config.size,
        "seed": config.seed,
        "world_frame": WORLD_FRAME,
        "camera": {
            "model": "RealSense D435 colour stream, depth registered to it",
            "fx": k.fx,
            "fy": k.fy,
            "cx": k.cx,
            "cy": k.cy,
            "width_px": k.width_px,
            "height_px": k.height_px,
        },
        "depth_scale_per_m": DEPTH_SCALE_PER_M,
        "rgb": "rgb/<stamp>.png: 8-bit, three identical channels (the renderer is "
        "monochrome; any colour-to-gray conversion gives the rendered image back)",
        "depth": "depth/<stamp>.png: uint16 z-depth * 5000, 0 = no depth (holes, out of "
        "range, or beyond 13.1 m); stamps offset from rgb by depth_time_offset_s; associate "
        "within 0.02 s",
        "frame_rate_hz": indoor.frame_rate_hz,
        "mocap_rate_hz": indoor.mocap_rate_hz,
        "rig": {
            "vehicle_frame": "origin on the floor below the rear axle, x forward, y left, z "
            "up; vehicle.txt speed is the rear axle's, at the rgb stamps",
            "T_vehicle_from_cam": _matrix(indoor.rig.T_vehicle_from_cam()),
        },
        "vehicle": asdict(indoor.vehicle),
        "camera_model": asdict(indoor.camera),
        "recording_errors": indoor.errors.to_dict(),
        "rooms": {
            name: {
                "size_m": list(room.config.size_m),
                "height_m": room.config.height_m,
                "centre_xy": list(room.config.centre_xy),
                "floor": room.floor_style,
                "track_width_m": room.config.track_width_m,
                "lap_length_m": round(lap_length_m(room.track), 3),
                "track_shape": asdict(room.track),
            }
            for name, room in world.rooms.items()
        },
        "sequences": [
            {
                "id": p.run,
                "run": p.run,
                "scenario": "indoor",
                "path": p.run,
                "room": p.room,
                "district": p.room,
                "seed": p.seed,
                "lighting": asdict(p.lighting),
                "obstacles_variant": p.obstacles_variant,
                "frames": len(p.rgb_times_s),
                "laps": p.laps,
                "route_length_m": round(p.route_length_m, 3),
                "depth_time_offset_s": round(p.depth_offset_s, 6),
                "first_rgb_stamp_s": round(p.stamp0_s + float(p.rgb_times_s[0]), 6),
            }
            for p in plans
        ],
    }
