"""TUM RGB-D text files (the format evo and TUM's tools read).

``groundtruth.txt`` (any TUM trajectory)  ``timestamp tx ty tz qx qy qz qw`` per line:
    T_world_from_cam, position in metres, unit quaternion (x, y, z, w).
``rgb.txt`` / ``depth.txt`` (file lists)  ``timestamp filename`` per line, the filename
    relative to the list's folder.

Both skip blank lines and '#' comments. Timestamps are seconds, written with 6 decimals
(``stamp_text``); TUM names an image file after its stamp as listed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats._text import Source, data_lines, finite_numbers, number_rows, read_lines
from monoloc.core.geometry import R_from_quaternion_xyzw, quaternion_xyzw_from_R

QUATERNION_NORM_TOL = 0.01  # TUM's files give 4 decimals


def stamp_text(t_s: float) -> str:
    """A timestamp as TUM files write it (and name images after it): 6 decimals."""
    return f"{t_s:.6f}"


@dataclass(frozen=True)
class TumTrajectory:
    """Poses as read: timestamps_s (N,), position_world_m (N, 3) and q_world_from_cam_xyzw
    (N, 4), the quaternion as written (unit within QUATERNION_NORM_TOL)."""

    timestamps_s: np.ndarray
    position_world_m: np.ndarray = field(repr=False)
    q_world_from_cam_xyzw: np.ndarray = field(repr=False)

    def __len__(self) -> int:
        return len(self.timestamps_s)

    @property
    def T_world_from_cam(self) -> np.ndarray:
        """(N, 4, 4) float64 poses."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        for i, (position, q) in enumerate(
            zip(self.position_world_m, self.q_world_from_cam_xyzw, strict=True)
        ):
            T[i, :3, :3] = R_from_quaternion_xyzw(q)
            T[i, :3, 3] = position
        return T


def read_trajectory(source: Source) -> TumTrajectory:
    """A TUM trajectory (groundtruth.txt) -> TumTrajectory, in file order; at least one
    pose, every number finite, every quaternion of norm 1 (within 0.01)."""
    path, rows, numbers = number_rows(source, 8, "ground-truth pose")
    if len(rows) == 0:
        raise InputFileError(path, "no ground-truth poses")
    norms = np.linalg.norm(rows[:, 4:8], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_NORM_TOL)
    if len(bad):
        raise InputFileError(
            path, f"quaternion norm {norms[bad[0]]:.4f} is not 1 (qx qy qz qw)", numbers[bad[0]]
        )
    return TumTrajectory(rows[:, 0], rows[:, 1:4], rows[:, 4:8])


def write_trajectory(
    handle: TextIO,
    timestamps_s: np.ndarray,
    T_world_from_cam: np.ndarray,
    *,
    comments: Sequence[str] = (),
    position_decimals: int = 9,
    quaternion_decimals: int = 9,
) -> None:
    """``# comment`` lines, then ``t tx ty tz qx qy qz qw`` per (4, 4) pose (qw >= 0)."""
    if len(timestamps_s) != len(T_world_from_cam):
        raise InvalidInputError("timestamps and poses differ in length")
    for comment in comments:
        handle.write(f"# {comment}\n")
    for t, T in zip(timestamps_s, T_world_from_cam, strict=True):
        q = quaternion_xyzw_from_R(T[:3, :3])
        position = " ".join(f"{v:.{position_decimals}f}" for v in T[:3, 3])
        rotation = " ".join(f"{v:.{quaternion_decimals}f}" for v in q)
        handle.write(f"{stamp_text(t)} {position} {rotation}\n")


def read_file_list(source: Source, root: Path | None = None) -> tuple[np.ndarray, list[str]]:
    """rgb.txt / depth.txt -> (timestamps_s (N,), filenames as listed); at least one.
    With ``root``, every listed file must exist under it (the error names the line)."""
    path, lines = read_lines(source, "file list")
    stamps, names = [], []
    for number, fields in data_lines(lines):
        if len(fields) != 2:
            raise InputFileError(
                path, f"expected 'timestamp filename', got {len(fields)} fields", number
            )
        stamps.extend(finite_numbers(path, number, fields[:1], "timestamp"))
        if root is not None and not (Path(root) / fields[1]).is_file():
            raise InputFileError(path, f"lists {fields[1]}, which does not exist", number)
        names.append(fields[1])
    if not names:
        raise InputFileError(path, "lists no files")
    return np.asarray(stamps, dtype=np.float64), names


def write_file_list(
    handle: TextIO, timestamps_s: np.ndarray, names: Sequence[str], *, comments: Sequence[str] = ()
) -> None:
    """``# comment`` lines, then ``timestamp filename`` per file."""
    if len(timestamps_s) != len(names):
        raise InvalidInputError("timestamps and filenames differ in length")
    for comment in comments:
        handle.write(f"# {comment}\n")
    for t, name in zip(timestamps_s, names, strict=True):
        handle.write(f"{stamp_text(t)} {name}\n")
