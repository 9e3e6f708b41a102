"""Generate a KITTI-like dataset of one city: plan the runs (``monoloc.sim.urban.runs``),
render them in chunks (``monoloc.sim.urban.record``), write dataset.json
(``monoloc.sim.urban.info``).

Generation is deterministic in the seed: the same config gives the same bytes, whatever
the number of worker processes.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from monoloc.sim import kitti_writer as kw
from monoloc.sim.summary import DatasetSummary, SequenceSummary
from monoloc.sim.urban.city import build_city
from monoloc.sim.urban.info import dataset_info, kitti_world
from monoloc.sim.urban.record import prepare_run_files, render_chunk, write_run_metadata
from monoloc.sim.urban.runs import plan_runs

CHUNK_FRAMES = 25


def generate_urban_dataset(
    config,
    out_dir: Path,
    progress: Callable[[str, int, int], None] | None = None,
) -> DatasetSummary:
    """Write the urban dataset of ``config`` (a validated
    ``monoloc.sim.generate.GenerateConfig``) under ``out_dir``; ``progress(seq_id, done,
    total)`` is called as frames are written."""
    start = time.perf_counter()
    out_dir = Path(out_dir)
    city = build_city(config.city_config(), config.seed)
    plans = plan_runs(city, config)
    written = {p.seq_id: prepare_run_files(p, config, out_dir) for p in plans}
    defining = next((p for p in plans if p.kind == "map"), plans[0])
    frames = kitti_world(written[defining.seq_id].T_written[0])
    for plan in plans:
        write_run_metadata(plan, written[plan.seq_id], frames, config, out_dir)
    jobs = [
        (plan, a, min(a + CHUNK_FRAMES, len(plan.frame_times_s)))
        for plan in plans
        for a in range(0, len(plan.frame_times_s), CHUNK_FRAMES)
    ]
    done = dict.fromkeys((p.seq_id for p in plans), 0)
    totals = {p.seq_id: len(p.frame_times_s) for p in plans}

    def report(plan, a, b):
        done[plan.seq_id] += b - a
        if progress is not None:
            progress(plan.seq_id, done[plan.seq_id], totals[plan.seq_id])

    if config.workers <= 1:
        for plan, a, b in jobs:
            render_chunk(config, plan, a, b, out_dir)
            report(plan, a, b)
    else:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=config.workers, mp_context=ctx) as pool:
            futures = {
                pool.submit(render_chunk, config, plan, a, b, out_dir): (plan, a, b)
                for plan, a, b in jobs
            }
            for fut in as_completed(futures):
                fut.result()
                report(*futures[fut])
    kw.write_dataset_json(out_dir, dataset_info(config, plans, written, frames))
    summaries = [
        SequenceSummary(p.seq_id, p.kind, p.lighting.name, len(p.frame_times_s), p.route_length_m)
        for p in plans
    ]
    return DatasetSummary(root=out_dir, sequences=summaries, seconds=time.perf_counter() - start)
