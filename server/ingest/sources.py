"""The recordings a map is built from, as the ingestion pipeline's sources: a format's run,
opened and validated by its reader in ``monoloc.core.formats`` (KITTI sequences, TUM
RGB-D runs, ROS bags), with ``load(frame)``, which reads the frame's image and its 3D
source (a LiDAR scan, a depth image, a right camera image) for ``build_entry``.

A source has ``format`` ("kitti" | "tum" | "rosbag"), ``name``, ``intrinsics``,
``frames`` (each with ``index``, ``timestamp_s``, ``image_path``, ``T_world_from_cam``),
``read_skips`` (frames dropped at read time, reason -> count) and ``load(frame) ->
LoadedFrame`` (thread-safe, no database access). A source whose images are not files (a
ROS bag: ``image_path`` then only names the message) also has ``read_image(frame) ->
(bytes, (H, W) uint8 image)``. The COLMAP and kapture importers (``server/formats``) give
sources of the same shape.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats import kitti, rosbag, tum
from monoloc.server.ingest.common import LoadedFrame, decode_depth, decode_gray, read_bytes


def _as(cls, record):
    """``record`` (a format's run) as its subclass ``cls`` (the same fields)."""
    return cls(**{f.name: getattr(record, f.name) for f in dataclasses.fields(record) if f.init})


@dataclass(frozen=True)
class KittiSource(kitti.KittiSequence):
    def load(self, frame: kitti.KittiFrame) -> LoadedFrame:
        """The frame's image and scan, or its right image when the depth comes from
        stereo."""
        from monoloc.server.entry_builder import LidarSource, StereoSource

        data = read_bytes(frame.image_path, "image")
        image = decode_gray(data, frame.image_path)
        if self.depth_from == "stereo":
            right_path = frame.right_image_path
            assert right_path is not None and self.stereo_baseline_m is not None
            right = decode_gray(read_bytes(right_path, "image"), right_path)
            if right.shape != image.shape:
                raise InputFileError(
                    right_path,
                    f"right image is {right.shape[1]}x{right.shape[0]}, the left "
                    f"{image.shape[1]}x{image.shape[0]}: a rectified pair has one size",
                )
            return LoadedFrame(data, image, StereoSource(right, self.stereo_baseline_m))
        if self.depth_from != "lidar":
            raise InvalidInputError(f"{self.name}: opened for its images only, no 3D source")
        scan = kitti.read_scan(frame.scan_path)
        return LoadedFrame(data, image, LidarSource(scan, self.T_cam_from_lidar))


def read_kitti_sequence(
    root: Path,
    sequence: str | None = None,
    frames: slice | None = None,
    depth_from: str = "lidar",
) -> KittiSource:
    """A KITTI sequence (``kitti.read_sequence``: layout, validation) as a source."""
    return _as(KittiSource, kitti.read_sequence(root, sequence, frames, depth_from))


@dataclass(frozen=True)
class TumSource(tum.TumRun):
    def load(self, frame: tum.TumFrame) -> LoadedFrame:
        """The frame's colour and depth images."""
        from monoloc.server.entry_builder import DepthSource

        data = read_bytes(frame.image_path, "image")
        image = decode_gray(data, frame.image_path)
        depth = decode_depth(read_bytes(frame.depth_path, "depth image"), frame.depth_path)
        return LoadedFrame(data, image, DepthSource(depth, self.depth_scale_per_m))


def read_tum_run(
    root: Path,
    *,
    intrinsics: CameraIntrinsics | None = None,
    camera: str | None = None,
    max_difference_s: float = 0.02,
    gt_max_gap_s: float = 0.1,
    frames: slice | None = None,
) -> TumSource:
    """A TUM RGB-D run (``tum.read_run``: association, ground truth, intrinsics) as a
    source."""
    run = tum.read_run(
        root,
        intrinsics=intrinsics,
        camera=camera,
        max_difference_s=max_difference_s,
        gt_max_gap_s=gt_max_gap_s,
        frames=frames,
    )
    return _as(TumSource, run)


@dataclass
class RosbagSource(rosbag.RosbagRun):
    _messages: rosbag.MessageReader = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._messages = rosbag.MessageReader(self.root)

    def read_image(self, frame: rosbag.RosbagFrame) -> tuple[bytes, np.ndarray]:
        """(the message's image bytes, the (H, W) uint8 grayscale image)."""
        msgtype, msg = self._messages(self.topics["image"], frame.image_time_ns)
        try:
            if msgtype == rosbag.COMPRESSED_IMAGE:
                data = bytes(msg.data)
                return data, decode_gray(data, frame.image_path)
            pixels = rosbag.raw_image_array(msg)
            return bytes(msg.data), _gray(pixels, rosbag.image_encoding(msg))
        except InvalidInputError as exc:
            raise InputFileError(frame.image_path, str(exc)) from exc

    def load(self, frame: rosbag.RosbagFrame) -> LoadedFrame:
        """The frame's image and its depth image or scan."""
        from monoloc.server.entry_builder import DepthSource, LidarSource

        data, image = self.read_image(frame)
        if (image.shape[1], image.shape[0]) != (
            self.intrinsics.width_px,
            self.intrinsics.height_px,
        ):
            raise InputFileError(
                frame.image_path,
                f"image is {image.shape[1]}x{image.shape[0]}, the camera "
                f"{self.intrinsics.width_px}x{self.intrinsics.height_px}",
            )
        role, where = self.depth_role, self.partner_path(frame)
        msgtype, msg = self._messages(self.topics[role], frame.partner_time_ns)
        try:
            if role == "cloud":
                source = LidarSource(rosbag.pointcloud_xyz(msg), self.T_cam_from_lidar)
            else:
                source = DepthSource(rosbag.depth_mm(msgtype, msg), rosbag.DEPTH_MM_PER_M)
        except InvalidInputError as exc:
            raise InputFileError(where, str(exc)) from exc
        if role == "depth" and source.depth_raw.shape != image.shape:
            raise InputFileError(
                where, f"depth image {source.depth_raw.shape} is not registered to {image.shape}"
            )
        return LoadedFrame(data, image, source)


def _gray(pixels: np.ndarray, encoding: str) -> np.ndarray:
    import cv2

    if pixels.dtype == np.uint16:
        pixels = (pixels >> 8).astype(np.uint8)  # as decode_gray does for 16-bit images
    if pixels.dtype != np.uint8:
        raise InvalidInputError(f"a camera image must be 8 or 16 bit, got {encoding}")
    if pixels.ndim == 2:
        return np.ascontiguousarray(pixels)
    code = {
        "rgb8": cv2.COLOR_RGB2GRAY,
        "rgba8": cv2.COLOR_RGBA2GRAY,
        "bgra8": cv2.COLOR_BGRA2GRAY,
    }.get(encoding, cv2.COLOR_BGR2GRAY)
    return cv2.cvtColor(np.ascontiguousarray(pixels), code)


def read_rosbag_run(
    root: Path,
    *,
    topics: dict[str, str] | None = None,
    intrinsics: CameraIntrinsics | None = None,
    fallback_intrinsics: CameraIntrinsics | None = None,
    frames: slice | None = None,
    max_difference_s: float = 0.02,
    cloud_max_difference_s: float = 0.05,
    pose_max_gap_s: float = 0.5,
) -> RosbagSource:
    """A ROS bag (``rosbag.read_mapping_run``: topics, poses, pairing; the map's camera
    ``fallback_intrinsics`` when the bag has no CameraInfo) as a source; the messages are
    read again, lazily, when a frame is loaded."""
    run = rosbag.read_mapping_run(
        root,
        topics=topics,
        intrinsics=intrinsics,
        fallback_intrinsics=fallback_intrinsics,
        frames=frames,
        max_difference_s=max_difference_s,
        cloud_max_difference_s=cloud_max_difference_s,
        pose_max_gap_s=pose_max_gap_s,
    )
    return _as(RosbagSource, run)
