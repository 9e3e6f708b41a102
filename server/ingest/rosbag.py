"""Reader of ROS 2 bags as mapping runs (through ``rosbags``; message handling shared with
the vehicle's replay in ``monoloc.core.formats.rosbag``).

Topics (``topics``: role -> topic name; a role left out is found by message type when the
bag has exactly one topic of that type):

- ``image``: ``sensor_msgs/Image`` or ``CompressedImage``, the reference images;
- ``camera_info``: ``sensor_msgs/CameraInfo`` of that camera (or ``intrinsics`` given);
- ``depth`` (a registered depth ``Image``: 16UC1/mono16 in millimetres, 32FC1 in metres)
  or ``cloud`` (``PointCloud2``): the 3D source. When both exist, the depth image wins
  unless ``cloud`` is named;
- ``pose``: ``nav_msgs/Odometry`` (its pose is ``T_<frame_id>_from_<child_frame_id>``);
  without one, the one moving transform of ``/tf``.

The camera's pose at an image's stamp: the body pose interpolated (translation linearly,
rotation by slerp) between the two samples bracketing the stamp when they are at most
``pose_max_gap_s`` apart, else the nearest within ``max_difference_s``, times the static
transform (``/tf_static``) from the body frame to the image's ``frame_id`` (identity when
they are the same frame). A point cloud's frame must reach the camera's by static
transforms. Depth images and scans pair with images by stamp (greedy, closest first,
within ``max_difference_s`` / ``cloud_max_difference_s``). Images without a pose or a 3D
partner are counted in ``read_skips`` (``no_ground_truth``, ``no_depth``).

Reading is lazy: the bag is indexed when opened (headers only) and each frame's messages
are read again when the pipeline loads it (one reader, behind a lock; decoding runs
outside it).
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats import rosbag as bag
from monoloc.server.ingest.common import LoadedFrame, decode_gray
from monoloc.server.ingest.tum import associate, ground_truth_at

ROLES = ("image", "camera_info", "depth", "cloud", "pose")
DEPTH_MM_PER_M = 1000.0


@dataclass(frozen=True)
class RosbagFrame:
    """One image with its pose; ``image_path`` names the message (``<bag>#<topic>@<ns>``)
    in errors; ``partner`` is the depth image's or scan's bag time (ns)."""

    index: int
    timestamp_s: float
    image_path: Path
    image_time_ns: int
    partner_time_ns: int
    T_world_from_cam: np.ndarray = field(repr=False)


@dataclass
class RosbagRun:
    root: Path
    intrinsics: CameraIntrinsics
    topics: dict[str, str]
    frames: list[RosbagFrame] = field(repr=False)
    T_cam_from_lidar: np.ndarray | None = field(default=None, repr=False)
    read_skips: dict[str, int] = field(default_factory=dict)
    format: str = "rosbag"
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _reader: object = field(default=None, repr=False)

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def name(self) -> str:
        return str(self.root)

    def _message(self, topic: str, t_ns: int):
        with self._lock:
            if self._reader is None:
                self._reader = bag.open_reader(self.root)
                # closed with this run, or at exit (before the interpreter tears down)
                weakref.finalize(self, self._reader.close)
            return bag.read_message(self._reader, topic, t_ns)

    def read_image(self, frame: RosbagFrame) -> tuple[bytes, np.ndarray]:
        """(the message's image bytes, the (H, W) uint8 grayscale image)."""
        msgtype, msg = self._message(self.topics["image"], frame.image_time_ns)
        try:
            if msgtype == bag.COMPRESSED_IMAGE:
                data = bytes(msg.data)
                return data, decode_gray(data, frame.image_path)
            return bytes(msg.data), _gray(bag.raw_image_array(msg), bag.image_encoding(msg))
        except InvalidInputError as exc:
            raise InputFileError(frame.image_path, str(exc)) from exc

    def load(self, frame: RosbagFrame) -> LoadedFrame:
        """The frame's image and its depth image or scan (thread-safe)."""
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
        role = "depth" if "depth" in self.topics else "cloud"
        where = Path(f"{self.root}#{self.topics[role]}@{frame.partner_time_ns}")
        msgtype, msg = self._message(self.topics[role], frame.partner_time_ns)
        try:
            if role == "cloud":
                source = LidarSource(bag.pointcloud_xyz(msg), self.T_cam_from_lidar)
            else:
                source = DepthSource(_depth_mm(msgtype, msg, where), DEPTH_MM_PER_M)
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


def _depth_mm(msgtype: str, msg, where: Path) -> np.ndarray:
    """A depth message -> (H, W) uint16 millimetres (0: no depth)."""
    if msgtype != bag.IMAGE:
        raise InvalidInputError("a depth topic must be a raw sensor_msgs/Image")
    depth = bag.raw_image_array(msg)
    if depth.ndim != 2:
        raise InvalidInputError(f"depth image must be single-channel, got {msg.encoding}")
    if depth.dtype == np.float32:  # metres
        mm = np.where(np.isfinite(depth) & (depth > 0), depth * DEPTH_MM_PER_M + 0.5, 0.0)
        return np.clip(mm, 0, 65535).astype(np.uint16)
    if depth.dtype != np.uint16:
        raise InvalidInputError(f"depth image must be 16UC1 (mm) or 32FC1 (m), got {msg.encoding}")
    return depth


def _resolve_topics(reader, root: Path, given: dict[str, str]) -> dict[str, str]:
    """role -> topic: the named ones checked, the others found by type (and, for the
    depth image and the camera info, by name when types alone are ambiguous)."""
    unknown = sorted(set(given) - set(ROLES))
    if unknown:
        raise InvalidInputError(f"unknown topic role(s) {unknown}: roles are {list(ROLES)}")
    types = bag.topic_types(reader)
    topics: dict[str, str] = {}
    if "depth" in given or "cloud" not in given:
        named_depth = {t: k for t, k in types.items() if "depth" in t and t != given.get("image")}
        pool = types if "depth" in given else named_depth
        found = bag.choose_topic(pool, (bag.IMAGE,), given.get("depth"), "depth", root)
        if found is not None:
            topics["depth"] = found
    cameras = {t: k for t, k in types.items() if t != topics.get("depth")}
    found = bag.choose_topic(cameras, bag.IMAGE_TYPES, given.get("image"), "image", root)
    if found is None:
        raise InvalidInputError(f"{root}: no image topic (sensor_msgs/Image or CompressedImage)")
    topics["image"] = found
    info = given.get("camera_info")
    sibling = found.rsplit("/", 1)[0] + "/camera_info"
    if info is None and types.get(sibling) == bag.CAMERA_INFO:
        info = sibling
    found = bag.choose_topic(types, (bag.CAMERA_INFO,), info, "camera_info", root)
    if found is not None:
        topics["camera_info"] = found
    if "depth" not in topics:
        found = bag.choose_topic(types, (bag.POINT_CLOUD,), given.get("cloud"), "cloud", root)
        if found is None:
            raise InvalidInputError(
                f"{root}: no 3D source: a depth image topic or a PointCloud2 topic is needed"
            )
        topics["cloud"] = found
    found = bag.choose_topic(types, (bag.ODOMETRY,), given.get("pose"), "pose", root)
    if found is not None:
        topics["pose"] = found
    return topics


def _intrinsics(reader, topics, given: CameraIntrinsics | None, root: Path) -> CameraIntrinsics:
    if given is not None:
        return given
    if "camera_info" not in topics:
        raise InvalidInputError(
            f"{root}: no CameraInfo topic: name one (--topic camera_info=...) or give "
            "the intrinsics"
        )
    connections = [c for c in reader.connections if c.topic == topics["camera_info"]]
    for connection, _, raw in reader.messages(connections=connections):
        return bag.intrinsics_from_camera_info(reader.deserialize(raw, connection.msgtype))
    raise InvalidInputError(f"{root}: topic {topics['camera_info']!r} holds no message")


def _pair(images: list[bag.BagImage], partners: list[bag.BagImage], max_s: float):
    """image index -> partner index, TUM's greedy association by stamp."""
    a = np.array([i.stamp_s for i in images])
    b = np.array([p.stamp_s for p in partners])
    return dict(associate(a, b, max_s)) if len(a) and len(b) else {}


def read_rosbag_run(
    root: Path,
    *,
    topics: dict[str, str] | None = None,
    intrinsics: CameraIntrinsics | None = None,
    frames: slice | None = None,
    max_difference_s: float = 0.02,
    cloud_max_difference_s: float = 0.05,
    pose_max_gap_s: float = 0.5,
) -> RosbagRun:
    """Open and index a bag as a mapping run (see the module docstring). ``frames``
    selects frames (images with a pose and a 3D partner) with Python slice semantics."""
    root = Path(root).expanduser().resolve()
    with bag.open_bag(root) as reader:
        chosen = _resolve_topics(reader, root, dict(topics or {}))
        camera = _intrinsics(reader, chosen, intrinsics, root)
        tree = bag.read_frame_tree(reader)
        if "pose" in chosen:
            track = bag.read_odometry(reader, chosen["pose"])
            body, pose_rows = track.body, track.pose_rows
        else:
            _, body, pose_rows = tree.dynamic_rows(None, root)
        images = bag.list_images(reader, chosen["image"])
        role = "depth" if "depth" in chosen else "cloud"
        partners = bag.list_images(reader, chosen[role])
    if not images:
        raise InvalidInputError(f"{root}: topic {chosen['image']!r} holds no image")
    camera_frame = images[0].frame_id
    T_body_from_cam = tree.static_between(body, camera_frame)
    if T_body_from_cam is None:
        raise InvalidInputError(
            f"{root}: no static transform (/tf_static) from the pose's frame {body!r} to the "
            f"camera's {camera_frame!r}"
        )
    T_cam_from_lidar = None
    if role == "cloud" and partners:
        T_cam_from_cloud = tree.static_between(camera_frame, partners[0].frame_id)
        if T_cam_from_cloud is None:
            raise InvalidInputError(
                f"{root}: no static transform from the camera's frame {camera_frame!r} to "
                f"the point cloud's {partners[0].frame_id!r}"
            )
        T_cam_from_lidar = T_cam_from_cloud
    limit = max_difference_s if role == "depth" else cloud_max_difference_s
    pairs = _pair(images, partners, limit)
    skips = {"no_depth": 0, "no_ground_truth": 0}
    out: list[RosbagFrame] = []
    for i, image in enumerate(images):
        if i not in pairs:
            skips["no_depth"] += 1
            continue
        T_world_from_body = ground_truth_at(
            pose_rows, image.stamp_s, max_difference_s, pose_max_gap_s
        )
        if T_world_from_body is None:
            skips["no_ground_truth"] += 1
            continue
        where = Path(f"{root}#{image.topic}@{image.bag_time_ns}")
        T = T_world_from_body @ T_body_from_cam
        out.append(
            RosbagFrame(
                i, image.stamp_s, where, image.bag_time_ns, partners[pairs[i]].bag_time_ns, T
            )
        )
    if frames is not None:
        out = out[frames]
    return RosbagRun(
        root=root,
        intrinsics=camera,
        topics=chosen,
        frames=out,
        T_cam_from_lidar=T_cam_from_lidar,
        read_skips={k: v for k, v in skips.items() if v},
    )
