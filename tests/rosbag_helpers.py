"""Write a ROS bag (rosbags' writers: ROS 2 sqlite3 or mcap, ROS 1) from a sim run in KITTI
layout, the way a car would record it: camera images (raw mono8 or PNG CompressedImage),
CameraInfo (or none), a LiDAR PointCloud2 in the velodyne frame (or a 32FC1 depth image),
the ground-truth poses and the vehicle's speed and yaw rate in one of the layouts
recorders produce (``poses``):

- ``odometry``: nav_msgs/Odometry of ``base_link`` in ``map``;
- ``odometry_camera``: Odometry of the camera's own frame; /tf_static holds only the
  LiDAR's mounting on the camera (none without a cloud);
- ``pose_stamped``: geometry_msgs/PoseStamped of ``base_link`` (unnamed, as PoseStamped
  is) in ``map``, no /tf;
- ``tf``: one moving /tf transform map -> base_link;
- ``tf_chain``: /tf map -> odom (a slow drift correction, 2 Hz) and odom -> base_link;
- ``none``: no poses;

and the rig in /tf_static (base_link -> camera_optical, base_link -> velodyne)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monoloc.core.formats import kitti as kitti_format
from monoloc.core.formats import vehicle as vehicle_format
from monoloc.core.geometry import invert_rigid, kitti_to_zup, quaternion_xyzw_from_R

T0_S = 1_700_000_000  # stamps start here (a real recording's epoch time)
# base_link (x forward, y left, z up) <- camera optical frame (x right, y down, z forward):
# the camera 1.2 m ahead of the base and 1.5 m up
T_BASE_FROM_CAM = np.array(
    [[0.0, 0.0, 1.0, 1.2], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0]]
)


@dataclass(frozen=True)
class SimRun:
    """A sim run's files: images, scans, depth images, calib, poses and signals."""

    seq_dir: Path
    images: list[Path]
    scans: list[Path]
    times_s: np.ndarray
    T_world_from_cam: np.ndarray  # (N, 4, 4) z-up
    T_cam_from_lidar: np.ndarray
    K: np.ndarray
    signals: np.ndarray  # (N, 2) speed, yaw rate

    @classmethod
    def read(cls, root: Path, seq: str) -> SimRun:
        seq_dir = root / "sequences" / seq
        calib = kitti_format.read_calib(seq_dir / "calib.txt")
        P0 = calib.P_image_from_cam0[0]
        Tr = calib.T_cam0_from_lidar
        poses = kitti_to_zup(kitti_format.read_poses(root / "poses" / f"{seq}.txt"))
        signals = vehicle_format.read_vehicle(seq_dir / "vehicle.txt")
        return cls(
            seq_dir,
            sorted((seq_dir / "image_0").glob("*.png")),
            sorted((seq_dir / "velodyne").glob("*.bin")),
            kitti_format.read_times(seq_dir / "times.txt"),
            poses,
            Tr,
            P0[:, :3],
            np.column_stack([signals.speed_mps, signals.yaw_rate_radps]),
        )


def _time(typestore, t_s: float):
    Time = typestore.types["builtin_interfaces/msg/Time"]
    total_ns = round(t_s * 1e9)
    return Time(sec=total_ns // 10**9, nanosec=total_ns % 10**9)


def _header(typestore, t_s: float, frame_id: str):
    Header = typestore.types["std_msgs/msg/Header"]
    if "seq" in Header.__dataclass_fields__:  # ROS 1
        return Header(seq=0, stamp=_time(typestore, t_s), frame_id=frame_id)
    return Header(stamp=_time(typestore, t_s), frame_id=frame_id)


def _pose_parts(typestore, T: np.ndarray):
    types = typestore.types
    q = quaternion_xyzw_from_R(T[:3, :3])
    quaternion = types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])
    return T[:3, 3], quaternion


def _transform(typestore, t_s: float, parent: str, child: str, T: np.ndarray):
    types = typestore.types
    translation, rotation = _pose_parts(typestore, T)
    return types["geometry_msgs/msg/TransformStamped"](
        header=_header(typestore, t_s, parent),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](*translation), rotation=rotation
        ),
    )


def _odometry(
    typestore,
    t_s: float,
    T_world_from_base: np.ndarray,
    speed: float,
    yaw_rate: float,
    child: str = "base_link",
):
    types = typestore.types
    position, orientation = _pose_parts(typestore, T_world_from_base)
    vec = types["geometry_msgs/msg/Vector3"]
    return types["nav_msgs/msg/Odometry"](
        header=_header(typestore, t_s, "map"),
        child_frame_id=child,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](*position), orientation=orientation
            ),
            covariance=np.zeros(36),
        ),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](
                linear=vec(speed, 0.0, 0.0), angular=vec(0.0, 0.0, yaw_rate)
            ),
            covariance=np.zeros(36),
        ),
    )


def _pose_stamped(typestore, t_s: float, T_world_from_base: np.ndarray):
    types = typestore.types
    position, orientation = _pose_parts(typestore, T_world_from_base)
    return types["geometry_msgs/msg/PoseStamped"](
        header=_header(typestore, t_s, "map"),
        pose=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](*position), orientation=orientation
        ),
    )


def _image(typestore, t_s: float, pixels: np.ndarray, encoding: str, frame_id: str):
    item = pixels.dtype.itemsize * (pixels.shape[2] if pixels.ndim == 3 else 1)
    return typestore.types["sensor_msgs/msg/Image"](
        header=_header(typestore, t_s, frame_id),
        height=pixels.shape[0],
        width=pixels.shape[1],
        encoding=encoding,
        is_bigendian=0,
        step=pixels.shape[1] * item,
        data=np.frombuffer(np.ascontiguousarray(pixels).tobytes(), dtype=np.uint8),
    )


def _cloud(typestore, t_s: float, points: np.ndarray):
    types = typestore.types
    Field = types["sensor_msgs/msg/PointField"]
    fields = [Field(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    fields.append(Field(name="intensity", offset=12, datatype=7, count=1))
    data = np.ascontiguousarray(points[:, :4], dtype="<f4")
    return types["sensor_msgs/msg/PointCloud2"](
        header=_header(typestore, t_s, "velodyne"),
        height=1,
        width=len(data),
        fields=fields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * len(data),
        data=np.frombuffer(data.tobytes(), dtype=np.uint8),
        is_dense=True,
    )


def _camera_info(typestore, t_s: float, K: np.ndarray, width: int, height: int):
    types = typestore.types
    P = np.zeros((3, 4))
    P[:, :3] = K
    CameraInfo = types["sensor_msgs/msg/CameraInfo"]
    matrices = {"d": np.zeros(5), "k": K.ravel().astype(np.float64), "r": np.eye(3).ravel()}
    matrices["p"] = P.ravel()
    if "K" in CameraInfo.__dataclass_fields__:  # ROS 1 spells them D, K, R, P
        matrices = {name.upper(): value for name, value in matrices.items()}
    return CameraInfo(
        header=_header(typestore, t_s, "camera_optical"),
        height=height,
        width=width,
        distortion_model="plumb_bob",
        **matrices,
        binning_x=0,
        binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )


def write_sim_bag(
    run: SimRun,
    out: Path,
    *,
    image: str = "raw",  # raw | compressed
    three_d: str = "cloud",  # cloud | depth | none
    poses: str = "odometry",  # odometry | odometry_camera | pose_stamped | tf | tf_chain | none
    storage: str = "sqlite3",  # sqlite3 | mcap (ROS 2) | ros1 (``out`` is then a .bag file)
    camera_info: bool = True,
    T_base_from_cam: np.ndarray = T_BASE_FROM_CAM,
) -> Path:
    """Write the bag ``out`` (see the module docstring), the camera mounted at
    ``T_base_from_cam`` on base_link (/tf_static); returns it."""
    import cv2
    from rosbags.typesys import Stores, get_typestore

    first = cv2.imread(str(run.images[0]), cv2.IMREAD_GRAYSCALE)
    height, width = first.shape
    if storage == "ros1":
        from rosbags.rosbag1 import Writer
        from rosbags.typesys import get_types_from_msg

        store = get_typestore(Stores.ROS1_NOETIC)
        # noetic's store leaves tf2_msgs out; its definition, as a ROS 1 recorder writes it
        tf_msg = "geometry_msgs/TransformStamped[] transforms"
        store.register(get_types_from_msg(tf_msg, "tf2_msgs/msg/TFMessage"))
        bag_writer, serialize = Writer(out), store.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        store = get_typestore(Stores.ROS2_HUMBLE)
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        bag_writer = Writer(out, version=8, storage_plugin=plugin)
        serialize = store.serialize_cdr
    with bag_writer as writer:

        def connection(topic: str, msgtype: str):
            return writer.add_connection(topic, msgtype, typestore=store)

        def write(conn, t_s: float, msg, latency_s: float = 0.003) -> None:
            writer.write(conn, round((t_s + latency_s) * 1e9), serialize(msg, conn.msgtype))

        if poses != "odometry_camera" or three_d == "cloud":
            tf_static = connection("/tf_static", "tf2_msgs/msg/TFMessage")
        if camera_info:
            info = connection("/camera/camera_info", "sensor_msgs/msg/CameraInfo")
        if image == "raw":
            camera = connection("/camera/image_raw", "sensor_msgs/msg/Image")
        else:
            camera = connection("/camera/image_raw/compressed", "sensor_msgs/msg/CompressedImage")
        if three_d == "cloud":
            cloud = connection("/velodyne_points", "sensor_msgs/msg/PointCloud2")
        elif three_d == "depth":
            depth = connection("/camera/depth/image", "sensor_msgs/msg/Image")
        if poses in ("odometry", "odometry_camera"):
            odom = connection("/odom", "nav_msgs/msg/Odometry")
        elif poses == "pose_stamped":
            pose_topic = connection("/vehicle/pose", "geometry_msgs/msg/PoseStamped")
        elif poses in ("tf", "tf_chain"):
            tf = connection("/tf", "tf2_msgs/msg/TFMessage")
        TFMessage = store.types["tf2_msgs/msg/TFMessage"]
        t_first = T0_S + float(run.times_s[0])
        T_base_from_velo = T_base_from_cam @ run.T_cam_from_lidar
        statics = [
            _transform(store, t_first, "base_link", "camera_optical", T_base_from_cam),
            _transform(store, t_first, "base_link", "velodyne", _orthonormal(T_base_from_velo)),
        ]
        if poses == "odometry_camera" and three_d == "cloud":
            T_cam_from_velo = _orthonormal(run.T_cam_from_lidar)
            statics = [_transform(store, t_first, "camera_optical", "velodyne", T_cam_from_velo)]
        if poses != "odometry_camera" or three_d == "cloud":
            write(tf_static, t_first, TFMessage(transforms=statics), latency_s=0.0)
        for i, path in enumerate(run.images):
            t = T0_S + float(run.times_s[i])
            T_world_from_base = run.T_world_from_cam[i] @ invert_rigid(T_base_from_cam)
            speed, yaw_rate = run.signals[i]
            if poses == "odometry":
                write(odom, t, _odometry(store, t, T_world_from_base, speed, yaw_rate))
            elif poses == "odometry_camera":
                T = run.T_world_from_cam[i]
                msg = _odometry(store, t, T, speed, yaw_rate, child="camera_optical")
                write(odom, t, msg)
            elif poses == "pose_stamped":
                write(pose_topic, t, _pose_stamped(store, t, T_world_from_base))
            elif poses == "tf":
                moving = _transform(store, t, "map", "base_link", T_world_from_base)
                write(tf, t, TFMessage(transforms=[moving]))
            elif poses == "tf_chain":
                last = i == len(run.images) - 1
                for edge in _chain(store, t, i, last, T_world_from_base):
                    write(tf, t, TFMessage(transforms=[edge]))
            if camera_info:
                write(info, t, _camera_info(store, t, run.K, width, height))
            gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if image == "raw":
                write(camera, t, _image(store, t, gray, "mono8", "camera_optical"))
            else:
                msg = store.types["sensor_msgs/msg/CompressedImage"](
                    header=_header(store, t, "camera_optical"),
                    format="png",
                    data=np.frombuffer(path.read_bytes(), dtype=np.uint8),
                )
                write(camera, t, msg)
            if three_d == "cloud":
                points = np.fromfile(run.scans[i], dtype=np.float32).reshape(-1, 4)
                write(cloud, t + 0.01, _cloud(store, t + 0.01, points))
            elif three_d == "depth":
                raw = cv2.imread(str(run.seq_dir / "depth" / path.name), cv2.IMREAD_UNCHANGED)
                depth_m = raw.astype(np.float32) / 256.0  # the sim's KITTI depth encoding
                write(depth, t, _image(store, t, depth_m, "32FC1", "camera_optical"))
    return out


# map -> odom: a drift correction that grows along the run, published at 2 Hz (every
# other frame of the sim's 10 Hz), as a localization node does; odom -> base_link carries
# the rest.
def _T_map_from_odom(k: int) -> np.ndarray:
    yaw = 0.002 * k
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:3, 3] = [0.3 + 0.01 * k, -0.2 + 0.005 * k, 0.0]
    return T


def _chain(store, t_s: float, i: int, last: bool, T_map_from_base: np.ndarray) -> list:
    """The /tf transforms of frame ``i``: odom -> base_link every frame; map -> odom on even
    frames and the last one. In between, odom -> base_link is written against the
    correction a reader interpolates there (linear in k, so the midpoint's)."""
    T_map_from_odom = _T_map_from_odom(i)
    T_odom_from_base = invert_rigid(T_map_from_odom) @ T_map_from_base
    edges = [_transform(store, t_s, "odom", "base_link", T_odom_from_base)]
    if i % 2 == 0 or last:
        edges.append(_transform(store, t_s, "map", "odom", T_map_from_odom))
    return edges


def _orthonormal(T: np.ndarray) -> np.ndarray:
    """Re-orthonormalise a composed rigid transform (float round-off)."""
    u, _, vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = u @ vt
    return out
