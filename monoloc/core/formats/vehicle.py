"""``vehicle.txt``: the vehicle's measured speed and yaw rate, one line per camera frame
(monoloc's own file, next to KITTI sequences and TUM runs alike)::

    timestamp_s speed_mps yaw_rate_radps

Blank lines and '#' comments are skipped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TextIO

import numpy as np

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats._text import Source, number_rows


@dataclass(frozen=True)
class VehicleSignals:
    """timestamps_s, speed_mps and yaw_rate_radps, each (N,) float64."""

    timestamps_s: np.ndarray
    speed_mps: np.ndarray
    yaw_rate_radps: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps_s)


def read_vehicle(source: Source) -> VehicleSignals:
    """vehicle.txt -> VehicleSignals; three finite numbers per line, at least one line."""
    path, rows, _ = number_rows(source, 3, "vehicle signal")
    if len(rows) == 0:
        raise InputFileError(path, "no vehicle signals")
    return VehicleSignals(rows[:, 0], rows[:, 1], rows[:, 2])


def write_vehicle(
    handle: TextIO, timestamps_s: np.ndarray, speed_mps: np.ndarray, yaw_rate_radps: np.ndarray
) -> None:
    """One ``t speed yaw_rate`` line per frame (6, 6 and 7 decimals)."""
    columns = [
        np.asarray(c, dtype=np.float64).reshape(-1)
        for c in (timestamps_s, speed_mps, yaw_rate_radps)
    ]
    if len({len(c) for c in columns}) != 1:
        raise InvalidInputError("timestamps, speeds and yaw rates differ in length")
    for t, v, w in zip(*columns, strict=True):
        handle.write(f"{t:.6f} {v:.6f} {w:.7f}\n")
