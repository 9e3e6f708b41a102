"""A fleet car's lap through `drive` against a live server (issue 48, deliverables 2 and
3 end to end): the sim's fleet run (another camera than the mapping car's: 1024x576,
f 640 px, plumb_bob k1 -0.28, mounted 0.4 m behind, 0.1 m left and 0.23 m below the
mapping camera, 3 deg down, 0.8 deg left) is read with its camera.yaml (lens and
T_vehicle_from_cam), the camera registered once and named by id in every raw,
distorted frame; the drive uses the mounting in its motion model, and scores within
1.5x of the mapping camera's lap on the same street (issue 48's goal, on the sim). Slow:
its own city (map, query and fleet runs at full resolution) and server."""

from __future__ import annotations

import dataclasses
import json

import pytest
from e2e_helpers import ADMIN_KEY, create_keys, live_server, make_settings, upload_map_run

from monoloc.client.api import MonolocClient
from monoloc.client.drive import DriveConfig, drive
from monoloc.client.replay import read_run

pytestmark = pytest.mark.slow


def test_the_fleet_cars_raw_lap_drives_with_its_registered_camera(tmp_path):
    from monoloc.sim.fleet_camera import FLEET_CAMERAS
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig

    root = tmp_path / "city"
    fleet_camera = dataclasses.replace(FLEET_CAMERAS["issue48"], ahead_m=-0.4, left_m=0.1)
    config = GenerateConfig(
        runs=("map", "query", "fleet"),
        max_frames=60,
        lidar=LidarConfig(azimuth_steps=1000),
        fleet_camera=fleet_camera,
        seed=0,
    )
    generate_dataset(config, root)
    meta = json.loads((root / "dataset.json").read_text())
    seq = {s["run"]: s["id"] for s in meta["sequences"]}
    run = read_run(root, seq["fleet"])
    assert run.intrinsics == fleet_camera.intrinsics() and run.intrinsics.distortion
    assert run.mounting is not None and (root / "sequences" / seq["fleet"] / "camera.yaml").exists()
    with live_server(make_settings(tmp_path / "data")) as (url, _app):
        with MonolocClient(url, ADMIN_KEY, timeout_s=60.0) as admin:
            keys = create_keys(admin)
            map_id = upload_map_run(admin, "city", root, seq["map"])
        with MonolocClient(url, keys.localize, timeout_s=60.0) as client:
            model, _ = client.measurement_model(map_id)
            result = drive(client, map_id, run, model, DriveConfig())
            fleet_cameras = client.cameras()
            mapping = drive(client, map_id, read_run(root, seq["query"]), model, DriveConfig())
    assert [c[2] for c in fleet_cameras] == [run.intrinsics]  # registered once, lens included
    assert not result.errors, list(result.errors.items())[:3]
    m, q = result.metrics, mapping.metrics
    # measured on 2026-12-01 (uncalibrated 60-frame map; the server draws its own RANSAC
    # seeds): the fleet lap 0.060-0.110 m over four drives, the mapping camera's lap on
    # the same street 0.107 m; on one server, filter seeds 0 and 1: fleet 0.060/0.063 m
    # with its mounting, 0.073/0.077 m without, 0.88/0.99 m with its raw frames read
    # as pinhole
    print(f"RMSE: fleet lap {m.position_rmse_m:.3f} m, mapping camera {q.position_rmse_m:.3f} m")
    assert m.coverage >= 0.9 and q.coverage >= 0.9, (m, q)
    assert m.position_rmse_m <= 1.5 * q.position_rmse_m, (m, q)  # issue 48's goal
