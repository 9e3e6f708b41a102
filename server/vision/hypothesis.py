"""Global pose hypotheses from a reference's pose and a relative pose (docs/method.md 6.5)."""

from __future__ import annotations

import numpy as np

from monoloc.core.geometry import check_rigid, planar_from_T_world_from_cam


def compose_hypothesis(T_world_from_ref: np.ndarray, T_ref_from_query: np.ndarray) -> np.ndarray:
    """T_world_from_query = T_world_from_ref @ T_ref_from_query, both (4, 4) rigid.

    Raises InvalidInputError if either is not a finite rigid transform (a rejected
    :class:`~server.vision.pnp.RelativePose` carries NaNs: filter on ``accepted`` first).
    """
    T_world_from_ref = check_rigid(T_world_from_ref, "T_world_from_ref")
    T_ref_from_query = check_rigid(T_ref_from_query, "T_ref_from_query")
    return T_world_from_ref @ T_ref_from_query


def planar_hypothesis(T_world_from_ref: np.ndarray, T_ref_from_query: np.ndarray) -> np.ndarray:
    """Planar pose z = (X, Y, psi) of the query camera, (3,) float64 (docs/method.md 6.5, 9)."""
    return planar_from_T_world_from_cam(compose_hypothesis(T_world_from_ref, T_ref_from_query))
