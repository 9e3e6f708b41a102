"""A ROS 2 bag replayed the way a vehicle drives: its camera frames, speed and yaw rate,
and (when the bag has one) a ground-truth track (``monoloc drive BAG``).

Topics (``topics``: role -> topic name; a role left out is found by message type when
the bag has exactly one topic of that type):

- ``image``: ``sensor_msgs/CompressedImage`` (its JPEG/PNG bytes are sent as they are)
  or ``sensor_msgs/Image`` (encoded to PNG with Pillow: 8-bit mono, 16-bit mono, RGB,
  BGR, RGBA, BGRA); topics whose name holds "depth" are not taken for it;
- ``odometry``: ``nav_msgs/Odometry``, whose twist gives the speed
  (``linear.x``, m/s) and yaw rate (``angular.z``, rad/s), interpolated at each image's
  stamp; or a ``PoseStamped`` / ``PoseWithCovarianceStamped`` topic, whose poses both are
  differentiated from. Without one, they are differentiated from the moving ``/tf``
  transforms above the camera (``map -> odom -> base_link`` composed);
- ``truth`` (optional, never guessed): a pose topic (Odometry, PoseStamped) with the
  true poses of a body frame; with the static transform from that frame to the camera's
  it gives the planar ground truth the drive is scored against.

The camera's mounting: ``/tf_static`` from the speed reference frame (the odometry's
child frame, e.g. ``base_link``) to the camera's is the run's ``T_vehicle_from_cam``
(``ReplayRun.mounting``, monoloc.core.mounting: lever arm, lateral offset, height, roll,
pitch, yaw); the motion model moves the camera with that frame by its planar part, and
the drive reports that frame's pose.

Frame times are the images' header stamps. Reading the bag needs ``rosbags`` (and
``Pillow`` for raw images): ``pip install 'monoloc[bags]'``.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from monoloc.client.replay import ReplayRun, mounting_note
from monoloc.core.errors import InvalidInputError, MonolocError
from monoloc.core.formats import rosbag as bag
from monoloc.core.geometry import planar_from_T_world_from_cam, wrap_angle
from monoloc.core.mounting import CameraMounting

BAG_SUFFIXES = (".bag", ".mcap", ".db3")
ROLES = ("image", "camera_info", "odometry", "truth")
MISSING_PILLOW = "replaying raw ROS images needs Pillow: pip install 'monoloc[bags]'"


def is_bag(path: Path) -> bool:
    """A rosbag2 folder (metadata.yaml) or a bag file (.bag, .mcap, .db3)."""
    path = Path(path)
    return (path.is_dir() and (path / "metadata.yaml").is_file()) or (
        path.is_file() and path.suffix in BAG_SUFFIXES
    )


def png_from_raw(pixels: np.ndarray, encoding: str) -> bytes:
    """PNG bytes of a raw image (``monoloc.core.formats.rosbag.raw_image_array``)."""
    try:
        from PIL import Image
    except ModuleNotFoundError as exc:
        raise MonolocError(MISSING_PILLOW) from exc
    if encoding in ("bgr8", "8uc3"):
        pixels = pixels[:, :, ::-1]
    elif encoding == "bgra8":
        pixels = pixels[:, :, [2, 1, 0, 3]]
    if pixels.dtype == np.uint16:
        image = Image.fromarray(np.ascontiguousarray(pixels), mode="I;16")
    elif pixels.dtype == np.uint8:
        image = Image.fromarray(np.ascontiguousarray(pixels))
    else:
        raise InvalidInputError(f"a camera image must be 8 or 16 bit, got {encoding}")
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


class _BagImages:
    """Reads frame images back from the bag by their bag time (``bag.MessageReader``)."""

    def __init__(self, root: Path, topic: str, times_ns: dict[Path, int]) -> None:
        self.topic, self.times_ns = topic, times_ns
        self._messages = bag.MessageReader(root)

    def __call__(self, key: Path) -> bytes:
        msgtype, msg = self._messages(self.topic, self.times_ns[key])
        if msgtype == bag.COMPRESSED_IMAGE:
            return bytes(msg.data)
        return png_from_raw(bag.raw_image_array(msg), bag.image_encoding(msg))


def _body_yaw_rad(rows: np.ndarray) -> np.ndarray:
    """Heading of a body's +x axis (ROS: x forward) from pose rows (t x y z qx qy qz qw)."""
    qx, qy, qz, qw = rows[:, 4], rows[:, 5], rows[:, 6], rows[:, 7]
    return np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))


def signals_from_pose_rows(rows: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """Speed (m/s, unsigned) and yaw rate (rad/s) (N, 2) at ``times_s`` by differences of
    the body's planar poses (``/tf``), interpolated at the mid-points."""
    if len(rows) < 2:
        raise InvalidInputError("speed and yaw rate from /tf need at least two poses")
    t = rows[:, 0]
    dt = np.diff(t)
    keep = dt > 0
    speed = np.linalg.norm(np.diff(rows[:, 1:3], axis=0), axis=1)[keep] / dt[keep]
    yaw_rate = wrap_angle(np.diff(_body_yaw_rad(rows)))[keep] / dt[keep]
    mid = 0.5 * (t[1:] + t[:-1])[keep]
    return np.column_stack([np.interp(times_s, mid, speed), np.interp(times_s, mid, yaw_rate)])


def _truth(track: bag.PoseTrack, tree: bag.FrameTree, camera_frame: str, times_s):
    """Planar ground truth (N, 3) of the camera at ``times_s``."""
    body = bag.pose_body(track, tree, camera_frame)
    T_body_from_cam = tree.static_between(body, camera_frame)
    if T_body_from_cam is None:
        raise InvalidInputError(
            f"no static transform from the truth's frame {body!r} to the camera's {camera_frame!r}"
        )
    planar = []
    for row in track.pose_rows:
        T_world_from_body = bag.T_from_pose_row(row)
        planar.append(planar_from_T_world_from_cam(T_world_from_body @ T_body_from_cam))
    planar = np.asarray(planar)
    t = track.pose_rows[:, 0]
    yaw = np.unwrap(planar[:, 2])
    return np.column_stack(
        [
            np.interp(times_s, t, planar[:, 0]),
            np.interp(times_s, t, planar[:, 1]),
            wrap_angle(np.interp(times_s, t, yaw)),
        ]
    )


def _mounting(
    tree: bag.FrameTree, body: str, camera_frame: str
) -> tuple[CameraMounting | None, str]:
    """(where the camera sits on ``body``: the whole static transform body -> camera of
    /tf_static, a note), or (None, "") when no static transform joins them."""
    T_body_from_cam = tree.static_between(body, camera_frame)
    if T_body_from_cam is None or body == camera_frame.lstrip("/"):
        return None, ""
    try:
        mounting = CameraMounting.from_T_vehicle_from_cam(T_body_from_cam)
    except InvalidInputError as exc:
        raise InvalidInputError(f"/tf_static {body} -> {camera_frame}: {exc}") from exc
    return mounting, mounting_note(mounting, f"/tf_static {body} -> {camera_frame}")


def read_bag_run(path: Path, topics: dict[str, str] | None = None) -> ReplayRun:
    """The bag's camera frames with speed, yaw rate, the camera's lever arm from
    /tf_static and optional truth (module docstring)."""
    root = Path(path).expanduser().resolve()
    given = dict(topics or {})
    unknown = sorted(set(given) - set(ROLES))
    if unknown:
        raise InvalidInputError(f"unknown topic role(s) {unknown}: roles are {list(ROLES)}")
    notes = []
    with bag.open_bag(root) as reader:
        types = bag.topic_types(reader)
        cameras = {t: k for t, k in types.items() if "depth" not in t or t == given.get("image")}
        image = bag.choose_topic(cameras, bag.IMAGE_TYPES, given.get("image"), "image", root)
        if image is None:
            raise InvalidInputError(
                f"{root}: no image topic (sensor_msgs/Image or CompressedImage)"
            )
        # the truth topic is not the vehicle's odometry unless named as both
        candidates = {
            t: k for t, k in types.items() if t != given.get("truth") or "odometry" in given
        }
        odometry = given.get("odometry")
        if odometry is None:  # an Odometry topic first, else one pose topic
            odometry = bag.choose_topic(candidates, (bag.ODOMETRY,), None, "odometry", root)
        if odometry is None:
            odometry = bag.choose_topic(candidates, bag.POSE_TYPES, None, "odometry", root)
        else:
            bag.choose_topic(candidates, bag.POSE_TYPES, odometry, "odometry", root)
        truth_track = None
        if "truth" in given:
            bag.choose_topic(types, bag.POSE_TYPES, given["truth"], "truth", root)
            truth_track = bag.read_pose_track(reader, given["truth"])
        images = bag.list_images(reader, image)
        if not images:
            raise InvalidInputError(f"{root}: topic {image!r} holds no image")
        camera_frame = images[0].frame_id.lstrip("/")
        intrinsics = _camera_info(reader, types, image, given.get("camera_info"), root)
        times = np.array([i.stamp_s for i in images])
        tree = bag.read_frame_tree(reader)
        if odometry is not None:
            track = bag.read_pose_track(reader, odometry)
            body = bag.pose_body(track, tree, camera_frame)
            if track.signal_rows is not None:
                signals = bag.signals_at(track.signal_rows, times)
                notes.append(f"speed and yaw rate from {odometry} (twist)")
            else:
                signals = signals_from_pose_rows(track.pose_rows, times)
                notes.append(f"speed and yaw rate differentiated from {odometry} ({body})")
        else:
            hint = "name an Odometry or pose topic (--topic odometry=...)"
            _, body, rows = tree.body_track(camera_frame, root, hint)
            signals = signals_from_pose_rows(rows, times)
            notes.append(f"no Odometry topic: speed and yaw rate differentiated from /tf ({body})")
    mounting, note = _mounting(tree, body, camera_frame)
    if note:
        notes.append(note)
    truth = None
    if truth_track is not None:
        truth = _truth(truth_track, tree, camera_frame, times)
    keys = [Path(f"{root}#{image}@{i.bag_time_ns}") for i in images]
    reader_fn = _BagImages(
        root, image, {k: i.bag_time_ns for k, i in zip(keys, images, strict=True)}
    )
    return ReplayRun(
        f"rosbag:{root.name}",
        keys,
        times,
        signals,
        truth,
        notes,
        None if mounting is None else mounting.lever_arm_m,
        reader_fn,
        camera_frame or None,
        intrinsics,
        mounting,
    )


def _camera_info(reader, types: dict[str, str], image: str, given: str | None, root: Path):
    """The camera's intrinsics from its CameraInfo (the topic named, the image topic's
    sibling ``camera_info``, else the bag's only one), or None without one."""
    sibling = image.rsplit("/", 1)[0] + "/camera_info"
    if given is None and types.get(sibling) == bag.CAMERA_INFO:
        given = sibling
    topic = bag.choose_topic(types, (bag.CAMERA_INFO,), given, "camera_info", root)
    if topic is None:
        return None
    for connection, _, raw in bag.messages(reader, [topic]):
        return bag.intrinsics_from_camera_info(reader.deserialize(raw, connection.msgtype))
    raise InvalidInputError(f"{root}: topic {topic!r} holds no message")
