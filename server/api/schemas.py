"""Request and response bodies of the API (pydantic v2), each with an OpenAPI example.

Naming follows the FastAPI template: ``XCreate`` / ``XUpdate`` in, ``XPublic`` out.
Poses are in the z-up world (docs/method.md section 9): metres and radians; a 4x4
``T_world_from_cam`` travels as 16 numbers, row-major. API keys and health: see
server/api/schemas_admin.py; localization: server/api/schemas_localize.py.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import (
    AliasChoices,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)

from monoloc.core.measurement import (
    DEFAULT_COVARIANCE,
    DEFAULT_RELATIVE_VLAD,
    DEFAULT_RETRIEVAL_FRAME,
    DEFAULT_VLAD_EVIDENCE,
)
from monoloc.server.api.errors import PATTERN_RULES
from monoloc.server.api.openapi_rules import (
    GEO_REFERENCE_ONE_OF,
    PNP_COVARIANCE_NEEDS_PNP,
    rules_extra,
)

# The server's own rules, as patterns in the OpenAPI description (storage checks them too):
# map names (storage/maps.py MAP_NAME_RE), tags (storage/entry_checks.py TAG_RE; the API
# lower-cases them first), vocabulary hashes (vision/vocabulary.py: 16 hex digits).
MAP_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
TAG_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.:-]{0,63}$"
VOCABULARY_REF_PATTERN = r"^(default|[0-9a-f]{16})$"
_TAG_RULE = "1-64 of a-z, 0-9, '_', '.', ':', '-', starting with a letter or digit"
PATTERN_RULES.update(
    {
        MAP_NAME_PATTERN: "invalid map name: 1-64 letters, digits, '.', '_' or '-', starting "
        "with a letter or digit",
        TAG_PATTERN: f"invalid tag: {_TAG_RULE}",
        VOCABULARY_REF_PATTERN: "a vocabulary is 'default' or a stored hash (16 hex digits)",
    }
)
Tag = Annotated[str, Field(pattern=TAG_PATTERN, examples=["night"])]
# A form's comma-separated tags: empty items and spaces around items are ignored.
_TAG = r"[A-Za-z0-9][A-Za-z0-9_.:-]{0,63}"
TAG_LIST_PATTERN = rf"^[\s,]*(?:{_TAG}(?:\s*,[\s,]*{_TAG})*)?[\s,]*$"
RUN_KIND_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,31}$"  # storage/runs.py KIND_RE
# ingest/common.py parse_frame_range: A:B, A:, :B, A:B:S (S not 0), or empty.
PATTERN_RULES.update(
    {
        TAG_LIST_PATTERN: f"invalid tag in a comma-separated list: each tag {_TAG_RULE}",
        RUN_KIND_PATTERN: "invalid run kind: 1-32 of a-z, 0-9, '_', '-'",
    }
)
FRAME_RANGE_PATTERN = r"^\s*(?:-?\d*\s*:\s*-?\d*\s*(?::\s*(?:-?0*[1-9]\d*)?\s*)?)?$"


def _integral(value: Any) -> Any:
    """173.0 is the integer 173, as JSON Schema reads it (the OpenAPI's "integer"); a
    strict model's int field takes it, and still refuses 173.5, true and "173"."""
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


# An integer field of a strict request body: a JSON number with no fraction.
JsonInt = Annotated[int, BeforeValidator(_integral)]


def _row(n: int) -> Any:
    return Annotated[list[float], Field(min_length=n, max_length=n)]


_T_EXAMPLE = [0.0, 0.0, 1.0, 12.5, -1.0, 0.0, 0.0, 3.2, 0.0, -1.0, 0.0, 1.65, 0.0, 0.0, 0.0, 1.0]
TIME_EXAMPLE = "2024-05-01T12:00:00Z"


def example(**values: Any) -> ConfigDict:
    return ConfigDict(json_schema_extra={"examples": [values]})


def strict_example(rules: dict[str, Any] | None = None, **values: Any) -> ConfigDict:
    """``example`` of a request body, validated strictly: ``false`` is not 0.0, ``"1"`` is
    not 1, an unknown field is refused (so the body fits its JSON schema exactly when the
    server accepts it). ``rules``: the body's cross-field rules as JSON Schema
    (``openapi_rules.rules_extra``)."""
    extra = {"examples": [values], **(rules or {})}
    return ConfigDict(strict=True, extra="forbid", json_schema_extra=extra)


def record_example(**values: Any) -> ConfigDict:
    """``example`` of a response built from a storage record: ``X.model_validate(record)``."""
    return ConfigDict(from_attributes=True, json_schema_extra={"examples": [values]})


class ErrorDetail(BaseModel):
    code: str
    message: str


class ErrorResponse(BaseModel):
    model_config = example(error={"code": "not_found", "message": "map 7 does not exist"})
    error: ErrorDetail


class Camera(BaseModel):
    """Pinhole intrinsics in pixels of the map's camera."""

    model_config = ConfigDict(
        from_attributes=True,
        strict=True,
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={
            "examples": [
                dict(fx=718.856, fy=718.856, cx=607.1928, cy=185.2157, width_px=1241, height_px=376)
            ]
        },
    )
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width_px: JsonInt = Field(gt=0, le=100_000)
    height_px: JsonInt = Field(gt=0, le=100_000)


class MapCreate(BaseModel):
    model_config = strict_example(
        name="kitti-00",
        camera=Camera.model_config["json_schema_extra"]["examples"][0],
        vocabulary="default",
    )
    name: str = Field(
        pattern=MAP_NAME_PATTERN,
        description="1-64 letters, digits, '.', '_' or '-', starting with a letter or digit.",
    )
    camera: Camera
    geo_reference: GeoReferenceUpdate | None = Field(
        default=None,
        description="Optional: places the map on the WGS84 ellipsoid, so that answers carry "
        "OGC GeoPoses (also settable later: PUT /v1/maps/{map_id}/geo-reference).",
    )
    vocabulary: str = Field(
        default="default",
        pattern=VOCABULARY_REF_PATTERN,
        description="'default' (the shipped 64-word vocabulary) or the hash of a vocabulary "
        "already stored (e.g. trained for another map). For a vocabulary trained on this "
        "map's own data, upload its first run with train_vocabulary=true.",
    )


_GEO_ORIGIN_EXAMPLE = dict(lat_deg=48.858370, lon_deg=2.294481, h_m=35.0, x_axis_heading_deg=90.0)


class GeoOriginSpec(BaseModel):
    """WGS84 position of the map world's origin and the compass heading of its +X axis."""

    model_config = ConfigDict(
        strict=True,
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={"examples": [_GEO_ORIGIN_EXAMPLE]},
    )
    lat_deg: float = Field(ge=-90.0, le=90.0, description="WGS84 latitude (degrees).")
    lon_deg: float = Field(ge=-180.0, le=180.0, description="WGS84 longitude (degrees).")
    h_m: float = Field(
        default=0.0,
        ge=-12_000.0,
        le=100_000.0,
        description="Height above the WGS84 ellipsoid (m) of the world's origin (z = 0).",
    )
    x_axis_heading_deg: float = Field(
        ge=0.0,
        lt=360.0,
        description="Compass heading of the world's +X axis, degrees clockwise from true "
        "north (90: +X points east; the world is then the origin's local ENU frame).",
    )


class GeoReferenceUpdate(BaseModel):
    """A map's geographic reference: exactly one of ``origin`` and ``T_ecef_from_world``
    (422 otherwise, or when the transform is not rigid or not near the Earth's surface)."""

    model_config = strict_example(rules_extra(GEO_REFERENCE_ONE_OF), origin=_GEO_ORIGIN_EXAMPLE)
    origin: GeoOriginSpec | None = None
    T_ecef_from_world: list[Annotated[float, Field(allow_inf_nan=False)]] | None = Field(
        default=None,
        min_length=16,
        max_length=16,
        description="Rigid transform from the map's world to WGS84 ECEF (m), 4x4 row-major.",
    )

    def to_reference(self) -> dict[str, Any]:
        """The storage form (``monoloc.core.geo.GeoReference``), checked."""
        from monoloc.core.errors import InvalidInputError
        from monoloc.core.geo import GeoReference

        if (self.origin is None) == (self.T_ecef_from_world is None):
            raise InvalidInputError("give exactly one of origin and T_ecef_from_world")
        values = {"T_ecef_from_world": self.T_ecef_from_world}
        if self.origin is not None:
            values = {"origin": self.origin.model_dump()}
        return GeoReference.from_dict(values).to_dict()


class GeoReferencePublic(BaseModel):
    """The map's geographic reference: the origin when it was given as one, and always the
    transform from the map's world to WGS84 ECEF."""

    model_config = example(
        origin=_GEO_ORIGIN_EXAMPLE,
        T_ecef_from_world=[
            -0.04004, -0.75248, 0.6574, 4200961.4,
            0.9992, -0.03015, 0.02634, 168322.7,
            0.0, 0.65792, 0.75309, 4780237.2,
            0.0, 0.0, 0.0, 1.0,
        ],
    )  # fmt: skip
    origin: GeoOriginSpec | None
    T_ecef_from_world: list[float] = Field(min_length=16, max_length=16)


class VocabularyPublic(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: int
    # a storage record calls it version_hash
    hash: str = Field(validation_alias=AliasChoices("hash", "version_hash"))
    n_words: int
    description: str


class PlanarPose(BaseModel):
    """(X, Y, psi): position on the ground plane and heading of the optical axis."""

    model_config = example(x_m=12.5, y_m=3.2, yaw_rad=0.0)
    x_m: float
    y_m: float
    yaw_rad: float


_MAP_EXAMPLE = dict(
    id=1,
    name="kitti-00",
    camera=Camera.model_config["json_schema_extra"]["examples"][0],
    vocabulary={"id": 1, "hash": "3f9a0c", "n_words": 64, "description": "default"},
    version=4012,
    n_entries=3860,
    calibrated=False,
    created_at=TIME_EXAMPLE,
    updated_at=TIME_EXAMPLE,
)


class MapPublic(BaseModel):
    model_config = example(**_MAP_EXAMPLE)
    id: int
    name: str
    camera: Camera
    vocabulary: VocabularyPublic
    version: int = Field(description="Bumped by every entry add/remove and vocabulary change.")
    n_entries: int
    calibrated: bool = Field(description="Whether the measurement model was calibrated.")
    calibrated_conditions: list[str] = Field(
        default_factory=list,
        description="The conditions (entry tags, e.g. night) with a model of their own in the "
        "calibration.",
    )
    geo_reference: GeoReferencePublic | None = Field(
        default=None, description="The map's geographic reference; null: not geo-referenced."
    )
    features: dict[str, Any] | None = Field(
        default=None,
        description='How the map\'s entries picked their ORB corners: {"rule": "grid", '
        '"grid_cells": [8, 5], "candidates_factor": 2.0, "fast_thresholds": [20, 12]} (a '
        "grid map built before the second FAST threshold has none: one pass at 20) or "
        '{"rule": "strongest"} (ORB\'s own, every map built before the grid).',
    )
    features_current: bool = Field(
        default=True,
        description="Whether the map's entries picked their corners by this server's default "
        "rule. False: the map is served by its own rule (its new entries and its queries "
        "are described as its first entries were), without the default's gain; upload its "
        "runs again into a new map to rebuild it with the default.",
    )
    created_at: datetime
    updated_at: datetime


class MapDetail(MapPublic):
    model_config = example(
        **_MAP_EXAMPLE, n_runs=2, tag_counts={"night": 120}, index_loaded=True, indexed_entries=3860
    )
    n_runs: int
    tag_counts: dict[str, int]
    index_loaded: bool
    indexed_entries: int | None


class MapList(BaseModel):
    model_config = example(items=[_MAP_EXAMPLE])
    items: list[MapPublic]


_ENTRY_EXAMPLE = dict(
    id=42,
    map_id=1,
    run_id=1,
    pose={"x_m": 12.5, "y_m": 3.2, "yaw_rad": 0.0},
    tags=["night"],
    n_points=612,
    image_width_px=1241,
    image_height_px=376,
    timestamp_s=4.2,
    source_image_hash="9b1c...",
    vocabulary_id=1,
    created_at=TIME_EXAMPLE,
)


class EntryPublic(BaseModel):
    model_config = example(**_ENTRY_EXAMPLE)
    id: int
    map_id: int
    run_id: int | None
    pose: PlanarPose
    tags: list[str]
    n_points: int = Field(description="Keypoints with a 3D point.")
    image_width_px: int
    image_height_px: int
    timestamp_s: float | None
    source_image_hash: str
    vocabulary_id: int
    created_at: datetime


class EntryDetail(EntryPublic):
    model_config = example(**_ENTRY_EXAMPLE, T_world_from_cam=_T_EXAMPLE)
    T_world_from_cam: list[float] = Field(
        min_length=16, max_length=16, description="4x4 row-major."
    )


class EntryCreated(BaseModel):
    model_config = example(
        entry=_ENTRY_EXAMPLE | {"T_world_from_cam": _T_EXAMPLE}, created=True, map_version=4013
    )
    entry: EntryDetail
    created: bool = Field(description="False if the same image was already in the map.")
    map_version: int


class EntryList(BaseModel):
    model_config = example(items=[_ENTRY_EXAMPLE], total=1, limit=100, offset=0)
    items: list[EntryPublic]
    total: int
    limit: int
    offset: int


class TagsUpdate(BaseModel):
    model_config = strict_example(tags=["night", "off-center"])
    tags: list[Tag] = Field(
        max_length=64,
        description="1-64 of letters, digits, '_', '.', ':', '-', starting with a letter or "
        "digit; stored lower-case, duplicates dropped.",
    )


_RUN_EXAMPLE = dict(
    id=1,
    map_id=1,
    kind="map",
    source_format="kitti",
    source_name="00.tar",
    status="running",
    frames_total=3861,
    frames_done=1200,
    entries_added=1190,
    frames_skipped=10,
    skip_reasons={"too_few_points": 10},
    error=None,
    created_at=TIME_EXAMPLE,
    updated_at=TIME_EXAMPLE,
)


class RunPublic(BaseModel):
    model_config = record_example(**_RUN_EXAMPLE)
    id: int
    map_id: int
    kind: str
    source_format: str
    source_name: str
    status: str
    frames_total: int
    frames_done: int
    entries_added: int
    frames_skipped: int
    skip_reasons: dict[str, int]
    error: str | None
    created_at: datetime
    updated_at: datetime
    registration: dict[str, Any] | None = Field(
        None,
        description="How the run was registered to the map before its entries were built "
        "(uploaded with register_to_map=true): frames measured and used, the mean and "
        "largest shift (m, world x / y), the noise of one measured offset; null if not.",
    )


_JOB_EXAMPLE = dict(
    id=3,
    kind="ingest",
    map_id=1,
    run_id=1,
    state="running",
    progress=0.31,
    message="frame 1200 of 3861",
    error=None,
    params={"format": "kitti", "sequence": "00"},
    result=None,
    created_at=TIME_EXAMPLE,
    updated_at=TIME_EXAMPLE,
    finished_at=None,
)


# Job parameters of the server's own bookkeeping (where its upload lives), not shown.
_PRIVATE_JOB_PARAMS = ("upload",)


class JobPublic(BaseModel):
    model_config = record_example(**_JOB_EXAMPLE)
    id: int
    kind: str
    map_id: int | None
    run_id: int | None
    state: Literal["queued", "running", "done", "failed", "interrupted"]
    progress: float = Field(ge=0, le=1)
    message: str
    error: str | None
    params: dict[str, Any]
    result: dict[str, Any] | None
    created_at: datetime
    updated_at: datetime
    finished_at: datetime | None

    @field_validator("params")
    @classmethod
    def _public_params(cls, params: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in params.items() if k not in _PRIVATE_JOB_PARAMS}


class JobList(BaseModel):
    model_config = example(items=[_JOB_EXAMPLE])
    items: list[JobPublic]


class UploadAccepted(BaseModel):
    model_config = example(
        job=_JOB_EXAMPLE | {"state": "queued", "progress": 0.0},
        run=_RUN_EXAMPLE | {"status": "pending"},
        n_files=7724,
        total_bytes=1_950_000_000,
    )
    job: JobPublic
    run: RunPublic
    n_files: int
    total_bytes: int


class VocabularyJobCreate(BaseModel):
    model_config = strict_example(vocabulary="default")
    vocabulary: str = Field(
        pattern=VOCABULARY_REF_PATTERN,
        description="'default' or the hash of a stored vocabulary. To train a map's own "
        "vocabulary, upload a run with train_vocabulary=true.",
    )


_CALIBRATION_EXAMPLE = dict(
    mu1=[0.02, -0.01, 0.001],
    Sigma1=[[0.04, 0, 0], [0, 0.04, 0], [0, 0, 0.0007]],
    mu2=[0.9, 0.0, 0.0, 0.0],
    Sigma2=[[0.06, 0, 0, 0], [0, 64, 0, 0], [0, 0, 64, 0], [0, 0, 0, 0.27]],
    outlier_log_density=-16.0,
    provenance={"training_run": "kitti-05", "method": "ML, unbiased covariance"},
)


class _MeasurementModelFields(BaseModel):
    """The measurement model's parameters (docs/method.md section 7) and provenance, as a
    calibration is set and as it is served."""

    mu1: list[float] = Field(min_length=3, max_length=3, description="Bias of (X, Y, psi).")
    Sigma1: list[_row(3)] = Field(
        min_length=3, max_length=3, description="3x3, symmetric positive definite."
    )
    mu2: list[float] = Field(min_length=4, max_length=4, description="Mean of e_i.")
    Sigma2: list[_row(4)] = Field(
        min_length=4, max_length=4, description="4x4, symmetric positive definite."
    )
    outlier_log_density: float | None = -16.0
    quality: dict[str, Any] | None = Field(
        default=None,
        description="Quality-aware pose-error model (mu1, Sigma1, beta, n_ref, error_ref_px, "
        "log_scale_bounds, tail_weight, tail_scale; monoloc.core.measurement.QualityModel), "
        "fitted and stored by a calibration job beside the others; null: none.",
    )
    pnp: dict[str, Any] | None = Field(
        default=None,
        description="PnP-covariance pose-error model (mu1, pixel_std_px, floor 3x3, "
        "outlier_weight w: each hypothesis's error ~ (1 - w) N(mu1, pixel_std_px^2 C + floor) "
        "+ w times the paper covariance's density, C its pose_covariance from the localize "
        "answer; monoloc.core.measurement.PnpCovarianceModel); null: none.",
    )
    relative_vlad: list[float] = Field(
        default_factory=lambda: list(DEFAULT_RELATIVE_VLAD),
        min_length=2,
        max_length=2,
        description="(mean, std > 0) of a hypothesis's VLAD distance minus its frame's "
        "smallest, fitted by a calibration job: the retrieval term's VLAD evidence when "
        "vlad_evidence is relative.",
    )
    tail_weight: float = Field(
        default=0.0,
        ge=0.0,
        lt=1.0,
        description="Share eps of the paper covariance's heavy tail: each hypothesis's "
        "error is (1 - eps) N(mu1, Sigma1) + eps N(mu1, tail_scale^2 Sigma1); 0: the paper's "
        "single Gaussian (a calibration job sets 0.3).",
    )
    tail_scale: float = Field(
        default=1.0, ge=1.0, lt=1000.0, description="Spread of that tail over Sigma1's (10)."
    )
    provenance: dict[str, Any] = Field(default_factory=dict)
    conditions: dict[Tag, dict[str, Any]] = Field(
        default_factory=dict,
        description="Models calibrated on a training run of one condition, by the entry tag "
        "that names it (e.g. night: a night run against its own night map): a hypothesis "
        "whose entry carries the tag is weighed by that condition's model (the same fields "
        "as this one, no conditions of their own; with their own provenance and "
        "updated_at) instead of this one. Calibrated by a calibration job with "
        "condition=<tag>; names are lower-cased.",
    )


def _check_choices(values: dict[str, Any], where: str) -> None:
    """ValueError naming a choice the product does not offer (the lab's variants of
    monoloc.core.measurement are served when stored, never taken)."""
    offered = {
        "covariance": (None, "paper", DEFAULT_COVARIANCE),
        "retrieval_frame": (None, DEFAULT_RETRIEVAL_FRAME),
        "vlad_evidence": (None, DEFAULT_VLAD_EVIDENCE),
    }
    for name, allowed in offered.items():
        if values.get(name) not in allowed:
            raise ValueError(
                f"{where}{name} {values[name]!r} is not offered: "
                f"{' or '.join(repr(a) for a in allowed if a is not None)}"
            )


def _offered(value: str) -> dict[str, Any]:
    return {"anyOf": [{"const": value}, {"type": "null"}]}


def _calibration_update_schema(schema: dict[str, Any]) -> None:
    """What the checks of a calibration PUT take, in its JSON schema: the choices the
    product offers (``_check_choices``: null or the product's), and each condition as a
    measurement model of its own (mu1, Sigma1, mu2, Sigma2; no conditions of its own)."""
    properties = schema["properties"]
    choices = "Left out or null: the product's; any other value is refused (422)."
    properties["retrieval_frame"] = {**_offered(DEFAULT_RETRIEVAL_FRAME), "description": choices}
    properties["vlad_evidence"] = {**_offered(DEFAULT_VLAD_EVIDENCE), "description": choices}
    model = {k: properties[k] for k in ("mu1", "Sigma1", "mu2", "Sigma2")}
    condition = {
        "type": "object",
        "required": list(model),
        "properties": {
            **model,
            "covariance": {"anyOf": [{"enum": ["paper", DEFAULT_COVARIANCE]}, {"type": "null"}]},
            "retrieval_frame": properties["retrieval_frame"],
            "vlad_evidence": properties["vlad_evidence"],
            "provenance": {"type": "object"},
            "conditions": {"type": "object", "maxProperties": 0},
        },
        **rules_extra(PNP_COVARIANCE_NEEDS_PNP),
    }
    conditions = properties["conditions"]
    conditions.pop("patternProperties", None)
    conditions["propertyNames"] = {"pattern": TAG_PATTERN}
    conditions["additionalProperties"] = condition
    schema["examples"] = [_CALIBRATION_EXAMPLE]
    schema.update(rules_extra(PNP_COVARIANCE_NEEDS_PNP))


class CalibrationUpdate(_MeasurementModelFields):
    """Measurement-model parameters computed elsewhere, and their provenance. The offsets
    are along and across the vehicle's heading (``retrieval_frame``, stored)."""

    model_config = ConfigDict(
        strict=True, allow_inf_nan=False, json_schema_extra=_calibration_update_schema
    )
    covariance: Literal["paper", "pnp"] | None = Field(
        default=None,
        description="Which pose-error model the vehicle uses: pnp (each hypothesis's own "
        "PnP covariance; needs pnp) or paper (mu1, Sigma1 for every hypothesis); null: pnp "
        "when pnp is given, else paper.",
    )
    retrieval_frame: str | None = Field(
        default=None,
        validate_default=True,
        description="Axes of the offsets: vehicle (mu1, Sigma1 along / across the "
        "hypothesis's heading, mu2[1:3], Sigma2 along / across the vehicle's); null: "
        "vehicle. Parameters in world axes (an older server's) are refused: calibrate again.",
    )

    @field_validator("retrieval_frame", mode="after")
    @classmethod
    def _product_frame(cls, value: str | None) -> str:
        return value or DEFAULT_RETRIEVAL_FRAME

    @model_validator(mode="before")
    @classmethod
    def _offered_choices(cls, values: Any) -> Any:
        if isinstance(values, dict):
            _check_choices(values, "")
            conditions = values.get("conditions")
            for name, condition in (conditions if isinstance(conditions, dict) else {}).items():
                if isinstance(condition, dict):
                    _check_choices(condition, f"conditions.{name}.")
        return values


class CalibrationPublic(_MeasurementModelFields):
    """The map's measurement model as the vehicle downloads it."""

    model_config = ConfigDict(
        allow_inf_nan=False,
        **example(
            **_CALIBRATION_EXAMPLE,
            covariance="paper",
            calibrated=True,
            source="put",
            updated_at=TIME_EXAMPLE,
        ),
    )
    covariance: str = Field(
        description="The pose-error model the vehicle uses: pnp or paper (as stored: a "
        "calibration stored by an older server may name another)."
    )
    retrieval_frame: str = Field(
        default=DEFAULT_RETRIEVAL_FRAME,
        description="Frame of the retrieval vector's offset (mu2[1:3], Sigma2): world, "
        "X_i - X and Y_i - Y (as stored: a calibration stored by an older server may name "
        "another).",
    )
    vlad_evidence: str = Field(
        default=DEFAULT_VLAD_EVIDENCE,
        description="How the retrieval term reads a hypothesis's VLAD distance: absolute "
        "(e_vlad against mu2[0]) or relative (against the frame's smallest, relative_vlad).",
    )
    calibrated: bool = Field(description="False: these are the documented defaults.")
    fit: dict[str, Any] | None = Field(
        default=None,
        description="How the calibration matches this map: the VLAD distances between "
        "entries 2-6 m apart on this map (map: mean, std, n) against those of the "
        "calibration's training run (training), the shift in training spreads, fits "
        "(|shift| <= 1) and a warning when it does not fit; null for the defaults (or a "
        "calibration stored before the check).",
    )
    source: str
    updated_at: datetime | None = None


PATTERN_RULES[FRAME_RANGE_PATTERN] = "invalid frame range: expected A:B, A:, :B or A:B:S (S not 0)"
