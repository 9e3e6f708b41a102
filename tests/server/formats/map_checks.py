"""What the format tests ask of an imported map: that it localizes query frames."""

from __future__ import annotations

import numpy as np

from monoloc.core.geometry import planar_from_T_world_from_cam


def query_position_errors_m(registry, map_id: int, query_run, frames=slice(1, 5)) -> list[float]:
    """Per query frame of ``query_run`` (the ``frames`` slice of its frames) the planar
    position error (m) of the map's best hypothesis against the frame's true pose; inf
    where the frame got none. One seeded rng for the whole pass."""
    from monoloc.server.localize import LocalizeConfig

    rng = np.random.default_rng(0)
    errors = []
    for frame in query_run.frames[frames]:
        result, _ = registry.localize(
            map_id, query_run.load(frame).image_gray, LocalizeConfig(), rng
        )
        true_xy = planar_from_T_world_from_cam(frame.T_world_from_cam)[:2]
        best = result.best
        error_m = np.inf if best is None else np.linalg.norm(best.pose_world[:2] - true_xy)
        errors.append(float(error_m))
    return errors
