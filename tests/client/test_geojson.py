"""The drive's GeoJSON track (monoloc.client.geojson): the filter's estimates, dead-reckoned
frames included, placed on WGS84 through the map's reference; the camera height from the
hypotheses; how the client reads the reference. Against a scripted stream here; over a
live server with a ROS bag in tests/server/api/test_api_geo.py."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pymap3d
import pytest
from test_client_drive import FILTER, FakeClient, FakeStream, _run

from monoloc.client.api import MonolocClient, ServerError
from monoloc.client.drive import DriveConfig, drive, write_geojson
from monoloc.client.geojson import track_heights_m
from monoloc.core.errors import InvalidInputError
from monoloc.core.geo import GeoOrigin, GeoReference
from monoloc.core.geometry import R_from_quaternion_xyzw
from monoloc.core.measurement import MeasurementModel

# heading 90: the world is the origin's East-North-Up frame
ORIGIN = GeoOrigin(lat_deg=-33.8568, lon_deg=151.2153, h_m=5.0, x_axis_heading_deg=90.0)
CAMERA_HEIGHT_M = 1.5


class GeoStream(FakeStream):
    """FakeStream whose hypotheses carry a T_world_from_cam (camera ~1.5 m up) and a
    GeoPose, as a geo-referenced map's answers do."""

    def _answer(self, seq):
        answer = super()._answer(seq)
        for h in answer.get("hypotheses", []):
            T = np.eye(4)
            T[:3, 3] = [h["pose"]["x_m"], h["pose"]["y_m"], CAMERA_HEIGHT_M]
            T[2, 3] += self.rng.normal(0.0, 0.02)
            h["T_world_from_cam"] = T.ravel().tolist()
            h["geopose"] = {"position": {"lat": 0.0, "lon": 0.0, "h": float(seq)}}
        return answer


class GeoClient(FakeClient):
    def __init__(self, stream, geo):
        super().__init__(stream)
        self.geo, self.asked = geo, 0

    def geo_reference(self, map_id):
        self.asked += 1
        return self.geo


def test_the_track_is_the_filters_estimate_dead_reckoned_frames_included(tmp_path):
    run = _run(tmp_path, n=20)
    stream = GeoStream(run.truth_world, dropped={5, 6}, errors={9})
    client = GeoClient(stream, GeoReference.from_origin(ORIGIN))
    config = DriveConfig(filter=FILTER)
    result = drive(client, 1, run, MeasurementModel(), config)
    assert client.asked == 1  # once per drive, not per frame
    path = write_geojson(result, tmp_path / "out" / "drive")
    line, *points = json.loads(path.read_text())["features"]
    props = [p["properties"] for p in points]
    assert [p["frame"] for p in props] == list(range(len(run)))
    assert [p["source"] for p in props] == ["initialisation"] + [
        "dead_reckoning" if i in (5, 6, 9) else "measurement_update" for i in range(1, len(run))
    ]
    for i in (5, 6, 9):
        assert props[i]["n_hypotheses"] == 0 and props[i]["best_hypothesis_geopose"] is None
    assert props[4]["best_hypothesis_geopose"]["position"]["h"] == 4.0  # the server's, as sent

    # positions: pymap3d's ENU -> geodetic of the estimates, at the stated height
    est = result.estimates_world
    z_m = np.array([p["estimate_world"]["z_m"] for p in props])
    lat, lon, h = pymap3d.enu2geodetic(
        est[:, 0], est[:, 1], z_m, ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.h_m
    )
    lon_got, lat_got, h_got = np.array(line["geometry"]["coordinates"]).T
    offset_m = np.column_stack(pymap3d.geodetic2enu(lat_got, lon_got, h_got, lat, lon, h))
    assert np.abs(offset_m).max() < 1e-3
    assert [p["estimate_world"]["x_m"] for p in props] == est[:, 0].tolist()
    # the height: the hypotheses' (1.5 m +- 2 cm each), held through the misses
    assert np.all(np.abs(z_m - CAMERA_HEIGHT_M) < 0.05)
    assert z_m[5] == z_m[6] == z_m[4]
    # the orientation: a level camera along the estimate's yaw (east-north here)
    for p, (_, _, yaw) in zip(props, est, strict=True):
        q = p["geopose"]["quaternion"]
        R_enu_from_cam = R_from_quaternion_xyzw([q["x"], q["y"], q["z"], q["w"]])
        np.testing.assert_allclose(R_enu_from_cam[:, 2], [np.cos(yaw), np.sin(yaw), 0], atol=1e-5)
        np.testing.assert_allclose(R_enu_from_cam[:, 1], [0, 0, -1], atol=1e-5)


def test_no_reference_or_no_estimate_writes_no_geojson(tmp_path):
    run = _run(tmp_path, n=6)
    config = DriveConfig(filter=FILTER)
    plain = drive(GeoClient(GeoStream(run.truth_world), None), 1, run, MeasurementModel(), config)
    assert np.all(np.isfinite(plain.estimates_world))
    assert write_geojson(plain, tmp_path / "plain") is None
    assert not list(tmp_path.glob("*.geojson"))
    lost = GeoStream(run.truth_world, dropped=range(6))  # never initialised
    geo = GeoReference.from_origin(ORIGIN)
    result = drive(GeoClient(lost, geo), 1, run, MeasurementModel(), config)
    assert write_geojson(result, tmp_path / "lost") is None


def test_track_heights_are_a_running_median_held_through_gaps():
    heights = np.array([np.nan, 1.0, 3.0, np.nan, 2.0, 10.0, np.nan])
    # window 3: medians of [1], [1, 3], [1, 3], [1, 3, 2], [3, 2, 10], [3, 2, 10]
    np.testing.assert_array_equal(track_heights_m(heights, 3), [0, 1, 2, 2, 2, 3, 3])
    np.testing.assert_array_equal(track_heights_m(heights, 1), [0, 1, 3, 3, 2, 10, 10])
    with pytest.raises(InvalidInputError, match="window"):
        track_heights_m(heights, 0)


def _client(handler) -> MonolocClient:
    return MonolocClient("http://fake", "k", retries=0, transport=httpx.MockTransport(handler))


def test_the_client_reads_the_maps_reference():
    ref = GeoReference.from_origin(ORIGIN)
    seen = []

    def answer(body, status=200):
        def handler(request):
            seen.append((request.url.path, request.headers["x-api-key"]))
            return httpx.Response(status, json=body)

        return handler

    with _client(answer(ref.to_dict())) as client:
        got = client.geo_reference(4)
    assert seen == [("/v1/maps/4/geo-reference", "k")]
    assert got.origin == ORIGIN
    np.testing.assert_allclose(got.T_ecef_from_world, ref.T_ecef_from_world, atol=1e-9)
    missing = {"error": {"code": "not_found", "message": "map 4 has no geographic reference"}}
    with _client(answer(missing, 404)) as client:
        assert client.geo_reference(4) is None
    for bad in ({"origin": None, "T_ecef_from_world": [1.0] * 3}, [1, 2], {"origin": {"x": 1}}):
        with _client(answer(bad)) as client, pytest.raises(ServerError, match="malformed geo"):
            client.geo_reference(4)
