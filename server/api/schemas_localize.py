"""Bodies of the localization answers (HTTP and WebSocket stream), with examples."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from monoloc.server.api.schemas import PlanarPose

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


class HypothesisPublic(BaseModel):
    """One accepted PnP solution against one retrieved entry (METHOD.md s. 6 step 5)."""

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
    model_config = ConfigDict(
        json_schema_extra={"examples": [{"seq": 18, "t": 1.8, "dropped": True, "reason": "stale"}]}
    )
    seq: int
    t: float | None = None
    dropped: bool = True
    reason: str = "stale"
