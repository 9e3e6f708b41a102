"""``monoloc localize``: one image against a map, hypotheses and per-stage timings.
Re-exported by ``server/cli.py``; shares the database options of server/map_cli.py."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from monoloc.server.map_cli import DataDir, MapRef, open_database


def localize(
    image: Annotated[Path, typer.Argument(help="Query image (PNG/JPEG).")],
    map_ref: MapRef,
    prior: Annotated[
        str | None,
        typer.Option(
            help="x,y,radius (m) or x,y,radius,yaw_deg,tol_deg: only entries inside compete."
        ),
    ] = None,
    k: Annotated[int, typer.Option(help="Entries retrieved.")] = 10,
    json_out: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
    seed: Annotated[int, typer.Option(help="RANSAC seed.")] = 0,
    repeat: Annotated[
        int,
        typer.Option(
            min=0,
            help="Localize the image this many more times and show their p50 stage timings "
            "(warm) beside the first query's (cold).",
        ),
    ] = 0,
    data_dir: DataDir = None,
) -> None:
    """Localize one image against a map: hypotheses and per-stage timings."""
    import time

    import numpy as np

    from monoloc.server.index.warmup import warm_up as warm_up_index
    from monoloc.server.ingest.common import decode_gray, read_bytes
    from monoloc.server.ingest.manage import find_map, parse_prior
    from monoloc.server.ingest.report import print_localization
    from monoloc.server.localize import LocalizeConfig
    from monoloc.server.map_registry import MapRegistry
    from monoloc.server.threads import limit_threads
    from monoloc.server.vision.warmup import warm_up as warm_up_vision

    # A one-shot process loads its compiled kernels once; do it before the query so that the
    # stage timings printed hold no compilation, and say what it cost.
    start = time.perf_counter()
    warm_up_vision()
    warm_up_index()
    warm_up_s = time.perf_counter() - start
    settings, factory = open_database(None, data_dir)
    record = find_map(factory, map_ref)
    gray = decode_gray(read_bytes(image, "image"), image)
    registry = MapRegistry(factory, settings.index_dir)
    rng = np.random.default_rng(seed)
    config = LocalizeConfig(k=k)
    with limit_threads(settings):  # the server's thread counts, so its figures compare
        start = time.perf_counter()
        registry.get(record.id)
        map_load_s = time.perf_counter() - start
        result, version = registry.localize(
            record.id, gray, config, rng, prior=parse_prior(prior), k=k
        )
        repeats = [
            registry.localize(record.id, gray, config, rng, prior=parse_prior(prior), k=k)[0]
            for _ in range(repeat)
        ]
    print_localization(
        record,
        result,
        version,
        json_out,
        warm_up_s=warm_up_s,
        map_load_s=map_load_s,
        warm_timings_ms=[r.timings_ms for r in repeats],
    )
