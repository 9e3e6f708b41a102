"""The training-run options (GenerateConfig.train_run, CityConfig.train_seed) do what they
say: route shape, length and direction, speed, frame rate, another district, lighting and
exposure; and with default options the training run is the one without them."""

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.core.formats import kitti
from monoloc.sim.generate import GenerateConfig, generate_dataset
from monoloc.sim.recording import RecordingErrors
from monoloc.sim.urban.city import CityConfig, build_city
from monoloc.sim.urban.runs import TrainRunConfig, plan_runs

TINY = GenerateConfig(
    seed=3,
    runs=("map", "train"),
    max_frames=2,
    image_scale=0.1,
    write_lidar=False,
    errors=RecordingErrors.none(),
)


def _train_plan(options: TrainRunConfig | None, city: CityConfig | None = None, frames=None):
    config = replace(TINY, runs=("train",), train_run=options, city=city, max_frames=frames)
    return plan_runs(build_city(config.city_config(), config.seed), config)[0]


def _states(plan):
    return plan.states.sample(plan.frame_times_s)


def test_a_short_straight_route_is_straight_short_and_heads_where_asked():
    plan = _train_plan(TrainRunConfig(route="straight", direction="north", length_m=80.0))
    st = _states(plan)
    xy = np.stack([st["x_m"], st["y_m"]], axis=1)
    driven = np.linalg.norm(xy[-1] - xy[0])
    assert plan.route_length_m <= 80.0
    assert 60.0 < driven <= 80.0
    assert np.ptp(st["x_m"]) < 0.5  # no turn: the lateral spread is the controller's
    heading = np.arctan2(np.diff(st["y_m"]), np.diff(st["x_m"]))
    assert np.all(np.abs(heading - math.pi / 2) < math.radians(3))
    loop = _states(_train_plan(None))
    # the default route turns: it covers the district in both directions
    assert np.ptp(loop["x_m"]) > 50.0 and np.ptp(loop["y_m"]) > 50.0


def test_speed_and_frame_rate_set_the_time_step_and_the_spacing():
    fast = TrainRunConfig(route="straight", speed_mps=(25.0, 30.0), frame_period_s=0.2)
    plan = _train_plan(fast, replace(CityConfig(), train_blocks=(5, 2)), frames=30)
    assert np.allclose(np.diff(plan.frame_times_s), 0.2)
    st = _states(plan)
    assert 24.0 < np.median(st["speed_mps"]) < 31.0
    step_m = np.hypot(np.diff(st["x_m"]), np.diff(st["y_m"]))
    assert 4.8 < np.median(step_m) < 6.2
    default = _train_plan(None, frames=30)
    assert np.allclose(np.diff(default.frame_times_s), 0.1)


def test_default_options_give_the_run_without_them():
    with_defaults, without = _train_plan(TrainRunConfig()), _train_plan(None)
    assert np.array_equal(with_defaults.frame_times_s, without.frame_times_s)
    assert np.array_equal(with_defaults.states.x_m, without.states.x_m)
    assert with_defaults.lighting == without.lighting


def test_bad_options_are_refused():
    for bad in (
        TrainRunConfig(route="zigzag"),
        TrainRunConfig(direction="up"),
        TrainRunConfig(frame_period_s=0.0),
        TrainRunConfig(lighting="noon"),
    ):
        with pytest.raises(InvalidInputError):
            replace(TINY, train_run=bad).validate()


def _image(root, seq_id, frame=0):
    path = kitti.sequence_dir(root, seq_id) / "image_0" / f"{frame:06d}.png"
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)


def test_another_district_seed_and_exposure_change_the_training_images(tmp_path):
    generate_dataset(TINY, tmp_path / "base")
    other = replace(TINY, city=replace(CityConfig(), train_seed=77))
    generate_dataset(other, tmp_path / "other")
    darker = replace(TINY, train_run=TrainRunConfig(exposure_ev=-1.5))
    generate_dataset(darker, tmp_path / "dark")
    base, moved, dark = (tmp_path / n for n in ("base", "other", "dark"))
    # the map run is untouched by the run's options; another district keeps the map's
    # streets (its parked cars are one draw over the city's spots: they move)
    assert np.array_equal(_image(base, "00"), _image(dark, "00"))
    main, main_other = (build_city(c.city_config(), c.seed).grids["main"] for c in (TINY, other))
    assert np.array_equal(main.xs, main_other.xs) and np.array_equal(main.ys, main_other.ys)
    # another training district: other images
    assert np.mean(np.abs(_image(base, "01") - _image(moved, "01"))) > 5.0
    # 1.5 EV less exposure: the same view darker (by ~ 2^1.5 before the gamma and clipping)
    assert _image(dark, "01").mean() < 0.75 * _image(base, "01").mean()
    times = np.loadtxt(kitti.sequence_dir(base, "01") / "times.txt")
    assert np.allclose(np.diff(times), 0.1)
