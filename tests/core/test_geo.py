"""Geo-referenced maps (monoloc/core/geo.py): conversions checked against known points to the
millimetre, round trips, and the GeoPose orientation convention (R_enu_from_cam)."""

from __future__ import annotations

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.core.geo import GeoOrigin, GeoReference
from monoloc.core.geometry import R_from_quaternion_xyzw, T_world_from_cam_planar

MM = 1e-3
WGS84_A_M = 6_378_137.0
WGS84_B_M = 6_356_752.314245  # semi-minor axis
WGS84_E2 = 6.69437999014e-3


def _ecef_closed_form(lat_deg: float, lon_deg: float, h_m: float) -> np.ndarray:
    """Geodetic -> ECEF by the textbook closed form (independent of pymap3d)."""
    lat, lon = np.deg2rad(lat_deg), np.deg2rad(lon_deg)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    return np.array(
        [
            (n + h_m) * np.cos(lat) * np.cos(lon),
            (n + h_m) * np.cos(lat) * np.sin(lon),
            (n * (1.0 - WGS84_E2) + h_m) * np.sin(lat),
        ]
    )


def _ecef_reference(T_ecef_from_world: np.ndarray) -> GeoReference:
    return GeoReference.from_ecef(T_ecef_from_world)


def test_known_ecef_points_to_the_millimetre():
    # an ECEF-referenced world whose axes are ECEF's, shifted to the equator at lon 0
    T = np.eye(4)
    T[:3, 3] = [WGS84_A_M, 0.0, 0.0]
    ref = _ecef_reference(T)
    cases = [
        ((0.0, 0.0, 0.0), [WGS84_A_M, 0.0, 0.0]),  # equator, Greenwich
        ((0.0, 90.0, 0.0), [0.0, WGS84_A_M, 0.0]),  # equator, 90 E
        ((90.0, 0.0, 0.0), [0.0, 0.0, WGS84_B_M]),  # north pole
        ((0.0, 0.0, 1000.0), [WGS84_A_M + 1000.0, 0.0, 0.0]),
        ((48.8584, 2.2945, 35.0), _ecef_closed_form(48.8584, 2.2945, 35.0)),
        ((-33.8568, 151.2153, 5.0), _ecef_closed_form(-33.8568, 151.2153, 5.0)),
    ]
    for geodetic, ecef in cases:
        world = np.asarray(ecef) - T[:3, 3]
        np.testing.assert_allclose(ref.world_from_geodetic(np.array(geodetic)), [world], atol=MM)
        lat, lon, h = ref.geodetic_from_world(world)[0]
        assert abs(h - geodetic[2]) < MM
        # angles to ~1e-9 deg: 0.1 mm on the ground (the pole's longitude is arbitrary)
        assert abs(lat - geodetic[0]) < 1e-9
        if abs(geodetic[0]) < 90.0:
            assert abs(lon - geodetic[1]) < 1e-9


def test_a_point_1000_m_east_and_north_of_the_origin():
    import pymap3d

    origin = GeoOrigin(lat_deg=48.8584, lon_deg=2.2945, h_m=35.0, x_axis_heading_deg=90.0)
    ref = GeoReference.from_origin(origin)
    # heading 90: the world is ENU at the origin, +X east, +Y north
    for world, enu in (([1000.0, 0, 0], (1000.0, 0, 0)), ([0, 1000.0, 0], (0, 1000.0, 0))):
        got = ref.geodetic_from_world(np.array(world))[0]
        e, n, u = pymap3d.geodetic2enu(*got, origin.lat_deg, origin.lon_deg, origin.h_m)
        np.testing.assert_allclose([e, n, u], enu, atol=MM)
        # and the ECEF of that point is the closed form's
        np.testing.assert_allclose(ref.ecef_from_world(world)[0], _ecef_closed_form(*got), atol=MM)
        np.testing.assert_allclose(ref.world_from_geodetic(got)[0], world, atol=MM)
    # 1000 m east on a tangent plane: the ellipsoid has dropped by d^2 / (2 R) ~ 7.8 cm
    h = ref.geodetic_from_world(np.array([1000.0, 0, 0]))[0, 2]
    assert h - origin.h_m == pytest.approx(1000.0**2 / (2 * 6_388_000.0), abs=2e-3)

    # heading 0: +X points north, so +Y (90 deg counter-clockwise) points west
    north_up = GeoReference.from_origin(
        GeoOrigin(origin.lat_deg, origin.lon_deg, origin.h_m, x_axis_heading_deg=0.0)
    )
    for world, enu in (([1000.0, 0, 0], (0, 1000.0, 0)), ([0, 1000.0, 0], (-1000.0, 0, 0))):
        got = north_up.geodetic_from_world(np.array(world))[0]
        e, n, u = pymap3d.geodetic2enu(*got, origin.lat_deg, origin.lon_deg, origin.h_m)
        np.testing.assert_allclose([e, n, u], enu, atol=MM)


def test_origin_and_ecef_forms_agree_and_round_trip_through_storage():
    rng = np.random.default_rng(7)
    origin = GeoOrigin(lat_deg=37.8719, lon_deg=-122.2585, h_m=52.0, x_axis_heading_deg=123.4)
    by_origin = GeoReference.from_origin(origin)
    by_ecef = GeoReference.from_ecef(by_origin.T_ecef_from_world)
    stored = GeoReference.from_dict(by_origin.to_dict())
    assert stored.origin == origin and by_ecef.origin is None
    points = rng.uniform(-3000, 3000, size=(50, 3)) * [1, 1, 0.01]
    geodetic = by_origin.geodetic_from_world(points)
    np.testing.assert_allclose(by_ecef.geodetic_from_world(points), geodetic, atol=1e-12)
    np.testing.assert_allclose(stored.world_from_geodetic(geodetic), points, atol=MM)


def test_geopose_is_the_camera_orientation_in_local_enu():
    ref = GeoReference.from_origin(GeoOrigin(10.0, 20.0, 0.0, x_axis_heading_deg=90.0))
    for yaw_rad in (0.0, 0.7, -2.0):
        # a level camera at 1.5 m looking along yaw (counter-clockwise from world +X = east)
        T = T_world_from_cam_planar(40.0, -25.0, yaw_rad, 1.5)
        pose = ref.geopose(T)
        R_enu_from_cam = R_from_quaternion_xyzw(pose.quaternion_xyzw)
        # the optical axis points at yaw from east in the local ENU (the local frame 47 m
        # away is turned by the meridians' convergence: sin(lat) * dlon ~ 4e-6 rad)
        np.testing.assert_allclose(
            R_enu_from_cam @ [0, 0, 1], [np.cos(yaw_rad), np.sin(yaw_rad), 0.0], atol=1e-5
        )
        np.testing.assert_allclose(R_enu_from_cam @ [0, 1, 0], [0, 0, -1], atol=1e-5)  # y down
        lat, lon, h = ref.geodetic_from_world(T[:3, 3])[0]
        assert (pose.lat_deg, pose.lon_deg, pose.h_m) == (lat, lon, h)
        assert pose.to_json()["position"] == {"lat": lat, "lon": lon, "h": h}
        assert set(pose.to_json()["quaternion"]) == {"x", "y", "z", "w"}


@pytest.mark.parametrize(
    "values, message",
    [
        ((91.0, 0.0, 0.0, 0.0), "lat_deg"),
        ((0.0, -180.5, 0.0, 0.0), "lon_deg"),
        ((0.0, 0.0, 2e5, 0.0), "h_m"),
        ((0.0, 0.0, 0.0, 360.0), "x_axis_heading_deg"),
        ((float("nan"), 0.0, 0.0, 0.0), "finite"),
    ],
)
def test_bad_origins_are_refused(values, message):
    with pytest.raises(InvalidInputError, match=message):
        GeoOrigin(*values)


def test_bad_ecef_transforms_are_refused():
    T = np.eye(4)
    T[:3, 3] = [WGS84_A_M, 0, 0]
    sheared = T.copy()
    sheared[0, 1] = 0.2
    with pytest.raises(InvalidInputError, match="not a rigid transform"):
        GeoReference.from_ecef(sheared)
    with pytest.raises(InvalidInputError, match="Earth's centre"):
        GeoReference.from_ecef(np.eye(4))  # the world origin at the Earth's centre
    with pytest.raises(InvalidInputError, match="origin or T_ecef_from_world"):
        GeoReference.from_dict({})
