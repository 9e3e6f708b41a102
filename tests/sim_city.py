"""A small sim city ingested into a real SQLite map, for the tests that localize frames
in process through the map registry (a module of its own: tests directories are not
packages)."""

from __future__ import annotations

from pathlib import Path


def ingested_city(root: Path, seed: int = 5, frames: int = 40, fleet: bool = False):
    """(MapRegistry holding map 1, the query run): the sim's map and query runs at full
    KITTI resolution, ``frames`` each, the map run ingested from its LiDAR. ``fleet``:
    the dataset also holds the ``fleet`` run (the query's drive by issue 48's fleet
    camera; :func:`read_fleet_run`), the map and query runs unchanged."""
    from monoloc.server.ingest.manage import create_map, ingest_source
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.map_registry import MapRegistry
    from monoloc.server.settings import Settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory
    from monoloc.server.storage.migrate import upgrade_database
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig

    generate_dataset(
        GenerateConfig(
            seed=seed,
            runs=("map", "query", "fleet") if fleet else ("map", "query"),
            max_frames=frames,
            lidar=LidarConfig(azimuth_steps=1500),
        ),
        root,
    )
    settings = Settings(data_dir=root / "data")
    upgrade_database(settings.database_url)
    factory = make_session_factory(create_engine_for(settings))
    map_run, query_run = read_kitti_sequence(root, "00"), read_kitti_sequence(root, "01")
    create_map(factory, "city", map_run.intrinsics)
    ingest_source(factory, "city", map_run)
    return MapRegistry(factory, settings.index_dir), query_run


def read_fleet_run(root: Path):
    """The ``fleet`` run of an :func:`ingested_city` (``fleet=True``) as a server source,
    with the camera its camera.json gives (lens included)."""
    import dataclasses

    from monoloc.core.formats import kitti, tum
    from monoloc.server.ingest.sources import read_kitti_sequence

    run = read_kitti_sequence(root, "02")
    camera = tum.read_run_camera(kitti.sequence_dir(root, "02"), run.frames[0].image_path)
    return dataclasses.replace(run, intrinsics=camera)
