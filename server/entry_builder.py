"""Turn a reference image with a pose and a 3D source into a map entry (docs/method.md s. 5).

Pure: arrays in, a ``NewEntry`` out. The 3D source is one of a LiDAR scan with its
extrinsics, a registered depth image with its scale, the right image of a rectified
stereo pair with its baseline, explicit points for the image's ORB keypoints, or observed
points (a reconstruction's own 2D observations with their 3D points, described with ORB
where they are). VLAD is computed from all of the image's ORB descriptors (as at query
time); the entry keeps only the keypoints that have a 3D point.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import check_rigid
from monoloc.server.storage.records import EntryImageData, NewEntry
from monoloc.server.vision.binary_code import vlad_binary_code
from monoloc.server.vision.depth import (
    DepthAssociationConfig,
    points_from_depth_image,
    points_from_lidar,
)
from monoloc.server.vision.features import (
    Features,
    OrbConfig,
    describe_keypoints,
    extract_features,
)
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
class ObservedPoints:
    """A reconstruction's observations in one image: keypoints_px (N, 2) float (OpenCV
    pixel convention) and their 3D points points_cam (N, 3) in this camera's frame. The
    entry keeps them as they are, with ORB descriptors computed at those pixels."""

    keypoints_px: np.ndarray
    points_cam: np.ndarray


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
    # The console shows each entry's image: a grey JPEG, its longer side at most this
    # many pixels (0 keeps no image), at this JPEG quality. ~20 kB for a KITTI frame.
    image_max_side_px: int = 640
    image_jpeg_quality: int = 80


def entry_image(
    image_gray: np.ndarray, keypoints_without_point_px: np.ndarray, config: BuildConfig
) -> EntryImageData | None:
    """The small JPEG of a reference image kept for people (None when disabled)."""
    if config.image_max_side_px <= 0:
        return None
    height, width = image_gray.shape[:2]
    scale = min(1.0, config.image_max_side_px / max(width, height))
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    small = (
        image_gray if scale == 1.0 else cv2.resize(image_gray, size, interpolation=cv2.INTER_AREA)
    )
    if small.dtype != np.uint8:  # 16-bit sources: keep the visible range
        small = cv2.normalize(small, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, config.image_jpeg_quality])
    if not ok:  # pragma: no cover - OpenCV encodes any 2D uint8 array
        return None
    return EntryImageData(
        jpeg=jpeg.tobytes(),
        width_px=size[0],
        height_px=size[1],
        keypoints_without_point_px=np.asarray(keypoints_without_point_px, dtype=np.float32),
    )


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
    source: Source3d | ObservedPoints | np.ndarray,
    intrinsics: CameraIntrinsics,
    vocabulary: Vocabulary,
    vocabulary_id: int | None,
    config: BuildConfig = BuildConfig(),
    tags: tuple[str, ...] = (),
    timestamp_s: float | None = None,
) -> NewEntry:
    """A map entry from one image. ``source`` may also be explicit points (N, 3) float
    for the image's own keypoints as :func:`extract_features` returns them (NaN or
    z <= 0: none), or :class:`ObservedPoints`.

    Raises TooFewPointsError when fewer than ``config.min_points`` keypoints have depth.
    """
    T_world_from_cam = check_rigid(T_world_from_cam, "T_world_from_cam")
    if image_gray.shape[:2] != (intrinsics.height_px, intrinsics.width_px):
        raise InvalidInputError(
            f"image is {image_gray.shape[1]}x{image_gray.shape[0]}, the camera is "
            f"{intrinsics.width_px}x{intrinsics.height_px}"
        )
    features = extract_features(image_gray, config.orb)
    if isinstance(source, ObservedPoints):
        keypoints_px, descriptors, points_cam = _observed(image_gray, source, config)
        without_point_px = features.keypoints_px  # the image's ORB keypoints: none is kept
    else:
        if isinstance(source, LidarSource | DepthSource | StereoSource):
            points_all, has = points_for(features, source, intrinsics, config, image_gray)
        else:
            points_all = np.asarray(source, dtype=np.float32)
            if points_all.shape != (len(features), 3):
                raise InvalidInputError(
                    f"explicit 3D points must be ({len(features)}, 3), got {points_all.shape}"
                )
            has = np.all(np.isfinite(points_all), axis=1) & (points_all[:, 2] > 0)
        keypoints_px, descriptors = features.keypoints_px[has], features.descriptors[has]
        points_cam, without_point_px = points_all[has], features.keypoints_px[~has]
    n_points = len(keypoints_px)
    if n_points < config.min_points:
        raise TooFewPointsError(
            f"only {n_points} keypoints have a 3D point (need {config.min_points}; the "
            f"image has {len(features)} ORB features)"
        )
    vlad = compute_vlad(features.descriptors, vocabulary)
    return NewEntry(
        source_image_hash=source_hash,
        T_world_from_cam=T_world_from_cam,
        vlad=vlad,
        code=vlad_binary_code(vlad),
        keypoints_px=np.ascontiguousarray(keypoints_px, dtype=np.float32),
        descriptors=np.ascontiguousarray(descriptors, dtype=np.uint8),
        points_cam=np.ascontiguousarray(points_cam, dtype=np.float32),
        image_width_px=intrinsics.width_px,
        image_height_px=intrinsics.height_px,
        tags=tags,
        timestamp_s=timestamp_s,
        vocabulary_id=vocabulary_id,
        image=entry_image(image_gray, without_point_px, config),
    )


def _observed(image_gray, source: ObservedPoints, config: BuildConfig):
    """(keypoints (K, 2) float32, descriptors (K, 32), points_cam (K, 3)) of the observed
    points that lie in front of the camera and inside ORB's border."""
    keypoints_px = np.asarray(source.keypoints_px, dtype=np.float64).reshape(-1, 2)
    points_cam = np.asarray(source.points_cam, dtype=np.float64).reshape(-1, 3)
    if len(keypoints_px) != len(points_cam):
        raise InvalidInputError(
            f"{len(keypoints_px)} observed keypoints but {len(points_cam)} 3D points"
        )
    front = np.all(np.isfinite(points_cam), axis=1) & (points_cam[:, 2] > 0)
    kept, descriptors = describe_keypoints(image_gray, keypoints_px[front], config.orb)
    return (
        keypoints_px[front][kept].astype(np.float32),
        descriptors,
        points_cam[front][kept],
    )
