"""Filter step time: 1000 particles, 10 hypotheses (target <= 2 ms per step).

Baseline measured in the same run: a per-particle Python loop over the same mixture
(what an unvectorised implementation costs). Writes bench/results/filter.json.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from monoloc.client.particle_filter import FilterConfig, ParticleFilter
from monoloc.core.measurement import Hypotheses, MeasurementModel, gaussian_log_pdf, log_likelihood

RESULTS = Path(__file__).parent / "results"


def make_hypotheses(rng: np.random.Generator, truth: np.ndarray, n: int) -> Hypotheses:
    poses = truth + rng.normal(scale=[0.2, 0.2, 0.01], size=(n, 3))
    entries = truth + rng.normal(scale=[2.0, 2.0, 0.05], size=(n, 3))
    return Hypotheses(poses, entries, np.full(n, 0.9))


def loop_log_likelihood(particles, hyps, model):
    out = np.empty(len(particles))
    for p, x in enumerate(particles):
        terms = []
        for z, entry, ev in zip(hyps.pose_world, hyps.entry_pose_world, hyps.e_vlad, strict=True):
            r1 = x - (z + model.mu1)
            r1[2] = math.remainder(r1[2], 2 * math.pi)
            e = (
                np.array(
                    [
                        ev,
                        entry[0] - x[0],
                        entry[1] - x[1],
                        math.remainder(entry[2] - x[2], 2 * math.pi),
                    ]
                )
                - model.mu2
            )
            terms.append(
                gaussian_log_pdf(r1[None], model.Sigma1)[0]
                + gaussian_log_pdf(e[None], model.Sigma2)[0]
            )
        out[p] = np.logaddexp.reduce(terms)
    return out


def p50_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1e3)
    return float(np.median(times))


def main() -> None:
    rng = np.random.default_rng(0)
    truth = np.array([10.0, 20.0, 0.5])
    pf = ParticleFilter(FilterConfig(n_particles=1000), MeasurementModel(), rng)
    pf.initialise(truth, 1.0, 0.05)
    hyps = make_hypotheses(rng, truth, 10)
    step_ms = p50_ms(lambda: pf.step(0.1, 8.0, 0.02, hyps), 300)
    vec_ms = p50_ms(lambda: log_likelihood(pf.particles, hyps, pf.model), 300)
    loop_ms = p50_ms(lambda: loop_log_likelihood(pf.particles, hyps, pf.model), 3)
    result = {
        "n_particles": 1000,
        "n_hypotheses": 10,
        "step_p50_ms": step_ms,
        "likelihood_vectorised_p50_ms": vec_ms,
        "likelihood_loop_baseline_p50_ms": loop_ms,
        "speedup_vs_loop": loop_ms / vec_ms,
        "target_step_ms": 2.0,
        "meets_target": step_ms <= 2.0,
    }
    print(f"{'stage':<38}{'p50 ms':>10}{'baseline ms':>14}{'target':>10}")
    print(f"{'filter step (predict+update+estimate)':<38}{step_ms:>10.3f}{'':>14}{'<= 2.0':>10}")
    print(f"{'mixture likelihood (vectorised)':<38}{vec_ms:>10.3f}{loop_ms:>14.1f}{'':>10}")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "filter.json").write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
