"""The options of one query (form fields, query parameters or a stream frame's header)
and the bodies of the localization answers (HTTP and WebSocket stream), with examples."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Self

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, model_validator

from monoloc.core.camera import LensDistortion
from monoloc.core.errors import InvalidInputError
from monoloc.core.prior import RetrievalPrior
from monoloc.server.api.errors import describe_validation
from monoloc.server.api.openapi_rules import LOCALIZE_RULES, rules_extra
from monoloc.server.api.schemas import ErrorDetail, PlanarPose

MAX_K = 100
_FOCAL = ("fx", "fy", "cx", "cy")
_PRIOR = ("prior_x_m", "prior_y_m", "prior_radius_m")
_YAW = ("prior_yaw_rad", "prior_yaw_tolerance_rad")


def _finite(name: str, value: float) -> float:
    if not math.isfinite(value):
        raise InvalidInputError(f"{name} must be finite, got {value!r}")
    return value


class LocalizeOptions(BaseModel):
    """Optional inputs of one query: intrinsics (fx, fy, cx, cy: all or none), a retrieval
    prior (prior_x_m, prior_y_m, prior_radius_m: all or none; prior_yaw_rad with
    prior_yaw_tolerance_rad), k and seed. Out of range or incomplete: 422 invalid_input."""

    # The checks raise InvalidInputError, not ValueError: pydantic lets it through, so a
    # value out of range answers 422 invalid_input with the check's message, like any other
    # bad input. A value of the wrong type stays a pydantic error: a form's 422
    # validation_error, or InvalidInputError from ``parse``.
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                dict(prior_x_m=12.5, prior_y_m=3.2, prior_radius_m=20.0, k=10, seed=2718281828)
            ],
            **rules_extra(*LOCALIZE_RULES),
        }
    )
    fx: float | None = Field(
        default=None,
        description="Focal length x (px); fx, fy, cx, cy all or none (none: the map's camera).",
        examples=[718.856],
        json_schema_extra={"exclusiveMinimum": 0},
    )
    fy: float | None = Field(
        default=None,
        description="Focal length y (px).",
        examples=[718.856],
        json_schema_extra={"exclusiveMinimum": 0},
    )
    cx: float | None = Field(default=None, description="Principal point x (px).", examples=[607.2])
    cy: float | None = Field(default=None, description="Principal point y (px).", examples=[185.2])
    camera_id: int | None = Field(
        default=None,
        description="A camera registered with POST /v1/cameras (its intrinsics and lens), "
        "instead of fx, fy, cx, cy (both: 422; an unknown id: 404). Neither: the map's "
        "camera.",
        json_schema_extra={"minimum": 1, "maximum": 2**63 - 1},
        examples=[3],
    )
    distortion_model: str | None = Field(
        default=None,
        description="The lens's distortion model, with fx, fy, cx, cy: plumb_bob (k1 k2 p1 "
        "p2 [k3]), rational_polynomial (k1 k2 p1 p2 k3 k4 k5 k6) or equidistant (fisheye: "
        "k1 k2 k3 k4), as ROS CameraInfo names them; none or pinhole: no distortion. The "
        "query's keypoints are undistorted, not its image.",
        examples=["plumb_bob"],
    )
    distortion: str | None = Field(
        default=None,
        description="The model's coefficients (ROS CameraInfo's D), comma-separated.",
        examples=["-0.28,0.09,0.0006,-0.0004"],
    )
    prior_x_m: float | None = Field(
        default=None,
        description="Prior position x (m); with prior_y_m and prior_radius_m.",
        examples=[12.5],
    )
    prior_y_m: float | None = Field(
        default=None, description="Prior position y (m).", examples=[3.2]
    )
    prior_radius_m: float | None = Field(
        default=None,
        description="Only entries within this distance (m, > 0) of the prior position compete.",
        examples=[20.0],
        json_schema_extra={"exclusiveMinimum": 0},
    )
    prior_yaw_rad: float | None = Field(
        default=None, description="Prior heading; with prior_yaw_tolerance_rad.", examples=[0.0]
    )
    prior_yaw_tolerance_rad: float | None = Field(
        default=None,
        description="Only entries whose heading is within this (rad, > 0) of prior_yaw_rad "
        "compete.",
        examples=[0.5],
        json_schema_extra={"exclusiveMinimum": 0},
    )
    k: int | None = Field(
        default=None,
        description="Entries to retrieve (default 10).",
        json_schema_extra={"minimum": 1, "maximum": MAX_K},
        examples=[10],
    )
    seed: int | None = Field(
        default=None,
        description="RANSAC seed, below 2^63 (default: server draws one; the answer reports it).",
        json_schema_extra={"minimum": 0, "maximum": 2**63 - 1},
        examples=[2718281828],
    )
    _prior: RetrievalPrior | None = PrivateAttr(default=None)
    _lens: LensDistortion | None = PrivateAttr(default=None)

    @property
    def lens(self) -> LensDistortion | None:
        """The lens distortion sent with the intrinsics, or None (a pinhole)."""
        return self._lens

    @property
    def focal(self) -> tuple[float, float, float, float] | None:
        """(fx, fy, cx, cy) in pixels, or None: the map's camera."""
        if self.fx is None or self.fy is None or self.cx is None or self.cy is None:
            return None  # all or none: see _check_focal
        return (self.fx, self.fy, self.cx, self.cy)

    @property
    def prior(self) -> RetrievalPrior | None:
        """The retrieval prior built from the prior_* fields, or None."""
        return self._prior

    @model_validator(mode="after")
    def _check(self) -> Self:
        self._check_focal()
        self._lens = self._build_lens()
        self._prior = self._build_prior()
        if self.k is not None and not 1 <= self.k <= MAX_K:
            raise InvalidInputError(f"k must be an integer in 1..{MAX_K}, got {self.k!r}")
        if self.seed is not None and not 0 <= self.seed < 2**63:
            raise InvalidInputError(f"seed must be an integer in [0, 2^63), got {self.seed!r}")
        return self

    def _given(self, names: tuple[str, ...]) -> list[str]:
        return [n for n in names if getattr(self, n) is not None]

    def _check_focal(self) -> None:
        given = self._given(_FOCAL)
        if self.camera_id is not None:
            if not 1 <= self.camera_id <= 2**63 - 1:
                raise InvalidInputError(
                    f"camera_id must be a camera's id (1 to 2^63 - 1), got {self.camera_id!r}"
                )
            lens = self._given(("distortion_model", "distortion"))
            if given or lens:
                raise InvalidInputError(
                    f"give camera_id or the camera's intrinsics, not both (got camera_id and "
                    f"{given + lens})"
                )
        if given and len(given) != 4:
            raise InvalidInputError(f"give all of fx, fy, cx, cy or none (got only {given})")
        if given:
            fx, fy, _, _ = (_finite(n, getattr(self, n)) for n in _FOCAL)
            if fx <= 0 or fy <= 0:
                raise InvalidInputError(f"fx and fy must be positive, got {fx}, {fy}")

    def _build_lens(self) -> LensDistortion | None:
        if self.distortion_model is None and self.distortion is None:
            return None
        if self.focal is None:
            raise InvalidInputError("a lens distortion needs the camera's fx, fy, cx, cy")
        try:
            values = [float(v) for v in (self.distortion or "").split(",") if v.strip()]
        except ValueError as exc:
            raise InvalidInputError(
                f"distortion must be comma-separated numbers, got {self.distortion!r}"
            ) from exc
        return LensDistortion.parse(self.distortion_model, values)

    def _build_prior(self) -> RetrievalPrior | None:
        got_pos, got_yaw = self._given(_PRIOR), self._given(_YAW)
        if not got_pos and not got_yaw:
            return None
        if len(got_pos) != 3:
            raise InvalidInputError(
                f"a prior needs prior_x_m, prior_y_m and prior_radius_m (got {got_pos + got_yaw})"
            )
        if len(got_yaw) == 1:
            raise InvalidInputError("give prior_yaw_rad and prior_yaw_tolerance_rad together")
        x, y, r = (_finite(n, getattr(self, n)) for n in _PRIOR)
        if r <= 0:
            raise InvalidInputError(f"prior_radius_m must be positive, got {r}")
        if not got_yaw:
            return RetrievalPrior(x, y, r)
        yaw, tol = (_finite(n, getattr(self, n)) for n in _YAW)
        if tol <= 0:
            raise InvalidInputError(f"prior_yaw_tolerance_rad must be positive, got {tol}")
        return RetrievalPrior(x, y, r, yaw, tol)

    @classmethod
    def parse(cls, values: Mapping[str, Any]) -> LocalizeOptions:
        """Options from flat values (query parameters, a stream header's fields); None and
        "" count as absent, extra names are ignored. Every error is InvalidInputError."""
        present = {n: v for n, v in values.items() if v is not None and v != ""}
        try:
            return cls.model_validate(present)
        except ValidationError as exc:
            raise InvalidInputError(describe_validation(exc.errors())) from exc

    def over(self, fallback: Mapping[str, Any]) -> LocalizeOptions:
        """These options, each one not given taken from ``fallback`` (query parameters)."""
        values = {n: fallback.get(n) for n in type(self).model_fields}
        return self.parse(values | self.model_dump(exclude_none=True))


_HYPOTHESIS = dict(
    entry_id=42,
    pose={"x_m": 12.61, "y_m": 3.18, "yaw_rad": 0.012},
    entry_pose={"x_m": 12.5, "y_m": 3.2, "yaw_rad": 0.0},
    T_world_from_cam=[
        0.0,
        0.0,
        1.0,
        12.61,
        -1.0,
        0.0,
        0.0,
        3.18,
        0.0,
        -1.0,
        0.0,
        1.65,
        0.0,
        0.0,
        0.0,
        1.0,
    ],
    e_vlad=0.71,
    n_inliers=212,
    n_matches=388,
    reprojection_error_px=0.84,
)
_TIMINGS = {
    "decode": 1.9,
    "features": 6.1,
    "vlad": 0.4,
    "retrieval": 0.3,
    "lookup": 0.2,
    "matching": 3.8,
    "pnp": 2.6,
    "total": 13.4,
}


class GeoPosition(BaseModel):
    lat: float = Field(description="WGS84 latitude (degrees).")
    lon: float = Field(description="WGS84 longitude (degrees).")
    h: float = Field(description="Height above the WGS84 ellipsoid (m).")


class GeoQuaternion(BaseModel):
    x: float
    y: float
    z: float
    w: float


class GeoPosePublic(BaseModel):
    """OGC GeoPose 1.0 Basic-Quaternion of the query camera: its centre's WGS84 position,
    and the unit quaternion (Hamilton) rotating the camera frame (OpenCV: x right, y down,
    z forward) into the local East-North-Up frame at that position (``R_enu_from_cam``)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "position": {"lat": 48.858482, "lon": 2.294651, "h": 36.65},
                    "quaternion": {"x": -0.7071068, "y": 0.0, "z": 0.0, "w": 0.7071068},
                }
            ]
        }
    )
    position: GeoPosition
    quaternion: GeoQuaternion


class HypothesisPublic(BaseModel):
    """One accepted PnP solution against one retrieved entry (docs/method.md s. 6 step 5)."""

    model_config = ConfigDict(json_schema_extra={"examples": [_HYPOTHESIS]})
    entry_id: int
    pose: PlanarPose = Field(description="Planar pose of T_world_from_cam (the query).")
    entry_pose: PlanarPose = Field(description="Planar pose of the retrieved entry.")
    T_world_from_cam: list[float] = Field(
        min_length=16, max_length=16, description="Query camera pose, 4x4 row-major."
    )
    e_vlad: float = Field(description="L2 distance between the query's and entry's VLADs.")
    n_inliers: int
    n_matches: int
    reprojection_error_px: float
    joint: bool = Field(
        default=False,
        description="True: the joint pose of several entries (the union of their inliers in "
        "the world frame), not one entry's; entry_id, entry_pose and e_vlad are its anchor's, "
        "n_matches / n_inliers count the union. Clients that ignore this field should skip "
        "joint hypotheses for the paper's measurement model.",
    )
    entry_ids: list[int] = Field(
        default_factory=list, description="Joint pose: the entries whose inliers it used."
    )
    geopose: GeoPosePublic | None = Field(
        default=None,
        description="The pose as an OGC GeoPose (Basic-Quaternion) when the map has a "
        "geographic reference; null otherwise.",
    )
    method: str = Field(
        default="ransac",
        description="How the pose was found: ransac (the entry's own RANSAC), guided (a pose "
        "found for another entry, re-scored and refined on this entry's own correspondences), "
        "joint, pooled (one RANSAC on the matches of several entries, for a frame none of "
        "whose entries gave a pose of its own; entry_ids lists them), or alternative (the same "
        "on the matches the frame's most-inlier pose leaves unexplained, for a frame whose "
        "poses are poorly pinned down).",
    )
    pose_covariance: list[float] | None = Field(
        default=None,
        min_length=9,
        max_length=9,
        description="Covariance (3x3 row-major) of the planar pose (x_m, y_m, yaw_rad) from "
        "the hypothesis's own inliers at 1 px of pixel noise (times the pyramid scale of the "
        "ORB level each query keypoint was found on): how well its geometry pins the pose "
        "down (where the inliers lie, how many, how deep, how coarse). Multiply by the squared "
        "pixel noise of the map's calibration (its pnp model). A joint or pooled pose's "
        "comes from the inliers of all its entries. Null when the inliers do not determine "
        "the pose.",
    )
    entry_tags: list[str] = Field(
        default_factory=list,
        description="The tags of the entry the hypothesis names (e.g. night): a map calibrated "
        "for that condition (the calibration's conditions) weighs the hypothesis by that "
        "condition's model.",
    )


class RetrievedPublic(BaseModel):
    entry_id: int
    distance: float = Field(description="VLAD L2 distance (e_vlad).")


class RejectedPublic(BaseModel):
    entry_id: int
    reason: str


_LOCALIZE = dict(
    map_id=1,
    map_version=4012,
    hypotheses=[_HYPOTHESIS],
    retrieved=[{"entry_id": 42, "distance": 0.71}, {"entry_id": 43, "distance": 0.93}],
    rejected=1,
    rejected_entries=[{"entry_id": 43, "reason": "too few inliers"}],
    n_features=1000,
    timings_ms=_TIMINGS,
    seed=2718281828,
)


class LocalizeResponse(BaseModel):
    """Hypotheses of one frame, with the retrieval, timings (ms) and the map version."""

    model_config = ConfigDict(json_schema_extra={"examples": [_LOCALIZE]})
    map_id: int
    map_version: int
    hypotheses: list[HypothesisPublic] = Field(description="Best (most inliers) first.")
    retrieved: list[RetrievedPublic] = Field(description="Top-k retrieval, best first.")
    rejected: int = Field(description="Retrieved entries whose PnP was rejected.")
    rejected_entries: list[RejectedPublic]
    n_features: int
    timings_ms: dict[str, float] = Field(description="Per stage, plus decode and total.")
    seed: int = Field(description="Seed of this request's RANSAC RNG (pass it to repeat).")


class StreamAnswer(LocalizeResponse):
    """A stream answer: the localize answer plus the frame's seq and timestamp."""

    model_config = ConfigDict(json_schema_extra={"examples": [dict(_LOCALIZE, seq=17, t=1.7)]})
    seq: int
    t: float | None = None


class StreamDropped(BaseModel):
    """A frame dropped unprocessed: newer frames arrived while it waited (``stale``), the
    server's localize lane was full (``overloaded``) or its deadline passed first
    (``deadline``)."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"seq": 18, "t": 1.8, "dropped": True, "reason": "stale"}]}
    )
    seq: int
    t: float | None = None
    dropped: bool = True
    reason: str = "stale"


class StreamError(BaseModel):
    """A frame that could not be processed. ``t`` is left out (unset) when the frame's
    header was rejected: ``seq`` is then null if it could not be read."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "seq": 19,
                    "t": 1.9,
                    "error": {
                        "code": "unsupported_media_type",
                        "message": "image is not a PNG or JPEG image",
                    },
                }
            ]
        }
    )
    seq: int | None
    t: float | None = None
    error: ErrorDetail
