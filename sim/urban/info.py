"""The ``dataset.json`` of an urban (KITTI layout) dataset, and the world frame its
poses are written in.

World frame of every ``poses/NN.txt``: the camera-0 frame of the first frame of the
``map`` run as written (or of the first run when there is no map run), in KITTI's
convention; see :func:`kitti_world`.
"""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from monoloc.core.geometry import T_ZUP_FROM_KITTI, invert_rigid
from monoloc.sim.urban.runs import FRAME_PERIOD_S, T_vehicle_from_run_cam


def kitti_world(T_simworld_from_cam0: np.ndarray) -> dict[str, np.ndarray]:
    """The dataset's world frames, given the (written) pose of the defining camera frame.

    ``T_simworld_from_kittiworld``: the KITTI world is that camera frame itself.
    ``T_simworld_from_zupworld``: the z-up world a reader gets from
    ``monoloc.core.geometry.kitti_to_zup`` (T_zup = T_ZUP_FROM_KITTI @ T_kitti), i.e.
    T_simworld_from_kittiworld @ inv(T_ZUP_FROM_KITTI). This is the one place the sim's
    internal city frame is tied to the files' frames.
    """
    T_sk = np.asarray(T_simworld_from_cam0, dtype=np.float64)
    return {
        "T_simworld_from_kittiworld": T_sk,
        "T_simworld_from_zupworld": T_sk @ invert_rigid(T_ZUP_FROM_KITTI),
    }


def _matrix(T: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(T)]


def _stereo_keys(draws) -> dict:
    """The run's disparity offset, written only when the error is on (the default
    recording's dataset.json keeps its bytes)."""
    if draws.stereo_disparity_offset_px == 0:
        return {}
    return {"stereo_disparity_offset_px": round(draws.stereo_disparity_offset_px, 4)}


def dataset_info(config, plans, written, frames) -> dict:
    """dataset.json of ``config`` (a ``monoloc.sim.generate.GenerateConfig``): its
    ``plans``, the ``written`` calibration of each run and the world ``frames``
    (:func:`kitti_world`)."""
    k = config.intrinsics()
    return {
        "format": "kitti-odometry",
        "generator": "monoloc sim",
        "scenario": config.scenario,
        "size": config.size,
        "seed": config.seed,
        "world_frame": (
            "All poses/NN.txt (T_world_from_cam0, 3x4 row-major) share one world frame: "
            "the camera-0 frame of the first frame of the map run as written (or of the "
            "first run if there is no map run), KITTI convention (x right, y down, z "
            "forward). monoloc.core.geometry.kitti_to_zup converts it to monoloc's z-up world."
        ),
        "T_simworld_from_kittiworld": _matrix(frames["T_simworld_from_kittiworld"]),
        "T_simworld_from_zupworld": _matrix(frames["T_simworld_from_zupworld"]),
        "camera": {
            "fx": k.fx,
            "fy": k.fy,
            "cx": k.cx,
            "cy": k.cy,
            "width_px": k.width_px,
            "height_px": k.height_px,
        },
        "frame_period_s": FRAME_PERIOD_S,
        "rig": {
            "vehicle_frame": "origin on the ground below the rear axle, x forward, y left, "
            "z up; vehicle.txt speed is the rear axle's",
            "T_vehicle_from_cam0": _matrix(config.rig.T_vehicle_from_cam()),
            "T_vehicle_from_lidar": _matrix(config.rig.T_vehicle_from_lidar()),
            "T_cam0_from_lidar_true": _matrix(config.rig.T_cam_from_lidar()),
        },
        "lidar": asdict(config.lidar),
        "camera_model": asdict(config.camera),
        "recording_errors": config.errors.to_dict(),
        "depth": (
            "sequences/NN/depth/%06d.png: uint16 z-depth * 256, 0 = none"
            if config.write_depth
            else None
        ),
        "stereo": (
            f"sequences/NN/image_1/%06d.png: the right camera, P1 in calib.txt, baseline "
            f"{config.rig.stereo_baseline_m:g} m"
            if config.write_stereo
            else None
        ),
        "sequences": [
            {
                "id": p.seq_id,
                "run": p.kind,
                "scenario": config.scenario,
                "district": p.district,
                "seed": p.seed,
                "lighting": asdict(p.lighting),
                "parked_cars_variant": p.car_variant,
                "frames": len(p.frame_times_s),
                "route_length_m": round(p.route_length_m, 2),
                "T_cam0_from_lidar_written": _matrix(written[p.seq_id].Tr_written),
                "exposure_bias_ev": round(written[p.seq_id].draws.exposure_bias_ev, 4),
                "lidar_time_offset_mean_s": round(
                    float(np.mean(written[p.seq_id].draws.lidar_time_offsets_s)), 5
                ),
                **_stereo_keys(written[p.seq_id].draws),
                **_train_run_keys(p, config),
                **_camera_keys(p, config),
            }
            for p in plans
        ],
    }


def _camera_keys(plan, config) -> dict:
    """A run recorded by another camera than the mapping camera (the fleet run): its
    camera, lens and mounting (nothing for the others, so their datasets keep their
    bytes)."""
    if plan.camera is None:
        return {}
    k = plan.camera.intrinsics(config.image_scale)
    lens = k.distortion
    return {
        "camera": {
            "name": plan.camera.name,
            "fx": k.fx,
            "fy": k.fy,
            "cx": k.cx,
            "cy": k.cy,
            "width_px": k.width_px,
            "height_px": k.height_px,
            "distortion_model": "none" if lens is None else lens.model,
            "D": [] if lens is None else list(lens.coefficients),
        },
        "fleet_camera": asdict(plan.camera),
        "T_vehicle_from_cam": _matrix(T_vehicle_from_run_cam(plan, config.rig)),
    }


def _train_run_keys(plan, config) -> dict:
    """What a training run's options changed (``GenerateConfig.train_run``; nothing
    without them, so the datasets without them keep their bytes)."""
    options = config.train_run
    if options is None or plan.kind not in ("train", "trainnight"):
        return {}
    return {
        "train_run": asdict(options),
        "frame_period_s": options.frame_period_s,
        "exposure_offset_ev": plan.exposure_offset_ev,
    }
