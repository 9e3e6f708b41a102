"""A COLMAP model of a sim run, built the way a user's would be: SIFT keypoints (not
monoloc's ORB) observing 3D points, here from the run's LiDAR instead of triangulation,
in a world that is KITTI's (the first camera's frame: -y up), images in their own folder.
With a ``lens``, the images are first remapped through that lens distortion (what the
camera would have recorded) and the model's camera is the distorted one."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from monoloc.core.geometry import zup_to_kitti


def distort_image(image, lens):
    """The pinhole ``image`` as the camera with ``lens`` (same K and size) records it."""
    import cv2

    from monoloc.server.vision.undistort import undistort_pixels

    h, w = image.shape
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), axis=-1).reshape(-1, 2)
    ideal = undistort_pixels(grid.astype(np.float64), lens).reshape(h, w, 2).astype(np.float32)
    return cv2.remap(image, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR)


def build_sift_model(run, out: Path, max_frames: int | None = None, n_sift: int = 1500, lens=None):
    """Write ``out/sparse`` (COLMAP model, no monoloc marker) and ``out/images`` from a KITTI
    sequence source; returns (model_dir, images_dir, {name: T_world_from_cam (z-up)})."""
    import cv2

    from monoloc.server.formats.colmap import write_colmap_model
    from monoloc.server.formats.model import ModelView
    from monoloc.server.vision.depth import points_from_lidar
    from monoloc.server.vision.undistort import undistort_pixels

    images_dir, model_dir = out / "images", out / "sparse"
    images_dir.mkdir(parents=True)
    sift = cv2.SIFT_create(nfeatures=n_sift)
    views, truth = [], {}
    for frame in run.frames[:max_frames]:
        loaded = run.load(frame)
        name = f"frame_{frame.index:04d}.png"
        image = loaded.image_gray
        if lens is not None:
            image = distort_image(image, lens)
            cv2.imwrite(str(images_dir / name), image)
        else:
            shutil.copyfile(frame.image_path, images_dir / name)
        keypoints = sift.detect(image, None)
        keypoints_px = cv2.KeyPoint_convert(keypoints).reshape(-1, 2).astype(np.float64)
        ideal_px = keypoints_px if lens is None else undistort_pixels(keypoints_px, lens)
        scan = loaded.source
        points_cam, has = points_from_lidar(
            ideal_px, scan.points_lidar, scan.T_cam_from_lidar, run.intrinsics
        )
        T_model_from_cam = zup_to_kitti(frame.T_world_from_cam)
        points_model = points_cam[has] @ T_model_from_cam[:3, :3].T + T_model_from_cam[:3, 3]
        camera = run.intrinsics if lens is None else lens
        views.append(ModelView(name, camera, T_model_from_cam, keypoints_px[has], points_model))
        truth[name] = frame.T_world_from_cam
    write_colmap_model(views, model_dir)
    return model_dir, images_dir, truth
