"""A map's world frame is an arbitrary choice (an ENU origin, a SLAM frame): turning it
changes nothing physical, so the product's calibrated measurement model must give the
same likelihood and the same filter estimate, turned (issue 47). A model whose pose bias
and covariance or retrieval offsets are in world axes does not: calibrated on a short
straight road (entries ahead of the query by 2.4 m on average, 7.4 m spread along the
road, 1.0 m across it) it weighs a street running another way as if its entries sat
beside the query.

Recorded, not invented: ``data/world_frame_drive.npz`` holds the calibration samples of
bench/transfer.py's short straight road (51 frames at 5 Hz, stereo) and the first 50
frames of a drive on its urban 5 Hz test street (entries every 2.5 m), each frame's
hypotheses as the server answered them. Written by ``python -m bench.transfer --train
"short straight" --test "urban 5 Hz, entry every 2.5" --record-fixture
tests/core/data/world_frame_drive.npz``.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from monoloc.client.particle_filter import FilterConfig
from monoloc.client.tracking import Tracker
from monoloc.core.measurement import Hypotheses, MeasurementModel, log_likelihood

DRIVE = Path(__file__).parent / "data" / "world_frame_drive.npz"
SAMPLE_FIELDS = (
    "truth",
    "hypothesis",
    "e_vlad",
    "e_vlad_best",
    "entry_pose",
    "n_inliers",
    "error_px",
    "joint",
    "pose_covariance",
    "query_index",
    "entry_index",
    "neighbour_e_vlad",
)
# the test street turned onto the training road's across-axis, and an oblique turn
TURNS_DEG = (90.0, 37.0)


@pytest.fixture(scope="module")
def drive() -> dict:
    with np.load(DRIVE) as data:
        return {key: data[key] for key in data.files}


def _fitted(drive: dict, retrieval_frame: str | None) -> MeasurementModel:
    """The model ``monoloc map calibrate`` fits on the recorded samples: the product's
    choices (None), or with the offsets' frame set."""
    from monoloc.server.calibrate import CalibrationConfig, CalibrationSamples, fit_samples
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    samples = CalibrationSamples(
        **{k: list(drive[f"sample_{k}"]) for k in SAMPLE_FIELDS},
    )
    config = CalibrationConfig()
    if retrieval_frame is not None:
        config = replace(config, retrieval_frame=retrieval_frame)
    per_run = json.loads(str(drive["per_run"]))
    return fit_samples(samples, per_run, ["train"], config, load_default_vocabulary()).model


@pytest.fixture(scope="module")
def models(drive) -> dict[str, MeasurementModel]:
    return {"product": _fitted(drive, None), "world": _fitted(drive, "world")}


def _turn(poses: np.ndarray, angle_rad: float) -> np.ndarray:
    """Planar poses (..., 3) in the world frame turned by ``angle_rad`` about z."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    out = np.array(poses, dtype=np.float64, copy=True)
    out[..., 0] = c * poses[..., 0] - s * poses[..., 1]
    out[..., 1] = s * poses[..., 0] + c * poses[..., 1]
    out[..., 2] = (poses[..., 2] + angle_rad + math.pi) % (2 * math.pi) - math.pi
    return out


def _frames(drive: dict, angle_rad: float = 0.0) -> list[Hypotheses]:
    """The recorded hypotheses of each frame, in the world frame turned by ``angle_rad``
    (poses, entry poses and pose covariances; VLAD distances and PnP quality unchanged)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    ends = np.cumsum(drive["hyp_count"])
    frames = []
    for start, end in zip(ends - drive["hyp_count"], ends, strict=True):
        part = slice(start, end)
        frames.append(
            Hypotheses(
                _turn(drive["hyp_pose_world"][part].reshape(-1, 3), angle_rad),
                _turn(drive["hyp_entry_pose_world"][part].reshape(-1, 3), angle_rad),
                drive["hyp_e_vlad"][part].reshape(-1),
                n_inliers=drive["hyp_n_inliers"][part].reshape(-1),
                reprojection_error_px=drive["hyp_reprojection_error_px"][part].reshape(-1),
                joint=drive["hyp_joint"][part].reshape(-1),
                pose_covariance=R @ drive["hyp_pose_covariance"][part] @ R.T,
                method=tuple(str(m) for m in drive["hyp_method"][part]),
            )
        )
    return frames


def _drive(drive: dict, model: MeasurementModel, angle_rad: float) -> np.ndarray:
    """The vehicle's filter over the recorded frames in the turned world; its estimates
    (N, 3) turned back into the recording's frame."""
    config = FilterConfig()
    config = replace(config, motion=replace(config.motion, lever_arm_m=float(drive["lever_arm_m"])))
    tracker = Tracker(
        config, model, np.random.default_rng(0), drive["timestamps_s"], drive["signals"]
    )
    for i, hypotheses in enumerate(_frames(drive, angle_rad)):
        tracker.step(i, hypotheses)
    return _turn(tracker.estimates_world, -angle_rad)


def test_the_product_model_weighs_a_turned_world_alike(drive, models):
    """The log-likelihood of particles about each recorded frame is the same, up to one
    constant per frame (which the filter's normalisation removes), when the world turns."""
    rng = np.random.default_rng(0)
    truth = drive["truth_world"]
    spreads = {}
    for name, model in models.items():
        worst = 0.0
        for i, hypotheses in enumerate(_frames(drive)[:20]):
            if not len(hypotheses):
                continue
            particles = truth[i] + rng.normal(size=(300, 3)) * [0.5, 0.5, 0.02]
            here = log_likelihood(particles, hypotheses, model)
            for turn_deg in TURNS_DEG:
                turn = math.radians(turn_deg)
                there = log_likelihood(_turn(particles, turn), _frames(drive, turn)[i], model)
                worst = max(worst, float(np.ptp(there - here)))
        spreads[name] = worst
    assert spreads["product"] < 1e-6, spreads
    # world axes remember the training road's direction (so the check above can fail)
    assert spreads["world"] > 1.0, spreads


def test_the_product_filter_on_a_turned_map_gives_the_turned_estimate(drive, models):
    """The same calibrated model driven over the same recorded frames, the map's world
    frame turned: the estimate turned back is the estimate."""
    truth = drive["truth_world"]
    differences, errors = {}, {}
    for name, model in models.items():
        here = _drive(drive, model, 0.0)
        ok = np.isfinite(here[:, 0])
        assert ok.mean() > 0.9
        errors[name] = float(np.sqrt(np.mean(np.sum((here[ok, :2] - truth[ok, :2]) ** 2, 1))))
        for turn_deg in TURNS_DEG:
            there = _drive(drive, model, math.radians(turn_deg))
            gap = np.hypot(*(there[ok, :2] - here[ok, :2]).T)
            differences[name, turn_deg] = float(np.sqrt(np.mean(gap**2)))
    # the filter's own draws are along and across the headings too: equal to rounding
    for turn_deg in TURNS_DEG:
        assert differences["product", turn_deg] < 1e-6, (differences, errors)
    # a calibration in world axes moves by centimetres (so the check above can fail)
    assert max(differences["world", t] for t in TURNS_DEG) > 0.005, differences


def _log_gauss(r: np.ndarray, cov: np.ndarray) -> float:
    return float(-0.5 * (r @ np.linalg.solve(cov, r) + np.linalg.slogdet(2 * math.pi * cov)[1]))


def _rotation(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_the_vehicle_frame_is_the_papers_formula_along_and_across_each_heading():
    """Written out: the pose term's bias and floor turned by the hypothesis's heading
    (its own PnP covariance is in world axes), the retrieval offset turned into the
    particle's heading."""
    from monoloc.core.measurement import PnpCovarianceModel

    rng = np.random.default_rng(4)
    pnp = PnpCovarianceModel(
        mu1=np.array([0.05, -0.02, 0.001]),
        pixel_std_px=1.3,
        floor=np.diag([0.001**2, 0.03**2, 1e-6]),
    )
    model = MeasurementModel(
        mu1=np.array([0.1, 0.03, 0.0]),
        Sigma1=np.diag([0.2**2, 0.1**2, 1e-4]),
        mu2=np.array([1.2, 2.4, 0.1, 0.0]),
        Sigma2=np.diag([0.06**2, 7.0**2, 1.0, 0.05**2]),
        outlier_log_density=None,
        pnp=pnp,
        covariance="pnp",
        retrieval_frame="vehicle",
    )
    poses = np.array([[3.0, 4.0, 1.2], [3.4, 3.7, -2.0], [2.5, 4.4, 0.3]])
    entries = poses + [[1.0, 4.0, 0.02], [-3.0, 1.0, -0.01], [4.0, 0.5, 0.0]]
    covariances = np.array([np.diag([0.02, 0.05, 1e-5]) * (1 + k) for k in range(3)])
    e_vlad = np.array([1.15, 1.25, 1.2])
    hypotheses = Hypotheses(poses, entries, e_vlad, pose_covariance=covariances)
    particles = poses[0] + rng.normal(size=(5, 3)) * [0.3, 0.3, 0.05]
    got = log_likelihood(particles, hypotheses, model)
    for particle, value in zip(particles, got, strict=True):
        terms = []
        for pose, entry, C, ev in zip(poses, entries, covariances, e_vlad, strict=True):
            R = _rotation(pose[2])
            S = 1.3**2 * C + R @ pnp.floor @ R.T
            r1 = particle - (pose + R @ pnp.mu1)
            r1[2] = (r1[2] + math.pi) % (2 * math.pi) - math.pi
            offset = _rotation(particle[2]).T @ (entry - particle)
            r2 = np.array([ev, offset[0], offset[1], entry[2] - particle[2]]) - model.mu2
            r2[3] = (r2[3] + math.pi) % (2 * math.pi) - math.pi
            terms.append(_log_gauss(r1, S) + _log_gauss(r2, model.Sigma2))
        assert value == pytest.approx(np.logaddexp.reduce(terms), abs=1e-9)
    # and the same model in world axes is another number (so the check above can fail)
    world = replace(model, retrieval_frame="world")
    assert np.max(np.abs(log_likelihood(particles, hypotheses, world) - got)) > 0.1
