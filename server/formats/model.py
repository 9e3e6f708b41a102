"""A posed image collection read from another tool's format, and how it becomes map entries.

Both the COLMAP and the kapture readers produce a :class:`PosedImages`: per image its file,
camera, ``T_model_from_cam`` in the model's own world, and optionally its 2D observations
of the model's 3D points. Conventions, stated once here:

- Pixels: COLMAP (and kapture, whose converters copy COLMAP's numbers as they are) put
  pixel (0, 0)'s centre at (0.5, 0.5); monoloc (OpenCV) at (0, 0). Readers subtract 0.5
  from principal points and observations, writers add it back.
- World: the model's world is turned into monoloc's z-up world by one rotation chosen by
  ``up`` (:func:`R_zup_from_model`), then scaled by ``scale`` (models are taken as metric;
  an SfM model is only up to scale: give its metres-per-unit). ``z``: the model is
  already z-up (geo-registered, ENU, or written by monoloc). ``-y``: the model's -y is up,
  as in a world started at a vehicle camera's frame (COLMAP's incremental mapper and
  KITTI start there); converted with KITTI's fixed rotation. ``y``: +y is up. ``auto``:
  up is the mean of the cameras' own up directions (-y of each camera): right for a
  vehicle camera held level, off by the mean camera pitch otherwise.
- 3D points of an entry are in its camera frame, so they do not depend on ``up``.

Two ways to give an entry its 3D points (``points``), both measured in bench/formats.py:

- ``orb`` (default): ORB features are detected on the image as for any mapping image, and
  a keypoint takes a 3D point from the model's observations within ``radius_px`` of it:
  the nearest one's depth, on the keypoint's own ray, provided every observation within
  the radius agrees with it within ``max_relative_spread`` (a window across a depth edge
  gets none). The entry is then built exactly like a LiDAR-built one.
- ``model``: the model's observations are the entry's keypoints as they are, with their
  3D points unchanged; ORB descriptors are computed at those pixels (ORB's own
  orientation and patch, at full resolution).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.geometry import R_ZUP_FROM_KITTI, invert_rigid
from monoloc.server.ingest.common import LoadedFrame, decode_gray, read_bytes
from monoloc.server.vision.features import OrbConfig

UP_CHOICES = ("z", "-y", "y", "auto")
POINT_MODES = ("orb", "model")
MARKER_FILE = "monoloc.json"  # written beside an export: {"up": "z", ...}
# COLMAP and kapture put a pixel's centre at (0.5, 0.5) from the image corner; monoloc
# (OpenCV) at (0, 0): imports subtract this, exports add it.
PIXEL_SHIFT = 0.5
# Camera models (COLMAP's names, which kapture shares) -> index of (fx, fy, cx, cy) in
# their parameters (fy = fx with one focal); the others are distortion coefficients.
_PINHOLE_PARAMS = {
    "SIMPLE_PINHOLE": (0, 0, 1, 2),
    "PINHOLE": (0, 1, 2, 3),
    "SIMPLE_RADIAL": (0, 0, 1, 2),
    "RADIAL": (0, 0, 1, 2),
    "OPENCV": (0, 1, 2, 3),
    "FULL_OPENCV": (0, 1, 2, 3),
}


def pinhole_intrinsics(
    model: str, params, width_px: int, height_px: int, where: str
) -> CameraIntrinsics:
    """Intrinsics (OpenCV pixel convention) of a camera given as a COLMAP/kapture model
    name and its parameters; InvalidInputError for other models or any distortion (monoloc
    imports pinhole cameras: undistort first, e.g. colmap image_undistorter)."""
    if model not in _PINHOLE_PARAMS:
        raise InvalidInputError(
            f"{where}: the camera is {model}; monoloc imports pinhole cameras "
            "(undistort first, e.g. colmap image_undistorter)"
        )
    values = np.asarray(params, dtype=np.float64)
    ifx, ify, icx, icy = _PINHOLE_PARAMS[model]
    distortion = np.delete(values, sorted({ifx, ify, icx, icy}))
    if np.any(distortion != 0):
        raise InvalidInputError(
            f"{where}: the camera ({model}) has distortion {distortion.tolist()}; undistort "
            "first (colmap image_undistorter)"
        )
    return CameraIntrinsics(
        float(values[ifx]),
        float(values[ify]),
        float(values[icx]) - PIXEL_SHIFT,
        float(values[icy]) - PIXEL_SHIFT,
        int(width_px),
        int(height_px),
    )


@dataclass(frozen=True)
class Association:
    """The ``orb`` rule: observations within ``radius_px`` of a keypoint, all agreeing in
    depth within ``max_relative_spread`` (max / min - 1)."""

    radius_px: float = 3.0
    max_relative_spread: float = 0.05

    def __post_init__(self) -> None:
        if not self.radius_px > 0 or not self.max_relative_spread >= 0:
            raise InvalidInputError(f"invalid association {self}")


@dataclass(frozen=True)
class PosedImage:
    """One registered image. ``keypoints_px`` (N, 2) OpenCV pixel convention, with
    ``points_model`` (N, 3) their 3D points in the model's world (no 3D point: row absent).
    ``depth`` / ``lidar``: a 3D source other than observations (kapture records), an
    object whose ``load()`` reads it as a ``DepthSource`` / ``LidarSource``."""

    name: str
    image_path: Path
    intrinsics: CameraIntrinsics
    T_model_from_cam: np.ndarray = field(repr=False)
    timestamp_s: float | None = None
    keypoints_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)
    points_model: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)), repr=False)
    depth: object | None = field(default=None, repr=False)
    lidar: object | None = field(default=None, repr=False)


@dataclass(frozen=True)
class PosedImages:
    """What a reader found: registered images and the images it could not use (reason)."""

    name: str
    images: list[PosedImage]
    skipped: dict[str, int] = field(default_factory=dict)
    default_up: str = "z"


@dataclass(frozen=True)
class ModelView:
    """What a writer needs of one image: name, camera, pose in the written world, its
    keypoints (N, 2) (OpenCV pixels), their points (N, 3) in that world, and optionally
    their ORB descriptors (N, 32) uint8 and a record number (kapture's timestamp)."""

    name: str
    intrinsics: CameraIntrinsics
    T_world_from_cam: np.ndarray = field(repr=False)
    keypoints_px: np.ndarray = field(repr=False)
    points_world: np.ndarray = field(repr=False)
    descriptors: np.ndarray | None = field(default=None, repr=False)
    record: int = 0


def rotation_taking(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking unit direction ``a`` to unit direction ``b``."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1.0 + 1e-12:  # opposite: half a turn about any axis normal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def R_zup_from_model(up: str, R_model_from_cams: np.ndarray | None = None) -> np.ndarray:
    """The rotation (3, 3) from the model's world to monoloc's z-up world (module doc).
    ``auto`` needs the cameras' rotations (N, 3, 3)."""
    if up == "z":
        return np.eye(3)
    if up == "-y":
        return R_ZUP_FROM_KITTI.copy()
    if up == "y":
        return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    if up == "auto":
        if R_model_from_cams is None or len(R_model_from_cams) == 0:
            raise InvalidInputError("--up auto needs at least one registered image")
        up_model = -np.asarray(R_model_from_cams)[:, :, 1].mean(axis=0)
        if np.linalg.norm(up_model) < 1e-6:
            raise InvalidInputError("--up auto: the cameras' up directions cancel out")
        return rotation_taking(up_model, np.array([0.0, 0.0, 1.0]))
    raise InvalidInputError(f"unknown up axis {up!r}: one of {', '.join(UP_CHOICES)}")


def read_marker_up(root: Path) -> str | None:
    """The ``up`` that monoloc wrote beside its own export, if any."""
    import json

    path = Path(root) / MARKER_FILE
    if not path.is_file():
        return None
    try:
        up = json.loads(path.read_text()).get("up")
    except (OSError, ValueError, AttributeError) as exc:
        raise InputFileError(path, f"unreadable monoloc marker: {exc}") from exc
    if up not in UP_CHOICES:
        raise InputFileError(path, f"unknown up axis {up!r}")
    return up


def T_world_from_model(up: str, scale: float, images: list[PosedImage]) -> np.ndarray:
    """(4, 4) similarity taking model coordinates to the z-up world in metres."""
    if not (np.isfinite(scale) and scale > 0):
        raise InvalidInputError(f"scale must be positive, got {scale}")
    rotations = np.stack([im.T_model_from_cam[:3, :3] for im in images]) if images else None
    T = np.eye(4)
    T[:3, :3] = scale * R_zup_from_model(up, rotations)
    return T


def associate_points(
    keypoints_px: np.ndarray,
    observed_px: np.ndarray,
    observed_cam: np.ndarray,
    intrinsics: CameraIntrinsics,
    rule: Association = Association(),
) -> np.ndarray:
    """The ``orb`` rule (module doc): (N, 3) float32 points in the camera frame for the
    keypoints (N, 2), NaN where none; observations observed_px (M, 2) with their points
    observed_cam (M, 3) in the same camera frame."""
    from scipy.spatial import cKDTree

    keypoints_px = np.asarray(keypoints_px, dtype=np.float64).reshape(-1, 2)
    out = np.full((len(keypoints_px), 3), np.nan, dtype=np.float32)
    front = observed_cam[:, 2] > 0
    observed_px, depth = observed_px[front], observed_cam[front, 2]
    if len(observed_px) == 0 or len(keypoints_px) == 0:
        return out
    tree = cKDTree(observed_px)
    nearest_d, nearest = tree.query(keypoints_px, distance_upper_bound=rule.radius_px)
    for i, neighbours in enumerate(tree.query_ball_point(keypoints_px, rule.radius_px)):
        if not np.isfinite(nearest_d[i]) or not neighbours:
            continue
        window = depth[neighbours]
        if window.max() > window.min() * (1.0 + rule.max_relative_spread):
            continue
        z = depth[nearest[i]]
        u, v = keypoints_px[i]
        out[i] = (
            (u - intrinsics.cx) * z / intrinsics.fx,
            (v - intrinsics.cy) * z / intrinsics.fy,
            z,
        )
    return out


@dataclass(frozen=True)
class ImportFrame:
    """A frame for the ingestion pipeline (``monoloc.server.ingest.pipeline``)."""

    index: int
    timestamp_s: float | None
    image_path: Path
    T_world_from_cam: np.ndarray = field(repr=False)
    image: PosedImage = field(repr=False)


@dataclass(frozen=True)
class ImportSource:
    """A reader's images as an ingestion source, for one camera (the pipeline builds a
    run's entries with one camera): ``frames``, ``intrinsics``, ``load(frame)``."""

    format: str
    name: str
    intrinsics: CameraIntrinsics
    frames: list[ImportFrame] = field(repr=False)
    T_world_from_model: np.ndarray = field(repr=False)
    points: str = "orb"
    association: Association = field(default_factory=Association)
    orb: OrbConfig = field(default_factory=OrbConfig)  # the ingestion's (build_entry's)
    read_skips: dict[str, int] = field(default_factory=dict)

    def load(self, frame: ImportFrame) -> LoadedFrame:
        """Read the image and give it its 3D source (thread-safe; no database access)."""
        from monoloc.server.entry_builder import ObservedPoints
        from monoloc.server.vision.features import extract_features

        data = read_bytes(frame.image_path, "image")
        gray = decode_gray(data, frame.image_path)
        image = frame.image
        recorded = image.depth if image.depth is not None else image.lidar
        if recorded is not None:  # a kapture depth map or LiDAR scan: read it now
            return LoadedFrame(data, gray, recorded.load())
        scale = np.linalg.norm(self.T_world_from_model[:3, 0])
        # Points in the camera frame, in metres: the camera frame is rotated with the
        # world, so only the scale applies.
        T_cam_from_model = invert_rigid(image.T_model_from_cam)
        points_cam = image.points_model @ T_cam_from_model[:3, :3].T + T_cam_from_model[:3, 3]
        points_cam = points_cam * scale
        if self.points == "model":
            return LoadedFrame(data, gray, ObservedPoints(image.keypoints_px, points_cam))
        if gray.shape != (self.intrinsics.height_px, self.intrinsics.width_px):
            return LoadedFrame(data, gray, np.zeros((0, 3)))  # build_entry names the size
        features = extract_features(gray, self.orb)
        explicit = associate_points(
            features.keypoints_px, image.keypoints_px, points_cam, self.intrinsics, self.association
        )
        return LoadedFrame(data, gray, explicit)


def import_sources(
    model: PosedImages,
    *,
    fmt: str,
    up: str | None,
    scale: float = 1.0,
    points: str = "orb",
    association: Association = Association(),
    orb: OrbConfig | None = None,
) -> list[ImportSource]:
    """One ingestion source per camera of the model, poses in the z-up world (metres)."""
    if points not in POINT_MODES:
        raise InvalidInputError(f"unknown points mode {points!r}: orb or model")
    if not model.images:
        raise InvalidInputError(f"{model.name}: no registered image to import")
    T = T_world_from_model(up or model.default_up, scale, model.images)
    R = T[:3, :3] / scale
    by_camera: dict[CameraIntrinsics, list[PosedImage]] = {}
    for image in model.images:
        by_camera.setdefault(image.intrinsics, []).append(image)
    sources = []
    for k, (intrinsics, images) in enumerate(by_camera.items()):
        frames = []
        for i, image in enumerate(images):
            T_world_from_cam = np.eye(4)
            T_world_from_cam[:3, :3] = R @ image.T_model_from_cam[:3, :3]
            T_world_from_cam[:3, 3] = T[:3, :3] @ image.T_model_from_cam[:3, 3]
            frames.append(
                ImportFrame(i, image.timestamp_s, image.image_path, T_world_from_cam, image)
            )
        name = model.name if len(by_camera) == 1 else f"{model.name} (camera {k + 1})"
        sources.append(
            ImportSource(
                fmt,
                name,
                intrinsics,
                frames,
                T,
                points,
                association,
                orb or OrbConfig(),
                dict(model.skipped) if k == 0 else {},
            )
        )
    return sources
