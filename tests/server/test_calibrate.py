"""Calibration of the measurement model (docs/method.md section 7) on tiny sim `train` runs
at full KITTI resolution (30 frames: a temporary map of 15 entries, 15 queries).

- With the sim's realistic recording errors: finite, positive-definite covariances and
  sane position errors.
- With exact geometry (every recording error off, no LiDAR range noise) and the nearest
  entries only: a small Sigma1; and a constant offset planted in the truth of the query
  frames (+0.5 m in X, +0.02 rad in heading) comes out in mu1 with its sign, which pins
  the convention e = truth - hypothesis.
- ``monoloc map calibrate`` on a local database: progress, parameters in cm/deg,
  provenance, a job row; a too-short run fails with one clear message and a failed job.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.server.calibrate import (
    CalibrationConfig,
    TrainingFrame,
    TrainingRun,
    calibrate,
    calibrate_runs,
)

N_FRAMES = 30
OFFSET_X_M = 0.5
OFFSET_YAW_RAD = 0.02


def _generate(root: Path, exact: bool) -> Path:
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig
    from monoloc.sim.recording import RecordingErrors

    config = GenerateConfig(
        size="small",
        runs=("train",),
        max_frames=N_FRAMES,
        lidar=LidarConfig(azimuth_steps=1000, range_noise_m=0.0 if exact else 0.02),
        errors=RecordingErrors.none() if exact else RecordingErrors(),
        seed=0,
    )
    generate_dataset(config, root)
    return root


@pytest.fixture(scope="module")
def noisy_run(tmp_path_factory) -> Path:
    return _generate(tmp_path_factory.mktemp("train_noisy"), exact=False)


@pytest.fixture(scope="module")
def exact_run(tmp_path_factory) -> Path:
    return _generate(tmp_path_factory.mktemp("train_exact"), exact=True)


def _frames(
    root: Path,
    offset_x_m: float = 0.0,
    offset_yaw_rad: float = 0.0,
    offset_ahead_m: float = 0.0,
    turn_world_rad: float = 0.0,
) -> list:
    """TrainingFrames of sequence 00 in its world frame turned by ``turn_world_rad`` about
    z; the query frames' (odd frames') truth is moved by +offset_x_m along world X and
    +offset_ahead_m along the camera's heading, and turned by +offset_yaw_rad about z."""
    from monoloc.server.ingest.sources import read_kitti_sequence

    source = read_kitti_sequence(root)
    c, s = math.cos(offset_yaw_rad), math.sin(offset_yaw_rad)
    R_turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    c, s = math.cos(turn_world_rad), math.sin(turn_world_rad)
    R_world = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    frames = []
    for i, frame in enumerate(source.frames):
        loaded = source.load(frame)
        T = np.array(frame.T_world_from_cam, dtype=np.float64)
        T[:3] = R_world @ T[:3]
        if i % 2 == 1:
            T[:3, :3] = R_turn @ T[:3, :3]
            T[0, 3] += offset_x_m
            heading = math.atan2(T[1, 2], T[0, 2])
            T[:2, 3] += offset_ahead_m * np.array([math.cos(heading), math.sin(heading)])
        frames.append(TrainingFrame(loaded.image_gray, T, loaded.source))
    return frames


def _calibrate(root: Path, config: CalibrationConfig, progress=None, **offsets):
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    intrinsics = read_kitti_sequence(root).intrinsics
    return calibrate(
        _frames(root, **offsets),
        intrinsics,
        load_default_vocabulary(),
        config,
        np.random.default_rng(0),
        progress=progress,
        source_name="sim train",
    )


def _position_std_m(Sigma: np.ndarray) -> np.ndarray:
    return np.sqrt(np.diag(Sigma)[:2])


def test_calibration_on_a_sim_training_run_is_sane(noisy_run):
    calls = []
    result = _calibrate(noisy_run, CalibrationConfig(), progress=lambda d, t: calls.append((d, t)))
    model, prov = result.model, result.provenance
    for cov in (model.Sigma1, model.Sigma2):
        assert np.all(np.isfinite(cov)) and np.allclose(cov, cov.T)
        assert np.linalg.eigvalsh(cov).min() > 0.0
    std_m = _position_std_m(model.Sigma1)
    assert np.all((std_m > 0.01) & (std_m < 1.0)), std_m
    assert math.degrees(math.sqrt(model.Sigma1[2, 2])) < 5.0
    assert np.hypot(*model.mu1[:2]) < 0.2, model.mu1
    assert 0.0 < model.mu2[0] < 2.0  # e_vlad: a distance between unit vectors
    assert prov["frames"] == N_FRAMES and prov["query_frames"] == N_FRAMES // 2
    assert prov["map_frames"] + prov["map_frames_skipped"] == N_FRAMES // 2
    assert prov["used"] == prov["hypotheses"] - prov["gated_outliers"] >= 10
    assert prov["k"] == 10 and prov["source"] == "sim train" and "unbiased" in prov["covariance"]
    # The quality-aware and paper models are fitted beside the PnP covariance model, the
    # one selected. More inliers must not widen a hypothesis.
    assert model.covariance == "pnp" and model.pnp is not None and model.quality is not None
    assert model.retrieval_frame == "vehicle"
    # the relative VLAD evidence is fitted beside the absolute one: a frame's hypotheses
    # lie a few hundredths above its best, well inside the absolute spread
    mean_rel, std_rel = model.relative_vlad
    assert model.vlad_evidence == "absolute" and (mean_rel, std_rel) != (0.0, 0.25)
    assert 0.0 <= mean_rel < model.mu2[0] and 0.01 <= std_rel < 0.5
    assert (
        np.sqrt(model.Sigma2[3, 3]) >= 0.05
        and np.linalg.eigvalsh(model.Sigma2[1:3, 1:3]).min() >= 1.0 - 1e-9
    )
    assert prov["joint_used"] == prov["joint_hypotheses"] - prov["joint_gated_outliers"] > 0
    assert model.quality.beta[0] < 0.0, model.quality.beta
    assert np.linalg.eigvalsh(model.quality.Sigma1).min() > 0.0
    # PnP errors have a heavy tail: the fit keeps one (a share of the hypotheses several
    # times as spread as the core) and the core is no wider than the paper's one Gaussian.
    # Within 5 %: on these 127 hypotheses the fit trades the core's width against the
    # tail's weight (0.75x the paper's trace with tail weight 0.15 before the joint pose's
    # Cauchy refit moved 15 joint poses, 1.02x with 0.11 after).
    assert 0.0 < model.quality.tail_weight < 0.5 and model.quality.tail_scale > 1.5
    assert np.trace(model.quality.Sigma1[:2, :2]) < 1.05 * np.trace(model.Sigma1[:2, :2])
    # The PnP covariance model: a pixel noise of the order of a pixel, a floor under the
    # paper's spread, the paper tail's settings; the strategy gave every per-entry
    # hypothesis its covariance.
    pnp = model.pnp
    assert pnp is not None and 0.2 < pnp.pixel_std_px < 10.0, pnp
    assert np.all(np.sqrt(np.diag(pnp.floor))[:2] < std_m), pnp.floor
    assert pnp.outlier_weight == model.tail_weight
    assert "sigma_px^2 C" in prov["pnp_model"]
    done = [d for d, _ in calls]
    assert done == sorted(done) and calls[-1][0] == calls[-1][1] == N_FRAMES + N_FRAMES // 2


def test_exact_geometry_gives_a_small_sigma1(exact_run):
    model = _calibrate(exact_run, CalibrationConfig(k=3)).model
    assert np.all(_position_std_m(model.Sigma1) < 0.05), model.Sigma1
    assert np.hypot(*model.mu1[:2]) < 0.02 and abs(model.mu1[2]) < math.radians(0.1)


def test_the_pnp_covariance_model_can_be_selected_and_needs_the_covariances(exact_run):
    from bench.lab.paper import independent_pose_hypotheses

    model = _calibrate(exact_run, CalibrationConfig(k=3, covariance="pnp")).model
    assert model.covariance == "pnp" and model.pnp is not None
    # a pose stage that gives no pose covariances: the paper's independent PnP (bench/)
    without = independent_pose_hypotheses
    config = CalibrationConfig(k=3, pose_stage=without, covariance="paper")
    paper = _calibrate(exact_run, config)
    assert paper.model.pnp is None and paper.provenance["pnp_model"].startswith("none")
    assert paper.provenance["pnp"] != "guided"
    with pytest.raises(InvalidInputError, match="pnp covariance model"):
        _calibrate(exact_run, CalibrationConfig(k=3, pose_stage=without))  # "pnp" by default


def test_the_pnp_model_is_fitted_on_covariances_with_the_keypoints_pyramid_scales(exact_run):
    """The calibration gives the pose stage the query keypoints' scales, which weigh the
    covariances: each inlier's noise is then at least the 1 px of a full-resolution
    keypoint, the covariances grow, and the fitted pixel noise (of a full-resolution
    keypoint) falls; the paper's model does not move."""
    from monoloc.server.localize import pose_hypotheses

    def full_resolution(*args, keypoint_scales=None, **kwargs):
        """The pose stage told nothing of the scales: every keypoint at full resolution."""
        return pose_hypotheses(*args, **kwargs)

    def fitted(pose_stage):
        return _calibrate(exact_run, CalibrationConfig(k=3, pose_stage=pose_stage)).model

    weighed, plain = fitted(pose_hypotheses), fitted(full_resolution)
    assert weighed.pnp.pixel_std_px < 0.95 * plain.pnp.pixel_std_px, (weighed.pnp, plain.pnp)
    np.testing.assert_allclose(weighed.Sigma1, plain.Sigma1)


def test_planted_offset_shows_up_in_mu1_with_its_sign(exact_run):
    """e = truth - hypothesis: truth moved by +0.5 m in X -> mu1_x = +0.5, and so on (in
    world axes, the paper's)."""
    config = CalibrationConfig(k=3, retrieval_frame="world")
    planted = _calibrate(exact_run, config, offset_x_m=OFFSET_X_M, offset_yaw_rad=OFFSET_YAW_RAD)
    mu1 = planted.model.mu1
    assert mu1[0] == pytest.approx(OFFSET_X_M, abs=0.02), mu1
    assert abs(mu1[1]) < 0.02, mu1
    assert mu1[2] == pytest.approx(OFFSET_YAW_RAD, abs=0.002), mu1
    assert np.all(_position_std_m(planted.model.Sigma1) < 0.05)
    # The paper's second moment about zero keeps the planted bias inside Sigma1.
    paper = _calibrate(
        exact_run,
        CalibrationConfig(k=3, unbiased=False, retrieval_frame="world"),
        offset_x_m=OFFSET_X_M,
        offset_yaw_rad=OFFSET_YAW_RAD,
    ).model
    n, floor = planted.provenance["used"], 0.01**2
    expected = (planted.model.Sigma1[0, 0] - floor) * (n - 1) / n + mu1[0] ** 2 + floor
    assert paper.Sigma1[0, 0] == pytest.approx(expected, rel=1e-6)
    assert np.allclose(paper.mu1, mu1)


def test_the_product_fits_the_pose_error_along_and_across_the_heading(exact_run):
    """The truth moved 0.5 m ahead of each query frame: the product's mu1 is +0.5 m along
    the heading and nothing across it, whichever way the run's world frame is turned (the
    paper's world axes turn it with the frame)."""
    turned = _calibrate(
        exact_run, CalibrationConfig(k=3), offset_ahead_m=OFFSET_X_M, turn_world_rad=math.pi / 2
    ).model
    for model in (
        _calibrate(exact_run, CalibrationConfig(k=3), offset_ahead_m=OFFSET_X_M).model,
        turned,
    ):
        assert model.retrieval_frame == "vehicle"
        assert model.mu1[0] == pytest.approx(OFFSET_X_M, abs=0.02), model.mu1
        assert abs(model.mu1[1]) < 0.02 and np.all(_position_std_m(model.Sigma1) < 0.05), model
    world = _calibrate(
        exact_run,
        CalibrationConfig(k=3, retrieval_frame="world"),
        offset_ahead_m=OFFSET_X_M,
        turn_world_rad=math.pi / 2,
    ).model
    assert abs(world.mu1[0]) < 0.02 and world.mu1[1] == pytest.approx(OFFSET_X_M, abs=0.02)


def test_runs_are_pooled_each_against_its_own_map(exact_run):
    """Two training runs (e.g. day and night): each is split into its own map and
    queries, and one fit covers the samples of both. The second run's query truths carry
    a planted +0.5 m X offset, the first's none, so the pooled mu1 X is the offset times
    the second run's share of the samples."""
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    runs = [
        TrainingRun(_frames(exact_run), "day"),
        TrainingRun(_frames(exact_run, offset_x_m=OFFSET_X_M), "shifted"),
    ]
    calls = []
    result = calibrate_runs(
        runs,
        read_kitti_sequence(exact_run).intrinsics,
        load_default_vocabulary(),
        CalibrationConfig(k=3),
        np.random.default_rng(0),
        progress=lambda d, t: calls.append((d, t)),
    )
    prov = result.provenance
    per_run = {r["source"]: r for r in prov["runs"]}
    assert prov["source"] == "day + shifted" and prov["frames"] == 2 * N_FRAMES
    assert per_run["day"]["frames"] == per_run["shifted"]["frames"] == N_FRAMES
    assert per_run["day"]["used"] + per_run["shifted"]["used"] == prov["used"]
    share = per_run["shifted"]["used"] / prov["used"]
    assert 0.3 < share < 0.7
    assert result.model.mu1[0] == pytest.approx(OFFSET_X_M * share, abs=0.03)
    assert calls[-1][0] == calls[-1][1] == 2 * (N_FRAMES + N_FRAMES // 2)
    with pytest.raises(InvalidInputError, match="at least one training run"):
        calibrate_runs([], None, None, CalibrationConfig(), np.random.default_rng(0))


def test_too_short_a_run_is_refused(noisy_run):
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    with pytest.raises(InvalidInputError, match="at least 10 map frames .* got 6 map frames"):
        calibrate(
            _frames(noisy_run)[:12],
            read_kitti_sequence(noisy_run).intrinsics,
            load_default_vocabulary(),
            CalibrationConfig(),
            np.random.default_rng(0),
        )
    with pytest.raises(InvalidInputError):
        CalibrationConfig(k=0)
    assert CalibrationConfig(k=10).min_frames == 20


def test_map_calibrate_cli(noisy_run, tmp_path):
    from typer.testing import CliRunner

    from monoloc import cli
    from monoloc.server.jobs import store as jobs_repo
    from monoloc.server.settings import Settings
    from monoloc.server.storage import maps as maps_repo
    from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope

    cli._register()
    env = {"MONOLOC_DATA_DIR": str(tmp_path / "data")}
    runner = CliRunner()
    result = runner.invoke(cli.app, ["map", "create", "street", "--camera", "kitti"], env=env)
    assert result.exit_code == 0, result.output
    args = ["map", "calibrate", "--map", "street", "--run", str(noisy_run), "--format", "kitti"]
    result = runner.invoke(cli.app, args, env=env, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    out = result.output
    assert "job 1 done: map 1 calibrated" in out
    assert "std1   along" in out and " cm" in out and " deg" in out
    assert "entry offset (along / across the vehicle's heading)" in out
    paper_tail, quality_tail = calibration_tail_lines(out)
    assert paper_tail == "tail   30 % of hypotheses, 10.0x the spread"
    assert quality_tail.endswith("x the spread") and "% of hypotheses" in quality_tail
    # the PnP covariance model: fitted pixel noise and floor
    assert "pnp covariance: sigma^2 C + floor" in out
    assert "sigma " in out and " px" in out and "floor  X" in out
    assert "outliers 30 % of hypotheses, as the paper covariance's" in out
    assert "used:" in out and "gated_outliers:" in out and "vocabulary_hash:" in out
    # an empty map: how the calibration fits it cannot be told yet
    assert "fit to this map: not known" in out

    short = runner.invoke(cli.app, [*args, "--frames", "0:10"], env=env)
    assert isinstance(short.exception, InvalidInputError)
    assert "too short to calibrate: 10 frames" in str(short.exception)
    # which pose-error model is stored selected is no option (the product's, pnp); a bad
    # parameter is a usage error naming it, before any job is recorded
    gone = runner.invoke(cli.app, [*args, "--covariance", "paper"], env=env)
    assert gone.exit_code == 2 and "No such option" in gone.output
    for bad in (["--k", "0"], ["--depth-from", "sonar"]):
        refused = runner.invoke(cli.app, [*args, *bad], env=env)
        assert refused.exit_code == 2 and f"'{bad[0]}'" in refused.output, refused.output

    engine = create_engine_for(Settings(data_dir=tmp_path / "data"))
    with session_scope(make_session_factory(engine)) as session:
        record = maps_repo.find_map(session, "street")
        jobs = {j.id: j for j in jobs_repo.list_jobs(session, map_id=record.id)}
    engine.dispose()
    assert record.n_entries == 0  # the training run is not part of the map
    calibration = record.calibration
    assert calibration["provenance"]["job_id"] == 1 and calibration["source"] == "calibrated"
    assert calibration["provenance"]["vocabulary_hash"] == record.vocabulary_hash
    assert f"{100 * calibration['mu1'][0]:+.1f} cm" in out
    assert jobs[1].kind == "calibrate" and jobs[1].state == "done"
    assert jobs[1].result["provenance"] == calibration["provenance"]
    assert jobs[2].state == "failed" and "too short" in jobs[2].error and sorted(jobs) == [1, 2]
    assert "covariance model: pnp" in out
    assert calibration["covariance"] == "pnp" and calibration["pnp"]["pixel_std_px"] > 0
    assert jobs[1].params["k"] == 10 and jobs[1].params["path"] == str(noisy_run)


def test_map_calibrate_cli_condition(noisy_run, tmp_path):
    """--condition: a bad name and a map without a base calibration are refused before
    any job; after the base, the night run's model is stored as conditions.night."""
    from typer.testing import CliRunner

    from monoloc import cli
    from monoloc.core.errors import ConflictError
    from monoloc.server.jobs import store as jobs_repo
    from monoloc.server.settings import Settings
    from monoloc.server.storage import maps as maps_repo
    from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope

    cli._register()
    env = {"MONOLOC_DATA_DIR": str(tmp_path / "data")}
    runner = CliRunner()
    assert (
        runner.invoke(cli.app, ["map", "create", "street", "--camera", "kitti"], env=env).exit_code
        == 0
    )
    args = ["map", "calibrate", "--map", "street", "--run", str(noisy_run), "--k", "3"]
    args += ["--frames", "0:16"]

    bad = runner.invoke(cli.app, [*args, "--condition", "no good"], env=env)
    assert bad.exit_code == 2 and "invalid condition name 'no good'" in bad.output
    early = runner.invoke(cli.app, [*args, "--condition", "night"], env=env)
    assert isinstance(early.exception, ConflictError)
    assert "calibrate the map without a condition first" in str(early.exception)

    base = runner.invoke(cli.app, args, env=env, catch_exceptions=False)
    assert base.exit_code == 0 and "job 1 done: map 1 calibrated" in base.output
    night = runner.invoke(cli.app, [*args, "--condition", "Night"], env=env, catch_exceptions=False)
    assert night.exit_code == 0, night.output
    assert "job 2 done: map 1 condition night calibrated" in night.output
    assert "std1   along" in night.output and "condition: night" in night.output

    engine = create_engine_for(Settings(data_dir=tmp_path / "data"))
    with session_scope(make_session_factory(engine)) as session:
        record = maps_repo.find_map(session, "street")
        jobs = jobs_repo.list_jobs(session, map_id=record.id)
    engine.dispose()
    assert [(j.id, j.state, j.params["condition"]) for j in sorted(jobs, key=lambda j: j.id)] == [
        (1, "done", None),
        (2, "done", "night"),
    ]
    stored = record.calibration
    assert stored["provenance"]["job_id"] == 1 and list(stored["conditions"]) == ["night"]
    assert stored["conditions"]["night"]["provenance"]["job_id"] == 2


def test_the_calibration_description_names_the_offsets_frame():
    from monoloc.core.measurement import MeasurementModel
    from monoloc.server.jobs.calibration import describe_calibration

    stored = MeasurementModel(retrieval_frame="vehicle").to_dict()
    text = "\n".join(describe_calibration(stored))
    assert "entry offset (along / across the vehicle's heading)" in text
    assert "along +0.00 m, across +0.00 m" in text
    assert "pose error e = truth - hypothesis (along / across the hypothesis's heading)" in text
    assert "mu1    along +0.0 cm, across +0.0 cm" in text
    stored["retrieval_frame"] = "world"
    world = "\n".join(describe_calibration(stored))
    assert "X +0.00 m, Y +0.00 m" in world and "mu1    X +0.0 cm, Y +0.0 cm" in world
    # the paper covariance's tail: none for a model without one (or stored before it)
    assert "tail   none (one Gaussian)" in text
    tailed = MeasurementModel(tail_weight=0.3, tail_scale=10.0).to_dict()
    assert "tail   30 % of hypotheses, 10.0x the spread" in describe_calibration(tailed)[3]


def calibration_tail_lines(output: str) -> list[str]:
    """The tail lines of ``monoloc map calibrate``'s output: the paper covariance's, then
    the quality model's."""
    lines = [line.strip() for line in output.splitlines() if line.strip().startswith("tail ")]
    assert len(lines) == 2, output
    return lines
