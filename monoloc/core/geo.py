"""Geo-referenced maps: the map's z-up world placed on the WGS84 ellipsoid, and poses
given as OGC GeoPose (Basic-Quaternion). Conversions through ``pymap3d`` (pure Python,
a base dependency). The one implementation: the server answers hypotheses with it, the
vehicle (``monoloc.client.geojson``) converts its filter's track with it.

A reference is given one of two ways, and is held as ``T_ecef_from_world`` (4, 4):

- an **origin**: the WGS84 latitude, longitude (degrees) and ellipsoidal height (m) of
  the world's origin, and the compass heading of the world's +X axis (degrees clockwise
  from true north: 90 means +X points east, and the world is then the local ENU frame
  at the origin). The world's +Z is the origin's local up;
- an **ECEF transform** ``T_ecef_from_world``: a rigid transform from the map's world to
  WGS84 ECEF (metres), e.g. from a survey.

GeoPose (OGC GeoPose 1.0, Basic-Quaternion): ``position`` {lat, lon (degrees), h
(metres above the WGS84 ellipsoid)} of the camera centre, ``quaternion`` {x, y, z, w}
(Hamilton, unit) of the camera's orientation in the local East-North-Up tangent frame at
that position: it rotates the camera frame's axes (monoloc's camera frame is OpenCV's:
x right, y down, z forward) into ENU, i.e. ``R_enu_from_cam``. So a camera looking due
north, level, has its z axis along ENU's +Y (north) and its y axis along -Z (down).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import check_rigid, quaternion_xyzw_from_R

# Bounds of a sensible reference (the API's schema says the same).
MAX_ABS_LAT_DEG = 90.0
MAX_ABS_LON_DEG = 180.0
MIN_HEIGHT_M, MAX_HEIGHT_M = -12_000.0, 100_000.0
# |ECEF origin| of a point between MIN_HEIGHT_M and MAX_HEIGHT_M on the ellipsoid
_MIN_ECEF_NORM_M, _MAX_ECEF_NORM_M = 6_356_752.0 - 12_000.0, 6_378_137.0 + 100_000.0


@dataclass(frozen=True)
class GeoOrigin:
    """The world origin's WGS84 position and the heading of the world's +X axis."""

    lat_deg: float
    lon_deg: float
    h_m: float
    x_axis_heading_deg: float

    def __post_init__(self) -> None:
        values = (self.lat_deg, self.lon_deg, self.h_m, self.x_axis_heading_deg)
        if not all(np.isfinite(v) for v in values):
            raise InvalidInputError(f"a geographic origin must be finite numbers, got {values}")
        if abs(self.lat_deg) > MAX_ABS_LAT_DEG:
            raise InvalidInputError(f"lat_deg must be in [-90, 90], got {self.lat_deg}")
        if abs(self.lon_deg) > MAX_ABS_LON_DEG:
            raise InvalidInputError(f"lon_deg must be in [-180, 180], got {self.lon_deg}")
        if not MIN_HEIGHT_M <= self.h_m <= MAX_HEIGHT_M:
            raise InvalidInputError(
                f"h_m must be in [{MIN_HEIGHT_M:g}, {MAX_HEIGHT_M:g}] m, got {self.h_m}"
            )
        if not 0.0 <= self.x_axis_heading_deg < 360.0:
            raise InvalidInputError(
                f"x_axis_heading_deg must be in [0, 360), got {self.x_axis_heading_deg}"
            )


def R_ecef_from_enu(lat_deg, lon_deg) -> np.ndarray:
    """(3, 3) (or (N, 3, 3) for arrays of N latitudes and longitudes) whose columns are the
    local East, North, Up unit vectors in ECEF (pymap3d's ``enu2uvw`` of the three axes)."""
    import pymap3d

    lat, lon = np.asarray(lat_deg, dtype=np.float64), np.asarray(lon_deg, dtype=np.float64)
    ones, zeros = np.ones_like(lat), np.zeros_like(lat)
    axes = ((ones, zeros, zeros), (zeros, ones, zeros), (zeros, zeros, ones))
    columns = [np.stack(pymap3d.enu2uvw(*axis, lat, lon), axis=-1) for axis in axes]
    return np.stack(columns, axis=-1)  # (..., 3 ECEF components, 3 axes)


def _R_enu_from_world(x_axis_heading_deg: float) -> np.ndarray:
    """World -> ENU at the origin: a turn about up by the +X axis' angle from east
    (counter-clockwise), 90 deg - its compass heading."""
    angle = np.deg2rad(90.0 - x_axis_heading_deg)
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class GeoReference:
    """A map's geographic reference; ``origin`` is set when it was given as one."""

    T_ecef_from_world: np.ndarray = field(repr=False)
    origin: GeoOrigin | None = None

    @classmethod
    def from_origin(cls, origin: GeoOrigin) -> GeoReference:
        import pymap3d

        T = np.eye(4)
        T[:3, :3] = R_ecef_from_enu(origin.lat_deg, origin.lon_deg) @ _R_enu_from_world(
            origin.x_axis_heading_deg
        )
        T[:3, 3] = pymap3d.geodetic2ecef(origin.lat_deg, origin.lon_deg, origin.h_m)
        return cls(T, origin)

    @classmethod
    def from_ecef(cls, T_ecef_from_world: np.ndarray) -> GeoReference:
        T = np.asarray(T_ecef_from_world, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InvalidInputError("T_ecef_from_world must be a finite 4x4 matrix")
        if np.abs(T[:3, :3]).max() > 1.0 + 1e-6:  # (and no overflow in the check below)
            raise InvalidInputError("T_ecef_from_world is not a rigid transform (|R_ij| > 1)")
        check_rigid(T, "T_ecef_from_world", tol=1e-6)
        norm = float(np.linalg.norm(T[:3, 3]))
        if not _MIN_ECEF_NORM_M <= norm <= _MAX_ECEF_NORM_M:
            raise InvalidInputError(
                f"T_ecef_from_world puts the world origin {norm:.0f} m from the Earth's "
                "centre, not near its surface (ECEF coordinates are in metres)"
            )
        return cls(T.copy())

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (the database column)."""
        data: dict[str, Any] = {"T_ecef_from_world": self.T_ecef_from_world.ravel().tolist()}
        if self.origin is not None:
            o = self.origin
            data["origin"] = {
                "lat_deg": o.lat_deg,
                "lon_deg": o.lon_deg,
                "h_m": o.h_m,
                "x_axis_heading_deg": o.x_axis_heading_deg,
            }
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> GeoReference:
        """Inverse of ``to_dict``; an origin, when present, is authoritative."""
        if data.get("origin") is not None:
            return cls.from_origin(GeoOrigin(**data["origin"]))
        values = np.asarray(data.get("T_ecef_from_world", ()), dtype=np.float64)
        if values.size != 16:
            raise InvalidInputError("a geo reference needs an origin or T_ecef_from_world")
        return cls.from_ecef(values.reshape(4, 4))

    # --- conversions ------------------------------------------------------------------

    def ecef_from_world(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world points (m) -> (N, 3) ECEF (m)."""
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        return p @ self.T_ecef_from_world[:3, :3].T + self.T_ecef_from_world[:3, 3]

    def geodetic_from_world(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 3) WGS84 (lat_deg, lon_deg, h_m)."""
        import pymap3d

        ecef = self.ecef_from_world(points_world)
        lat, lon, h = pymap3d.ecef2geodetic(ecef[:, 0], ecef[:, 1], ecef[:, 2])
        return np.column_stack([lat, lon, h])

    def world_from_geodetic(self, geodetic: np.ndarray) -> np.ndarray:
        """(N, 3) WGS84 (lat_deg, lon_deg, h_m) -> (N, 3) world points (m)."""
        import pymap3d

        g = np.asarray(geodetic, dtype=np.float64).reshape(-1, 3)
        ecef = np.column_stack(pymap3d.geodetic2ecef(g[:, 0], g[:, 1], g[:, 2]))
        R, t = self.T_ecef_from_world[:3, :3], self.T_ecef_from_world[:3, 3]
        return (ecef - t) @ R

    def geopose(self, T_world_from_cam: np.ndarray) -> GeoPose:
        """The camera's OGC GeoPose (see the module docstring)."""
        return self.geoposes(np.asarray(T_world_from_cam)[None])[0]

    def geoposes(self, T_world_from_cam: np.ndarray) -> list[GeoPose]:
        """GeoPoses of (N, 4, 4) camera poses (one pymap3d call per step for all N)."""
        T = np.asarray(T_world_from_cam, dtype=np.float64).reshape(-1, 4, 4)
        if len(T) == 0:
            return []
        geodetic = self.geodetic_from_world(T[:, :3, 3])
        R_enu_from_ecef = np.swapaxes(R_ecef_from_enu(geodetic[:, 0], geodetic[:, 1]), 1, 2)
        R_enu_from_cam = R_enu_from_ecef @ self.T_ecef_from_world[:3, :3] @ T[:, :3, :3]
        out = []
        for (lat, lon, h), R in zip(geodetic, R_enu_from_cam, strict=True):
            q = quaternion_xyzw_from_R(R)
            out.append(GeoPose(float(lat), float(lon), float(h), tuple(float(v) for v in q)))
        return out


@dataclass(frozen=True)
class GeoPose:
    """OGC GeoPose Basic-Quaternion: WGS84 position and ``R_enu_from_cam`` as (x, y, z, w)."""

    lat_deg: float
    lon_deg: float
    h_m: float
    quaternion_xyzw: tuple[float, float, float, float]

    def to_json(self) -> dict[str, Any]:
        """The standard's JSON encoding."""
        x, y, z, w = self.quaternion_xyzw
        return {
            "position": {"lat": self.lat_deg, "lon": self.lon_deg, "h": self.h_m},
            "quaternion": {"x": x, "y": y, "z": z, "w": w},
        }
