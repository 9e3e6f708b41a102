"""Never lost for good (issue 13.3): the vehicle's loop against a fake map whose
retrieval respects the prior and whose facades repeat along a stretch of the route.
A kidnapped start, a lock on an aliased place and injected wrong hypotheses all
recover; a few frames that contradict the vehicle's motion do not re-seed the filter."""

from __future__ import annotations

import math

import numpy as np

from monoloc.client.api import LocalizeAnswer
from monoloc.client.motion import advance
from monoloc.client.particle_filter import FilterConfig
from monoloc.client.tracking import PriorConfig, Tracker, track
from monoloc.client.trajectory import time_to_recover
from monoloc.core.measurement import Hypotheses, MeasurementModel

DT_S, SPEED_MPS = 0.1, 8.0
ALIAS_FRAMES = 20  # the facades repeat every 16 m: 20 frames at 8 m/s and 10 Hz


def _route(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (n,), signals (n, 2) and truth (n, 3): straight, a left turn, straight."""
    rates = np.zeros(n)
    rates[n // 3 : n // 3 + 30] = 0.4
    truth = [np.array([0.0, 0.0, 0.2])]
    for rate in rates[:-1]:
        truth.append(advance(truth[-1][None], SPEED_MPS, rate, DT_S)[0])
    signals = np.stack([np.full(n, SPEED_MPS), rates], axis=1)
    return np.arange(n) * DT_S, signals, np.array(truth)


class RepetitiveMap:
    """Answers frame i with hypotheses of the places whose map entries the prior lets
    retrieval reach: the true place (3 hypotheses), and, on the frames in ``repetitive``,
    the place ALIAS_FRAMES ahead whose facades look the same (1 hypothesis; 2 when the
    true place is out of reach). ``injected`` frames get the given poses instead."""

    def __init__(self, truth, repetitive=range(0), injected=None, seed=0) -> None:
        self.truth, self.repetitive = truth, set(repetitive)
        self.injected = injected or {}
        self.rng = np.random.default_rng(seed)
        self.priors = []

    def _near(self, pose: np.ndarray, n: int) -> np.ndarray:
        return pose + self.rng.normal(0.0, [0.05, 0.05, 0.003], size=(n, 3))

    def localize(self, i, prior=None, k=None) -> LocalizeAnswer:
        self.priors.append(prior)
        if i in self.injected:
            poses = np.atleast_2d(self.injected[i])
        else:
            reach = (lambda p: True) if prior is None else (lambda p: prior.mask(p[None])[0])
            true, alias = self.truth[i], self.truth[min(i + ALIAS_FRAMES, len(self.truth) - 1)]
            parts = []
            if reach(true):
                parts.append(self._near(true, 3))
            if i in self.repetitive and reach(alias):
                parts.append(self._near(alias, 1 if parts else 2))
            poses = np.vstack(parts) if parts else np.zeros((0, 3))
        hyps = Hypotheses(poses, poses - [2.0, 0.0, 0.0], np.full(len(poses), 0.9))
        return LocalizeAnswer(hyps, None, {"total": 1.0}, {})


def _drive(n, localizer, start_world=None, seed=3, model=None):
    times, signals, truth = _route(n)
    tracker = Tracker(
        FilterConfig(n_particles=400),
        model or MeasurementModel(),
        np.random.default_rng(seed),
        times,
        signals,
    )
    if start_world is not None:
        tracker.filter.initialise(start_world, 0.5, math.radians(2.0))
    estimates = track(tracker, localizer, range(n))
    error = np.linalg.norm(estimates[:, :2] - truth[:, :2], axis=1)
    return tracker, error, times


def test_a_kidnapped_start_widens_the_prior_searches_the_map_and_recovers():
    n = 120
    _, _, truth = _route(n)
    localizer = RepetitiveMap(truth)
    # initialised 40 m to the side of the truth: the prior's disc holds no right entry
    start = truth[0] + [0.0, 40.0, 0.0]
    tracker, error, times = _drive(n, localizer, start)
    radii = [p.radius_m if p is not None else math.inf for p in localizer.priors]
    assert radii[1] == PriorConfig().min_radius_m  # no hypotheses yet: a normal prior
    assert max(r for r in radii if r < math.inf) > 40.0  # then wider, until truth is in
    assert tracker.filter.n_reseeds == 1
    recover_s = time_to_recover(error, times, since=0, tolerance_m=0.3)
    assert recover_s < 1.5, recover_s
    assert error[-60:].max() < 0.3


def test_a_lock_on_repeating_facades_ends_with_the_repetition():
    n = 150
    _, _, truth = _route(n)
    repetitive = range(0, 50)
    localizer = RepetitiveMap(truth, repetitive)
    # kidnapped onto the aliased place: while the facades repeat, the hypotheses there
    # move like the car and the filter cannot tell; once they stop, it must come back
    tracker, error, times = _drive(n, localizer, truth[ALIAS_FRAMES])
    assert np.median(error[5:45]) > 10.0
    recover_s = time_to_recover(error, times, since=50, tolerance_m=0.3)
    assert recover_s < 2.5, recover_s
    assert error[-50:].max() < 0.3


def test_a_wrong_place_that_moves_like_the_car_for_fewer_frames_than_the_track_is_ignored():
    n = 100
    _, _, truth = _route(n)
    # 10 frames of a consistent wrong place 35 m off (the right place out of sight):
    # enough agreeing frames for a re-seed, but fewer than the 20 that agreed with the
    # filter's own track before them
    injected = {i: truth[i] + [25.0, -25.0, 0.0] for i in range(40, 50)}
    tracker, error, _ = _drive(n, RepetitiveMap(truth, injected=injected))
    assert tracker.filter.n_reseeds == 0
    assert error[5:].max() < 0.3


def test_injected_wrong_hypotheses_that_outlast_the_track_are_followed_and_left_again():
    n = 160
    _, _, truth = _route(n)
    # 30 frames of a consistent wrong place 35 m off: it outweighs the track after 11
    injected = {i: truth[i] + [25.0, -25.0, 0.0] for i in range(40, 70)}
    localizer = RepetitiveMap(truth, injected=injected)
    tracker, error, times = _drive(n, localizer)
    assert error[30:40].max() < 0.3
    assert tracker.filter.n_reseeds >= 2 and error[60:70].min() > 10.0  # it did follow
    recover_s = time_to_recover(error, times, since=70, tolerance_m=0.3)
    assert recover_s < 2.5, recover_s
    assert error[-40:].max() < 0.3


def _turned_street(truth: np.ndarray) -> np.ndarray:
    """The route turned by 90 degrees and moved 115 m away: a street whose facades look
    like the car's and whose hypotheses move like the car, on another heading."""
    turn = np.array([[0.0, -1.0], [1.0, 0.0]])
    elsewhere = truth.copy()
    elsewhere[:, :2] = truth[:, :2] @ turn.T + [80.0, 83.0]
    elsewhere[:, 2] += math.pi / 2
    return elsewhere


def test_after_a_silence_an_aliased_street_elsewhere_does_not_take_the_filter():
    # Found by the city's closed-loop study (a half-route run): hypotheses stopped for
    # about 3 s on the right street; the whole-map search then found a street 115 m away,
    # turned by 90 degrees, whose hypotheses moved like the car, and a few frames of them
    # re-seeded the filter there. Here 4 s of it, every frame, after 3 s of silence.
    n = 140
    _, _, truth = _route(n)
    elsewhere = _turned_street(truth)
    silent = {i: np.zeros((0, 3)) for i in range(25, 55)}
    injected = silent | {i: np.repeat(elsewhere[i][None], 3, axis=0) for i in range(55, 95)}
    tracker, error, _ = _drive(n, RepetitiveMap(truth, injected=injected))
    assert np.hypot(*(elsewhere[55, :2] - truth[55, :2])) > 100.0
    assert tracker.filter.n_reseeds == 0
    assert error[5:].max() < 0.5


def test_after_a_long_silence_off_the_map_an_aliased_street_does_not_take_the_filter():
    # Found by fresh seed 3197: the car drove on beyond the map's last street, no
    # hypothesis for 10 s, then 4 frames of a street 157 m away whose facades look like
    # the unmapped one's, moving like the car, re-seeded the filter there for good. The
    # track's support had aged out (FilterConfig.track_memory_frames); a place that far
    # beyond what the dead reckoning can have drifted must outweigh it all the same.
    n = 220
    _, _, truth = _route(n)
    silent = {i: np.zeros((0, 3)) for i in range(30, 160)}
    elsewhere = {
        i: np.repeat((truth[i] + [150.0, 40.0, 0.0])[None], 3, axis=0) for i in range(160, 168)
    }
    tracker, error, _ = _drive(n, RepetitiveMap(truth, injected=silent | elsewhere))
    assert tracker.filter.n_reseeds == 0
    assert error[5:].max() < 1.0


def test_after_a_long_silence_a_wrong_track_is_left_once_contradicted_long_enough():
    # The other side: a filter locked on a wrong place (supported there, then silent for
    # 13 s) leaves it once the right place's frames outweigh that support (never lost for
    # good), however far the right place lies
    n = 240
    _, _, truth = _route(n)
    wrong = {i: np.repeat((truth[i] + [150.0, 40.0, 0.0])[None], 3, axis=0) for i in range(30)}
    silent = {i: np.zeros((0, 3)) for i in range(30, 160)}
    localizer = RepetitiveMap(truth, injected=wrong | silent)
    tracker, error, times = _drive(n, localizer, truth[0] + [150.0, 40.0, 0.0])
    assert error[5:160].min() > 100.0
    recover_s = time_to_recover(error, times, since=160, tolerance_m=0.3)
    assert recover_s < 2.5, recover_s
    assert error[-50:].max() < 0.3


def test_a_lock_on_a_street_turned_the_other_way_ends_once_its_support_has_aged():
    # The other side of the rule above: a filter started on the turned street, supported
    # there for 3 s, leaves it once the right street's frames outweigh what is left of
    # that support in the last 10 s (FilterConfig.track_memory_frames)
    n = 200
    _, _, truth = _route(n)
    elsewhere = _turned_street(truth)
    injected = {i: np.repeat(elsewhere[i][None], 2, axis=0) for i in range(0, 30)}
    tracker, error, times = _drive(n, RepetitiveMap(truth, injected=injected), elsewhere[0])
    assert error[5:30].min() > 100.0
    recover_s = time_to_recover(error, times, since=30, tolerance_m=0.3)
    assert recover_s < 10.0, recover_s
    assert error[-50:].max() < 0.3


def test_frames_that_agreed_with_the_filter_do_not_support_a_candidate_beside_it():
    # Found on fresh seed 6121 (filter seed 1): four frames of wrong hypotheses a few
    # decimetres off, too far for a calibrated (tight) Sigma1, re-seeded the filter onto
    # the last of them: within the re-seed tolerance (1 m) the twenty right frames before
    # them "agreed" with that candidate too, though they lay nearer the filter. A past
    # frame supports a candidate only where it lies nearer the candidate than the filter.
    n = 100
    _, _, truth = _route(n)
    tight = MeasurementModel(Sigma1=np.diag([0.05**2, 0.05**2, math.radians(0.3) ** 2]))
    # 0.39 m and 2 deg off: unlikely under the tight Sigma1, within the re-seed tolerances
    wrong = [0.3, 0.25, math.radians(2.0)]
    injected = {i: np.repeat((truth[i] + wrong)[None], 3, axis=0) for i in range(40, 44)}
    tracker, error, _ = _drive(n, RepetitiveMap(truth, injected=injected), model=tight)
    assert tracker.filter.n_reseeds == 0
    assert error[5:].max() < 0.2


def test_a_few_frames_that_contradict_the_motion_do_not_reseed():
    n = 100
    _, _, truth = _route(n)
    rng = np.random.default_rng(11)
    # eight frames of confident wrong places that jump about (each frame elsewhere),
    # then three frames of one wrong place that does move like the car
    injected = {i: truth[i] + [*rng.uniform(-50, 50, 2), 0.0] for i in range(30, 38)}
    injected.update({i: truth[i] + [0.0, 30.0, 0.0] for i in range(60, 63)})
    localizer = RepetitiveMap(truth, injected=injected)
    tracker, error, _ = _drive(n, localizer)
    assert tracker.filter.n_reseeds == 0
    assert np.nanmax(error[5:]) < 0.3
