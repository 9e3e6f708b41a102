"""Turn a reference image with a pose and a 3D source into a map entry (METHOD.md s. 5).

Pure: arrays in, a ``NewEntry`` out. The 3D source is one of a LiDAR scan with its
extrinsics, a registered depth image with its scale, the right image of a rectified
stereo pair with its baseline, or explicit per-keypoint points.
VLAD is computed from all of the image's descriptors (as at query time); the entry
keeps only the keypoints that received a 3D point.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import check_rigid
from monoloc.server.storage.records import NewEntry
from monoloc.server.vision.binary_code import vlad_binary_code
from monoloc.server.vision.depth import (
    DepthAssociationConfig,
    points_from_depth_image,
    points_from_lidar,
)
from monoloc.server.vision.features import Features, OrbConfig, extract_features
from monoloc.server.vision.stereo import StereoConfig, points_from_stereo
from monoloc.server.vision.vlad import compute_vlad
from monoloc.server.vision.vocabulary import Vocabulary


@dataclass(frozen=True)
class LidarSource:
    """A scan (N, 3 or 4) float32 in the LiDAR frame and T_cam_from_lidar (4, 4)."""

    points_lidar: np.ndarray
    T_cam_from_lidar: np.ndarray


@dataclass(frozen=True)
class DepthSource:
    """A registered depth image (H, W) in raw units, ``scale_per_m`` raw units per metre."""

    depth_raw: np.ndarray
    scale_per_m: float


@dataclass(frozen=True)
class StereoSource:
    """The right image (H, W) uint8 of a rectified pair whose left image is the entry's,
    taken ``baseline_m`` to the right of it (``monoloc.server.vision.stereo``)."""

    right_gray: np.ndarray
    baseline_m: float


Source3d = LidarSource | DepthSource | StereoSource


@dataclass(frozen=True)
class BuildConfig:
    orb: OrbConfig = field(default_factory=OrbConfig)
    depth: DepthAssociationConfig = field(default_factory=DepthAssociationConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    min_points: int = 20  # an entry with fewer 3D keypoints cannot support PnP


class TooFewPointsError(InvalidInputError):
    """The image has too few keypoints with a 3D point to be a useful map entry."""


def points_for(
    features: Features,
    source: Source3d,
    intrinsics: CameraIntrinsics,
    config: BuildConfig,
    image_gray: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(points_cam (N, 3), has_point (N,)) for the image's keypoints from the 3D source
    (a stereo source also needs the (left) ``image_gray`` the features came from)."""
    if isinstance(source, StereoSource):
        if image_gray is None:
            raise InvalidInputError("stereo depth needs the left image")
        return points_from_stereo(
            features.keypoints_px,
            image_gray,
            source.right_gray,
            source.baseline_m,
            intrinsics,
            config.stereo,
        )
    if isinstance(source, LidarSource):
        T = check_rigid(source.T_cam_from_lidar, "T_cam_from_lidar")
        return points_from_lidar(
            features.keypoints_px, source.points_lidar, T, intrinsics, config.depth
        )
    if source.depth_raw.shape != (intrinsics.height_px, intrinsics.width_px):
        raise InvalidInputError(
            f"depth image is {source.depth_raw.shape[1]}x{source.depth_raw.shape[0]}, the "
            f"camera is {intrinsics.width_px}x{intrinsics.height_px}"
        )
    return points_from_depth_image(
        features.keypoints_px, source.depth_raw, source.scale_per_m, intrinsics, config.depth
    )


def build_entry(
    image_gray: np.ndarray,
    source_hash: str,
    T_world_from_cam: np.ndarray,
    source: Source3d | np.ndarray,
    intrinsics: CameraIntrinsics,
    vocabulary: Vocabulary,
    vocabulary_id: int | None,
    config: BuildConfig = BuildConfig(),
    tags: tuple[str, ...] = (),
    timestamp_s: float | None = None,
) -> NewEntry:
    """A map entry from one image. ``source`` may also be explicit points (N, 3) float
    for the image's own keypoints as :func:`extract_features` returns them.

    Raises TooFewPointsError when fewer than ``config.min_points`` keypoints have depth.
    """
    T_world_from_cam = check_rigid(T_world_from_cam, "T_world_from_cam")
    if image_gray.shape[:2] != (intrinsics.height_px, intrinsics.width_px):
        raise InvalidInputError(
            f"image is {image_gray.shape[1]}x{image_gray.shape[0]}, the camera is "
            f"{intrinsics.width_px}x{intrinsics.height_px}"
        )
    features = extract_features(image_gray, config.orb)
    if isinstance(source, LidarSource | DepthSource | StereoSource):
        points_cam, has = points_for(features, source, intrinsics, config, image_gray)
    else:
        points_cam = np.asarray(source, dtype=np.float32)
        if points_cam.shape != (len(features), 3):
            raise InvalidInputError(
                f"explicit 3D points must be ({len(features)}, 3), got {points_cam.shape}"
            )
        has = np.all(np.isfinite(points_cam), axis=1) & (points_cam[:, 2] > 0)
    n_points = int(has.sum())
    if n_points < config.min_points:
        raise TooFewPointsError(
            f"only {n_points} of {len(features)} keypoints have a 3D point "
            f"(need {config.min_points})"
        )
    vlad = compute_vlad(features.descriptors, vocabulary)
    return NewEntry(
        source_image_hash=source_hash,
        T_world_from_cam=T_world_from_cam,
        vlad=vlad,
        code=vlad_binary_code(vlad),
        keypoints_px=features.keypoints_px[has],
        descriptors=features.descriptors[has],
        points_cam=points_cam[has].astype(np.float32),
        image_width_px=intrinsics.width_px,
        image_height_px=intrinsics.height_px,
        tags=tags,
        timestamp_s=timestamp_s,
        vocabulary_id=vocabulary_id,
    )
