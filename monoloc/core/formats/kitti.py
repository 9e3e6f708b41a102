"""KITTI odometry text files.

``poses/NN.txt``  one pose per line: 12 numbers, the top 3x4 of T_kittiworld_from_cam0,
                  row-major. KITTI's world is its first camera frame (x right, y down,
                  z forward); ``monoloc.core.geometry.kitti_to_zup`` converts it.
``times.txt``     one timestamp (s) per frame.
``calib.txt``     ``NAME: 12 numbers`` lines: ``P0`` .. ``P3`` (3x4, the rectified camera-0
                  frame to camera i's pixels) and ``Tr`` (top 3x4 of T_cam0_from_lidar).
                  Other names are ignored.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import TextIO

import numpy as np

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats._text import Source, finite_numbers, number_rows, read_lines
from monoloc.core.geometry import check_rigid

RIGID_TOL = 1e-3  # the files hold 9 to 12 significant digits
_PROJECTION_RE = re.compile(r"^P(\d+)$")


def _rigid_4x4(top_3x4: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :] = top_3x4
    return T


def read_poses(source: Source) -> np.ndarray:
    """poses/NN.txt -> (N, 4, 4) float64 T_kittiworld_from_cam; every pose finite and
    rigid, at least one."""
    path, rows, numbers = number_rows(source, 12, "pose")
    if len(rows) == 0:
        raise InputFileError(path, "no poses")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    for pose, number in zip(poses, numbers, strict=True):
        try:
            check_rigid(pose, "pose", tol=RIGID_TOL)
        except InvalidInputError as exc:
            raise InputFileError(
                path, "pose is not rigid (rotation not orthonormal)", number
            ) from exc
    return poses


def write_poses(handle: TextIO, T_kittiworld_from_cam: np.ndarray) -> None:
    """(N, 4, 4) or (N, 3, 4) poses -> one line of 12 numbers (top 3x4, row-major) each."""
    for T in np.asarray(T_kittiworld_from_cam, dtype=np.float64):
        handle.write(" ".join(f"{v:.9e}" for v in T[:3, :4].reshape(-1)) + "\n")


def read_times(source: Source) -> np.ndarray:
    """times.txt -> (N,) float64 timestamps_s, at least one."""
    path, rows, _ = number_rows(source, 1, "timestamp")
    if len(rows) == 0:
        raise InputFileError(path, "no timestamps")
    return rows[:, 0]


def write_times(handle: TextIO, timestamps_s: np.ndarray) -> None:
    """One timestamp (s) per line, 7 significant digits (KITTI's own precision)."""
    for t in np.asarray(timestamps_s, dtype=np.float64).reshape(-1):
        handle.write(f"{t:e}\n")


@dataclass(frozen=True)
class KittiCalib:
    """A sequence's calib.txt: the projections P0, P1, ... (3, 4) of the rectified
    camera-0 frame into each camera's image, and the LiDAR's pose (4, 4)."""

    P_image_from_cam0: tuple[np.ndarray, ...] = field(repr=False)
    T_cam0_from_lidar: np.ndarray = field(repr=False)


def _calib_fields(source: Source):
    path, lines = read_lines(source, "calibration")
    fields: dict[str, tuple[int, list[str]]] = {}
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise InputFileError(path, "expected 'NAME: numbers'", number)
        fields[key.strip()] = (number, rest.split())
    return path, fields


def _matrix_3x4(path, fields: dict, key: str) -> np.ndarray:
    if key not in fields:
        raise InputFileError(path, f"no {key} line (KITTI calib.txt needs P0 and Tr)")
    number, values = fields[key]
    if len(values) != 12:
        raise InputFileError(path, f"{key} has {len(values)} numbers, expected 12 (3x4)", number)
    return np.array(finite_numbers(path, number, values, key)).reshape(3, 4)


def read_calib(source: Source) -> KittiCalib:
    """calib.txt -> KittiCalib. P0 must be a pinhole camera matrix (fx, fy > 0), every
    ``Pi`` and ``Tr`` 12 finite numbers, Tr rigid; P0 .. Pn must be consecutive."""
    path, fields = _calib_fields(source)
    P0 = _matrix_3x4(path, fields, "P0")
    fx, fy = P0[0, 0], P0[1, 1]
    pinhole = abs(P0[0, 1]) < 1e-9 and abs(P0[1, 0]) < 1e-9 and np.allclose(P0[2, :3], [0, 0, 1])
    if not pinhole or fx <= 0 or fy <= 0:
        raise InputFileError(
            path,
            "P0 is not a pinhole camera matrix [fx 0 cx tx; 0 fy cy ty; 0 0 1 tz]",
            fields["P0"][0],
        )
    indices = sorted(int(m.group(1)) for key in fields if (m := _PROJECTION_RE.match(key)))
    if indices != list(range(len(indices))):
        listed = ", ".join(f"P{i}" for i in indices)
        raise InputFileError(path, f"projections {listed} are not P0, P1, ... without a gap")
    projections = (P0, *(_matrix_3x4(path, fields, f"P{i}") for i in indices[1:]))
    T_cam0_from_lidar = _rigid_4x4(_matrix_3x4(path, fields, "Tr"))
    try:
        check_rigid(T_cam0_from_lidar, "Tr", tol=RIGID_TOL)
    except InvalidInputError as exc:
        raise InputFileError(path, str(exc), fields["Tr"][0]) from exc
    return KittiCalib(projections, T_cam0_from_lidar)


def _row(values: np.ndarray) -> str:
    # + 0.0 turns -0.0 into 0.0
    return " ".join(f"{v + 0.0:.12e}" for v in np.asarray(values, dtype=np.float64).ravel())


def write_calib(handle: TextIO, calib: KittiCalib) -> None:
    """``P0: 12 numbers`` ... then ``Tr: 12 numbers``, 13 significant digits."""
    for i, P in enumerate(calib.P_image_from_cam0):
        handle.write(f"P{i}: {_row(P)}\n")
    handle.write(f"Tr: {_row(np.asarray(calib.T_cam0_from_lidar)[:3, :4])}\n")
