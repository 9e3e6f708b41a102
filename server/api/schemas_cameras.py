"""Request and response bodies of the camera registry (``/v1/cameras``), each with an
OpenAPI example; the conventions of server/api/schemas.py."""

from __future__ import annotations

from datetime import datetime
from typing import Self

from pydantic import BaseModel, ConfigDict, Field

from monoloc.core.camera import CameraIntrinsics, LensDistortion
from monoloc.server.api.openapi_rules import lens_model_pattern, lens_rules
from monoloc.server.api.schemas import TIME_EXAMPLE, JsonInt
from monoloc.server.storage.cameras import CameraRecord

_LENS = dict(
    fx=640.0,
    fy=640.0,
    cx=511.5,
    cy=287.5,
    width_px=1024,
    height_px=576,
    distortion_model="plumb_bob",
    distortion=[-0.28, 0.09, 0.0006, -0.0004],
)


class CameraCreate(BaseModel):
    """A vehicle's camera: pinhole intrinsics (px) for its images' size, and its lens."""

    model_config = ConfigDict(
        strict=True,
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={
            "examples": [dict(name="fleet-front", **_LENS)],
            **lens_rules("distortion_model", "distortion"),
        },
    )
    name: str = Field(
        min_length=1,
        max_length=128,
        pattern=r"\S",
        description="1-128 characters, not only spaces (e.g. the car and the camera).",
    )
    fx: float = Field(gt=0, description="Focal length x (px).")
    fy: float = Field(gt=0, description="Focal length y (px).")
    cx: float = Field(description="Principal point x (px; (0, 0): the top-left pixel's centre).")
    cy: float = Field(description="Principal point y (px).")
    width_px: JsonInt = Field(gt=0, le=100_000, description="Width of the camera's images.")
    height_px: JsonInt = Field(gt=0, le=100_000, description="Height of the camera's images.")
    distortion_model: str | None = Field(
        default=None,
        max_length=32,
        description="plumb_bob (k1 k2 p1 p2 [k3]), rational_polynomial (k1 k2 p1 p2 k3 k4 "
        "k5 k6) or equidistant (fisheye: k1 k2 k3 k4), as ROS CameraInfo names them; "
        "left out, none or pinhole: no distortion. Another model is refused by name.",
        json_schema_extra={"pattern": lens_model_pattern()},
    )
    distortion: list[float] | None = Field(
        default=None, max_length=16, description="The model's coefficients (CameraInfo's D)."
    )

    def intrinsics(self) -> CameraIntrinsics:
        """The camera (InvalidInputError, a 422, for an unknown model or a wrong D)."""
        lens = LensDistortion.parse(self.distortion_model, self.distortion)
        return CameraIntrinsics(
            self.fx, self.fy, self.cx, self.cy, self.width_px, self.height_px, lens
        )


_PUBLIC = dict(id=3, name="fleet-front", **_LENS, key_id=2, created_at=TIME_EXAMPLE)


class CameraPublic(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [_PUBLIC]})
    id: int
    name: str
    fx: float
    fy: float
    cx: float
    cy: float
    width_px: int
    height_px: int
    distortion_model: str | None = Field(description="null: a pinhole camera.")
    distortion: list[float] | None
    key_id: int | None = Field(description="The API key that registered it (null: gone).")
    created_at: datetime

    @classmethod
    def of(cls, record: CameraRecord) -> Self:
        cam = record.intrinsics
        lens = cam.distortion
        return cls(
            id=record.id,
            name=record.name,
            fx=cam.fx,
            fy=cam.fy,
            cx=cam.cx,
            cy=cam.cy,
            width_px=cam.width_px,
            height_px=cam.height_px,
            distortion_model=None if lens is None else lens.model,
            distortion=None if lens is None else list(lens.coefficients),
            key_id=record.key_id,
            created_at=record.created_at,
        )


class CameraList(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"items": [_PUBLIC]}]})
    items: list[CameraPublic]
