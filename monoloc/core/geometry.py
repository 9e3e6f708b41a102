"""Planar and rigid-body geometry shared by the vehicle and the server (pure numpy).

Conventions (docs/method.md section 9): camera frame is OpenCV (x right, y down, z forward);
world frame is right-handed with z up; a planar pose (X, Y, psi) is the camera position
on the ground plane and the heading of its optical axis, counter-clockwise from +X, in
(-pi, pi]. Transforms are named by what they map: ``T_world_from_cam`` takes camera
points to world points.
"""

from __future__ import annotations

import math

import numpy as np

from monoloc.core.errors import InvalidInputError

# KITTI's world is its first camera frame (x right, y down, z forward). The z-up world
# has x forward (KITTI z), y left (-KITTI x), z up (-KITTI y). This is the one place
# that conversion is defined.
R_ZUP_FROM_KITTI = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=np.float64)
T_ZUP_FROM_KITTI = np.eye(4)
T_ZUP_FROM_KITTI[:3, :3] = R_ZUP_FROM_KITTI


def wrap_angle(angle_rad: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to (-pi, pi]. Works on scalars and arrays of any shape."""
    wrapped = np.pi - np.mod(np.pi - np.asarray(angle_rad, dtype=np.float64), 2.0 * np.pi)
    if np.ndim(wrapped) == 0:
        return float(wrapped)
    return wrapped


def check_rigid(T: np.ndarray, name: str = "transform", tol: float = 1e-4) -> np.ndarray:
    """Return ``T`` as a float64 (4, 4) array, raising if it is not a finite rigid transform.

    Rigid: R R^T within ``tol`` of I (+ 1e-5 on the diagonal: np.allclose's relative
    term), the bottom row within ``tol`` of [0, 0, 0, 1] (the same), det R within ``tol``
    of 1. On plain floats: np.allclose and np.linalg.det cost ten times the test itself
    on a 3 x 3, and it runs for every pose hypothesis.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise InvalidInputError(f"{name} must be 4x4, got shape {T.shape}")
    rows = T.tolist()
    if not all(math.isfinite(v) for row in rows for v in row):
        raise InvalidInputError(f"{name} contains NaN or infinite values")
    R = [row[:3] for row in rows[:3]]
    orthonormal = all(
        abs(sum(R[i][k] * R[j][k] for k in range(3)) - (i == j)) <= tol + 1e-5 * (i == j)
        for i in range(3)
        for j in range(i, 3)
    )
    (a, b, c), (d, e, f), (g, h, i) = R
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    expected = (0.0, 0.0, 0.0, 1.0)
    bottom = all(abs(v - w) <= tol + 1e-5 * w for v, w in zip(rows[3], expected, strict=True))
    if not orthonormal or abs(det - 1.0) > tol or not bottom:
        raise InvalidInputError(f"{name} is not a rigid transform (rotation not orthonormal)")
    return T


def invert_rigid(T_a_from_b: np.ndarray) -> np.ndarray:
    """Invert a (4, 4) rigid transform: returns T_b_from_a."""
    R_t = T_a_from_b[:3, :3].T
    T_b_from_a = np.empty((4, 4))
    T_b_from_a[:3, :3] = R_t
    T_b_from_a[:3, 3] = -R_t @ T_a_from_b[:3, 3]
    T_b_from_a[3] = (0.0, 0.0, 0.0, 1.0)
    return T_b_from_a


def rotation_angle_rad(R: np.ndarray) -> float:
    """Angle of a (3, 3) rotation matrix, in [0, pi]."""
    cos_angle = (float(R[0, 0]) + float(R[1, 1]) + float(R[2, 2]) - 1.0) / 2.0
    if math.isnan(cos_angle):
        return cos_angle
    return math.acos(min(1.0, max(-1.0, cos_angle)))


def planar_from_T_world_from_cam(T_world_from_cam: np.ndarray) -> np.ndarray:
    """Planar pose (X, Y, psi) of a camera: position on the ground, optical-axis heading.

    Accepts (4, 4) or (N, 4, 4); returns (3,) or (N, 3) float64.
    """
    T = np.asarray(T_world_from_cam, dtype=np.float64)
    if T.shape == (4, 4):  # one pose (per hypothesis, per query): plain floats are faster
        (_, _, ax, x), (_, _, ay, y) = T[:2].tolist()
        psi = math.atan2(ay, ax)
        return np.array([x, y, math.pi - (math.pi - psi) % (2.0 * math.pi)])
    axis_world = T[..., :3, 2]
    psi = np.arctan2(axis_world[..., 1], axis_world[..., 0])
    return np.stack([T[..., 0, 3], T[..., 1, 3], wrap_angle(psi)], axis=-1)


def R_world_from_cam_level(yaw_rad: float, pitch_rad: float = 0.0, roll_rad: float = 0.0):
    """Rotation of a camera whose optical axis has heading ``yaw_rad`` (CCW from +X).

    Positive pitch tilts the optical axis up, positive roll rotates the image clockwise
    about the optical axis. Returns (3, 3) float64.
    """
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    # Level camera: x right, y down, z forward expressed in the z-up world.
    R_level = np.array([[sy, 0.0, cy], [-cy, 0.0, sy], [0.0, -1.0, 0.0]])
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    R_pitch = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    R_roll = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return R_level @ R_pitch @ R_roll


def T_world_from_cam_planar(
    x_m: float,
    y_m: float,
    yaw_rad: float,
    height_m: float = 0.0,
    pitch_rad: float = 0.0,
    roll_rad: float = 0.0,
) -> np.ndarray:
    """A camera pose at planar position (x, y), given height above z = 0 and heading."""
    T = np.eye(4)
    T[:3, :3] = R_world_from_cam_level(yaw_rad, pitch_rad, roll_rad)
    T[:3, 3] = [x_m, y_m, height_m]
    return T


def kitti_to_zup(T_kittiworld_from_cam: np.ndarray) -> np.ndarray:
    """Convert KITTI poses (world = first camera frame) to the z-up world. (4,4) or (N,4,4)."""
    return T_ZUP_FROM_KITTI @ np.asarray(T_kittiworld_from_cam, dtype=np.float64)


def zup_to_kitti(T_world_from_cam: np.ndarray) -> np.ndarray:
    """Inverse of :func:`kitti_to_zup`."""
    return T_ZUP_FROM_KITTI.T @ np.asarray(T_world_from_cam, dtype=np.float64)


def quaternion_xyzw_from_R(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (qx, qy, qz, qw), qw >= 0, of a (3, 3) rotation matrix."""
    m = np.asarray(R, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0.0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def R_from_quaternion_xyzw(q_xyzw: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix of a quaternion (qx, qy, qz, qw); normalises it first."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def circular_mean(angles_rad: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Weighted circular mean of angles, in (-pi, pi]."""
    angles = np.asarray(angles_rad, dtype=np.float64)
    w = np.ones_like(angles) if weights is None else np.asarray(weights, dtype=np.float64)
    return float(wrap_angle(np.arctan2(np.sum(w * np.sin(angles)), np.sum(w * np.cos(angles)))))
