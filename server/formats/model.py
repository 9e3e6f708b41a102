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
- Cameras: COLMAP's models (:func:`camera_intrinsics`) with their lens distortion; a
  distorted camera is undistorted at import (:class:`ImportSource`), so a map's camera
  and entries are pinhole.

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

import dataclasses
import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics, LensDistortion
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
# Camera models (COLMAP's names, which kapture's CameraType shares): parameter layout as
# (focal indices (fx, fy; one index twice for a single focal), principal point indices,
# monoloc's LensDistortion model or None, how the remaining parameters fill its
# coefficients: an index per coefficient, None for a coefficient the model lacks (0)).
# COLMAP's OPENCV is OpenCV's k1 k2 p1 p2, FULL_OPENCV its k1 k2 p1 p2 k3 k4 k5 k6, and
# OPENCV_FISHEYE / the *_FISHEYE models OpenCV's equidistant theta_d = theta (1 + k1
# theta^2 + k2 theta^4 + ...); tests/server/formats/test_cameras.py checks each against
# pycolmap's own projection.
_CAMERA_MODELS: dict[str, tuple[tuple[int, int], tuple[int, int], str | None, tuple]] = {
    "SIMPLE_PINHOLE": ((0, 0), (1, 2), None, ()),
    "PINHOLE": ((0, 1), (2, 3), None, ()),
    "SIMPLE_RADIAL": ((0, 0), (1, 2), "plumb_bob", (3, None, None, None)),
    "RADIAL": ((0, 0), (1, 2), "plumb_bob", (3, 4, None, None)),
    "OPENCV": ((0, 1), (2, 3), "plumb_bob", (4, 5, 6, 7)),
    "FULL_OPENCV": ((0, 1), (2, 3), "rational_polynomial", (4, 5, 6, 7, 8, 9, 10, 11)),
    "OPENCV_FISHEYE": ((0, 1), (2, 3), "equidistant", (4, 5, 6, 7)),
    "SIMPLE_RADIAL_FISHEYE": ((0, 0), (1, 2), "equidistant", (3, None, None, None)),
    "RADIAL_FISHEYE": ((0, 0), (1, 2), "equidistant", (3, 4, None, None)),
}
CAMERA_MODELS = tuple(_CAMERA_MODELS)


def _n_params(model: str) -> int:
    focal, centre, _, coefficients = _CAMERA_MODELS[model]
    indices = [*focal, *centre, *(i for i in coefficients if i is not None)]
    return max(indices) + 1


def camera_intrinsics(
    model: str, params, width_px: int, height_px: int, where: str
) -> CameraIntrinsics:
    """Intrinsics (OpenCV pixel convention) of a camera given as a COLMAP/kapture model
    name and its parameters, with its lens distortion (None when every distortion
    parameter is zero, but for a fisheye: an equidistant lens without coefficients is
    still one). InvalidInputError naming the model for one monoloc does not know
    (FOV, THIN_PRISM_FISHEYE, ...) or a wrong number of parameters."""
    if model not in _CAMERA_MODELS:
        raise InvalidInputError(
            f"{where}: the camera model {model} is not one monoloc knows "
            f"({', '.join(CAMERA_MODELS)})"
        )
    values = np.asarray(params, dtype=np.float64).ravel()
    if len(values) != _n_params(model) or not np.all(np.isfinite(values)):
        raise InvalidInputError(
            f"{where}: a {model} camera takes {_n_params(model)} finite parameters, got "
            f"{values.tolist()}"
        )
    (ifx, ify), (icx, icy), lens, layout = _CAMERA_MODELS[model]
    distortion = None
    if lens is not None:
        coefficients = [0.0 if i is None else float(values[i]) for i in layout]
        # zero coefficients make a pinhole, except for a fisheye (theta_d = theta)
        if lens == "equidistant" or any(coefficients):
            distortion = LensDistortion(lens, tuple(coefficients))
    return CameraIntrinsics(
        float(values[ifx]),
        float(values[ify]),
        float(values[icx]) - PIXEL_SHIFT,
        float(values[icy]) - PIXEL_SHIFT,
        int(width_px),
        int(height_px),
        distortion,
    )


def camera_model_of(c: CameraIntrinsics) -> tuple[str, list[float]]:
    """The COLMAP/kapture model name and parameters (COLMAP's pixel convention) of
    monoloc intrinsics: PINHOLE, OPENCV (plumb_bob without k3), FULL_OPENCV (plumb_bob
    with k3, rational_polynomial) or OPENCV_FISHEYE (equidistant)."""
    base = [float(c.fx), float(c.fy), float(c.cx) + PIXEL_SHIFT, float(c.cy) + PIXEL_SHIFT]
    d = c.distortion
    if d is None or (d.is_zero and d.model != "equidistant"):
        return "PINHOLE", base
    k = list(d.coefficients)
    if d.model == "equidistant":
        return "OPENCV_FISHEYE", base + k
    if d.model == "plumb_bob" and (len(k) == 4 or k[4] == 0.0):
        return "OPENCV", base + k[:4]
    return "FULL_OPENCV", base + (k + [0.0, 0.0, 0.0] if len(k) == 5 else k)


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
    notes: tuple[str, ...] = ()  # what the reader did beyond reading (a triangulation)


@dataclass(frozen=True)
class ModelView:
    """What a writer needs of one image: name, camera, pose in the written world, its
    keypoints (N, 2) (OpenCV pixels), their points (N, 3) in that world, and optionally
    their ORB descriptors (N, 32) uint8, a record number (kapture's timestamp), the
    points' track ids (N,) (keypoints of several views with one id are one 3D point with
    a multi-view track; None: a point per keypoint) and the image file's bytes to write
    under ``name`` (None: no file)."""

    name: str
    intrinsics: CameraIntrinsics
    T_world_from_cam: np.ndarray = field(repr=False)
    keypoints_px: np.ndarray = field(repr=False)
    points_world: np.ndarray = field(repr=False)
    descriptors: np.ndarray | None = field(default=None, repr=False)
    record: int = 0
    point_ids: np.ndarray | None = field(default=None, repr=False)
    image_bytes: bytes | None = field(default=None, repr=False)


def tracks_of(views: list[ModelView]) -> tuple[np.ndarray, list[np.ndarray]]:
    """(points (P, 3), per view the (N,) index of each keypoint's point): views with
    ``point_ids`` share a point per id (its mean position), the others get one each."""
    rows: dict[int, list[np.ndarray]] = {}
    index_of: dict[int, int] = {}
    per_view = []
    fresh = -1
    for view in views:
        xyz = np.asarray(view.points_world, dtype=np.float64).reshape(-1, 3)
        if view.point_ids is None:
            ids = np.arange(fresh, fresh - len(xyz), -1)  # negative: never shared
            fresh -= len(xyz)
        else:
            ids = np.asarray(view.point_ids, dtype=np.int64).ravel()
            if len(ids) != len(xyz) or (len(ids) and ids.min() < 0):
                raise InvalidInputError(f"{view.name}: one non-negative point id per keypoint")
        for i, p in zip(ids.tolist(), xyz, strict=True):
            if i not in index_of:
                index_of[i] = len(index_of)
            rows.setdefault(i, []).append(p)
        per_view.append(np.array([index_of[i] for i in ids.tolist()], dtype=np.int64))
    points = np.zeros((len(index_of), 3))
    for i, k in index_of.items():
        points[k] = np.mean(rows[i], axis=0)
    return points, per_view


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


@functools.lru_cache(maxsize=8)
def _undistort_maps(lens: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps from the pinhole camera of the same K and size to the lens."""
    import cv2

    K = lens.K
    D = np.asarray(lens.distortion.coefficients, dtype=np.float64)
    size = (lens.width_px, lens.height_px)
    if lens.distortion.model == "equidistant":
        return cv2.fisheye.initUndistortRectifyMap(K, D, np.eye(3), K, size, cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(K, D, None, K, size, cv2.CV_32FC1)


def undistort_image(image: np.ndarray, lens: CameraIntrinsics, nearest: bool = False):
    """The image (H, W) a pinhole camera with the lens's K and size would have taken
    (``nearest``: no interpolation, for depth maps)."""
    import cv2

    if lens.distortion is None:
        return image
    map_x, map_y = _undistort_maps(lens)
    interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(image, map_x, map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)


@dataclass(frozen=True)
class ImportSource:
    """A reader's images as an ingestion source, for one camera (the pipeline builds a
    run's entries with one camera): ``frames``, ``intrinsics``, ``load(frame)``.

    A camera with lens distortion (``lens``) is undistorted at import, once per image:
    the image is remapped to the pinhole camera of the same K and size (``intrinsics``,
    which the map and its entries then have) and the model's observations are
    undistorted (``cv2.undistortPoints`` / ``cv2.fisheye.undistortPoints``), so every
    stored keypoint, 3D point and preview is pinhole-consistent and the map is served,
    exported and re-imported like any other; queries keep undistorting their own
    keypoints only. The image rather than only the keypoints, because the entry's stored
    preview must agree with its keypoints (an export writes both) and a map's camera has
    no distortion; the cost is one remap per mapping image, and the lens's periphery that
    falls outside the pinhole frame (a fisheye's most of all) is lost."""

    format: str
    name: str
    intrinsics: CameraIntrinsics
    frames: list[ImportFrame] = field(repr=False)
    T_world_from_model: np.ndarray = field(repr=False)
    points: str = "orb"
    association: Association = field(default_factory=Association)
    orb: OrbConfig = field(default_factory=OrbConfig)  # the ingestion's (build_entry's)
    read_skips: dict[str, int] = field(default_factory=dict)
    lens: CameraIntrinsics | None = None

    def read_image(self, frame: ImportFrame) -> tuple[bytes, np.ndarray]:
        """The image file's bytes and the (undistorted) grey image entries are built on."""
        data = read_bytes(frame.image_path, "image")
        gray = decode_gray(data, frame.image_path)
        if self.lens is not None and gray.shape == (self.lens.height_px, self.lens.width_px):
            gray = undistort_image(gray, self.lens)
        return data, gray

    def load(self, frame: ImportFrame) -> LoadedFrame:
        """Read the image and give it its 3D source (thread-safe; no database access)."""
        from monoloc.server.entry_builder import DepthSource, ObservedPoints
        from monoloc.server.vision.features import extract_features
        from monoloc.server.vision.undistort import undistort_pixels

        data, gray = self.read_image(frame)
        image = frame.image
        recorded = image.depth if image.depth is not None else image.lidar
        if recorded is not None:  # a kapture depth map or LiDAR scan: read it now
            source = recorded.load()
            if self.lens is not None and isinstance(source, DepthSource):
                depth = undistort_image(np.asarray(source.depth_raw), self.lens, nearest=True)
                source = dataclasses.replace(source, depth_raw=depth)
            return LoadedFrame(data, gray, source)
        scale = np.linalg.norm(self.T_world_from_model[:3, 0])
        # Points in the camera frame, in metres: the camera frame is rotated with the
        # world, so only the scale applies.
        T_cam_from_model = invert_rigid(image.T_model_from_cam)
        points_cam = image.points_model @ T_cam_from_model[:3, :3].T + T_cam_from_model[:3, 3]
        points_cam = points_cam * scale
        observed_px = image.keypoints_px
        if self.lens is not None:
            observed_px = undistort_pixels(observed_px, self.lens)
            c = self.intrinsics
            inside = (
                (observed_px[:, 0] >= 0)
                & (observed_px[:, 0] <= c.width_px - 1)
                & (observed_px[:, 1] >= 0)
                & (observed_px[:, 1] <= c.height_px - 1)
            )
            observed_px, points_cam = observed_px[inside], points_cam[inside]
        if self.points == "model":
            return LoadedFrame(data, gray, ObservedPoints(observed_px, points_cam))
        if gray.shape != (self.intrinsics.height_px, self.intrinsics.width_px):
            return LoadedFrame(data, gray, np.zeros((0, 3)))  # build_entry names the size
        features = extract_features(gray, self.orb)
        explicit = associate_points(
            features.keypoints_px, observed_px, points_cam, self.intrinsics, self.association
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
                intrinsics.pinhole,
                frames,
                T,
                points,
                association,
                orb or OrbConfig(),
                dict(model.skipped) if k == 0 else {},
                lens=intrinsics if intrinsics.distortion is not None else None,
            )
        )
    return sources
