"""COLMAP sparse models (``cameras``, ``images``, ``points3D``; binary or text), read and
written through ``pycolmap``.

Reading: every registered image becomes a :class:`PosedImage` with its observations that
have a 3D point (conventions and the two point modes: ``monoloc.server.formats.model``).
Cameras: ``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``,
``FULL_OPENCV``, ``OPENCV_FISHEYE`` (and the radial fisheye models), each read with its
lens distortion, which the import takes off (``ImportSource``); another model (``FOV``,
``THIN_PRISM_FISHEYE``) is refused naming it.

A **poses-only model** (registered images, no 3D points: what a user has after mapping
with known poses) is triangulated from its poses with pycolmap (:func:`triangulate`):
SIFT features on the images, exhaustive matching with two-view verification (sequential
matching beyond ``TriangulationConfig.max_exhaustive_images``), then COLMAP's point
triangulator with the poses and cameras held fixed. When that cannot be done (images
missing, too few verified matches, no point triangulated) the model is refused naming why.

Writing: one camera per distinct intrinsics (its model and distortion written back,
``PINHOLE`` for a pinhole), one image per view, its pose as COLMAP's ``cam_from_world``,
its keypoints as the image's 2D points, and its points: views that carry ``point_ids``
share a 3D point per id (a multi-view track, as a map export merges them), else a point
per keypoint. Views with ``image_bytes`` get their image file in ``images/`` beside the
model. The world is the writer's (monoloc's export: the z-up world; ``monoloc.json``
beside the model says so, and the importer reads it).
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.geometry import invert_rigid
from monoloc.server.formats.model import (
    MARKER_FILE,
    PIXEL_SHIFT,
    ModelView,
    PosedImage,
    PosedImages,
    camera_intrinsics,
    camera_model_of,
    read_marker_up,
    tracks_of,
)

IMAGES_FOLDER = "images"  # an export's images, beside its model files


def _import_pycolmap():
    try:
        import pycolmap
    except ImportError as exc:  # the `formats` extra
        raise InvalidInputError(
            "COLMAP support needs pycolmap: pip install 'monoloc[formats]'"
        ) from exc
    return pycolmap


def intrinsics_of(camera, where: str) -> CameraIntrinsics:
    """A pycolmap camera as monoloc intrinsics (OpenCV pixel convention), with its lens."""
    return camera_intrinsics(
        camera.model.name,
        camera.params,
        camera.width,
        camera.height,
        f"{where}: camera {camera.camera_id}",
    )


@dataclass(frozen=True)
class TriangulationConfig:
    """How a poses-only model is triangulated: SIFT features per image, matching (all
    pairs up to ``max_exhaustive_images`` images, else each image with its
    ``sequential_overlap`` successors in name order), and what the result needs: pairs
    with at least ``min_pair_inliers`` verified matches, triangulated points per image."""

    max_features: int = 4096
    max_exhaustive_images: int = 150
    sequential_overlap: int = 10
    min_verified_pairs: int = 1
    min_pair_inliers: int = 15
    min_points_per_image: float = 20.0
    num_threads: int = 2

    def __post_init__(self) -> None:
        if self.max_features < 100 or self.max_exhaustive_images < 2 or self.num_threads < 1:
            raise InvalidInputError(f"invalid triangulation config {self}")


class _QuietColmap:
    """COLMAP's glog INFO lines off while it works (errors still shown)."""

    def __init__(self, pycolmap) -> None:
        self.logging = pycolmap.logging

    def __enter__(self):
        self.before = self.logging.minloglevel
        self.logging.minloglevel = 2
        return self

    def __exit__(self, *exc) -> None:
        self.logging.minloglevel = self.before


def _image_size(path: Path) -> tuple[int, int] | None:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return None if image is None else (int(image.shape[1]), int(image.shape[0]))


def triangulate(reconstruction, images_dir: Path, where: Path, config=TriangulationConfig()):
    """The poses-only ``reconstruction``'s points, triangulated from its fixed poses and
    cameras with features of the images under ``images_dir`` (module doc). Returns the
    triangulated pycolmap.Reconstruction; InputFileError naming why it cannot."""
    pycolmap = _import_pycolmap()
    names = {iid: reconstruction.images[iid].name for iid in reconstruction.reg_image_ids()}
    missing = sorted(n for n in names.values() if not (images_dir / n).is_file())
    if missing:
        raise InputFileError(
            where,
            f"the COLMAP model has {len(names)} posed images but no 3D points, and "
            f"{len(missing)} of its images are not under {images_dir} (first: {missing[0]}): "
            "cannot triangulate it",
        )
    for image_id, name in names.items():  # COLMAP would skip a mis-sized image silently
        camera = reconstruction.cameras[reconstruction.images[image_id].camera_id]
        size = _image_size(images_dir / name)
        if size != (camera.width, camera.height):
            what = "unreadable" if size is None else f"{size[0]}x{size[1]}"
            raise InputFileError(
                images_dir / name,
                f"image is {what} but its camera {camera.camera_id} is "
                f"{camera.width}x{camera.height}: cannot triangulate the poses-only model",
            )
    with tempfile.TemporaryDirectory(prefix="monoloc-triangulate-") as tmp, _QuietColmap(pycolmap):
        database_path = Path(tmp) / "database.db"
        database = pycolmap.Database.open(str(database_path))
        try:  # the model's cameras, rigs, images and frames under their own ids
            for camera in reconstruction.cameras.values():
                database.write_camera(camera, use_camera_id=True)
            for rig in reconstruction.rigs.values():
                database.write_rig(rig, use_rig_id=True)
            for image_id, name in names.items():
                image = reconstruction.images[image_id]
                bare = pycolmap.Image(name=name, camera_id=image.camera_id, image_id=image_id)
                database.write_image(bare, use_image_id=True)
            for frame_id, frame in reconstruction.frames.items():
                bare = pycolmap.Frame()
                bare.frame_id, bare.rig_id = frame_id, frame.rig_id
                for data_id in frame.data_ids:
                    bare.add_data_id(data_id)
                database.write_frame(bare, use_frame_id=True)
        finally:
            database.close()
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = config.num_threads
        extraction.sift.max_num_features = config.max_features
        try:
            pycolmap.extract_features(
                str(database_path),
                str(images_dir),
                image_names=list(names.values()),
                camera_mode=pycolmap.CameraMode.PER_IMAGE,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
            )
            matching = pycolmap.FeatureMatchingOptions()
            matching.num_threads = config.num_threads
            if len(names) <= config.max_exhaustive_images:
                pycolmap.match_exhaustive(
                    str(database_path), matching_options=matching, device=pycolmap.Device.cpu
                )
            else:
                pairing = pycolmap.SequentialPairingOptions()
                pairing.overlap = config.sequential_overlap
                pycolmap.match_sequential(
                    str(database_path),
                    matching_options=matching,
                    pairing_options=pairing,
                    device=pycolmap.Device.cpu,
                )
        except Exception as exc:  # pycolmap's C++ errors
            raise InputFileError(where, f"pycolmap could not match the images: {exc}") from exc
        database = pycolmap.Database.open(str(database_path))
        try:
            n_cameras = database.num_cameras()
            _, pair_inliers = database.read_two_view_geometry_num_inliers()
            verified = sum(n >= config.min_pair_inliers for n in pair_inliers)
            inliers = int(sum(pair_inliers))
        finally:
            database.close()
        if n_cameras != len(reconstruction.cameras):  # a camera the images did not fit
            raise InputFileError(
                where, "the images do not fit the model's cameras (size): cannot triangulate"
            )
        if verified < config.min_verified_pairs:
            raise InputFileError(
                where,
                f"the COLMAP model has no 3D points and its {len(names)} images give "
                f"{verified} verified image pairs ({inliers} matches): too few matches to "
                "triangulate it",
            )
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = config.num_threads
        output = Path(tmp) / "triangulated"
        output.mkdir()
        try:
            result = pycolmap.triangulate_points(
                reconstruction, str(database_path), str(images_dir), str(output), options=options
            )
        except Exception as exc:
            raise InputFileError(where, f"pycolmap could not triangulate: {exc}") from exc
    n_points = result.num_points3D()
    if n_points < config.min_points_per_image * len(names):
        raise InputFileError(
            where,
            f"triangulating the poses-only model gave {n_points} 3D points for {len(names)} "
            f"images (at least {config.min_points_per_image:g} per image needed): too few "
            "matches",
        )
    return result


def read_colmap_model(
    model_dir: Path, images_dir: Path, triangulation: TriangulationConfig = TriangulationConfig()
) -> PosedImages:
    """Open a COLMAP sparse model (a folder with cameras/images/points3D .bin or .txt);
    image files are looked up under ``images_dir`` by the model's image names. A
    poses-only model is triangulated first (module doc). Raises InputFileError
    (missing/unreadable model or images folder, a poses-only model that cannot be
    triangulated) and InvalidInputError (an unsupported camera)."""
    pycolmap = _import_pycolmap()
    model_dir, images_dir = Path(model_dir).expanduser(), Path(images_dir).expanduser()
    if not model_dir.is_dir():
        raise InputFileError(model_dir, "COLMAP model path is not a directory")
    if not any((model_dir / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
        raise InputFileError(model_dir, "not a COLMAP sparse model (no cameras.bin/.txt)")
    if not images_dir.is_dir():
        raise InputFileError(images_dir, "images path is not a directory")
    try:
        reconstruction = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises its own C++ errors as ValueError/RuntimeError
        raise InputFileError(model_dir, f"unreadable COLMAP model: {exc}") from exc
    cameras = {
        cid: intrinsics_of(cam, str(model_dir)) for cid, cam in reconstruction.cameras.items()
    }
    notes: list[str] = []
    if reconstruction.num_reg_images() and not reconstruction.num_points3D():
        reconstruction = triangulate(reconstruction, images_dir, model_dir, triangulation)
        notes.append(
            f"triangulated {reconstruction.num_points3D()} points from the "
            f"{reconstruction.num_reg_images()} posed images (pycolmap, poses fixed)"
        )
    images, skipped = [], {}
    for image_id in sorted(reconstruction.reg_image_ids()):
        image = reconstruction.images[image_id]
        path = images_dir / image.name
        if not path.is_file():
            skipped["missing_image"] = skipped.get("missing_image", 0) + 1
            continue
        T_cam_from_model = np.eye(4)
        T_cam_from_model[:3] = image.cam_from_world().matrix()
        observed = [p for p in image.points2D if p.has_point3D()]
        keypoints = np.array([p.xy for p in observed], dtype=np.float64).reshape(-1, 2)
        points = np.array(
            [reconstruction.points3D[p.point3D_id].xyz for p in observed], dtype=np.float64
        ).reshape(-1, 3)
        images.append(
            PosedImage(
                name=image.name,
                image_path=path,
                intrinsics=cameras[image.camera_id],
                T_model_from_cam=invert_rigid(T_cam_from_model),
                keypoints_px=keypoints - PIXEL_SHIFT,
                points_model=points,
            )
        )
    if not images and not skipped:
        raise InputFileError(model_dir, "the COLMAP model has no registered image")
    return PosedImages(
        name=str(model_dir),
        images=images,
        skipped=skipped,
        default_up=read_marker_up(model_dir) or "-y",
        notes=tuple(notes),
    )


def write_colmap_model(views: list[ModelView], out_dir: Path, marker: dict | None = None) -> Path:
    """Write ``views`` as a binary COLMAP sparse model in ``out_dir`` (created), their
    image files (if given) in ``out_dir/images``, and the ``marker`` dict as
    ``monoloc.json`` if given (monoloc's export: ``up`` z). Returns ``out_dir``."""
    pycolmap = _import_pycolmap()
    out_dir = Path(out_dir).expanduser()
    out_dir.mkdir(parents=True, exist_ok=True)
    reconstruction = pycolmap.Reconstruction()
    camera_ids: dict[CameraIntrinsics, int] = {}
    for view in views:
        c = view.intrinsics
        if c not in camera_ids:
            camera_ids[c] = len(camera_ids) + 1
            model, params = camera_model_of(c)
            camera = pycolmap.Camera(
                model=model,
                width=c.width_px,
                height=c.height_px,
                params=params,
                camera_id=camera_ids[c],
            )
            reconstruction.add_camera_with_trivial_rig(camera)
    points, point_index = tracks_of(views)
    tracks = [pycolmap.Track() for _ in range(len(points))]
    for image_id, (view, index) in enumerate(zip(views, point_index, strict=True), start=1):
        image = pycolmap.Image(
            name=view.name, camera_id=camera_ids[view.intrinsics], image_id=image_id
        )
        keypoints = np.asarray(view.keypoints_px, dtype=np.float64).reshape(-1, 2) + PIXEL_SHIFT
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(xy) for xy in keypoints])
        T_cam_from_world = invert_rigid(view.T_world_from_cam)
        cam_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(T_cam_from_world[:3, :3]), T_cam_from_world[:3, 3]
        )
        reconstruction.add_image_with_trivial_frame(image, cam_from_world)
        for k, p in enumerate(index.tolist()):
            tracks[p].add_element(image_id, k)
        if view.image_bytes is not None:
            target = out_dir / IMAGES_FOLDER / view.name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(view.image_bytes)
    for xyz, track in zip(points, tracks, strict=True):
        reconstruction.add_point3D(xyz, track)
    reconstruction.write(str(out_dir))
    if marker is not None:
        (out_dir / MARKER_FILE).write_text(json.dumps(marker, indent=2) + "\n")
    return out_dir
