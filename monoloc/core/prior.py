"""The retrieval prior: where on the map a query frame may be. The vehicle builds it
from its filter, sends it with a frame, and the server's index restricts retrieval to
the entries inside it; one type for both sides."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import wrap_angle


@dataclass(frozen=True)
class RetrievalPrior:
    """Only entries within ``radius_m`` of (x_m, y_m) in the world frame, and within
    ``yaw_tolerance_rad`` of ``yaw_rad`` when both are given, compete."""

    x_m: float
    y_m: float
    radius_m: float
    yaw_rad: float | None = None
    yaw_tolerance_rad: float | None = None

    def __post_init__(self) -> None:
        values = [self.x_m, self.y_m, self.radius_m]
        if self.yaw_rad is not None:
            values.append(self.yaw_rad)
        if self.yaw_tolerance_rad is not None:
            values.append(self.yaw_tolerance_rad)
        if not all(math.isfinite(v) for v in values) or self.radius_m <= 0:
            raise InvalidInputError(f"invalid retrieval prior {self}")

    def mask(self, poses_world: np.ndarray) -> np.ndarray:
        """Boolean (N,) of entries (planar poses (N, 3)) inside the prior."""
        d2 = (poses_world[:, 0] - self.x_m) ** 2 + (poses_world[:, 1] - self.y_m) ** 2
        inside = d2 <= self.radius_m**2
        if self.yaw_rad is not None and self.yaw_tolerance_rad is not None:
            inside &= np.abs(wrap_angle(poses_world[:, 2] - self.yaw_rad)) <= self.yaw_tolerance_rad
        return inside

    def to_fields(self) -> dict[str, float]:
        """The form fields of ``POST /v1/maps/{id}/localize`` (``prior_x_m``, ...)."""
        fields = {"prior_x_m": self.x_m, "prior_y_m": self.y_m, "prior_radius_m": self.radius_m}
        if self.yaw_rad is not None and self.yaw_tolerance_rad is not None:
            fields["prior_yaw_rad"] = self.yaw_rad
            fields["prior_yaw_tolerance_rad"] = self.yaw_tolerance_rad
        return fields

    def to_json(self) -> dict[str, float]:
        """The ``prior`` object of a stream frame header (``x_m``, ``y_m``, ...)."""
        return {key.removeprefix("prior_"): value for key, value in self.to_fields().items()}
