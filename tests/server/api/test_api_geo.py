"""Geo-referenced maps over the API: set, read and clear a map's reference (validated,
422 leaves the stored one untouched); localize answers carry each hypothesis as an OGC
GeoPose consistent with its T_world_from_cam; and a ROS 2 bag of the query run, driven
through the stream by the vehicle's loop, gives a GeoJSON track."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest
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


def test_driving_a_bag_writes_a_geojson_track(sim_dataset, map_copy, tmp_path):
    from monoloc.client.api import MonolocClient
    from monoloc.client.bag_replay import read_bag_run
    from monoloc.client.drive import DriveConfig, drive, write_geojson
    from monoloc.core.measurement import MeasurementModel

    run = SimRun.read(sim_dataset, "01")
    bag = write_sim_bag(run, tmp_path / "query_bag", image="compressed", three_d="none")
    replay = read_bag_run(bag)
    assert len(replay) == len(run.images)
    np.testing.assert_allclose(replay.signals, run.signals, atol=1e-12)  # the Odometry twist
    assert replay.image_bytes(3) == run.images[3].read_bytes()  # PNG bytes sent as recorded
    ref = GeoReference.from_origin(GeoOrigin(**ORIGIN))
    with live_server(make_settings(map_copy.data_dir)) as port:
        url = f"http://127.0.0.1:{port}"
        r = httpx.put(
            f"{url}/v1/maps/{map_copy.map_id}/geo-reference",
            json={"origin": ORIGIN},
            headers=map_copy.keys.header("write"),
        )
        assert r.status_code == 200, r.text
        with MonolocClient(url, map_copy.keys.localize) as client:
            result = drive(client, map_copy.map_id, replay, MeasurementModel(), DriveConfig())
    path = write_geojson(result, tmp_path / "out" / "drive")
    assert path is not None and path.name == "drive.geojson"
    collection = json.loads(path.read_text())
    assert collection["type"] == "FeatureCollection"
    line, points = collection["features"][0], collection["features"][1:]
    answered = [i for i, g in enumerate(result.geoposes) if g is not None]
    assert len(answered) >= len(replay) // 2
    assert line["geometry"]["type"] == "LineString"
    assert len(line["geometry"]["coordinates"]) == len(points) == len(answered)
    for point in points:
        i = point["properties"]["frame"]
        lon, lat, h = point["geometry"]["coordinates"]
        assert point["properties"]["t_s"] == pytest.approx(replay.timestamps_s[i])
        # the frame's GeoPose is within half a metre of its true position
        world = ref.world_from_geodetic(np.array([lat, lon, h]))[0]
        truth = ground_truth(sim_dataset, "01", i)[:3, 3]
        assert np.linalg.norm(world[:2] - truth[:2]) < 0.5, (i, world, truth)
