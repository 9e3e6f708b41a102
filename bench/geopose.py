"""Cost of GeoPose answers: building a localize answer of 10 hypotheses with and without
the map's geographic reference (the baseline, measured in the same run), and one
GeoPose converted alone. Writes bench/results/geopose.json.

The answer is built by the server's own converter (``monoloc.server.api.convert``) from
synthetic hypotheses, so the figure is the extra time a geo-referenced map adds to each
localized frame, not the localization itself.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from monoloc.core.geo import GeoOrigin, GeoReference
from monoloc.core.geometry import T_world_from_cam_planar
from monoloc.server.api.convert import localize_response
from monoloc.server.localize import LocalizationResult, PoseHypothesis

RESULTS = Path(__file__).parent / "results"
N_HYPOTHESES = 10


def _result(rng: np.random.Generator) -> LocalizationResult:
    hypotheses = []
    for i in range(N_HYPOTHESES):
        x, y, yaw = rng.uniform(-500, 500), rng.uniform(-500, 500), rng.uniform(-3, 3)
        T = T_world_from_cam_planar(x, y, yaw, 1.65)
        planar = np.array([x, y, yaw])
        hypotheses.append(
            PoseHypothesis(
                entry_id=i,
                T_world_from_cam=T,
                pose_world=planar,
                entry_pose_world=planar,
                e_vlad=0.7,
                n_inliers=100 - i,
                n_matches=200,
                reprojection_error_px=0.8,
            )
        )
    return LocalizationResult(
        hypotheses=hypotheses,
        retrieved_ids=np.arange(N_HYPOTHESES),
        retrieved_distances=np.full(N_HYPOTHESES, 0.7),
        rejected=[],
        n_features=1000,
        timings_ms={},
    )


def p50_us(fn, repeats: int = 400) -> float:
    for _ in range(20):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1e6)
    return float(np.median(times))


def main() -> None:
    rng = np.random.default_rng(0)
    result = _result(rng)
    stored = GeoReference.from_origin(GeoOrigin(52.516275, 13.377704, 74.0, 30.0)).to_dict()

    def plain():
        localize_response(1, 1, result, {}, 0)

    def geo():  # as a request does: parse the stored reference, then convert
        localize_response(1, 1, result, {}, 0, GeoReference.from_dict(stored))

    ref = GeoReference.from_dict(stored)
    one = result.hypotheses[0].T_world_from_cam
    figures = {
        "hypotheses": N_HYPOTHESES,
        "answer_plain_us_p50": p50_us(plain),
        "answer_with_geopose_us_p50": p50_us(geo),
        "one_geopose_us_p50": p50_us(lambda: ref.geopose(one)),
    }
    figures["geopose_overhead_us_p50"] = (
        figures["answer_with_geopose_us_p50"] - figures["answer_plain_us_p50"]
    )
    print(f"localize answer with {N_HYPOTHESES} hypotheses, p50 (one thread):")
    print(f"  baseline, no geo reference : {figures['answer_plain_us_p50']:8.1f} us")
    print(f"  with GeoPoses              : {figures['answer_with_geopose_us_p50']:8.1f} us")
    print(f"  overhead per frame         : {figures['geopose_overhead_us_p50']:8.1f} us")
    print(f"  one GeoPose alone          : {figures['one_geopose_us_p50']:8.1f} us")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "geopose.json").write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
