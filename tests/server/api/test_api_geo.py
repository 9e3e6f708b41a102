"""Geo-referenced maps over the API: set, read and clear a map's reference (validated,
422 leaves the stored one untouched); localize answers carry each hypothesis as an OGC
GeoPose consistent with its T_world_from_cam; and a ROS 2 bag of the query run, driven
through the stream by the vehicle's loop, gives a GeoJSON track."""

from __future__ import annotations

import json
import sys
from dataclasses import replace

import httpx
import numpy as np
from api_helpers import camera_of, frame_png, ground_truth, live_server, make_settings
from rosbag_helpers import SimRun, write_sim_bag

from monoloc.core.geo import GeoOrigin, GeoReference, R_ecef_from_enu
from monoloc.core.geometry import R_from_quaternion_xyzw

ORIGIN = dict(lat_deg=52.516275, lon_deg=13.377704, h_m=74.0, x_axis_heading_deg=30.0)


def test_geo_reference_lifecycle_and_validation(fresh):
    client, keys = fresh
    admin, write = keys.header("admin"), keys.header("write")
    body = {"name": "berlin", "camera": camera_of(None), "geo_reference": {"origin": ORIGIN}}
    r = client.post("/v1/maps", json=body, headers=admin)
    assert r.status_code == 201, r.text
    map_id, shown = r.json()["id"], r.json()["geo_reference"]
    assert shown["origin"] == ORIGIN
    expected = GeoReference.from_origin(GeoOrigin(**ORIGIN)).T_ecef_from_world.ravel()
    np.testing.assert_allclose(shown["T_ecef_from_world"], expected, atol=1e-6)
    url = f"/v1/maps/{map_id}/geo-reference"
    assert client.get(url, headers=keys.header("localize")).json() == shown

    bad = [
        {"origin": ORIGIN | {"lat_deg": 90.5}},
        {"origin": ORIGIN | {"x_axis_heading_deg": 360.0}},
        {"origin": ORIGIN, "T_ecef_from_world": expected.tolist()},  # both
        {},  # neither
        {"T_ecef_from_world": [1.0] * 16},  # not rigid
        {"T_ecef_from_world": np.eye(4).ravel().tolist()},  # at the Earth's centre
        {"T_ecef_from_world": [0.0] * 15},
    ]
    for payload in bad:
        r = client.put(url, json=payload, headers=write)
        assert r.status_code == 422, (payload, r.text)
        assert r.json()["error"]["message"]
    assert client.get(url, headers=keys.header("localize")).json() == shown  # untouched

    # the same place given as an ECEF transform: no origin, the same transform
    r = client.put(url, json={"T_ecef_from_world": expected.tolist()}, headers=write)
    assert r.status_code == 200 and r.json()["origin"] is None
    np.testing.assert_allclose(r.json()["T_ecef_from_world"], expected, atol=1e-6)

    assert client.delete(url, headers=write).status_code == 204
    assert client.get(url, headers=keys.header("localize")).status_code == 404
    assert (
        client.get(f"/v1/maps/{map_id}", headers=keys.header("localize")).json()["geo_reference"]
        is None
    )
    assert (
        client.put("/v1/maps/99/geo-reference", json={"origin": ORIGIN}, headers=write).status_code
        == 404
    )

    # a map created with a bad reference is not created
    body = {
        "name": "nowhere",
        "camera": camera_of(None),
        "geo_reference": {"origin": ORIGIN | {"lon_deg": 200.0}},
    }
    assert client.post("/v1/maps", json=body, headers=admin).status_code == 422
    names = [m["name"] for m in client.get("/v1/maps", headers=admin).json()["items"]]
    assert names == ["berlin"]


def _check_geopose(hypothesis: dict, ref: GeoReference) -> None:
    """The GeoPose is the hypothesis' T_world_from_cam in WGS84 and local ENU."""
    T = np.asarray(hypothesis["T_world_from_cam"]).reshape(4, 4)
    g = hypothesis["geopose"]
    position = [g["position"]["lat"], g["position"]["lon"], g["position"]["h"]]
    np.testing.assert_allclose(ref.world_from_geodetic(np.array(position))[0], T[:3, 3], atol=1e-3)
    q = g["quaternion"]
    R_enu_from_cam = R_from_quaternion_xyzw([q["x"], q["y"], q["z"], q["w"]])
    R_world_from_cam = (
        ref.T_ecef_from_world[:3, :3].T @ R_ecef_from_enu(position[0], position[1]) @ R_enu_from_cam
    )
    np.testing.assert_allclose(R_world_from_cam, T[:3, :3], atol=1e-9)


def test_localize_answers_carry_geoposes(sim_dataset, map_copy, client_on_copy):
    client, m = client_on_copy, map_copy
    url = f"/v1/maps/{m.map_id}/localize"
    image = {"image": ("f.png", frame_png(sim_dataset, "01", 9), "image/png")}
    plain = client.post(url, files=image, params={"seed": 1}, headers=m.keys.header("localize"))
    assert plain.status_code == 200 and plain.json()["hypotheses"]
    assert all(h["geopose"] is None for h in plain.json()["hypotheses"])

    r = client.put(
        f"/v1/maps/{m.map_id}/geo-reference",
        json={"origin": ORIGIN},
        headers=m.keys.header("write"),
    )
    assert r.status_code == 200
    answer = client.post(url, files=image, params={"seed": 1}, headers=m.keys.header("localize"))
    hypotheses = answer.json()["hypotheses"]
    assert [h["T_world_from_cam"] for h in hypotheses] == [
        h["T_world_from_cam"] for h in plain.json()["hypotheses"]
    ]
    ref = GeoReference.from_origin(GeoOrigin(**ORIGIN))
    for hypothesis in hypotheses:
        _check_geopose(hypothesis, ref)


def _drive_cli(url: str, map_copy, bag, out, monkeypatch, capsys, *extra: str) -> list[str]:
    """``monoloc drive`` of the bag in-process; its stderr lines."""
    from monoloc import cli

    argv = ["drive", str(bag), "--server", url, "--map", str(map_copy.map_id)]
    argv += ["--key", map_copy.keys.localize, "--particles", "300", "--out", str(out), *extra]
    monkeypatch.setattr(sys, "argv", ["monoloc", *argv])
    capsys.readouterr()
    cli.main()
    return capsys.readouterr().err.splitlines()


def _independent_geodetic(x_m, y_m, z_m, origin: dict) -> np.ndarray:
    """World -> WGS84 by pymap3d's ENU -> geodetic (not monoloc.core.geo's ECEF path): the
    world is the origin's ENU turned by 90 deg - heading about up."""
    import pymap3d

    a = np.deg2rad(90.0 - origin["x_axis_heading_deg"])
    east, north = x_m * np.cos(a) - y_m * np.sin(a), x_m * np.sin(a) + y_m * np.cos(a)
    lat, lon, h = pymap3d.enu2geodetic(
        east, north, z_m, origin["lat_deg"], origin["lon_deg"], origin["h_m"]
    )
    return np.column_stack([lat, lon, h])


def test_driving_a_bag_writes_the_filters_track_as_geojson(
    sim_dataset, map_copy, tmp_path, monkeypatch, capsys
):
    import cv2
    import pymap3d

    from monoloc.client.bag_replay import read_bag_run
    from monoloc.core.formats import tum

    run = SimRun.read(sim_dataset, "01")
    # three frames the camera sees nothing on: no hypotheses, the filter dead-reckons
    blank_frames = (6, 7, 11)
    shape = cv2.imread(str(run.images[0]), cv2.IMREAD_GRAYSCALE).shape
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full(shape, 128, np.uint8))
    images = [blank if i in blank_frames else path for i, path in enumerate(run.images)]
    bag = write_sim_bag(
        replace(run, images=images), tmp_path / "query_bag", image="compressed", three_d="none"
    )
    replay = read_bag_run(bag)
    assert len(replay) == len(run.images)
    np.testing.assert_allclose(replay.signals, run.signals, atol=1e-12)  # the Odometry twist
    assert replay.image_bytes(3) == run.images[3].read_bytes()  # PNG bytes sent as recorded

    with live_server(make_settings(map_copy.data_dir)) as port:
        url = f"http://127.0.0.1:{port}"
        # no geographic reference: trajectories, no GeoJSON, and one line that says so
        plain = tmp_path / "plain" / "drive"
        err = _drive_cli(url, map_copy, bag, plain, monkeypatch, capsys, "--frames", "0:4")
        said = [line for line in err if "GeoJSON" in line]
        assert said == [f"no GeoJSON track: map {map_copy.map_id} has no geographic reference"]
        assert plain.with_name("drive.tum.txt").exists()
        assert not plain.with_name("drive.geojson").exists()

        r = httpx.put(
            f"{url}/v1/maps/{map_copy.map_id}/geo-reference",
            json={"origin": ORIGIN},
            headers=map_copy.keys.header("write"),
        )
        assert r.status_code == 200, r.text
        out = tmp_path / "geo" / "drive"
        track_bag = tmp_path / "geo" / "track_bag"
        err = _drive_cli(url, map_copy, bag, out, monkeypatch, capsys, "--bag-out", str(track_bag))
        assert not [line for line in err if "no GeoJSON" in line]
        assert "track_bag" in "".join(err)  # named among the outputs (rich may wrap the line)
        # an existing --bag-out is refused before the drive starts (usage error, exit 2)
        again = tmp_path / "again" / "drive"
        try:
            _drive_cli(url, map_copy, bag, again, monkeypatch, capsys, "--bag-out", str(track_bag))
        except SystemExit as exc:
            assert exc.code == 2
        else:
            raise AssertionError("an existing --bag-out was accepted")
        assert not again.with_name("drive.tum.txt").exists()

    estimates = tum.read_trajectory(out.with_name("drive.tum.txt"))
    collection = json.loads(out.with_name("drive.geojson").read_text())
    assert collection["type"] == "FeatureCollection"
    line, points = collection["features"][0], collection["features"][1:]
    assert line["geometry"]["type"] == "LineString"
    frames = [p["properties"]["frame"] for p in points]
    # one point per TUM row, in order: the filter's track, not the answered frames
    assert len(frames) == len(estimates) >= len(replay) - 2 and frames == sorted(frames)
    np.testing.assert_allclose(
        [p["properties"]["t_s"] for p in points], estimates.timestamps_s, atol=1e-6
    )
    coordinates = np.array(line["geometry"]["coordinates"])
    assert coordinates.tolist() == [p["geometry"]["coordinates"] for p in points]

    # the positions are pymap3d's conversion of the TUM estimates (at the height stated
    # per point) to the millimetre
    z_m = np.array([p["properties"]["estimate_world"]["z_m"] for p in points])
    x_m, y_m, tum_z_m = estimates.position_world_m.T
    expected = _independent_geodetic(x_m, y_m, z_m, ORIGIN)
    lon, lat, h = coordinates.T
    offset_enu_m = np.column_stack(pymap3d.geodetic2enu(lat, lon, h, *expected.T))
    assert np.abs(offset_enu_m).max() < 1e-3, offset_enu_m
    ref = GeoReference.from_origin(GeoOrigin(**ORIGIN))
    got_world = ref.world_from_geodetic(coordinates[:, [1, 0, 2]])
    assert np.all(tum_z_m == 0.0)  # the TUM file's planar track; the GeoJSON adds a height
    # the height follows its rule exactly: the median world z of the best hypotheses of
    # the last 10 frames that had one (held through frames without)
    best_z_m = np.full(len(points), np.nan)
    for i, point in enumerate(points):
        geopose = point["properties"]["best_hypothesis_geopose"]
        if geopose is not None:
            p = geopose["position"]
            best_z_m[i] = ref.world_from_geodetic(np.array([[p["lat"], p["lon"], p["h"]]]))[0, 2]
    seen = [z for z in best_z_m if np.isfinite(z)]
    assert len(seen) >= len(points) - 3
    expected_z_m = [
        np.median([z for z in best_z_m[: i + 1] if np.isfinite(z)][-10:])
        for i in range(len(points))
    ]
    np.testing.assert_allclose(z_m, expected_z_m, atol=1e-6)
    # ... and is the camera's (1.5 m in the sim) within PnP's scatter: a single hypothesis
    # (the first frame) may be off by ~0.1 m on the sim's recording errors, the median less
    truths = np.stack([ground_truth(sim_dataset, "01", i) for i in frames])
    height_error_m = np.abs(z_m - truths[:, 2, 3])
    assert np.median(height_error_m) < 0.03 and height_error_m.max() < 0.25, height_error_m
    # and the estimate follows the truth, dead-reckoned frames too
    errors_m = np.linalg.norm(got_world[:, :2] - truths[:, :2, 3], axis=1)
    assert np.all(errors_m < 0.5), errors_m

    # the orientation: the TUM rotation (a level camera along the estimate's yaw) in ENU
    a = np.deg2rad(90.0 - ORIGIN["x_axis_heading_deg"])
    R_enu_from_world = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    for point, T in zip(points, estimates.T_world_from_cam, strict=True):
        q = point["properties"]["geopose"]["quaternion"]
        R_enu_from_cam = R_from_quaternion_xyzw([q["x"], q["y"], q["z"], q["w"]])
        # (the local ENU frames of points ~100 m apart differ by < 1e-5 rad)
        np.testing.assert_allclose(R_enu_from_cam, R_enu_from_world @ T[:3, :3], atol=1e-4)
        position = point["properties"]["geopose"]["position"]
        assert [position["lon"], position["lat"], position["h"]] == point["geometry"]["coordinates"]

    # the blank frames are in the track as dead reckoning, without a hypothesis' GeoPose;
    # the others carry their best hypothesis' GeoPose beside the estimate's
    by_frame = {p["properties"]["frame"]: p["properties"] for p in points}
    for i in blank_frames:
        assert by_frame[i]["source"] == "dead_reckoning", by_frame[i]
        assert by_frame[i]["n_hypotheses"] == 0 and by_frame[i]["best_hypothesis_geopose"] is None
    updated = [i for i, p in by_frame.items() if p["source"] == "measurement_update"]
    assert len(updated) >= len(replay) // 2
    for i in updated:
        best = by_frame[i]["best_hypothesis_geopose"]
        assert by_frame[i]["n_hypotheses"] > 0 and best is not None
        world = ref.world_from_geodetic(
            np.array([best["position"]["lat"], best["position"]["lon"], best["position"]["h"]])
        )[0]
        assert np.linalg.norm(world[:2] - truths[frames.index(i), :2, 3]) < 0.5
    assert [p["source"] for p in by_frame.values()].count("initialisation") == 1

    # the same track as a ROS 2 bag: one Odometry per TUM row, at the frame's stamp, the
    # camera's pose in `map` at the GeoJSON's height, child frame the bag's camera frame
    from monoloc.core.formats import rosbag as bag_format

    with bag_format.open_bag(track_bag) as reader:
        assert bag_format.topic_types(reader) == {"/monoloc/odometry": bag_format.ODOMETRY}
        track = bag_format.read_odometry(reader, "/monoloc/odometry")
    assert (track.world, track.body) == ("map", "camera_optical")
    rows = track.pose_rows
    np.testing.assert_allclose(rows[:, 0], estimates.timestamps_s, atol=1e-6)
    np.testing.assert_allclose(rows[:, 1:3], estimates.position_world_m[:, :2], atol=1e-9)
    np.testing.assert_allclose(rows[:, 3], z_m, atol=1e-9)
    for row, T in zip(rows, estimates.T_world_from_cam, strict=True):
        R_world_from_cam = bag_format.T_from_pose_row(row)[:3, :3]
        np.testing.assert_allclose(R_world_from_cam, T[:3, :3], atol=1e-6)  # TUM: 9 digits
