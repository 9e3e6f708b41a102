"""The drive's track as GeoJSON (RFC 7946), from the GeoPoses a geo-referenced map answers.

One ``FeatureCollection``: a ``LineString`` of the frames' positions in order, then one
``Point`` per frame with its properties (frame index, time, number of hypotheses, the
GeoPose's quaternion, the filter's planar estimate in the map's world). The positions are
the GeoPose of each frame's best hypothesis (the one ``LocalizeAnswer.best_pose_world``
names): the vehicle library does no geodesy, so the filter's own estimate is given in
the map's world only. Coordinates are ``[lon, lat, h]`` (degrees, degrees, metres above
the WGS84 ellipsoid), as RFC 7946 orders them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np


def _estimate(row: np.ndarray) -> dict | None:
    if not np.all(np.isfinite(row)):
        return None
    return {"x_m": float(row[0]), "y_m": float(row[1]), "yaw_rad": float(row[2])}


def track_geojson(
    name: str,
    timestamps_s: np.ndarray,
    geoposes: Sequence[dict | None],
    estimates_world: np.ndarray,
) -> dict | None:
    """The FeatureCollection of the frames that have a GeoPose, or None when none has."""
    points, coordinates = [], []
    for i, geopose in enumerate(geoposes):
        if geopose is None:
            continue
        p = geopose["position"]
        position = [float(p["lon"]), float(p["lat"]), float(p["h"])]
        if not all(math.isfinite(v) for v in position):
            continue
        coordinates.append(position)
        properties = {
            "frame": i,
            "t_s": float(timestamps_s[i]),
            "quaternion": geopose["quaternion"],
            "estimate_world": _estimate(np.asarray(estimates_world[i])),
        }
        points.append(
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": position},
                "properties": properties,
            }
        )
    if not points:
        return None
    line = {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": coordinates},
        "properties": {
            "name": name,
            "frames": len(points),
            "positions": "GeoPose of each frame's best hypothesis",
        },
    }
    # a LineString needs two positions (RFC 7946 3.1.4)
    features = ([line] if len(coordinates) >= 2 else []) + points
    return {"type": "FeatureCollection", "features": features}


def write_track_geojson(path: Path, collection: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(collection, indent=1))
    return path
