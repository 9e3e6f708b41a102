"""Guided PnP and the joint multi-entry pose on synthetic street scenes: a known query pose,
world points seen by several reference cameras, projected into the query image."""

import math

import numpy as np
import pytest

from bench.lab.paper import independent_pose_hypotheses
from monoloc.core.camera import KITTI_CAM0 as CAM
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import (
    T_world_from_cam_planar,
    invert_rigid,
    planar_from_T_world_from_cam,
    rotation_angle_rad,
    wrap_angle,
)
from monoloc.core.prior import RetrievalPrior
from monoloc.server.localize import AlternativeConfig, PoseConfig, ReferenceEntry, pose_hypotheses
from monoloc.server.vision.joint import (
    EntryInliers,
    JointConfig,
    PooledConfig,
    best_start,
    consistent_group,
    estimate_joint_pose,
    estimate_pooled_pose,
)
from monoloc.server.vision.pnp import (
    PnpConfig,
    estimate_relative_pose,
    estimate_relative_pose_guided,
)
from monoloc.server.vision.pose_covariance import position_spread_m

# "always its own RANSAC": a confirmation no frame of these scenes reaches
NEVER_CONFIRMED = 10**6


def _no_descriptors(**fields):
    """The pose stage for these scenes: correspondences without descriptors, so no
    refinement by projection (it needs the query's descriptors)."""
    return PoseConfig(**{"refine": None, **fields})


def _pose_error(T_a, T_b):
    delta = invert_rigid(T_a) @ T_b
    return np.linalg.norm(delta[:3, 3]), math.degrees(rotation_angle_rad(delta[:3, :3]))


def _street(rng, T_world_from_query, n=400):
    """World points (n, 3) 6-40 m in front of the query camera, within its image."""
    pixels = np.stack(
        [rng.uniform(0, CAM.width_px - 1, n), rng.uniform(0, CAM.height_px - 1, n)], 1
    )
    depth = rng.uniform(6.0, 40.0, n)
    points_cam = np.stack(
        [(pixels[:, 0] - CAM.cx) / CAM.fx * depth, (pixels[:, 1] - CAM.cy) / CAM.fy * depth, depth],
        1,
    )
    return points_cam @ T_world_from_query[:3, :3].T + T_world_from_query[:3, 3], pixels


def _entry(rng, points_world, pixels, T_world_from_ref, noise_px, outlier_fraction, subset=0.7):
    """One reference's correspondences: a random subset of the points in its camera frame,
    the query pixels with noise, a share of them replaced by random pixels (outliers)."""
    keep = rng.random(len(points_world)) < subset
    T_ref_from_world = invert_rigid(T_world_from_ref)
    points_ref = points_world[keep] @ T_ref_from_world[:3, :3].T + T_ref_from_world[:3, 3]
    observed = pixels[keep] + rng.normal(0.0, noise_px, (keep.sum(), 2))
    bad = rng.random(keep.sum()) < outlier_fraction
    observed[bad] = np.stack(
        [rng.uniform(0, CAM.width_px - 1, bad.sum()), rng.uniform(0, CAM.height_px - 1, bad.sum())],
        1,
    )
    return observed, points_ref


def _stacked(entries):
    """refs, matches and the query keypoints (N, 2) float32 of entries given as
    (T_world_from_ref, points_ref (M, 3), observed query pixels (M, 2)): one query keypoint
    per correspondence, so each entry's pairs index the stacked keypoints."""
    refs, matches, offset = [], [], 0
    for j, (T_world_from_ref, points_ref, observed) in enumerate(entries):
        refs.append(
            ReferenceEntry(j, T_world_from_ref, np.zeros((len(points_ref), 32)), points_ref)
        )
        m = len(observed)
        matches.append(np.stack([np.arange(offset, offset + m), np.arange(m)], 1))
        offset += m
    keypoints = np.concatenate([observed for _, _, observed in entries]).astype(np.float32)
    return refs, matches, keypoints


def _scene(seed, n_refs=5, noise_px=0.5, outlier_fraction=0.3):
    rng = np.random.default_rng(seed)
    T_world_from_query = T_world_from_cam_planar(
        100.0 + rng.uniform(-5, 5), -40.0 + rng.uniform(-5, 5), rng.uniform(-np.pi, np.pi), 1.65
    )
    points_world, pixels = _street(rng, T_world_from_query)
    query = planar_from_T_world_from_cam(T_world_from_query)
    entries = []
    for _ in range(n_refs):
        along = rng.uniform(-4.0, 4.0)
        T_world_from_ref = T_world_from_cam_planar(
            query[0] + along * math.cos(query[2]) + rng.uniform(-1, 1) * math.sin(query[2]),
            query[1] + along * math.sin(query[2]) - rng.uniform(-1, 1) * math.cos(query[2]),
            query[2] + rng.uniform(-0.1, 0.1),
            1.65,
        )
        observed, points_ref = _entry(
            rng, points_world, pixels, T_world_from_ref, noise_px, outlier_fraction
        )
        entries.append((T_world_from_ref, points_ref, observed))
    return T_world_from_query, *_stacked(entries)


@pytest.mark.parametrize("seed", range(6))
def test_guided_pnp_matches_full_ransac_on_clean_data(seed):
    T_world_from_query, refs, matches, keypoints = _scene(seed)
    config = _no_descriptors(joint=None)
    e_vlad = {r.entry_id: 0.8 for r in refs}
    guided, rej_g = pose_hypotheses(
        keypoints, refs, matches, e_vlad, CAM, config, np.random.default_rng(0)
    )
    # the paper's PnP (a bench baseline): every entry its own RANSAC
    full, rej_f = independent_pose_hypotheses(
        keypoints, refs, matches, e_vlad, CAM, config, np.random.default_rng(0)
    )
    assert not rej_g and not rej_f
    assert [h.entry_id for h in guided] == [h.entry_id for h in full] == list(range(len(refs)))
    # One entry (the most matches) searched from scratch, every other one guided.
    assert sorted(h.method for h in guided) == ["guided"] * (len(refs) - 1) + ["ransac"]
    assert {h.method for h in full} == {"ransac"}
    for g, f in zip(guided, full, strict=True):
        error_m, error_deg = _pose_error(g.T_world_from_cam, f.T_world_from_cam)
        assert error_m < 2e-3 and error_deg < 0.02
        assert abs(g.n_inliers - f.n_inliers) <= 2
        truth_m, _ = _pose_error(T_world_from_query, g.T_world_from_cam)
        assert truth_m < 0.05


def test_guided_pnp_falls_back_to_ransac_when_the_guess_keeps_too_few_inliers():
    T_world_from_query, refs, matches, keypoints = _scene(11)
    ref, pairs = refs[0], matches[0]
    pixels, points = keypoints[pairs[:, 0]], ref.points_cam[pairs[:, 1]]
    T_ref_from_query = invert_rigid(ref.T_world_from_cam) @ T_world_from_query
    # A guess 3 m to the side (e.g. an aliased entry's pose): few points project near
    # their pixels, so the entry must get its own RANSAC and still find the true pose.
    wrong = T_ref_from_query.copy()
    wrong[:3, 3] += [3.0, 0.0, 0.0]
    config = PnpConfig()
    rel = estimate_relative_pose_guided(
        pixels, points, [wrong], CAM, config, np.random.default_rng(0)
    )
    assert rel.accepted and rel.method == "ransac"
    assert _pose_error(T_ref_from_query, rel.T_ref_from_query)[0] < 0.05
    good = estimate_relative_pose_guided(
        pixels, points, [wrong, T_ref_from_query], CAM, config, np.random.default_rng(0)
    )
    assert good.accepted and good.method == "guided"
    assert _pose_error(T_ref_from_query, good.T_ref_from_query)[0] < 0.05
    # The same guess with a demanding ratio: the guided set is "too small", RANSAC decides.
    strict = PnpConfig(guided_min_inlier_ratio=1.0)
    assert (
        estimate_relative_pose_guided(
            pixels, points, [T_ref_from_query], CAM, strict, np.random.default_rng(0)
        ).method
        == "ransac"
    )


def test_guided_pnp_rejects_an_entry_of_another_place():
    rng = np.random.default_rng(3)
    n = 60
    pixels = np.stack([rng.uniform(0, CAM.width_px, n), rng.uniform(0, CAM.height_px, n)], 1)
    points = np.c_[rng.uniform(-10, 10, (n, 2)), rng.uniform(5, 40, n)]
    rel = estimate_relative_pose_guided(
        pixels, points, [np.eye(4)], CAM, PnpConfig(), np.random.default_rng(0)
    )
    assert not rel.accepted and rel.method == "ransac"


@pytest.mark.parametrize("seed", range(4))
def test_joint_pose_round_trip_recovers_the_query_pose(seed):
    # Known pose -> project -> joint PnP over every entry's inliers -> the same pose,
    # exactly without noise, and at least as close as the best single entry with noise.
    for noise_px, tol_m, tol_deg in ((0.0, 1e-6, 1e-5), (0.7, 0.03, 0.1)):
        T_world_from_query, refs, matches, keypoints = _scene(
            seed, noise_px=noise_px, outlier_fraction=0.2
        )
        e_vlad = {r.entry_id: 0.8 for r in refs}
        hyps, _ = pose_hypotheses(
            keypoints, refs, matches, e_vlad, CAM, _no_descriptors(), np.random.default_rng(seed)
        )
        joint = [h for h in hyps if h.joint]
        assert len(joint) == 1 and hyps[-1].joint and hyps[-1].method == "joint"
        joint = joint[0]
        assert sorted(joint.entry_ids) == list(range(len(refs)))
        assert joint.n_inliers > max(h.n_inliers for h in hyps if not h.joint)
        error_m, error_deg = _pose_error(T_world_from_query, joint.T_world_from_cam)
        assert error_m < tol_m and error_deg < tol_deg
        singles = [_pose_error(T_world_from_query, h.T_world_from_cam)[0] for h in hyps[:-1]]
        assert error_m <= np.median(singles) + 1e-9


def test_joint_pose_leaves_out_an_inconsistent_entry():
    poses = np.array([[0.0, 0.0, 0.1], [0.05, 0.02, 0.11], [12.0, 3.0, 0.1], [0.02, -0.03, 0.1]])
    group = consistent_group(poses, np.array([100, 80, 200, 50]), JointConfig())
    assert group[0] in (0, 1, 3) and sorted(group) == [0, 1, 3]
    assert wrap_angle(poses[group, 2] - poses[group[0], 2]).max() < JointConfig().yaw_gate_rad
    # The group is the one with the most inliers in total, not the most members.
    assert consistent_group(poses, np.array([100, 80, 300, 50]), JointConfig()) == [2]


def test_the_joint_pose_starts_from_the_member_pose_the_union_agrees_with_most():
    """Two member poses within the gates: the true one and one 0.45 m to the side and
    1.2 deg turned (distant facades' lateral / yaw ambiguity), listed first. The start is
    the pose under which more of the union reprojects within the threshold, whatever the
    order."""
    T_world_from_query, refs, matches, keypoints = _scene(3, noise_px=0.5, outlier_fraction=0.2)
    union = [
        EntryInliers(r.T_world_from_cam, keypoints[m[:, 0]], r.points_cam[m[:, 1]])
        for r, m in zip(refs, matches, strict=True)
    ]
    x, y, yaw = planar_from_T_world_from_cam(T_world_from_query)
    aside = T_world_from_cam_planar(
        x - 0.45 * math.sin(yaw), y + 0.45 * math.cos(yaw), yaw + math.radians(1.2), 1.65
    )
    assert best_start(union, [aside, T_world_from_query], CAM, PnpConfig()) == 1
    assert best_start(union, [T_world_from_query, aside], CAM, PnpConfig()) == 0
    assert best_start(union, [aside], CAM, PnpConfig()) == 0


def test_joint_pose_needs_two_entries():
    T_world_from_query, refs, matches, keypoints = _scene(5, n_refs=1)
    pairs = matches[0]
    one = EntryInliers(refs[0].T_world_from_cam, keypoints[pairs[:, 0]], refs[0].points_cam)
    assert estimate_joint_pose([one], T_world_from_query, CAM, PnpConfig(), JointConfig()) is None


def _with_mislabelled_entry(seed, subset):
    """A scene plus one more entry whose correspondences are right but whose map pose is
    5 m off (an aliased or mislabelled reference): its own RANSAC gives a pose 5 m away,
    which the other entries' poses do not explain."""
    T_world_from_query, refs, matches, keypoints = _scene(seed, n_refs=4, outlier_fraction=0.2)
    rng = np.random.default_rng(seed + 100)
    points_world, pixels = _street(rng, T_world_from_query)
    T_world_from_ref = T_world_from_query.copy()
    observed, points_ref = _entry(rng, points_world, pixels, T_world_from_ref, 0.5, 0.1, subset)
    T_labelled = T_world_from_ref.copy()
    T_labelled[:3, 3] += [5.0, 0.0, 0.0]
    refs.append(ReferenceEntry(len(refs), T_labelled, np.zeros((len(points_ref), 32)), points_ref))
    offset = len(keypoints)
    matches.append(
        np.stack([np.arange(offset, offset + len(observed)), np.arange(len(observed))], 1)
    )
    return (
        T_world_from_query,
        refs,
        matches,
        np.concatenate([keypoints, observed]).astype(np.float32),
    )


def _solve(refs, matches, keypoints, config, prior=None):
    e_vlad = {r.entry_id: 0.8 for r in refs}
    return pose_hypotheses(
        keypoints, refs, matches, e_vlad, CAM, config, np.random.default_rng(0), prior
    )


def test_no_fallback_ransac_once_two_entries_confirm_the_pose():
    # The mislabelled entry has the fewest matches: the others confirm the pose first.
    T_world_from_query, refs, matches, keypoints = _with_mislabelled_entry(7, subset=0.15)
    assert len(matches[-1]) == min(len(m) for m in matches)
    always, _ = _solve(
        refs,
        matches,
        keypoints,
        _no_descriptors(joint=None, fallback_until_confirmed=NEVER_CONFIRMED),
    )
    odd = [h for h in always if h.entry_id == refs[-1].entry_id]
    assert len(odd) == 1 and odd[0].method == "ransac"
    assert (
        np.hypot(*(odd[0].pose_world[:2] - planar_from_T_world_from_cam(T_world_from_query)[:2]))
        > 4.0
    )
    confirmed, rejected = _solve(refs, matches, keypoints, _no_descriptors(joint=None))
    assert [h.entry_id for h in confirmed] == [h.entry_id for h in always if h is not odd[0]]
    assert [e for e, _ in rejected] == [refs[-1].entry_id]
    assert "no own RANSAC" in rejected[0][1]


def test_fallback_ransac_still_runs_before_the_pose_is_confirmed():
    # The mislabelled entry has the most matches: its RANSAC pose (5 m off) guides the
    # others, which it does not explain; they fall back to their own RANSAC, agree with
    # each other, and every entry keeps its own hypothesis.
    T_world_from_query, refs, matches, keypoints = _with_mislabelled_entry(8, subset=1.0)
    assert len(matches[-1]) == max(len(m) for m in matches)
    hyps, rejected = _solve(refs, matches, keypoints, _no_descriptors(joint=None))
    assert not rejected and len(hyps) == len(refs)
    truth = planar_from_T_world_from_cam(T_world_from_query)
    good = [h for h in hyps if h.entry_id != refs[-1].entry_id]
    assert {h.method for h in good} == {"ransac", "guided"}
    assert all(np.hypot(*(h.pose_world[:2] - truth[:2])) < 0.05 for h in good)


def test_a_prior_with_a_heading_is_one_confirming_vote():
    # The filter's prediction (10 cm, 0.3 deg off) guides the first entry; that entry
    # agreeing with it confirms the pose, so the mislabelled entry gets no RANSAC even
    # with fallback_until_confirmed=2 and one entry solved so far.
    T_world_from_query, refs, matches, keypoints = _with_mislabelled_entry(7, subset=0.15)
    truth = planar_from_T_world_from_cam(T_world_from_query)
    prior = RetrievalPrior(
        truth[0] + 0.1, truth[1], 10.0, float(truth[2] + math.radians(0.3)), math.radians(20)
    )
    hyps, rejected = _solve(
        refs[:1] + refs[-1:],
        matches[:1] + matches[-1:],
        keypoints,
        _no_descriptors(joint=None),
        prior,
    )
    assert [h.method for h in hyps] == ["guided"]
    assert [e for e, _ in rejected] == [refs[-1].entry_id] and "no own RANSAC" in rejected[0][1]
    hyps, rejected = _solve(
        refs[:1] + refs[-1:],
        matches[:1] + matches[-1:],
        keypoints,
        _no_descriptors(joint=None, fallback_until_confirmed=NEVER_CONFIRMED),
        prior,
    )
    assert not rejected and sorted(h.method for h in hyps) == ["guided", "ransac"]


def test_count_inliers_agrees_with_the_inlier_errors():
    from monoloc.server.vision._pnp_kernel import count_inliers, inlier_errors

    rng = np.random.default_rng(4)
    T_world_from_query, refs, matches, keypoints = _scene(4, n_refs=1)
    pairs = matches[0]
    pixels = keypoints[pairs[:, 0]].astype(np.float64)
    points = refs[0].points_cam[pairs[:, 1]]
    T_query_from_ref = invert_rigid(T_world_from_query) @ refs[0].T_world_from_cam
    poses = [T_query_from_ref]
    for _ in range(5):  # perturbed poses, some with points behind the camera
        T = T_query_from_ref.copy()
        T[:3, 3] += rng.normal(0.0, [0.3, 0.3, 10.0])
        poses.append(T)
    R = np.ascontiguousarray(np.array([T[:3, :3] for T in poses]))
    t = np.ascontiguousarray(np.array([T[:3, 3] for T in poses]))
    counts = np.empty(len(poses), dtype=np.int64)
    K = CAM.K
    count_inliers(points, pixels, R, t, K[0, 0], K[1, 1], K[0, 2], K[1, 2], 3.0, counts)
    expected = []
    for g in range(len(poses)):
        errors, inliers = np.empty(len(points)), np.empty(len(points), dtype=bool)
        inlier_errors(
            points, pixels, R[g], t[g], K[0, 0], K[1, 1], K[0, 2], K[1, 2], 3.0, errors, inliers
        )
        expected.append(int(inliers.sum()))
    assert counts.tolist() == expected
    assert expected[0] > 0.6 * len(points) and min(expected) < expected[0]


def _sparse(scene, per_entry):
    """The scene with each entry cut to its first ``per_entry`` correspondences (a night
    frame: every entry under PnpConfig.min_inliers, the place seen by all of them)."""
    T_world_from_query, refs, matches, keypoints = scene
    return T_world_from_query, refs, [m[:per_entry] for m in matches], keypoints


@pytest.mark.parametrize("seed", range(4))
def test_a_frame_whose_entries_are_each_too_sparse_gets_one_pooled_pose(seed):
    T_world_from_query, refs, matches, keypoints = _sparse(
        _scene(seed, n_refs=5, outlier_fraction=0.3), per_entry=12
    )
    assert all(len(m) < PnpConfig().min_inliers for m in matches)
    no_pooled = _no_descriptors(pooled=None, alternative=None)
    without, rejected = _solve(refs, matches, keypoints, no_pooled)
    assert without == [] and len(rejected) == len(refs)
    hypotheses, _ = _solve(refs, matches, keypoints, _no_descriptors())
    assert [h.method for h in hypotheses] == ["pooled"]
    (pooled,) = hypotheses
    assert not pooled.joint and len(pooled.entry_ids) >= 2
    assert pooled.n_inliers >= PnpConfig().min_inliers
    position_m, angle_deg = _pose_error(pooled.T_world_from_cam, T_world_from_query)
    assert position_m < 0.15 and angle_deg < 0.5
    # its covariance, from the inliers of every member entry, describes its error
    assert _mahalanobis_sq(pooled, T_world_from_query, 0.5) < 16.3


def test_pooled_pnp_runs_only_for_a_frame_without_any_other_hypothesis():
    T_world_from_query, refs, matches, keypoints = _scene(2, n_refs=5, outlier_fraction=0.3)
    hypotheses, _ = _solve(refs, matches, keypoints, _no_descriptors())
    assert hypotheses and all(h.method != "pooled" for h in hypotheses)


def test_a_pose_one_entry_explains_alone_is_not_a_pooled_pose():
    """One entry's correct matches plus other entries whose matches are all wrong: RANSAC
    finds the pose, but with every inlier from one entry it is that entry's pose to give,
    not evidence pooled from several."""
    T_world_from_query, refs, matches, keypoints = _scene(3, n_refs=3, outlier_fraction=0.0)
    rng = np.random.default_rng(0)
    noise = [keypoints[m[:, 0]] for m in matches[1:]]
    scrambled = np.concatenate(
        [keypoints[matches[0][:, 0]]]
        + [
            np.stack(
                [rng.uniform(0, CAM.width_px, len(n)), rng.uniform(0, CAM.height_px, len(n))], 1
            )
            for n in noise
        ]
    )
    bounds = np.cumsum([0] + [len(m) for m in matches])
    pairs = [
        np.stack([np.arange(bounds[j], bounds[j + 1]), m[:, 1]], 1) for j, m in enumerate(matches)
    ]
    args = ([r.T_world_from_cam for r in refs], [r.points_cam for r in refs], pairs, CAM)
    own = estimate_relative_pose(
        scrambled[pairs[0][:, 0]], refs[0].points_cam, CAM, PnpConfig(), np.random.default_rng(1)
    )
    assert own.accepted  # the pose is there to find, from entry 0 alone
    pose = estimate_pooled_pose(
        scrambled, *args, PnpConfig(), np.random.default_rng(1), PooledConfig()
    )
    assert pose is None


def test_only_the_neighbours_of_the_entry_with_most_matches_are_pooled():
    """Entries that see one place are neighbours: an entry 100 m from the one with the
    most matches is left out of the pooled set (its matches, right or wrong, are not
    pooled), unless the radius reaches it."""
    T_world_from_query, refs, matches, keypoints = _sparse(
        _scene(11, n_refs=3, outlier_fraction=0.0), per_entry=12
    )
    # ties keep the scene's order: entry 0 is the anchor (12 matches each)
    far = np.array(T_world_from_query, dtype=np.float64)
    far[:3, 3] -= 100.0 * far[:3, 2]  # 100 m behind the query, looking the same way
    rng = np.random.default_rng(5)
    points_world, pixels = _street(rng, T_world_from_query, n=12)
    T_far_from_world = invert_rigid(far)
    points_far = points_world @ T_far_from_world[:3, :3].T + T_far_from_world[:3, 3]
    offset = len(keypoints)
    keypoints = np.concatenate([keypoints, pixels]).astype(np.float32)
    refs = [*refs, ReferenceEntry(len(refs), far, np.zeros((12, 32)), points_far)]
    matches = [*matches, np.stack([np.arange(offset, offset + 12), np.arange(12)], 1)]
    args = ([r.T_world_from_cam for r in refs], [r.points_cam for r in refs], matches, CAM)
    near = estimate_pooled_pose(
        keypoints, *args, PnpConfig(), np.random.default_rng(1), PooledConfig()
    )
    wide = estimate_pooled_pose(
        keypoints,
        *args,
        PnpConfig(),
        np.random.default_rng(1),
        PooledConfig(neighbour_radius_m=500.0),
    )
    assert near is not None and wide is not None
    assert len(refs) - 1 not in near.members and len(refs) - 1 in wide.members
    for pose in (near, wide):
        position_m, angle_deg = _pose_error(pose.T_world_from_cam, T_world_from_query)
        assert position_m < 0.15 and angle_deg < 0.5


def test_keypoint_scales_weigh_the_joint_pose_not_the_entries_poses_and_are_checked():
    """The query keypoints' pyramid scales weigh the joint pose's Cauchy refit and every
    pose's covariance; each entry's own pose counts every correspondence alike, so the
    scales leave it as it is."""
    T_world_from_query, refs, matches, keypoints = _scene(8)
    e_vlad = {r.entry_id: 0.8 for r in refs}

    def solve(scales):
        return pose_hypotheses(
            keypoints, refs, matches, e_vlad, CAM, _no_descriptors(), np.random.default_rng(0),
            None, scales,
        )[0]  # fmt: skip

    plain = solve(None)
    assert any(h.joint for h in plain)
    # Unit scales are full resolution: the very same poses and covariances.
    same = solve(np.ones(len(keypoints)))
    assert [h.T_world_from_cam.tolist() for h in same] == [
        h.T_world_from_cam.tolist() for h in plain
    ]
    for h_s, h_p in zip(same, plain, strict=True):
        np.testing.assert_array_equal(h_s.covariance_px1, h_p.covariance_px1)
    # Varied scales change the joint fit's weights and the covariances, not the truth.
    scales = 1.2 ** np.random.default_rng(1).integers(0, 8, len(keypoints))
    weighted = solve(scales)
    assert [h.method for h in weighted] == [h.method for h in plain]
    for h_w, h_p in zip(weighted, plain, strict=True):
        moved = not np.array_equal(h_w.T_world_from_cam, h_p.T_world_from_cam)
        assert moved == h_p.joint, h_p.method
        assert not np.allclose(h_w.covariance_px1, h_p.covariance_px1)
        assert _pose_error(h_w.T_world_from_cam, T_world_from_query)[0] < 0.1
    with pytest.raises(InvalidInputError, match="keypoint scales"):
        solve(np.ones(len(keypoints) - 1))


@pytest.mark.parametrize("seed", range(3))
def test_a_guess_guides_the_pooled_pose_without_its_ransac(seed):
    """A pose of the query found elsewhere (the pooled pose itself, when it is refit on
    matches by projection) chooses the pooled consensus (no RANSAC on the pooled matches:
    rng None would fail if one ran), and the result matches what the RANSAC finds. A
    wrong guess falls back to the RANSAC."""
    T_world_from_query, refs, matches, keypoints = _sparse(
        _scene(seed, n_refs=5, outlier_fraction=0.3), per_entry=12
    )
    args = ([r.T_world_from_cam for r in refs], [r.points_cam for r in refs], matches, CAM)
    guess = T_world_from_query.copy()
    guess[:3, 3] += [0.05, -0.04, 0.03]  # a pose found on fewer matches
    guided = estimate_pooled_pose(
        keypoints, *args, PnpConfig(), None, PooledConfig(), guesses_T_world_from_cam=[guess]
    )
    assert guided is not None and len(guided.members) >= 2
    ransac = estimate_pooled_pose(
        keypoints, *args, PnpConfig(), np.random.default_rng(seed), PooledConfig()
    )
    assert ransac is not None
    for pose in (guided, ransac):
        position_m, angle_deg = _pose_error(pose.T_world_from_cam, T_world_from_query)
        assert position_m < 0.15 and angle_deg < 0.5
    assert abs(guided.n_inliers - ransac.n_inliers) <= 2
    wrong = T_world_from_query.copy()
    wrong[:3, 3] += [8.0, 3.0, 0.0]
    fell_back = estimate_pooled_pose(
        keypoints, *args, PnpConfig(), np.random.default_rng(seed), PooledConfig(),
        guesses_T_world_from_cam=[wrong],
    )  # fmt: skip
    assert fell_back is not None
    assert _pose_error(fell_back.T_world_from_cam, T_world_from_query)[0] < 0.15
    with pytest.raises(AttributeError):  # the wrong guess left it to the RANSAC
        estimate_pooled_pose(
            keypoints, *args, PnpConfig(), None, PooledConfig(), guesses_T_world_from_cam=[wrong]
        )


def test_pooled_pnp_runs_usac_by_default_and_the_classic_ransac_finds_the_same_pose():
    T_world_from_query, refs, matches, keypoints = _sparse(
        _scene(6, n_refs=5, outlier_fraction=0.3), per_entry=12
    )
    args = ([r.T_world_from_cam for r in refs], [r.points_cam for r in refs], matches, CAM)
    assert PooledConfig().ransac == "usac"
    poses = [
        estimate_pooled_pose(
            keypoints, *args, PnpConfig(), np.random.default_rng(2), PooledConfig(ransac=method)
        )
        for method in ("usac", "opencv")
    ]
    assert all(pose is not None for pose in poses)
    for pose in poses:
        assert _pose_error(pose.T_world_from_cam, T_world_from_query)[0] < 0.15
    assert abs(poses[0].n_inliers - poses[1].n_inliers) <= 2
    with pytest.raises(InvalidInputError):
        PooledConfig(ransac="magic")


def _mahalanobis_sq(hypothesis, T_world_from_query, noise_px):
    """Squared Mahalanobis distance of a hypothesis's planar error under its covariance
    at the scene's pixel noise."""
    C = hypothesis.covariance_px1 * noise_px**2
    assert C.shape == (3, 3) and np.all(np.linalg.eigvalsh(C) > 0)
    e = planar_from_T_world_from_cam(T_world_from_query) - hypothesis.pose_world
    e[2] = wrap_angle(e[2])
    return float(e @ np.linalg.solve(C, e))


def test_each_hypothesis_carries_its_pose_covariance():
    """Every per-entry hypothesis gets the planar covariance of its own inliers (at 1 px),
    the joint pose that of the union's inliers, and with the scene's 0.5 px noise both
    describe the hypotheses' actual errors (squared Mahalanobis distances around
    chi-square, 3 dof: median 2.4); the joint pose, on more inliers, is pinned down
    better than any of its members."""
    per_entry, joint = [], []
    for seed in range(6):
        T_world_from_query, refs, matches, keypoints = _scene(seed, noise_px=0.5)
        hyps, _ = _solve(refs, matches, keypoints, _no_descriptors())
        for h in hyps:
            distance = _mahalanobis_sq(h, T_world_from_query, 0.5)
            (joint if h.joint else per_entry).append(distance)
        (together,) = [h for h in hyps if h.joint]
        members = [h for h in hyps if h.entry_id in together.entry_ids and not h.joint]
        assert position_spread_m(together.covariance_px1) < min(
            position_spread_m(h.covariance_px1) for h in members
        )
    assert len(per_entry) >= 20 and len(joint) == 6
    assert 0.8 < np.median(per_entry) < 6.0
    assert 0.3 < np.median(joint) < 8.0 and max(joint) < 16.3  # chi-square 3 dof: p 0.001


def test_pose_covariance_weighs_each_inlier_by_its_keypoint_scale():
    """An inlier from pyramid scale s counts as s px of noise (every keypoint at scale 2:
    four times the covariance at 1 px); the scales leave the poses alone (each entry's
    pose counts every correspondence alike; the joint pose's Cauchy refit measures its
    loss's scale in the errors divided by the scales, so one scale for every keypoint
    changes nothing)."""
    T_world_from_query, refs, matches, keypoints = _scene(3, noise_px=0.5)
    scales = np.full(len(keypoints), 2.0)

    def solve(keypoint_scales):
        e_vlad = {r.entry_id: 0.8 for r in refs}
        return pose_hypotheses(
            keypoints, refs, matches, e_vlad, CAM, _no_descriptors(), np.random.default_rng(0),
            keypoint_scales=keypoint_scales,
        )  # fmt: skip

    plain, _ = solve(None)
    weighed, _ = solve(scales)
    pairs = list(zip(plain, weighed, strict=True))
    assert len(pairs) >= 4 and any(p.joint for p, _ in pairs)
    for p, w in pairs:
        np.testing.assert_allclose(w.pose_world, p.pose_world)
        np.testing.assert_allclose(w.covariance_px1, 4 * p.covariance_px1, rtol=1e-9)


def _moved_car_scene(seed, n_refs=5, street_per_entry=10, car_per_entry=40, shift_m=1.0):
    """Every entry's matches dominated by a parked car that moved ``shift_m`` sideways
    between the mapping run and the query: its map points, seen where the car now is,
    agree on a query pose ``shift_m`` off; each entry also keeps ``street_per_entry``
    right matches on the street (fewer than PnP's minimum), and a few outliers."""
    rng = np.random.default_rng(seed)
    T_world_from_query = T_world_from_cam_planar(50.0, 20.0, 0.4, 1.65)
    query = planar_from_T_world_from_cam(T_world_from_query)
    left = np.array([-math.sin(query[2]), math.cos(query[2]), 0.0])
    street_world, street_px = _street(rng, T_world_from_query, n=street_per_entry * n_refs)
    # the car now: a 2 x 1.5 m patch of points 14 m ahead, slightly right of the axis
    forward = np.array([math.cos(query[2]), math.sin(query[2]), 0.0])
    car_now = (
        T_world_from_query[:3, 3]
        + 14.0 * forward
        - 1.0 * left
        + np.stack(
            [
                rng.uniform(-0.3, 0.3, car_per_entry),
                rng.uniform(-1.0, 1.0, car_per_entry),
                rng.uniform(-1.2, 0.3, car_per_entry),
            ],
            1,
        )
        @ np.stack([forward, left, [0, 0, 1.0]])
    )
    car_map = car_now + shift_m * left
    T_query_from_world = invert_rigid(T_world_from_query)
    car_cam = car_now @ T_query_from_world[:3, :3].T + T_query_from_world[:3, 3]
    car_px = np.stack(
        [
            CAM.fx * car_cam[:, 0] / car_cam[:, 2] + CAM.cx,
            CAM.fy * car_cam[:, 1] / car_cam[:, 2] + CAM.cy,
        ],
        1,
    )
    entries = []
    for j in range(n_refs):
        T_world_from_ref = T_world_from_cam_planar(
            query[0] - (2.0 + j) * forward[0], query[1] - (2.0 + j) * forward[1], query[2], 1.65
        )
        T_ref_from_world = invert_rigid(T_world_from_ref)
        street = slice(j * street_per_entry, (j + 1) * street_per_entry)
        points_world = np.concatenate([street_world[street], car_map])
        pixels = np.concatenate([street_px[street], car_px])
        pixels = pixels + rng.normal(0.0, 0.5, pixels.shape)
        bad = rng.random(len(pixels)) < 0.1
        pixels[bad] = rng.uniform([0, 0], [CAM.width_px - 1, CAM.height_px - 1], (bad.sum(), 2))
        points_ref = points_world @ T_ref_from_world[:3, :3].T + T_ref_from_world[:3, 3]
        entries.append((T_world_from_ref, points_ref, pixels))
    return T_world_from_query, *_stacked(entries)


def test_alternative_pose_for_a_frame_whose_entries_agree_on_a_moved_car():
    """AlternativeConfig: the entries agree on the moved car's pose (1 m off, poorly pinned
    down: its inliers on one patch); a pooled RANSAC on the matches that pose leaves finds
    the true pose from the street matches no entry had enough of. Without it, no
    hypothesis near the truth; on an ordinary frame it adds nothing."""
    T_world_from_query, refs, matches, keypoints = _moved_car_scene(0)
    truth = planar_from_T_world_from_cam(T_world_from_query)

    def solve(alternative, scene=(refs, matches, keypoints)):
        return _solve(*scene, _no_descriptors(alternative=alternative))[0]

    def off_m(h):
        return float(np.hypot(*(h.pose_world[:2] - truth[:2])))

    plain = solve(None)
    per_entry = [h for h in plain if not h.joint]
    assert len(per_entry) >= 3 and all(0.7 < off_m(h) < 1.3 for h in plain)
    assert np.median([position_spread_m(h.covariance_px1) for h in per_entry]) > 0.06
    found = solve(AlternativeConfig())
    assert len(found) == len(plain) + 1
    for before, after in zip(plain, found, strict=False):
        np.testing.assert_allclose(after.pose_world, before.pose_world)
    extra = [h for h in found if h.method == "alternative"]
    assert len(extra) == 1 and off_m(extra[0]) < 0.1 and len(extra[0].entry_ids) >= 2
    # an ordinary frame: the poses are pinned down, nothing is tried
    ordinary = _scene(1)[1:]
    base = solve(None, ordinary)
    assert [h.method for h in solve(AlternativeConfig(), ordinary)] == [h.method for h in base]


def test_alternative_pose_needs_pooled_pnp_and_bad_pose_configs_are_refused():
    with pytest.raises(InvalidInputError, match="pooled"):
        PoseConfig(pooled=None, alternative=AlternativeConfig())
    assert PoseConfig(pooled=None, alternative=None).pooled is None
    with pytest.raises(InvalidInputError):
        AlternativeConfig(residual_px=0.0)
    with pytest.raises(InvalidInputError, match="fallback_until_confirmed"):
        PoseConfig(fallback_until_confirmed=0)


def test_joint_pose_cauchy_refit_is_the_default_and_moves_the_least_squares_pose():
    """JointConfig's Cauchy refit: on by default; cauchy_rounds=0 (a bench baseline) gives
    the least-squares pose of the inlier rounds alone, and bad settings are refused."""
    from monoloc.server.vision.pnp import refine_from_pose

    T_world_from_query, refs, matches, keypoints = _scene(4, noise_px=0.7, outlier_fraction=0.2)
    union = [
        EntryInliers(r.T_world_from_cam, keypoints[m[:, 0]], r.points_cam[m[:, 1]])
        for r, m in zip(refs, matches, strict=True)
    ]
    plain = estimate_joint_pose(
        union, T_world_from_query, CAM, PnpConfig(), JointConfig(cauchy_rounds=0)
    )
    robust = estimate_joint_pose(union, T_world_from_query, CAM, PnpConfig(), JointConfig())
    assert plain is not None and robust is not None
    assert JointConfig().cauchy_rounds > 0
    # no Cauchy rounds: the inlier rounds' own pose, written out here in the union's world frame
    points = np.concatenate(
        [e.points_ref @ e.T_world_from_ref[:3, :3].T + e.T_world_from_ref[:3, 3] for e in union]
    )
    pixels = np.concatenate([e.pixels_px for e in union]).astype(np.float64)
    T0 = invert_rigid(T_world_from_query)
    R, t, _, _ = refine_from_pose(
        points, pixels, T0[:3, :3].copy(), T0[:3, 3].copy(), CAM.K, PnpConfig(),
        JointConfig().rounds,
    )  # fmt: skip
    T_rounds = np.eye(4)
    T_rounds[:3, :3], T_rounds[:3, 3] = R, t
    np.testing.assert_allclose(plain.T_world_from_cam, invert_rigid(T_rounds), atol=1e-6)
    # the refit moves the pose, a little, and keeps the inliers
    moved = np.linalg.norm(robust.T_world_from_cam[:3, 3] - plain.T_world_from_cam[:3, 3])
    assert 0.0 < moved < 0.05
    assert robust.n_inliers == plain.n_inliers
    for bad in ({"cauchy_scale_sigmas": 0.0}, {"cauchy_scale_sigmas": -1.0}, {"cauchy_rounds": -1}):
        with pytest.raises(InvalidInputError):
            JointConfig(**bad)
