"""The true camera poses of a generated urban dataset, in the frame its files use.

The files carry what a recording would measure (``monoloc.sim.recording``): ground-truth
poses with INS-like errors. The true poses are not written; they are re-planned here
from the dataset's config (planning is cheap and deterministic in the seed), so a
benchmark can tell what the recording errors alone cost.
"""

from __future__ import annotations

import numpy as np

from monoloc.core.geometry import invert_rigid, planar_from_T_world_from_cam
from monoloc.sim.urban.city import build_city
from monoloc.sim.urban.runs import plan_runs, true_camera_poses


def true_planar_poses(config, T_simworld_from_zupworld: np.ndarray) -> dict[str, np.ndarray]:
    """Per run kind of ``config`` (the ``monoloc.sim.generate.GenerateConfig`` the dataset
    was generated with; its size, seed, runs, max_frames, vehicle and rig matter), the
    true planar camera poses (N, 3) (X m, Y m, psi rad) in the dataset's z-up world, whose
    tie to the sim's city frame is dataset.json's ``T_simworld_from_zupworld`` (4, 4)."""
    city = build_city(config.city_config(), config.seed)
    T_zup_from_sim = invert_rigid(np.asarray(T_simworld_from_zupworld, dtype=np.float64))
    out = {}
    for plan in plan_runs(city, config):
        poses = T_zup_from_sim @ true_camera_poses(plan, config.rig)
        out[plan.kind] = np.array([planar_from_T_world_from_cam(T) for T in poses])
    return out
