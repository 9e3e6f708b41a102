"""The drive's track as GeoJSON (RFC 7946): the particle filter's estimate placed on the
WGS84 ellipsoid through the map's geographic reference (``monoloc.core.geo``, pymap3d).

One ``FeatureCollection``: a ``LineString`` of the estimate's positions, then one
``Point`` per frame with an estimate, in frame order. That is every frame from the one
that initialised the filter on, those without hypotheses (dead reckoning) included: the
same frames and planar poses as the TUM / KITTI files of the drive. Coordinates are
``[lon, lat, h]`` (degrees, degrees, metres above the WGS84 ellipsoid), as RFC 7946
orders them.

The filter estimates a planar pose (x, y, yaw); the GeoPose needs a 3D pose:

- **height**: the camera's world z is the median of the heights (world z of
  ``T_world_from_cam``) of the best hypotheses of the last ``height_window`` frames that
  had one, held through frames without: PnP heights scatter by centimetres from frame to
  frame, while a vehicle's camera rides at a near-constant height over the road (the
  window still follows a slope). Before any hypothesis height is known (never, in
  practice: the filter starts on a frame with hypotheses) the height is 0, the world's
  ground plane, as in the TUM file;
- **orientation**: a level camera (no roll, no pitch) looking along the estimate's yaw,
  as in the TUM file.

Each ``Point``'s properties: ``frame``, ``t_s``, ``source`` (``initialisation``: the frame
that started the filter; ``measurement_update``: the frame's hypotheses weighed the
particles; ``dead_reckoning``: no hypotheses, the filter only predicted), ``n_hypotheses``,
``geopose`` (the estimate's OGC GeoPose), ``estimate_world`` (the planar estimate and the
height used, in the map's world) and ``best_hypothesis_geopose`` (the GeoPose the server
gave the frame's best hypothesis, or null when the frame had none).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geo import GeoReference
from monoloc.core.geometry import T_world_from_cam_planar

HEIGHT_WINDOW_FRAMES = 10

SOURCE_INITIALISATION = "initialisation"
SOURCE_UPDATE = "measurement_update"
SOURCE_DEAD_RECKONING = "dead_reckoning"


def track_heights_m(best_heights_m: np.ndarray, window: int = HEIGHT_WINDOW_FRAMES) -> np.ndarray:
    """Per frame (N,), the median of the last ``window`` finite values of
    ``best_heights_m`` (N,) up to and including the frame (NaN: the frame had no
    hypothesis); 0 before the first finite one."""
    if window < 1:
        raise InvalidInputError(f"height window must be >= 1 frame, got {window}")
    heights = np.asarray(best_heights_m, dtype=np.float64).reshape(-1)
    out = np.zeros(len(heights))
    recent: list[float] = []
    for i, h in enumerate(heights):
        if np.isfinite(h):
            recent = (recent + [float(h)])[-window:]
        if recent:
            out[i] = float(np.median(recent))
    return out


def estimate_sources(estimates_world: np.ndarray, n_hypotheses: np.ndarray) -> list[str | None]:
    """Per frame, where the filter's estimate (N, 3) came from (the module's docstring);
    None for a frame without an estimate."""
    has_estimate = np.all(np.isfinite(np.asarray(estimates_world, dtype=np.float64)), axis=1)
    sources: list[str | None] = []
    started = False
    for ok, n in zip(has_estimate, np.asarray(n_hypotheses), strict=True):
        if not ok:
            sources.append(None)
        elif not started:
            sources.append(SOURCE_INITIALISATION)
        else:
            sources.append(SOURCE_UPDATE if n > 0 else SOURCE_DEAD_RECKONING)
        started = started or bool(ok)
    return sources


def track_geojson(
    name: str,
    geo: GeoReference,
    timestamps_s: np.ndarray,
    estimates_world: np.ndarray,
    n_hypotheses: np.ndarray,
    best_heights_m: np.ndarray,
    best_geoposes: Sequence[dict | None],
    height_window: int = HEIGHT_WINDOW_FRAMES,
) -> dict | None:
    """The FeatureCollection of the filter's track (estimates (N, 3) x_m, y_m, yaw_rad in
    the map's world, NaN rows before initialisation; per frame its number of hypotheses,
    its best hypothesis' height (NaN: none) and GeoPose (None: none)); None when the
    filter gave no estimate."""
    estimates = np.asarray(estimates_world, dtype=np.float64).reshape(-1, 3)
    n = len(estimates)
    if not len(timestamps_s) == len(n_hypotheses) == len(best_heights_m) == len(best_geoposes) == n:
        raise InvalidInputError("the per-frame arrays of a track must have one row per frame")
    frames = np.flatnonzero(np.all(np.isfinite(estimates), axis=1))
    if len(frames) == 0:
        return None
    heights = track_heights_m(best_heights_m, height_window)
    sources = estimate_sources(estimates, n_hypotheses)
    T_world_from_cam = np.stack(
        [T_world_from_cam_planar(*estimates[i], height_m=heights[i]) for i in frames]
    )
    geoposes = geo.geoposes(T_world_from_cam)
    points, coordinates = [], []
    for i, geopose in zip(frames, geoposes, strict=True):
        position = [geopose.lon_deg, geopose.lat_deg, geopose.h_m]
        coordinates.append(position)
        x_m, y_m, yaw_rad = (float(v) for v in estimates[i])
        properties = {
            "frame": int(i),
            "t_s": float(timestamps_s[i]),
            "source": sources[i],
            "n_hypotheses": int(n_hypotheses[i]),
            "geopose": geopose.to_json(),
            "estimate_world": {
                "x_m": x_m,
                "y_m": y_m,
                "yaw_rad": yaw_rad,
                "z_m": float(heights[i]),
            },
            "best_hypothesis_geopose": best_geoposes[i],
        }
        points.append(
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": position},
                "properties": properties,
            }
        )
    line = {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": coordinates},
        "properties": {
            "name": name,
            "frames": len(points),
            "positions": "the particle filter's estimate (as in the TUM / KITTI files)",
            "height": f"median height of the best hypotheses of the last {height_window} "
            "frames that had one",
            "orientation": "level camera along the estimate's yaw",
        },
    }
    # a LineString needs two positions (RFC 7946 3.1.4)
    features = ([line] if len(coordinates) >= 2 else []) + points
    return {"type": "FeatureCollection", "features": features}


def write_track_geojson(path: Path, collection: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(collection, indent=1))
    return path
