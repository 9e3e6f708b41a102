"""Projection-guided matching on synthetic street scenes whose descriptors alias: every
world point's descriptor also appears, a few bits off, at another place in the query
image (repeated facades, a lamp-lit night), so the global ratio test keeps few matches
while a search around each point's predicted position keeps most."""

import math
from dataclasses import replace

import numpy as np
import pytest

from monoloc.core.camera import KITTI_CAM0 as CAM
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import (
    T_world_from_cam_planar,
    invert_rigid,
    planar_from_T_world_from_cam,
)
from monoloc.server.localize import PoseConfig, ReferenceEntry, pose_hypotheses
from monoloc.server.vision.joint import PooledConfig, estimate_pooled_pose
from monoloc.server.vision.matching import MatchConfig, match_against_references, match_descriptors
from monoloc.server.vision.pnp import PnpConfig
from monoloc.server.vision.projection import (
    KeypointGrid,
    ProjectionMatchConfig,
    match_by_projection,
)

# a wide window for these scenes' poses a few decimetres off (the localizer's is 8 px)
WINDOW = ProjectionMatchConfig(radius_px=40.0)


def _flip_bits(rng, descriptors, n_bits):
    out = descriptors.copy()
    for row in out:
        for bit in rng.choice(256, n_bits, replace=False):
            row[bit // 8] ^= np.uint8(1 << (bit % 8))
    return out


def _aliased_scene(seed, n=300, n_refs=3, noise_px=0.5):
    """Query pose, query keypoints/descriptors, and references (T_world_from_ref, points
    (M, 3) in the ref frame, descriptors, index of each ref point's true query keypoint)."""
    rng = np.random.default_rng(seed)
    T_world_from_query = T_world_from_cam_planar(50.0, 20.0, rng.uniform(-np.pi, np.pi), 1.65)
    pixels = np.stack(
        [rng.uniform(0, CAM.width_px - 1, n), rng.uniform(0, CAM.height_px - 1, n)], 1
    )
    depth = rng.uniform(6.0, 40.0, n)
    points_cam = np.stack(
        [(pixels[:, 0] - CAM.cx) / CAM.fx * depth, (pixels[:, 1] - CAM.cy) / CAM.fy * depth, depth],
        1,
    )
    points_world = points_cam @ T_world_from_query[:3, :3].T + T_world_from_query[:3, 3]
    descriptors = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    # the query sees every point (a few bits off) and, far from it, a twin of its look
    seen = _flip_bits(rng, descriptors, 6)
    twins = _flip_bits(rng, descriptors, 6)
    twin_pixels = (pixels + np.array([CAM.width_px / 2, CAM.height_px / 2])) % np.array(
        [CAM.width_px, CAM.height_px]
    )
    keypoints = np.concatenate([pixels + rng.normal(0, noise_px, (n, 2)), twin_pixels])
    query_descriptors = np.concatenate([seen, twins])
    query = planar_from_T_world_from_cam(T_world_from_query)
    refs = []
    for _ in range(n_refs):
        along = rng.uniform(-4.0, 4.0)
        T_world_from_ref = T_world_from_cam_planar(
            query[0] + along * math.cos(query[2]), query[1] + along * math.sin(query[2]),
            query[2] + rng.uniform(-0.05, 0.05), 1.65,
        )  # fmt: skip
        keep = np.flatnonzero(rng.random(n) < 0.7)
        T_ref_from_world = invert_rigid(T_world_from_ref)
        points_ref = points_world[keep] @ T_ref_from_world[:3, :3].T + T_ref_from_world[:3, 3]
        refs.append((T_world_from_ref, points_ref, _flip_bits(rng, descriptors[keep], 4), keep))
    return T_world_from_query, keypoints, query_descriptors, refs


def _moved(T_world_from_cam, dx_m, dyaw_rad):
    x, y, yaw = planar_from_T_world_from_cam(T_world_from_cam)
    return T_world_from_cam_planar(
        x + dx_m * math.cos(yaw + 1.0), y + dx_m * math.sin(yaw + 1.0), yaw + dyaw_rad, 1.65
    )


@pytest.mark.parametrize("seed", range(3))
def test_projection_keeps_the_matches_the_global_ratio_test_loses_to_aliasing(seed):
    T_world_from_query, keypoints, descriptors, refs = _aliased_scene(seed)
    guess = _moved(T_world_from_query, 0.3, math.radians(0.5))  # a pose a little off
    grid = KeypointGrid(keypoints, descriptors, CAM, WINDOW.radius_px)
    for T_world_from_ref, points_ref, ref_descriptors, truth in refs:
        projected = match_by_projection(
            grid, ref_descriptors, points_ref,
            invert_rigid(guess) @ T_world_from_ref, WINDOW,
        )  # fmt: skip
        right = np.mean(projected[:, 0] == truth[projected[:, 1]])
        global_ = match_descriptors(descriptors, ref_descriptors, MatchConfig())
        assert len(projected) >= 0.8 * len(points_ref)
        assert right >= 0.98
        assert len(global_) <= 0.3 * len(points_ref)  # the twins defeat the ratio test
        assert len(np.unique(projected[:, 0])) == len(projected)  # one match per keypoint


def test_projected_matches_give_the_pose_and_a_wrong_prediction_gives_none():
    T_world_from_query, keypoints, descriptors, refs = _aliased_scene(7)
    pnp, pooled = PnpConfig(), PooledConfig()

    def pooled_pose(guess):
        grid = KeypointGrid(keypoints, descriptors, CAM, WINDOW.radius_px)
        matches = [
            match_by_projection(grid, d, p, invert_rigid(guess) @ T, WINDOW) for T, p, d, _ in refs
        ]
        return estimate_pooled_pose(
            keypoints, [r[0] for r in refs], [r[1] for r in refs], matches, CAM, pnp,
            np.random.default_rng(0), pooled,
        )  # fmt: skip

    found = pooled_pose(_moved(T_world_from_query, 0.4, math.radians(-0.8)))
    assert found is not None
    delta = invert_rigid(found.T_world_from_cam) @ T_world_from_query
    assert np.linalg.norm(delta[:3, 3]) < 0.05
    # a prediction 15 m off: its windows hold other points' keypoints; no consensus
    assert pooled_pose(_moved(T_world_from_query, 15.0, math.radians(4.0))) is None


def test_each_entrys_pose_refined_by_projection_keeps_more_inliers_and_comes_closer():
    """pose_hypotheses with the default pose stage refits every entry's pose on the entry's
    points matched around where that pose projects them; same hypotheses, more inliers,
    smaller errors than the poses from the aliased global matches alone."""
    gains, plain_errors, refined_errors = [], [], []
    for seed in range(4):
        T_world_from_query, keypoints, descriptors, scene_refs = _aliased_scene(seed, noise_px=1.0)
        refs = [ReferenceEntry(j, T, d, p) for j, (T, p, d, _) in enumerate(scene_refs)]
        matches = match_against_references(descriptors, [r.descriptors for r in refs])
        e_vlad = {r.entry_id: 0.5 for r in refs}
        solved = {}
        for name, config in (
            ("plain", PoseConfig(joint=None, refine=None)),
            ("refined", PoseConfig(joint=None)),
        ):
            hypotheses, _ = pose_hypotheses(
                keypoints, refs, matches, e_vlad, CAM, config, np.random.default_rng(seed),
                descriptors=descriptors,
            )  # fmt: skip
            solved[name] = {h.entry_id: h for h in hypotheses}
            assert len(solved[name]) == len(hypotheses)  # one per entry, no pose of several
        assert solved["plain"].keys() == solved["refined"].keys() and solved["plain"]
        for entry_id, plain in solved["plain"].items():
            refined = solved["refined"][entry_id]
            gains.append(refined.n_inliers / plain.n_inliers)
            for h, out in ((plain, plain_errors), (refined, refined_errors)):
                out.append(np.linalg.norm(h.T_world_from_cam[:3, 3] - T_world_from_query[:3, 3]))
    assert min(gains) > 1.5  # the twins cost the global matches most of each entry's points
    assert np.mean(refined_errors) < 0.7 * np.mean(plain_errors)


def test_a_pooled_pose_is_refined_by_projection_too():
    """Entries each too sparse for a pose of their own (a PnP config asking 40 inliers)
    give one pooled pose; with the default pose stage it is refit on every entry's points
    matched by projection from it: more inliers, closer to the truth, still pooled."""
    pnp = PnpConfig(min_inliers=40)
    plain_errors, refined_errors = [], []
    for seed in range(3):
        T_world_from_query, keypoints, descriptors, scene_refs = _aliased_scene(
            seed, n_refs=4, noise_px=1.0
        )
        refs = [ReferenceEntry(j, T, d, p) for j, (T, p, d, _) in enumerate(scene_refs)]
        matches = match_against_references(descriptors, [r.descriptors for r in refs])
        e_vlad = {r.entry_id: 0.5 for r in refs}
        pooled = {}
        for name, config in (
            ("plain", PoseConfig(pnp=pnp, refine=None)),
            ("refined", PoseConfig(pnp=pnp)),
        ):
            hypotheses, _ = pose_hypotheses(
                keypoints, refs, matches, e_vlad, CAM, config, np.random.default_rng(seed),
                descriptors=descriptors,
            )  # fmt: skip
            assert [h.method for h in hypotheses] == ["pooled"]
            pooled[name] = hypotheses[0]
        assert pooled["refined"].n_inliers > 2 * pooled["plain"].n_inliers
        assert len(pooled["refined"].entry_ids) >= 2
        for name, out in (("plain", plain_errors), ("refined", refined_errors)):
            T = pooled[name].T_world_from_cam
            out.append(np.linalg.norm(T[:3, 3] - T_world_from_query[:3, 3]))
    assert np.mean(refined_errors) < 0.7 * np.mean(plain_errors)


def test_refinement_needs_the_query_descriptors():
    _, keypoints, descriptors, scene_refs = _aliased_scene(0)
    refs = [ReferenceEntry(j, T, d, p) for j, (T, p, d, _) in enumerate(scene_refs)]
    matches = match_against_references(descriptors, [r.descriptors for r in refs])
    with pytest.raises(InvalidInputError, match="descriptors"):
        pose_hypotheses(
            keypoints, refs, matches, {j: 0.5 for j in range(3)}, CAM, PoseConfig(),
            np.random.default_rng(0),
        )  # fmt: skip


def test_points_behind_too_close_or_beyond_the_window_margin_are_not_matched():
    rng = np.random.default_rng(2)
    descriptors = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    centre = np.array([CAM.cx, CAM.cy])

    def matched(point_cam, keypoint_px):
        grid = KeypointGrid(np.array([keypoint_px]), descriptors[:1], CAM, WINDOW.radius_px)
        found = match_by_projection(grid, descriptors[:1], np.array([point_cam]), np.eye(4), WINDOW)
        return len(found) == 1

    assert matched([0.0, 0.0, 10.0], centre)  # in front, at the principal point
    assert not matched([0.0, 0.0, -10.0], centre)  # behind the camera
    assert not matched([0.0, 0.0, 0.2], centre)  # closer than min_depth_m
    # 30 px left of the image: its window still reaches a keypoint on the border
    left = [(-30.0 - CAM.cx) / CAM.fx * 10.0, 0.0, 10.0]
    assert matched(left, [0.0, CAM.cy])
    assert not matched(left, [15.0, CAM.cy])  # 45 px away: outside the window


def test_window_rule_nearest_in_the_radius_ratio_and_ties():
    rng = np.random.default_rng(1)
    ref_desc = rng.integers(0, 256, (1, 32), dtype=np.uint8)
    point = np.array([[0.0, 0.0, 10.0]])  # projects to the principal point
    centre = np.array([CAM.cx, CAM.cy])
    near = _flip_bits(rng, ref_desc, 3)
    far_twin = ref_desc.copy()  # identical, but outside the window
    keypoints = np.array([centre + [5.0, 0.0], centre + [300.0, 0.0]])

    def run(kps, descs, **cfg):
        grid = KeypointGrid(kps, np.concatenate(descs), CAM, WINDOW.radius_px)
        return match_by_projection(grid, ref_desc, point, np.eye(4), replace(WINDOW, **cfg))

    assert run(keypoints, [near, far_twin]).tolist() == [[0, 0]]
    # a rival inside the window, as close as the match: the ratio test refuses both
    assert len(run(np.array([centre + [5, 0], centre + [-5, 0]]), [near, near])) == 0
    # too many bits off
    assert len(run(keypoints[:1], [_flip_bits(rng, ref_desc, 80)])) == 0
    # two reference points both nearest to one keypoint at equal distance: no match
    grid = KeypointGrid(keypoints[:1], near, CAM, WINDOW.radius_px)
    twice = match_by_projection(
        grid, np.concatenate([ref_desc, ref_desc]), np.repeat(point, 2, 0), np.eye(4), WINDOW,
    )  # fmt: skip
    assert len(twice) == 0


def test_bad_configs_and_inputs_are_refused():
    for bad in ({"radius_px": 0.0}, {"ratio": 1.5}, {"max_hamming_bits": 300}, {"min_depth_m": 0}):
        with pytest.raises(InvalidInputError):
            ProjectionMatchConfig(**bad)
    with pytest.raises(InvalidInputError):
        KeypointGrid(np.zeros((3, 2)), np.zeros((2, 32), np.uint8), CAM, 40.0)
    with pytest.raises(InvalidInputError, match="radius"):
        KeypointGrid(np.zeros((2, 2)), np.zeros((2, 32), np.uint8), CAM, 0.0)
    with pytest.raises(InvalidInputError, match="NaN"):
        KeypointGrid(np.full((2, 2), np.nan), np.zeros((2, 32), np.uint8), CAM, 8.0)
    grid = KeypointGrid(np.zeros((1, 2)), np.zeros((1, 32), np.uint8), CAM, 40.0)
    with pytest.raises(InvalidInputError, match="uint8"):  # float descriptors
        match_by_projection(grid, np.zeros((2, 32)), np.zeros((2, 3)), np.eye(4), WINDOW)
    with pytest.raises(InvalidInputError, match="grid"):  # the grid's cells are 40 px
        match_by_projection(
            grid, np.zeros((2, 32), np.uint8), np.zeros((2, 3)), np.eye(4), ProjectionMatchConfig()
        )
