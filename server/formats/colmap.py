"""COLMAP sparse models (``cameras``, ``images``, ``points3D``; binary or text), read and
written through ``pycolmap``.

Reading: every registered image becomes a :class:`PosedImage` with its observations that
have a 3D point (conventions and the two point modes: ``monoloc.server.formats.model``).
Cameras must be pinhole: ``SIMPLE_PINHOLE``, ``PINHOLE``, or a distortion model whose
distortion parameters are all zero (undistort others first: ``colmap image_undistorter``).

Writing: one ``PINHOLE`` camera per distinct intrinsics, one image per entry (named
``entry_<id>.png``; the server keeps no pixels, so no image files are written), its pose
as COLMAP's ``cam_from_world``, its keypoints as the image's 2D points and each 3D point
(the entry's point in the world) as a point with a track of that one observation: entries
are built independently, so a point seen by two entries is two points. The world is
monoloc's z-up world; ``monoloc.json`` beside the model says so, and the importer reads it.
"""

from __future__ import annotations

import json
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
    pinhole_intrinsics,
    read_marker_up,
)


def _import_pycolmap():
    try:
        import pycolmap
    except ImportError as exc:  # the `formats` extra
        raise InvalidInputError(
            "COLMAP support needs pycolmap: pip install 'monoloc[formats]'"
        ) from exc
    return pycolmap


def intrinsics_of(camera, where: str) -> CameraIntrinsics:
    """A pycolmap camera as monoloc intrinsics (OpenCV pixel convention)."""
    return pinhole_intrinsics(
        camera.model.name,
        camera.params,
        camera.width,
        camera.height,
        f"{where}: camera {camera.camera_id}",
    )


def read_colmap_model(model_dir: Path, images_dir: Path) -> PosedImages:
    """Open a COLMAP sparse model (a folder with cameras/images/points3D .bin or .txt);
    image files are looked up under ``images_dir`` by the model's image names. Raises
    InputFileError (missing/unreadable model or images folder) and InvalidInputError
    (an unsupported camera)."""
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
    if reconstruction.num_reg_images() and not reconstruction.num_points3D():
        # what a user has after mapping with known poses, before triangulating: monoloc
        # needs the model's 3D points (its --points orb takes them by their observations)
        raise InputFileError(
            model_dir,
            f"the COLMAP model has {reconstruction.num_reg_images()} posed images but no 3D "
            "points: triangulate them first (colmap point_triangulator with these poses)",
        )
    cameras = {
        cid: intrinsics_of(cam, str(model_dir)) for cid, cam in reconstruction.cameras.items()
    }
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
    )


def write_colmap_model(views: list[ModelView], out_dir: Path, marker: dict | None = None) -> Path:
    """Write ``views`` as a binary COLMAP sparse model in ``out_dir`` (created), and the
    ``marker`` dict as ``monoloc.json`` if given (monoloc's export: ``up`` z). Returns
    ``out_dir``."""
    pycolmap = _import_pycolmap()
    out_dir = Path(out_dir).expanduser()
    out_dir.mkdir(parents=True, exist_ok=True)
    reconstruction = pycolmap.Reconstruction()
    camera_ids: dict[CameraIntrinsics, int] = {}
    for view in views:
        c = view.intrinsics
        if c not in camera_ids:
            camera_ids[c] = len(camera_ids) + 1
            camera = pycolmap.Camera(
                model="PINHOLE",
                width=c.width_px,
                height=c.height_px,
                params=[c.fx, c.fy, c.cx + PIXEL_SHIFT, c.cy + PIXEL_SHIFT],
                camera_id=camera_ids[c],
            )
            reconstruction.add_camera_with_trivial_rig(camera)
    for image_id, view in enumerate(views, start=1):
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
        for k, xyz in enumerate(np.asarray(view.points_world, dtype=np.float64).reshape(-1, 3)):
            track = pycolmap.Track()
            track.add_element(image_id, k)
            reconstruction.add_point3D(xyz, track)
    reconstruction.write(str(out_dir))
    if marker is not None:
        (out_dir / MARKER_FILE).write_text(json.dumps(marker, indent=2) + "\n")
    return out_dir
