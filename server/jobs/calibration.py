"""The ``calibrate`` job kind: fit a map's measurement model on a training run (docs/method.md
section 7) and store it, with its provenance, on the map. At the edges of
``monoloc.server.calibrate``: read the run's frames, fit, store.

The job runner (:func:`run_calibration`, a training run uploaded over HTTP) and
``monoloc map calibrate`` (:func:`run_calibration_job`, recorded as a job row like the
CLI's vocabulary job) both end in :func:`calibrate_map`, with the parameters of
:class:`CalibrationParams`: what an operator tunes (k, the seed, a condition) and the
run. The pose-error model the stored calibration selects is the product's
(``monoloc.core.measurement.DEFAULT_COVARIANCE``). The training run is never
added to the map: its temporary map lives in memory only. Calibrating again replaces
the stored parameters, so an interrupted calibration is resumed by running it again.

With a ``condition`` (an entry tag such as ``night``) the run, recorded in that
condition (a night run against the map's night entries), calibrates that condition's
model instead (``monoloc.server.calibration_conditions``): it needs the map's base
calibration, which it leaves untouched. Calibrating the base again keeps the conditions
calibrated with the same vocabulary.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from typing import Any, Literal, Self

import numpy as np
from pydantic import Field, field_validator, model_validator
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import ConflictError, InvalidInputError
from monoloc.core.measurement import DEFAULT_COVARIANCE, MeasurementModel
from monoloc.server import calibration_conditions as conditions
from monoloc.server.calibrate import (
    CalibrationConfig,
    TrainingFrame,
    calibrate,
    check_run_length,
)
from monoloc.server.ingest.manage import find_map
from monoloc.server.jobs.context import JobContext, JobInterruptedError
from monoloc.server.jobs.lifecycle import run_recorded_job
from monoloc.server.jobs.params import RunParams
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord
from monoloc.server.vision.features import orb_for_rule
from monoloc.server.vision.vocabulary import Vocabulary

JOB_KIND = "calibrate"


class CalibrationParams(RunParams):
    """A calibration: the training run (``RunParams``: uploaded over HTTP, or at ``path``
    for ``monoloc map calibrate``, which also reads ROS bags) and its name, k entries per
    query, the RANSAC seed, and the condition it calibrates (an entry tag; None: the
    base calibration)."""

    format: Literal["kitti", "tum", "rosbag"]
    source_name: str | None = None
    path: str | None = None
    k: int = Field(default=CalibrationConfig.k, ge=1, le=100)
    seed: int = Field(default=0, ge=0)
    condition: str | None = None
    upload: bool = False

    @field_validator("condition")
    @classmethod
    def _condition(cls, condition: str | None) -> str | None:
        try:
            return None if condition is None else conditions.condition_name(condition)
        except InvalidInputError as exc:
            raise ValueError(str(exc)) from None

    @model_validator(mode="after")
    def _named_upload(self) -> Self:
        if self.upload and self.source_name is None:
            raise ValueError("an uploaded run needs its source_name (the upload's name)")
        return self

    @property
    def config(self) -> CalibrationConfig:
        return CalibrationConfig(k=self.k)

    @classmethod
    def stored_shape(cls, job: JobRecord, stored: dict[str, Any]) -> dict[str, Any]:
        """Rows from when the calibration's pose-error model was a choice (``covariance``):
        they run if they chose the product's, and are refused if they chose another."""
        chosen = stored.pop("covariance", None)
        if chosen not in (None, DEFAULT_COVARIANCE):
            raise ConflictError(
                f"job {job.id} asked the calibration to select the {chosen!r} pose-error "
                f"model; this server selects {DEFAULT_COVARIANCE!r}: create a new "
                "calibration job"
            )
        return stored


def training_frames(source) -> Iterator[TrainingFrame]:
    """The frames of a KittiSequence / TumRun as TrainingFrames, read one at a time."""
    for frame in source.frames:
        loaded = source.load(frame)
        yield TrainingFrame(loaded.image_gray, frame.T_world_from_cam, loaded.source)


def _map_vocabulary(
    session_factory: sessionmaker[Session], map_id: int
) -> tuple[Vocabulary, dict[str, Any] | None]:
    """The map's vocabulary and its ORB rule (``maps.features``)."""
    with session_scope(session_factory) as session:
        record = maps_repo.get_map(session, map_id)
        vocab = maps_repo.get_vocabulary(session, record.vocabulary_id)
    vocabulary = Vocabulary.from_centres(np.asarray(vocab.centres), vocab.description)
    return vocabulary, record.features


def calibrate_map(
    session_factory: sessionmaker[Session],
    map_id: int,
    source,
    *,
    config: CalibrationConfig = CalibrationConfig(),
    seed: int = 0,
    job_id: int | None = None,
    source_name: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    condition: str | None = None,
) -> dict[str, Any]:
    """Fit the measurement model on ``source`` (a KittiSequence or TumRun, read with its
    own intrinsics) with the map's vocabulary, store it on map ``map_id`` and return the
    stored calibration (mu1, Sigma1, mu2, Sigma2, outlier floor, source, provenance,
    conditions).

    ``condition`` None: the base calibration, keeping the stored conditions calibrated
    with the same vocabulary (the others are dropped, and named in the provenance's
    ``conditions_dropped``). A condition (an entry tag, e.g. "night"): the fitted model,
    with its provenance and updated_at, becomes ``conditions[condition]`` of the stored
    calibration; ConflictError if the map has no base calibration.

    RANSAC draws from ``np.random.default_rng(seed)``, so a re-run gives the same model.
    ConflictError if the map's vocabulary changed meanwhile (e_vlad statistics depend on
    it); InvalidInputError if the run is too short or matches itself too poorly.
    """
    name = source_name or source.name
    check_run_length(len(source.frames), config, name)
    if condition is not None:
        condition = conditions.condition_name(condition)
        with session_scope(session_factory) as session:
            stored = maps_repo.get_map(session, map_id).calibration
        conditions.require_base(stored, map_id, condition)  # before the long fit
    vocabulary, features = _map_vocabulary(session_factory, map_id)
    # the training run described as the map's entries and its queries are (maps.features)
    build = dataclasses.replace(config.build, orb=orb_for_rule(features, config.build.orb))
    config = dataclasses.replace(config, build=build)
    result = calibrate(
        training_frames(source),
        source.intrinsics,
        vocabulary,
        config,
        np.random.default_rng(seed),
        progress=progress,
        n_frames=len(source.frames),
        source_name=name,
    )
    now = datetime.now(UTC).isoformat()
    provenance = {
        **result.provenance,
        "format": getattr(source, "format", ""),
        "intrinsics": dataclasses.asdict(source.intrinsics),
        "seed": seed,
        "job_id": job_id,
        "created_at": now,
    }
    return _store(session_factory, map_id, vocabulary, result.model, provenance, condition)


def _store(
    session_factory: sessionmaker[Session],
    map_id: int,
    vocabulary: Vocabulary,
    model: MeasurementModel,
    provenance: dict[str, Any],
    condition: str | None,
) -> dict[str, Any]:
    """Store a fitted model as the map's base calibration or as one condition's (see
    :func:`calibrate_map`); returns the stored calibration."""
    now = provenance["created_at"]
    if condition is None:
        fitted = {**model.to_dict(), "provenance": provenance, "updated_at": now}

        def change(stored):
            return conditions.with_new_base(stored, fitted)

    else:
        entry = conditions.condition_entry(model, {**provenance, "condition": condition}, now)

        def change(stored):
            return conditions.with_condition(stored, map_id, condition, entry)

    with session_scope(session_factory) as session:
        # checked under the write lock update_calibration takes; raising rolls it back
        record = maps_repo.update_calibration(session, map_id, change)
        if record.vocabulary_hash != vocabulary.version:
            raise ConflictError(
                f"map {map_id} switched from vocabulary {vocabulary.version} to "
                f"{record.vocabulary_hash} during calibration; calibrate again"
            )
        return record.calibration


def describe_calibration(calibration: dict[str, Any]) -> list[str]:
    """Human-readable lines: biases and standard deviations in cm and deg, provenance."""
    model = MeasurementModel.from_dict(calibration)
    mu1, mu2 = model.mu1, model.mu2
    std1, std2 = np.sqrt(np.diag(model.Sigma1)), np.sqrt(np.diag(model.Sigma2))
    deg = math.degrees
    if model.retrieval_frame == "vehicle":
        head, a, b = "along / across the vehicle's heading", "along", "across"
        pose = " (along / across the hypothesis's heading)"
    else:
        head, a, b = "X_i - X, Y_i - Y", "X", "Y"
        pose = ""
    lines = [
        f"pose error e = truth - hypothesis{pose}:",
        f"  mu1    {a} {100 * mu1[0]:+.1f} cm, {b} {100 * mu1[1]:+.1f} cm, "
        f"psi {deg(mu1[2]):+.2f} deg",
        f"  std1   {a} {100 * std1[0]:.1f} cm, {b} {100 * std1[1]:.1f} cm, "
        f"psi {deg(std1[2]):.2f} deg",
        *_describe_tail(calibration),
        f"retrieval vector [e_vlad, entry offset ({head}), psi_i - psi]:",
        f"  mu2    e_vlad {mu2[0]:.3f}, {a} {mu2[1]:+.2f} m, {b} {mu2[2]:+.2f} m, "
        f"psi {deg(mu2[3]):+.2f} deg",
        f"  std2   e_vlad {std2[0]:.3f}, {a} {std2[1]:.2f} m, {b} {std2[2]:.2f} m, "
        f"psi {deg(std2[3]):.2f} deg",
        f"outlier log density: {calibration.get('outlier_log_density')}",
        *_describe_quality(calibration, model.covariance),
        *_describe_pnp(calibration),
        *_describe_conditions(calibration),
        "provenance:",
    ]
    for key, value in (calibration.get("provenance") or {}).items():
        lines.append(f"  {key}: {value}")
    return lines


def _describe_quality(calibration: dict[str, Any], selected: str) -> list[str]:
    """The selected model, and the quality-aware model's lines (none for a calibration
    stored before it)."""
    quality = calibration.get("quality")
    if not quality:
        return [f"covariance model: {selected} (no quality-aware parameters stored)"]
    mu, beta = np.asarray(quality["mu1"]), np.asarray(quality["beta"])
    std = np.sqrt(np.diag(np.asarray(quality["Sigma1"])))
    return [
        f"covariance model: {selected} (both stored)",
        f"quality-aware: at {quality['n_ref']:.0f} inliers, {quality['error_ref_px']:.1f} px:",
        f"  mu1    X {100 * mu[0]:+.1f} cm, Y {100 * mu[1]:+.1f} cm, "
        f"psi {math.degrees(mu[2]):+.2f} deg",
        f"  std1   X {100 * std[0]:.1f} cm, Y {100 * std[1]:.1f} cm, "
        f"psi {math.degrees(std[2]):.2f} deg",
        f"  log-variance slopes: log inliers {beta[0]:+.2f}, log reprojection error "
        f"{beta[1]:+.2f}, joint {beta[2]:+.2f}",
    ] + _describe_tail(quality)


def _describe_pnp(calibration: dict[str, Any]) -> list[str]:
    """The PnP covariance model's lines (none for a calibration stored before it)."""
    pnp = calibration.get("pnp")
    if not pnp:
        return []
    mu, floor = np.asarray(pnp["mu1"]), np.sqrt(np.diag(np.asarray(pnp["floor"])))
    return [
        "pnp covariance: sigma^2 C + floor, C from each pose's own inliers at 1 px:",
        f"  mu1    X {100 * mu[0]:+.1f} cm, Y {100 * mu[1]:+.1f} cm, "
        f"psi {math.degrees(mu[2]):+.2f} deg",
        f"  sigma  {float(pnp['pixel_std_px']):.2f} px",
        f"  floor  X {100 * floor[0]:.1f} cm, Y {100 * floor[1]:.1f} cm, "
        f"psi {math.degrees(floor[2]):.2f} deg",
        f"  outliers {100 * float(pnp.get('outlier_weight') or 0.0):.0f} % of hypotheses, "
        "as the paper covariance's",
    ]


def _describe_conditions(calibration: dict[str, Any]) -> list[str]:
    """One line per condition's model (none for a calibration without conditions)."""
    lines = []
    for name, model in sorted((calibration.get("conditions") or {}).items()):
        std1 = np.sqrt(np.diag(np.asarray(model["Sigma1"])))
        lines.append(
            f"condition {name}: std1 X {100 * std1[0]:.1f} cm, Y {100 * std1[1]:.1f} cm, "
            f"psi {math.degrees(std1[2]):.2f} deg, covariance model "
            f"{MeasurementModel.from_dict(model).covariance}, updated {model.get('updated_at')}"
        )
    return lines


def _describe_tail(model: dict[str, Any]) -> list[str]:
    """The pose-error tail of the paper's parameters or the quality model's, one line."""
    weight = float(model.get("tail_weight") or 0.0)
    if weight <= 0.0:
        return ["  tail   none (one Gaussian)"]
    return [
        f"  tail   {100 * weight:.0f} % of hypotheses, {float(model['tail_scale']):.1f}x the spread"
    ]


def _frame_of(done: int, total: int) -> str:
    return f"frame {done} of {total}"


def run_calibration_job(
    session_factory: sessionmaker[Session],
    map_ref: str | int,
    source,
    params: CalibrationParams,
    *,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[JobRecord, dict[str, Any]]:
    """:func:`calibrate_map` of ``source`` (the run ``params`` describe) recorded as a job
    (state, progress, error, result) for the CLI. A condition on a map without a base
    calibration is refused (ConflictError) before any job is recorded."""
    record = find_map(session_factory, map_ref)
    condition = params.condition
    if condition is not None:
        conditions.require_base(record.calibration, record.id, condition)
    if params.source_name is None:
        params = params.model_copy(update={"source_name": source.name})

    def work(job: JobRecord, report: Callable[[int, int], None]) -> dict[str, Any]:
        return calibrate_map(
            session_factory,
            record.id,
            source,
            config=params.config,
            seed=params.seed,
            job_id=job.id,
            progress=report,
            condition=condition,
        )

    return run_recorded_job(
        session_factory,
        JOB_KIND,
        map_id=record.id,
        params=params.model_dump(mode="json"),
        started="calibrating",
        describe_progress=_frame_of,
        work=work,
        result_of=lambda calibration: job_result(calibration, condition),
        progress=progress,
    )


def job_result(calibration: dict[str, Any], condition: str | None = None) -> dict[str, Any]:
    """What a calibration job records as its result: the model it fitted (the base's, or
    the condition's) and its provenance; a base job also names the conditions it kept."""
    keys = (
        "mu1",
        "Sigma1",
        "mu2",
        "Sigma2",
        "outlier_log_density",
        "quality",
        "pnp",
        "covariance",
        "retrieval_frame",
        "tail_weight",
        "tail_scale",
        "provenance",
    )
    fitted = calibration if condition is None else calibration["conditions"][condition]
    result = {key: fitted.get(key) for key in keys}
    if condition is not None:
        return {"condition": condition, **result}
    return {**result, "conditions": sorted(calibration.get("conditions") or {})}


def run_calibration(ctx: JobContext) -> dict[str, Any]:
    """Fit the measurement model on the uploaded training run (its own intrinsics, the
    map's vocabulary) and store it on the map; the run is not added to the map. A stop
    request ends the job ``interrupted``; resuming it calibrates again from the start."""
    job = ctx.job
    params = CalibrationParams.from_row(job)
    if job.map_id is None:
        raise ConflictError(f"the map of job {job.id} was deleted")
    upload = ctx.upload_dir()
    if upload is None:
        raise ConflictError(
            f"job {job.id} was started by `monoloc map calibrate` (no upload): run it again"
        )
    if not upload.is_dir():
        raise ConflictError(f"the upload of job {job.id} is gone; upload the run again")
    source = params.open_upload(upload)

    def progress(done: int, total: int) -> None:
        if ctx.should_stop():
            raise JobInterruptedError(
                f"stopped at frame {done} of {total}; resume to calibrate again"
            )
        ctx.progress(done / max(total, 1), _frame_of(done, total), force=done == total)

    calibration = calibrate_map(
        ctx.sessions,
        job.map_id,
        source,
        config=params.config,
        seed=params.seed,
        job_id=job.id,
        source_name=params.source_name,
        progress=progress,
        condition=params.condition,
    )
    return job_result(calibration, params.condition)
