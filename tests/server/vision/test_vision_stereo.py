"""Keypoint depth from a stereo pair: sim frames whose true depth is known (the renderer's
z-buffer), and a textured plane shifted by a known disparity."""

from __future__ import annotations

import numpy as np
import pytest

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.server.ingest.sources import read_kitti_sequence
from monoloc.server.vision.features import OrbConfig, extract_features
from monoloc.server.vision.stereo import (
    StereoConfig,
    disparity_range,
    points_from_stereo,
    stereo_depth_at_keypoints,
)
from monoloc.sim.depth_truth import rendered_depth_at


def _frames(root):
    import cv2

    from monoloc.sim.kitti_writer import read_depth

    seq = root / "sequences" / "00"
    for i in range(6):
        left = cv2.imread(str(seq / "image_0" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(seq / "image_1" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        yield left, right, read_depth(seq / "depth" / f"{i:06d}.png")


def test_sim_stereo_depth_matches_the_rendered_depth(stereo_dataset):
    seq = read_kitti_sequence(stereo_dataset, "00", depth_from="stereo")
    assert seq.stereo_baseline_m == pytest.approx(0.5371657, abs=1e-6)
    shares, smooth_errors, all_errors = [], [], []
    for left, right, depth in _frames(stereo_dataset):
        kp = extract_features(left, OrbConfig()).keypoints_px
        d = stereo_depth_at_keypoints(kp, left, right, seq.stereo_baseline_m, seq.intrinsics)
        truth, smooth = rendered_depth_at(kp, depth)
        has = np.isfinite(d)
        shares.append(has.mean())
        rel = np.abs(d - truth) / truth
        smooth_errors.append(rel[has & smooth])
        all_errors.append(rel[has])
        assert np.all((d[has] >= 2.5) & (d[has] <= 40.0))
    smooth_rel, all_rel = np.concatenate(smooth_errors), np.concatenate(all_errors)
    # Most keypoints get a depth; where the surface is smooth it is within a few %.
    assert np.mean(shares) > 0.45
    assert len(smooth_rel) > 300
    assert np.median(smooth_rel) < 0.03
    assert np.mean(smooth_rel > 0.10) < 0.08
    # Over all keypoints, edges and leaves included (where the pixel's true depth is
    # the wall behind the leaf the keypoint sits on), the median stays small.
    assert np.median(all_rel) < 0.05


def test_swapped_pair_is_mostly_rejected(stereo_dataset):
    """Left and right swapped: true disparities are negative, outside the search range;
    the left-right and uniqueness checks keep far fewer depths, and those are wrong."""
    seq = read_kitti_sequence(stereo_dataset, "00", depth_from="stereo")
    left, right, _ = next(_frames(stereo_dataset))
    kp = extract_features(left, OrbConfig()).keypoints_px
    b, k = seq.stereo_baseline_m, seq.intrinsics
    good = np.isfinite(stereo_depth_at_keypoints(kp, left, right, b, k)).mean()
    swapped = np.isfinite(stereo_depth_at_keypoints(kp, right, left, b, k)).mean()
    assert swapped < 0.6 * good


def _textured(h, w, seed=0):
    import cv2

    rng = np.random.default_rng(seed)
    noise = rng.integers(0, 256, (h // 4 + 1, w // 4 + 1), dtype=np.uint8)
    return cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)


CAMERA = CameraIntrinsics(400.0, 400.0, 320.0, 120.0, 640, 240)


def test_plane_at_known_depth_and_a_step_edge():
    """Left of column 360 a plane at 8 m, right of it a plane at 20 m (behind). The right
    camera, ``baseline`` to the right, sees each shifted by its disparity fx * b / z, the
    near plane in front. Keypoints take those depths, on the rays through them; keypoints
    on the step get none."""
    import cv2

    baseline, near, far, edge = 0.5, 8.0, 20.0, 360
    h, w = CAMERA.height_px, CAMERA.width_px
    near_texture, far_texture = _textured(h, w + 64, seed=0), _textured(h, w + 64, seed=1)
    cols = np.arange(w, dtype=np.float32)
    rows = np.tile(np.arange(h, dtype=np.float32)[:, None], (1, w))
    left = np.where(cols[None, :] < edge, near_texture[:, :w], far_texture[:, :w])

    def shifted(texture, depth_m):
        map_x = np.tile(cols + CAMERA.fx * baseline / depth_m, (h, 1))
        return cv2.remap(texture, map_x, rows, cv2.INTER_LINEAR)

    in_front = (cols + CAMERA.fx * baseline / near)[None, :] < edge
    right = np.where(in_front, shifted(near_texture, near), shifted(far_texture, far))
    kp = np.array(
        [[200.0, 120.0], [300.0, 60.0], [450.0, 100.0], [560.0, 200.0], [359.0, 120.0]]
        + [[edge, 120.0]]
    )
    points, has = points_from_stereo(kp, left, right, baseline, CAMERA)
    assert has.tolist() == [True, True, True, True, False, False]
    assert np.allclose(points[:2, 2], near, rtol=0.01)
    assert np.allclose(points[2:4, 2], far, rtol=0.01)
    u = CAMERA.fx * points[has, 0] / points[has, 2] + CAMERA.cx
    assert np.allclose(u, kp[has, 0], atol=1e-3)


def test_bad_pairs_and_configs_are_refused():
    left = _textured(240, 640)
    kp = np.array([[100.0, 100.0]])
    with pytest.raises(InvalidInputError, match="one size"):
        stereo_depth_at_keypoints(kp, left, left[:, :600], 0.5, CAMERA)
    with pytest.raises(InvalidInputError, match="baseline"):
        stereo_depth_at_keypoints(kp, left, left, -0.5, CAMERA)
    with pytest.raises(InvalidInputError, match="min_depth_m"):
        StereoConfig(min_depth_m=50.0, max_depth_m=40.0)
    with pytest.raises(InvalidInputError, match="odd"):
        StereoConfig(block_size_px=4)
    # The search range covers min_depth_m (KITTI: 718 px * 0.54 m / 2.5 m = 155 -> 160).
    assert disparity_range(718.856, 0.5371657, StereoConfig()) == 160
    assert disparity_range(718.856, 0.5371657, StereoConfig(max_disparities=128)) == 128
