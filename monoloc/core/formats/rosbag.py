"""ROS 2 bags (rosbag2, sqlite3 or mcap storage; ROS 1 bags too), read with ``rosbags``
(pure Python, no ROS installation): the messages the vehicle's bag replay reads, a bag
opened as a mapping run (``read_mapping_run``, what the map server ingests) and the pose
bag ``monoloc drive`` writes (``write_pose_bag``).

``rosbags`` is not part of the bare vehicle install: it is imported when a bag is opened,
and its absence is one error naming ``pip install 'monoloc[bags]'`` (rosbags and Pillow,
no server).

Messages understood (ROS 2 names; REP-103 frames):

- ``sensor_msgs/msg/Image`` (mono8, mono16, 8UC1, 16UC1, 32FC1, rgb8, bgr8, rgba8, bgra8)
  and ``sensor_msgs/msg/CompressedImage`` (JPEG/PNG bytes): camera and depth images;
- ``sensor_msgs/msg/CameraInfo``: K and the lens distortion (distortion_model, D; ROS
  1's ``K``, ``D``): a replayed query carries it, a mapping run must be rectified;
- ``sensor_msgs/msg/PointCloud2`` with float32 x, y, z fields: LiDAR scans;
- ``nav_msgs/msg/Odometry``: poses (``pose.pose``: ``T_<header.frame_id>_from_<child>``)
  and the vehicle's speed and yaw rate (``twist.twist.linear.x``, ``angular.z`` in the
  child frame);
- ``geometry_msgs/msg/PoseStamped`` and ``PoseWithCovarianceStamped``: poses
  ``T_<header.frame_id>_from_<body>``; they do not name their body, which is taken to be
  the root of the camera's static tree (``base_link`` when ``/tf_static`` mounts the
  camera on it, REP-105), else the camera's own frame;
- ``tf2_msgs/msg/TFMessage`` on ``/tf`` and ``/tf_static``: transforms; a chain of moving
  ones (``map -> odom -> base_link``) is composed (``FrameTree.body_track``).

Frames: ROS worlds (``map``, ``odom``) are z-up like monoloc's, and a camera's optical
frame (``*_optical_frame``: x right, y down, z forward) is OpenCV's, so
``T_world_from_cam = T_world_from_body(t) @ T_body_from_optical`` needs no axis change.
Times: a message's ``header.stamp`` (sensor time) in seconds; the bag's own receive time
(integer ns) is only used to find a message again.
"""

from __future__ import annotations

import threading
import weakref
from collections import deque
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics, LensDistortion
from monoloc.core.errors import InputFileError, InvalidInputError, MonolocError
from monoloc.core.formats.tum import associate, ground_truth_at
from monoloc.core.geometry import R_from_quaternion_xyzw, invert_rigid, quaternion_xyzw_from_R

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED)
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
MISSING_ROSBAGS = "reading ROS bags needs the 'rosbags' package: pip install 'monoloc[bags]'"

# encoding -> (numpy dtype, channels)
_RAW_ENCODINGS = {
    "mono8": ("u1", 1),
    "8uc1": ("u1", 1),
    "mono16": ("u2", 1),
    "16uc1": ("u2", 1),
    "32fc1": ("f4", 1),
    "rgb8": ("u1", 3),
    "bgr8": ("u1", 3),
    "8uc3": ("u1", 3),
    "rgba8": ("u1", 4),
    "bgra8": ("u1", 4),
}
# PointField datatypes (sensor_msgs/PointField constants) -> numpy
_POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def parse_topic_options(items: list[str] | None) -> dict[str, str]:
    """``["image=/cam/image_raw", ...]`` (the CLIs' ``--topic`` values) -> {"image":
    "/cam/image_raw", ...}; ValueError for an item that is not ROLE=TOPIC."""
    topics: dict[str, str] = {}
    for item in items or []:
        role, sep, name = item.partition("=")
        if not sep or not role.strip() or not name.strip():
            raise ValueError(f"--topic must look like ROLE=TOPIC, got {item!r}")
        topics[role.strip()] = name.strip()
    return topics


def _any_reader():
    try:
        from rosbags.highlevel import AnyReader
    except ModuleNotFoundError as exc:
        if exc.name is not None and exc.name.split(".")[0] == "rosbags":
            raise MonolocError(MISSING_ROSBAGS) from exc
        raise
    return AnyReader


def open_reader(path: Path):
    """An opened ``rosbags.highlevel.AnyReader`` of the bag at ``path`` (a rosbag2 folder
    or its .db3 / .mcap file, or a ROS 1 .bag); InputFileError naming it if it is none.
    The caller closes it (``open_bag`` does)."""
    path = Path(path)
    if path.is_file() and path.suffix in (".db3", ".mcap"):
        path = path.parent  # rosbag2: the folder holds metadata.yaml
    if not path.exists():
        raise InputFileError(path, "no such bag")
    reader_class = _any_reader()
    from rosbags.highlevel import AnyReaderError

    try:
        reader = reader_class([path])
        reader.open()
    except (AnyReaderError, OSError, ValueError) as exc:
        raise InputFileError(path, f"not a readable ROS bag ({exc})") from exc
    return reader


@contextmanager
def open_bag(path: Path) -> Iterator:
    """``open_reader`` as a context manager."""
    reader = open_reader(path)
    try:
        yield reader
    finally:
        reader.close()


def messages(reader, topics: Sequence[str] | None = None, types: Sequence[str] = (), **kwargs):
    """``reader.messages`` of the connections on ``topics`` or of ``types``; nothing when
    none matches (rosbags reads an empty connection list as every connection)."""
    connections = [
        c
        for c in reader.connections
        if (topics is not None and c.topic in topics) or (c.msgtype in types)
    ]
    if not connections:
        return iter(())
    return reader.messages(connections=connections, **kwargs)


def _field(msg, name: str):
    """A message field by its ROS 2 name, or its ROS 1 spelling (CameraInfo's ``K``)."""
    value = getattr(msg, name, None)
    return getattr(msg, name.upper()) if value is None else value


def topic_types(reader) -> dict[str, str]:
    """topic -> message type of every connection of the bag."""
    return {c.topic: c.msgtype for c in reader.connections}


def choose_topic(
    topics: dict[str, str], types: Sequence[str], given: str | None, what: str, bag: Path
) -> str | None:
    """The topic for ``what``: ``given`` (checked), else the only topic of one of
    ``types`` (None when there is none; InvalidInputError when several compete)."""
    if given is not None:
        if given not in topics:
            raise InvalidInputError(f"{bag}: no topic {given!r} ({what}); topics: {sorted(topics)}")
        if topics[given] not in types:
            raise InvalidInputError(
                f"{bag}: topic {given!r} is {topics[given]}, not a {what} ({', '.join(types)})"
            )
        return given
    found = sorted(t for t, kind in topics.items() if kind in types)
    if len(found) > 1:
        raise InvalidInputError(
            f"{bag}: several {what} topics {found}: name one (e.g. --topic {what}={found[0]})"
        )
    return found[0] if found else None


def stamp_s(header) -> float:
    """A header's stamp in seconds."""
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def raw_image_array(msg) -> np.ndarray:
    """A ``sensor_msgs/Image``'s pixels: (H, W) or (H, W, C) in its own encoding's dtype,
    channel order as encoded (rgb8 stays RGB, bgr8 BGR). InvalidInputError on an encoding
    not listed in the module docstring or a buffer too short for height x step."""
    encoding = str(msg.encoding).lower()
    if encoding not in _RAW_ENCODINGS:
        raise InvalidInputError(
            f"unsupported image encoding {msg.encoding!r}; one of {sorted(_RAW_ENCODINGS)}"
        )
    kind, channels = _RAW_ENCODINGS[encoding]
    dtype = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = w * channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if h <= 0 or w <= 0 or step < row_bytes or data.size < h * step:
        raise InvalidInputError(
            f"image message of {data.size} bytes does not hold {h} rows of {step} bytes "
            f"({w} px x {channels} x {dtype.itemsize} B)"
        )
    rows = data[: h * step].reshape(h, step)[:, :row_bytes]
    pixels = np.ascontiguousarray(rows).view(dtype).reshape(h, w, channels)
    pixels = pixels.astype(dtype.newbyteorder("="), copy=False)
    return pixels[:, :, 0] if channels == 1 else pixels


def image_encoding(msg) -> str:
    """The raw encoding's name, lower-case (``sensor_msgs/Image`` only)."""
    return str(msg.encoding).lower()


def intrinsics_from_camera_info(msg) -> CameraIntrinsics:
    """Intrinsics from a ``CameraInfo``'s K (row-major 3x3), image size and lens
    distortion (distortion_model and D; all-zero D: a pinhole)."""
    K = np.asarray(_field(msg, "k"), dtype=np.float64).reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or msg.width <= 0 or msg.height <= 0:
        raise InvalidInputError(
            f"CameraInfo without a valid K or size (fx={K[0, 0]}, fy={K[1, 1]}, "
            f"{msg.width}x{msg.height})"
        )
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    model = getattr(msg, "distortion_model", None)
    coefficients = np.asarray(_field(msg, "d"), dtype=np.float64).reshape(-1).tolist()
    lens = LensDistortion.parse(model or None, coefficients)
    return CameraIntrinsics(fx, fy, cx, cy, int(msg.width), int(msg.height), lens)


def pointcloud_xyz(msg) -> np.ndarray:
    """(N, 3) float32 x, y, z of a ``PointCloud2`` (points with a non-finite coordinate
    dropped)."""
    fields = {f.name: f for f in msg.fields}
    if not all(name in fields for name in "xyz"):
        raise InvalidInputError(f"PointCloud2 without x, y, z fields (has {sorted(fields)})")
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in "xyz":
        f = fields[name]
        if f.datatype not in _POINT_FIELD_TYPES:
            raise InvalidInputError(f"PointCloud2 field {name!r} has datatype {f.datatype}")
        names.append(name)
        formats.append(order + _POINT_FIELD_TYPES[f.datatype])
        offsets.append(int(f.offset))
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                      "itemsize": int(msg.point_step)})  # fmt: skip
    n = int(msg.width) * int(msg.height)
    data = np.asarray(msg.data, dtype=np.uint8)
    if data.size < n * int(msg.point_step):
        raise InvalidInputError(f"PointCloud2 of {data.size} bytes holds fewer than {n} points")
    records = data[: n * int(msg.point_step)].view(dtype)
    xyz = np.column_stack([records[name].astype(np.float32) for name in names])
    return xyz[np.all(np.isfinite(xyz), axis=1)]


def T_from_pose(position, orientation) -> np.ndarray:
    """(4, 4) from a ROS position/translation and an orientation/rotation quaternion."""
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-9:
        raise InvalidInputError(f"invalid quaternion {q.tolist()}")
    T = np.eye(4)
    T[:3, :3] = R_from_quaternion_xyzw(q / norm)
    T[:3, 3] = [position.x, position.y, position.z]
    return T


def T_from_pose_row(row: np.ndarray) -> np.ndarray:
    """(4, 4) from a pose row ``t x y z qx qy qz qw``."""
    T = np.eye(4)
    T[:3, :3] = R_from_quaternion_xyzw(np.asarray(row[4:8], dtype=np.float64))
    T[:3, 3] = row[1:4]
    return T


def _pose_row(t_s: float, position, orientation) -> list[float]:
    q = [orientation.x, orientation.y, orientation.z, orientation.w]
    return [t_s, position.x, position.y, position.z, *q]


@dataclass
class FrameTree:
    """Transforms of a bag: static edges (``/tf_static``) and time series of dynamic ones
    (``/tf``) as rows ``t x y z qx qy qz qw`` of ``T_parent_from_child``."""

    static: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    dynamic: dict[tuple[str, str], list[list[float]]] = field(default_factory=dict)

    def add(self, msg, is_static: bool) -> None:
        for tf in msg.transforms:
            key = (tf.header.frame_id.lstrip("/"), tf.child_frame_id.lstrip("/"))
            if is_static:
                self.static[key] = T_from_pose(tf.transform.translation, tf.transform.rotation)
            else:
                row = _pose_row(stamp_s(tf.header), tf.transform.translation, tf.transform.rotation)
                self.dynamic.setdefault(key, []).append(row)

    def static_between(self, parent: str, child: str) -> np.ndarray | None:
        """``T_parent_from_child`` through static transforms (either direction), or None
        when the frames are not connected by them."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if parent == child:
            return np.eye(4)
        edges: dict[str, list[tuple[str, np.ndarray]]] = {}
        for (a, b), T_a_from_b in self.static.items():
            edges.setdefault(a, []).append((b, T_a_from_b))
            edges.setdefault(b, []).append((a, invert_rigid(T_a_from_b)))
        seen, queue = {parent}, deque([(parent, np.eye(4))])
        while queue:
            frame, T_parent_from_frame = queue.popleft()
            for nxt, T_frame_from_next in edges.get(frame, []):
                if nxt in seen:
                    continue
                T = T_parent_from_frame @ T_frame_from_next
                if nxt == child:
                    return T
                seen.add(nxt)
                queue.append((nxt, T))
        return None

    def static_root(self, frame: str) -> str:
        """The top of ``frame``'s static tree: its static parents followed up (``base_link``
        for a camera mounted on it), ``frame`` itself when it has none."""
        parents = {child: parent for parent, child in self.static}
        frame, seen = frame.lstrip("/"), set()
        while frame in parents and frame not in seen:
            seen.add(frame)
            frame = parents[frame]
        return frame

    def body_track(self, camera_frame: str, bag: Path, hint: str) -> tuple[str, str, np.ndarray]:
        """(world, body, rows (N, 8) ``t x y z qx qy qz qw`` of ``T_world_from_body``) from
        the moving transforms above ``camera_frame``: its parents followed up to the root
        (the world, e.g. ``map``); the body is the child of the lowest moving edge (e.g.
        ``base_link``), sampled at that edge's stamps; moving edges higher up (``map ->
        odom``, often slower) are interpolated there and held beyond their ends. A bag
        whose camera frame is not in the tree falls back to its one moving transform.
        ``hint`` names the option that gives poses another way, for the error."""
        parent_of: dict[str, str] = {c: p for p, c in self.static}
        parent_of.update({c: p for p, c in self.dynamic})
        chain, frame = [], camera_frame.lstrip("/")
        while frame in parent_of and len(chain) < 64:
            chain.append((parent_of[frame], frame))
            frame = parent_of[frame]
        moving = [edge for edge in chain if edge in self.dynamic]
        if not moving:
            if len(self.dynamic) != 1:
                raise InvalidInputError(
                    f"{bag}: no poses: no moving transform (/tf) above the camera's frame "
                    f"{camera_frame!r} (moving: {sorted(self.dynamic)}) and no pose topic: "
                    f"{hint}"
                )
            (edge,) = self.dynamic
            rows = self._rows(edge)
            return edge[0], edge[1], rows
        body = moving[0][1]
        rows = self._rows(moving[0])
        above = chain[chain.index(moving[0]) + 1 :]
        T_world_from_body = [T_from_pose_row(row) for row in rows]
        for edge in above:  # compose upwards: T_parent_from_child @ T_child_from_body
            if edge in self.dynamic:
                edge_rows = self._rows(edge)
                T_edge = [ground_truth_at(edge_rows, t, np.inf, np.inf) for t in rows[:, 0]]
            else:
                T_edge = [self.static[edge]] * len(rows)
            T_world_from_body = [Te @ T for Te, T in zip(T_edge, T_world_from_body, strict=True)]
        world = chain[-1][0]
        out = np.array([[t, *T[:3, 3], *quaternion_xyzw_from_R(T[:3, :3])]
                        for t, T in zip(rows[:, 0], T_world_from_body, strict=True)])  # fmt: skip
        return world, body, out

    def _rows(self, edge: tuple[str, str]) -> np.ndarray:
        rows = np.asarray(self.dynamic[edge], dtype=np.float64)
        return rows[np.argsort(rows[:, 0], kind="stable")]


def read_frame_tree(reader) -> FrameTree:
    """Every ``/tf`` and ``/tf_static`` message of the bag (an empty tree without them)."""
    tree = FrameTree()
    for connection, _, raw in messages(reader, types=(TF_MESSAGE,)):
        msg = reader.deserialize(raw, connection.msgtype)
        tree.add(msg, is_static=connection.topic.rstrip("/").endswith("tf_static"))
    return tree


@dataclass(frozen=True)
class PoseTrack:
    """A pose topic (Odometry, PoseStamped, PoseWithCovarianceStamped): rows ``t x y z qx
    qy qz qw`` of ``T_world_from_body`` (N, 8), and for Odometry its signals (N, 3) ``t
    speed_mps yaw_rate_radps`` (None otherwise); ``world`` is the header's frame id,
    ``body`` the child frame id ("" when the message names none)."""

    world: str
    body: str
    pose_rows: np.ndarray
    signal_rows: np.ndarray | None


def read_pose_track(reader, topic: str) -> PoseTrack:
    """All messages of the pose topic ``topic``, sorted by stamp."""
    poses, signals, world, body = [], [], "", ""
    for connection, _, raw in messages(reader, [topic]):
        msg = reader.deserialize(raw, connection.msgtype)
        t = stamp_s(msg.header)
        world = msg.header.frame_id.lstrip("/")
        pose = msg.pose if connection.msgtype == POSE_STAMPED else msg.pose.pose
        poses.append(_pose_row(t, pose.position, pose.orientation))
        if connection.msgtype == ODOMETRY:
            body = msg.child_frame_id.lstrip("/")
            signals.append([t, msg.twist.twist.linear.x, msg.twist.twist.angular.z])
    if not poses:
        raise InvalidInputError(f"topic {topic!r} holds no pose message")
    pose_rows = np.asarray(poses)
    order = np.argsort(pose_rows[:, 0], kind="stable")
    signal_rows = np.asarray(signals)[order] if signals else None
    return PoseTrack(world, body, pose_rows[order], signal_rows)


def read_odometry(reader, topic: str) -> PoseTrack:
    """``read_pose_track`` of a ``nav_msgs/Odometry`` topic (its signals are set)."""
    track = read_pose_track(reader, topic)
    if track.signal_rows is None:
        raise InvalidInputError(f"topic {topic!r} is not Odometry: it has no twist")
    return track


def pose_body(track: PoseTrack, tree: FrameTree, camera_frame: str) -> str:
    """The frame a pose topic's poses are of: the Odometry's child frame, else (a
    PoseStamped names none) the root of the camera's static tree."""
    return track.body or tree.static_root(camera_frame)


@dataclass(frozen=True)
class BagImage:
    """Where one image message is: its topic, bag time (ns, to read it again), stamp (s)
    and frame id."""

    topic: str
    bag_time_ns: int
    stamp_s: float
    frame_id: str


def list_images(reader, topic: str) -> list[BagImage]:
    """Every message of an image topic, in bag order (only headers are kept)."""
    images = []
    for connection, t_ns, raw in messages(reader, [topic]):
        msg = reader.deserialize(raw, connection.msgtype)
        images.append(BagImage(topic, int(t_ns), stamp_s(msg.header), msg.header.frame_id))
    return images


def read_message(reader, topic: str, bag_time_ns: int):
    """(message type, message) of the first message of ``topic`` at bag time
    ``bag_time_ns``; InvalidInputError if there is none."""
    for connection, t_ns, raw in messages(reader, [topic], start=bag_time_ns, stop=bag_time_ns + 1):
        if t_ns == bag_time_ns:
            return connection.msgtype, reader.deserialize(raw, connection.msgtype)
    raise InvalidInputError(f"no message of {topic!r} at bag time {bag_time_ns} ns")


def signals_at(signal_rows: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """Speed and yaw rate (N, 2) at ``times_s``, linearly interpolated between the rows
    ``t speed yaw_rate`` (held constant beyond the ends)."""
    t = signal_rows[:, 0]
    return np.column_stack(
        [np.interp(times_s, t, signal_rows[:, 1]), np.interp(times_s, t, signal_rows[:, 2])]
    )


ESTIMATE_TOPIC = "/monoloc/odometry"


def _writer_parts():
    try:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore
    except ModuleNotFoundError as exc:
        if exc.name is not None and exc.name.split(".")[0] == "rosbags":
            raise MonolocError(MISSING_ROSBAGS.replace("reading", "writing")) from exc
        raise
    return Writer, StoragePlugin, get_typestore(Stores.ROS2_HUMBLE)


def write_pose_bag(
    path: Path,
    times_s: np.ndarray,
    T_world_from_cam: np.ndarray,
    *,
    topic: str = ESTIMATE_TOPIC,
    world_frame: str = "map",
    camera_frame: str = "camera_optical_frame",
    storage: str = "sqlite3",
) -> Path:
    """A new rosbag2 folder ``path`` holding one ``nav_msgs/msg/Odometry`` per pose on
    ``topic``: ``header.stamp`` = ``times_s`` (the frames' sensor times), ``header.frame_id``
    = ``world_frame``, ``child_frame_id`` = ``camera_frame`` (the pose is
    ``T_<world_frame>_from_<camera_frame>``, the camera's optical frame as in the bags monoloc
    reads); twist and covariances are zero (not estimated). ``times_s`` (N,), increasing;
    ``T_world_from_cam`` (N, 4, 4). ``storage`` is "sqlite3" or "mcap". Refuses an
    existing ``path`` (a bag is never overwritten)."""
    path = Path(path)
    times_s = np.asarray(times_s, dtype=np.float64).reshape(-1)
    T_world_from_cam = np.asarray(T_world_from_cam, dtype=np.float64)
    if T_world_from_cam.shape != (len(times_s), 4, 4):
        raise InvalidInputError(
            f"poses must be ({len(times_s)}, 4, 4) for {len(times_s)} times, "
            f"got {T_world_from_cam.shape}"
        )
    if not len(times_s):
        raise InvalidInputError("no poses to write")
    if not np.all(np.isfinite(times_s)) or np.any(np.diff(times_s) <= 0) or times_s[0] < 0:
        raise InvalidInputError("pose times must be finite, >= 0 and increasing")
    if not np.all(np.isfinite(T_world_from_cam)):
        raise InvalidInputError("poses must be finite")
    if storage not in ("sqlite3", "mcap"):
        raise InvalidInputError(f"bag storage is sqlite3 or mcap, got {storage!r}")
    if path.exists():
        raise InputFileError(path, "already exists; a bag is written to a new folder")
    Writer, StoragePlugin, store = _writer_parts()

    types = store.types
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    zeros = np.zeros(36)
    with Writer(path, version=8, storage_plugin=plugin) as writer:
        connection = writer.add_connection(topic, ODOMETRY, typestore=store)
        for t_s, T in zip(times_s, T_world_from_cam, strict=True):
            ns = round(float(t_s) * 1e9)
            q = quaternion_xyzw_from_R(T[:3, :3])
            msg = types[ODOMETRY](
                header=types["std_msgs/msg/Header"](
                    stamp=types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                    frame_id=world_frame,
                ),
                child_frame_id=camera_frame,
                pose=types["geometry_msgs/msg/PoseWithCovariance"](
                    pose=types["geometry_msgs/msg/Pose"](
                        position=types["geometry_msgs/msg/Point"](*(float(v) for v in T[:3, 3])),
                        orientation=types["geometry_msgs/msg/Quaternion"](
                            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
                        ),
                    ),
                    covariance=zeros,
                ),
                twist=types["geometry_msgs/msg/TwistWithCovariance"](
                    twist=types["geometry_msgs/msg/Twist"](
                        linear=types["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
                        angular=types["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
                    ),
                    covariance=zeros,
                ),
            )
            writer.write(connection, ns, store.serialize_cdr(msg, ODOMETRY))
    return path


class MessageReader:
    """Messages of a bag read again by (topic, bag time), ``read_message``'s answer: one
    reader, opened on first use and kept open behind a lock (thread-safe), closed with
    this object or at exit (before the interpreter tears down)."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._lock = threading.Lock()
        self._reader = None

    def __call__(self, topic: str, bag_time_ns: int):
        with self._lock:
            if self._reader is None:
                self._reader = open_reader(self.root)
                weakref.finalize(self, self._reader.close)
            return read_message(self._reader, topic, bag_time_ns)


# ---- a bag as a mapping run ----------------------------------------------------------
#
# Topics (``topics``: role -> topic name; a role left out is found by message type when the
# bag has exactly one topic of that type):
#
# - ``image``: ``sensor_msgs/Image`` or ``CompressedImage``, the reference images;
# - ``camera_info``: ``sensor_msgs/CameraInfo`` of that camera (or ``intrinsics`` given;
#   without either, the map's camera, ``fallback_intrinsics``);
# - ``depth`` (a registered depth ``Image``: 16UC1/mono16 in millimetres, 32FC1 in metres)
#   or ``cloud`` (``PointCloud2``): the 3D source. When both exist, the depth image wins
#   unless ``cloud`` is named;
# - ``pose``: ``nav_msgs/Odometry`` (its pose is ``T_<frame_id>_from_<child_frame_id>``)
#   or ``PoseStamped`` / ``PoseWithCovarianceStamped`` (of the root of the camera's static
#   tree: ``pose_body``); without one, the moving transforms of ``/tf`` above the camera
#   (``FrameTree.body_track``: ``map -> odom -> base_link`` composed).
#
# The camera's pose at an image's stamp: the body pose interpolated (translation linearly,
# rotation by slerp: ``tum.ground_truth_at``) between the two samples bracketing the stamp
# when they are at most ``pose_max_gap_s`` apart, else the nearest within
# ``max_difference_s``, times the static transform (``/tf_static``) from the body frame to
# the image's ``frame_id`` (identity when they are the same frame). A point cloud's frame
# must reach the camera's by static transforms. Depth images and scans pair with images by
# stamp (``tum.associate``: greedy, closest first, within ``max_difference_s`` /
# ``cloud_max_difference_s``). Images without a pose or a 3D partner are counted in
# ``read_skips`` (``no_ground_truth``, ``no_depth``).
#
# Opening a run indexes the bag (headers only); each frame's messages are read again when
# it is loaded (``MessageReader``).

MAPPING_ROLES = ("image", "camera_info", "depth", "cloud", "pose")
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
    """A bag opened as a mapping run: its camera, the topic of each role, its frames."""

    root: Path
    intrinsics: CameraIntrinsics
    topics: dict[str, str]
    frames: list[RosbagFrame] = field(repr=False)
    T_cam_from_lidar: np.ndarray | None = field(default=None, repr=False)
    read_skips: dict[str, int] = field(default_factory=dict)
    format: str = "rosbag"

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def name(self) -> str:
        return str(self.root)

    @property
    def depth_role(self) -> str:
        """The role of the 3D source: ``depth`` or ``cloud``."""
        return "depth" if "depth" in self.topics else "cloud"

    def partner_path(self, frame: RosbagFrame) -> Path:
        """The name of the frame's depth image or scan message, for errors."""
        return Path(f"{self.root}#{self.topics[self.depth_role]}@{frame.partner_time_ns}")


def depth_mm(msgtype: str, msg) -> np.ndarray:
    """A depth message -> (H, W) uint16 millimetres (0: no depth)."""
    if msgtype != IMAGE:
        raise InvalidInputError("a depth topic must be a raw sensor_msgs/Image")
    depth = raw_image_array(msg)
    if depth.ndim != 2:
        raise InvalidInputError(f"depth image must be single-channel, got {msg.encoding}")
    if depth.dtype == np.float32:  # metres
        mm = np.where(np.isfinite(depth) & (depth > 0), depth * DEPTH_MM_PER_M + 0.5, 0.0)
        return np.clip(mm, 0, 65535).astype(np.uint16)
    if depth.dtype != np.uint16:
        raise InvalidInputError(f"depth image must be 16UC1 (mm) or 32FC1 (m), got {msg.encoding}")
    return depth


def _mapping_topics(reader, root: Path, given: dict[str, str]) -> dict[str, str]:
    """role -> topic: the named ones checked, the others found by type (and, for the
    depth image and the camera info, by name when types alone are ambiguous)."""
    unknown = sorted(set(given) - set(MAPPING_ROLES))
    if unknown:
        raise InvalidInputError(f"unknown topic role(s) {unknown}: roles are {list(MAPPING_ROLES)}")
    types = topic_types(reader)
    topics: dict[str, str] = {}
    if "depth" in given or "cloud" not in given:
        named_depth = {t: k for t, k in types.items() if "depth" in t and t != given.get("image")}
        pool = types if "depth" in given else named_depth
        found = choose_topic(pool, (IMAGE,), given.get("depth"), "depth", root)
        if found is not None:
            topics["depth"] = found
    cameras = {t: k for t, k in types.items() if t != topics.get("depth")}
    found = choose_topic(cameras, IMAGE_TYPES, given.get("image"), "image", root)
    if found is None:
        raise InvalidInputError(f"{root}: no image topic (sensor_msgs/Image or CompressedImage)")
    topics["image"] = found
    info = given.get("camera_info")
    sibling = found.rsplit("/", 1)[0] + "/camera_info"
    if info is None and types.get(sibling) == CAMERA_INFO:
        info = sibling
    found = choose_topic(types, (CAMERA_INFO,), info, "camera_info", root)
    if found is not None:
        topics["camera_info"] = found
    if "depth" not in topics:
        found = choose_topic(types, (POINT_CLOUD,), given.get("cloud"), "cloud", root)
        if found is None:
            raise InvalidInputError(
                f"{root}: no 3D source: a depth image topic or a PointCloud2 topic is needed"
            )
        topics["cloud"] = found
    found = choose_topic(types, POSE_TYPES, given.get("pose"), "pose", root)
    if found is not None:
        topics["pose"] = found
    return topics


def _camera(
    reader, topics, given: CameraIntrinsics | None, fallback: CameraIntrinsics | None, root: Path
) -> CameraIntrinsics:
    if given is not None:
        return given
    if "camera_info" not in topics:
        if fallback is not None:
            return fallback
        raise InvalidInputError(
            f"{root}: no CameraInfo topic: name one (--topic camera_info=...) or give "
            "the intrinsics"
        )
    for connection, _, raw in messages(reader, [topics["camera_info"]]):
        return intrinsics_from_camera_info(reader.deserialize(raw, connection.msgtype))
    raise InvalidInputError(f"{root}: topic {topics['camera_info']!r} holds no message")


def _pair(images: list[BagImage], partners: list[BagImage], max_s: float) -> dict[int, int]:
    """image index -> partner index, TUM's greedy association by stamp."""
    a = np.array([i.stamp_s for i in images])
    b = np.array([p.stamp_s for p in partners])
    return dict(associate(a, b, max_s)) if len(a) and len(b) else {}


def read_mapping_run(
    root: Path,
    *,
    topics: dict[str, str] | None = None,
    intrinsics: CameraIntrinsics | None = None,
    fallback_intrinsics: CameraIntrinsics | None = None,
    frames: slice | None = None,
    max_difference_s: float = 0.02,
    cloud_max_difference_s: float = 0.05,
    pose_max_gap_s: float = 0.5,
) -> RosbagRun:
    """Open and index a bag as a mapping run (see the comment above). ``intrinsics``
    overrides the bag's CameraInfo; ``fallback_intrinsics`` (the map's camera) is used
    when the bag has none. ``frames`` selects frames (images with a pose and a 3D
    partner) with Python slice semantics."""
    root = Path(root).expanduser().resolve()
    with open_bag(root) as reader:
        chosen = _mapping_topics(reader, root, dict(topics or {}))
        camera = _camera(reader, chosen, intrinsics, fallback_intrinsics, root)
        if camera.distortion is not None:
            raise InvalidInputError(
                f"{root}: the mapping camera has {camera.distortion.model} lens distortion; "
                "maps are built from rectified images (a query may be distorted)"
            )
        tree = read_frame_tree(reader)
        images = list_images(reader, chosen["image"])
        if not images:
            raise InvalidInputError(f"{root}: topic {chosen['image']!r} holds no image")
        camera_frame = images[0].frame_id.lstrip("/")
        if "pose" in chosen:
            track = read_pose_track(reader, chosen["pose"])
            body, pose_rows = pose_body(track, tree, camera_frame), track.pose_rows
        else:
            hint = "name an Odometry or PoseStamped topic (--topic pose=...)"
            _, body, pose_rows = tree.body_track(camera_frame, root, hint)
        role = "depth" if "depth" in chosen else "cloud"
        partners = list_images(reader, chosen[role])
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
