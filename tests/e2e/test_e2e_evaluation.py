"""The benchmark's engine (bench.lab.evaluation) on the tiny sim city: the map held in
memory, the frames answered by the in-process localizer and the vehicle's own loop."""

from __future__ import annotations

import numpy as np
import pytest
from e2e_helpers import MAP_SEQ, QUERY_SEQ

from monoloc.client.particle_filter import FilterConfig


@pytest.fixture(scope="module")
def memory_map(sim_city):
    from bench.lab.evaluation import MemoryMap
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    memory = MemoryMap.empty(load_default_vocabulary())
    assert memory.add_run(read_kitti_sequence(sim_city, MAP_SEQ)) > 30
    return memory


def test_every_variant_localizes_the_query_run(memory_map, sim_city):
    from bench.lab.evaluation import EvalConfig, evaluate_run
    from monoloc.client.replay import read_kitti_run, rig_lever_arm_m
    from monoloc.core.measurement import MeasurementModel
    from monoloc.server.ingest.sources import read_kitti_sequence

    query = read_kitti_sequence(sim_city, QUERY_SEQ)
    signals = read_kitti_run(sim_city, QUERY_SEQ).signals
    config = EvalConfig(filter=FilterConfig(n_particles=500))
    lever = rig_lever_arm_m(sim_city)
    result = evaluate_run(memory_map, query, signals, MeasurementModel(), config, lever)
    assert list(result.estimates) == ["full", "no_prior", "top1", "topk_mean", "best_pnp"]
    assert result.metrics["full"].coverage >= 0.8
    assert result.metrics["full"].position_rmse_m < 0.5, result.metrics["full"]
    assert result.metrics["no_prior"].position_rmse_m < 0.5
    assert result.metrics["top1"].position_rmse_m > result.metrics["full"].position_rmse_m
    # With the sim's recording errors of issue 13.4 (exposure and gray-level changes
    # between runs, calibration, LiDAR sync), query frames ~22-35 of this tiny run fall
    # below min_inliers; the filter carries them (coverage above).
    assert len(result.timings_ms) == query.n_frames and np.mean(result.n_hypotheses > 0) >= 0.6
    # what the filter was given: the full variant's hypotheses and their likeliest pose
    assert [len(h) for h in result.hypotheses_world] == result.n_hypotheses.tolist()
    with_hyp = result.n_hypotheses > 0
    assert np.isfinite(result.likeliest_world[with_hyp]).all()
    assert np.isnan(result.likeliest_world[~with_hyp]).all()
    assert result.timestamps_s.shape == (query.n_frames,) and result.reseeds["full"] >= 0
    # the same seeds give the same estimates; the full variant alone is the same loop
    alone = evaluate_run(
        memory_map, query, signals, MeasurementModel(), config, lever, variants=("full",)
    )
    assert np.isfinite(alone.estimates["full"]).any()
    again = evaluate_run(
        memory_map, query, signals, MeasurementModel(), config, lever, variants=("full",)
    )
    np.testing.assert_array_equal(alone.estimates["full"], again.estimates["full"])


def test_the_in_process_localizer_takes_png_bytes_or_arrays(memory_map, sim_city):
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.localize.in_process import InProcessLocalizer

    query = read_kitti_sequence(sim_city, QUERY_SEQ)
    frame = query.frames[5]
    png = next((sim_city / "sequences" / QUERY_SEQ / "image_0").glob("000005.png")).read_bytes()

    def localizer(seed: int) -> InProcessLocalizer:
        m = memory_map
        rng = np.random.default_rng(seed)
        return InProcessLocalizer(m.index, m.lookup, m.vocabulary, query.intrinsics, rng)

    from_array = localizer(1).localize(query.load(frame).image_gray, k=5)
    from_png = localizer(1).localize(png, k=5)
    assert len(from_array.hypotheses) > 0 and len(from_array.result.retrieved_ids) == 5
    np.testing.assert_array_equal(from_array.hypotheses.pose_world, from_png.hypotheses.pose_world)
    np.testing.assert_array_equal(from_array.best_pose_world, from_array.result.best.pose_world)
    assert set(from_array.timings_ms) >= {"features", "vlad"}


def test_localize_globally_gives_each_frame_its_truth_result_and_time(memory_map, sim_city):
    from dataclasses import replace as dc_replace

    from bench.lab.evaluation import localize_globally
    from monoloc.core.geometry import planar_from_T_world_from_cam
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.localize import LocalizeConfig, localize_frame

    query = read_kitti_sequence(sim_city, QUERY_SEQ)
    query = dc_replace(query, frames=query.frames[:4])
    config = LocalizeConfig()
    frames = list(localize_globally(memory_map, query, config, np.random.default_rng(3)))
    assert [f.index for f in frames] == [0, 1, 2, 3]
    rng = np.random.default_rng(3)
    for f, frame in zip(frames, query.frames, strict=True):
        np.testing.assert_allclose(
            f.truth_world, planar_from_T_world_from_cam(frame.T_world_from_cam)
        )
        assert f.cpu_ms > 0
        direct = localize_frame(
            query.load(frame).image_gray,
            query.intrinsics,
            memory_map.vocabulary,
            memory_map.index,
            memory_map.lookup,
            config,
            rng,
        )
        # the frame's own image through the server's pipeline: the same hypotheses
        assert [h.entry_id for h in f.result.hypotheses] == [h.entry_id for h in direct.hypotheses]
        for mine, theirs in zip(f.result.hypotheses, direct.hypotheses, strict=True):
            np.testing.assert_allclose(mine.pose_world, theirs.pose_world)
    assert any(len(f.result.hypotheses) for f in frames)
