"""`monoloc map bulk-tile` (server/ingest/bulk.py) on a rendered sim city: a few hundred
entries tiled into a real SQLite file and into PostgreSQL keep the map's invariants
(checked rows, one version and one change-log row per entry, the map's vocabulary), a
rerun adds nothing, and over HTTP a query frame of the city localizes on a turned,
perturbed tile copy at the tile's pose."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import planar_from_T_world_from_cam
from monoloc.server.ingest.bulk import (
    TileConfig,
    bulk_tile,
    perturb_descriptors,
    prepare_tiling,
    tile_hash,
)
from monoloc.server.settings import Settings
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope
from monoloc.server.storage.migrate import upgrade_database
from monoloc.server.storage.models import Entry, MapChange
from monoloc.server.vision.binary_code import vlad_binary_code
from monoloc.server.vision.vlad import compute_vlad

ADMIN_KEY = "mlk_" + "B" * 43
FRAMES = 16
ENTRIES = 7 * FRAMES + 11  # the last tile partial


@pytest.fixture(scope="module")
def city(tmp_path_factory) -> Path:
    """A map run and a query run of one sim street, KITTI size."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig

    root = tmp_path_factory.mktemp("bulk_city")
    generate_dataset(
        GenerateConfig(
            seed=3,
            runs=("map", "query"),
            max_frames=FRAMES,
            lidar=LidarConfig(azimuth_steps=1500),
        ),
        root,
    )
    return root


@pytest.fixture(params=["sqlite", "postgresql"])
def settings(request, tmp_path) -> Settings:
    extra = {}
    if request.param == "postgresql":
        extra["database_url"] = request.getfixturevalue("postgres_url")
    return Settings(data_dir=tmp_path / "data", bootstrap_admin_key=ADMIN_KEY, **extra)


def _source_and_tiles(settings: Settings, city: Path):
    from monoloc.server.ingest.manage import create_map, ingest_source
    from monoloc.server.ingest.sources import read_kitti_sequence

    upgrade_database(settings.database_url)
    engine = create_engine_for(settings)
    factory = make_session_factory(engine)
    run = read_kitti_sequence(city, "00")
    create_map(factory, "city", run.intrinsics)
    ingest_source(factory, "city", run)
    create_map(factory, "big", run.intrinsics)
    return engine, factory


def _localize(settings: Settings, map_id: int, image_path: Path, prior_xy, radius_m: float):
    from monoloc.server.api.app import create_app

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from fastapi.testclient import TestClient
    with TestClient(create_app(settings)) as client:
        fields = {"prior_x_m": repr(float(prior_xy[0])), "prior_y_m": repr(float(prior_xy[1]))}
        fields["prior_radius_m"] = repr(radius_m)
        r = client.post(
            f"/v1/maps/{map_id}/localize",
            files={"image": ("frame.png", image_path.read_bytes(), "image/png")},
            data={**fields, "seed": "1"},
            headers={"X-API-Key": ADMIN_KEY},
        )
    assert r.status_code == 200, r.text
    return r.json()


def test_bulk_tile_keeps_the_invariants_and_a_query_localizes_on_a_copy(settings, city):
    from monoloc.server.ingest.sources import read_kitti_sequence

    engine, factory = _source_and_tiles(settings, city)
    summary = bulk_tile(factory, "big", ["city"], TileConfig(entries=ENTRIES, batch_rows=64))
    with session_scope(factory) as session:
        source = maps_repo.get_map_by_name(session, "city")
        big = maps_repo.get_map_by_name(session, "big")
        rows = session.execute(
            select(Entry.id, Entry.source_image_hash, Entry.vocabulary_id, Entry.run_id)
            .where(Entry.map_id == big.id)
            .order_by(Entry.id)
        ).all()
        changes = session.execute(
            select(MapChange.version, MapChange.kind, MapChange.entry_id)
            .where(MapChange.map_id == big.id)
            .order_by(MapChange.version)
        ).all()
        source_data = entries_repo.get_entry_data(
            session, [s.id for s in entries_repo.list_entries(session, source.id, limit=1000)]
        )
        by_hash = {r[1]: r[0] for r in rows}
        # tile 0 is the source unturned; tile 3 is turned and perturbed
        plain = entries_repo.get_entry_data(
            session, [by_hash[tile_hash(0, e.summary.source_image_hash)] for e in source_data]
        )
        copies = entries_repo.get_entry_data(
            session, [by_hash[tile_hash(3, e.summary.source_image_hash)] for e in source_data]
        )
        vocabulary = maps_repo.get_vocabulary(session, big.vocabulary_id)
    n_source = source.n_entries
    assert n_source >= FRAMES // 2
    assert summary.entries_added == summary.entries_total == big.n_entries == ENTRIES
    assert summary.tiles == -(-ENTRIES // n_source)
    # one version and one 'add' row of the log per entry, in id order, no gap
    assert big.version == ENTRIES
    assert [c[0] for c in changes] == list(range(1, ENTRIES + 1))
    assert {c[1] for c in changes} == {"add"}
    assert [c[2] for c in changes] == [r[0] for r in rows]
    assert {r[2] for r in rows} == {big.vocabulary_id} and {r[3] for r in rows} == {None}

    # the copies: the unturned tile keeps the source's arrays; a perturbed one has its
    # descriptors changed at about the configured rate, its VLAD and code recomputed from
    # them, its pose one rigid move of the source's, its 3D points in the camera frame
    T_moves = []
    for original, same, copy in zip(source_data, plain, copies, strict=True):
        assert np.array_equal(same.descriptors, original.descriptors)
        assert np.array_equal(same.vlad, original.vlad)
        assert np.array_equal(copy.points_cam, original.points_cam)
        changed = np.unpackbits(copy.descriptors ^ original.descriptors).mean()
        assert 0.05 < changed < 0.3, changed
        assert np.allclose(copy.vlad, compute_vlad(copy.descriptors, vocabulary.centres), atol=1e-5)
        assert np.array_equal(copy.code, vlad_binary_code(copy.vlad))
        T_moves.append(copy.T_world_from_cam @ np.linalg.inv(original.T_world_from_cam))
    assert np.allclose(T_moves, T_moves[0], atol=1e-6)
    T_tile = T_moves[0]
    assert abs(np.arctan2(T_tile[1, 0], T_tile[0, 0])) > 1e-3  # turned
    assert np.linalg.norm(T_tile[:2, 3]) > 50.0  # and moved off the source

    # a rerun adds nothing; a larger target adds only the difference
    again = bulk_tile(factory, "big", ["city"], TileConfig(entries=ENTRIES, batch_rows=64))
    assert again.entries_added == 0 and again.version == ENTRIES
    bigger = TileConfig(entries=40 * n_source)  # more tiles: the first keep their place
    assert np.allclose(
        prepare_tiling(factory, "big", ["city"], bigger).tiles[3].T_world_from_source, T_tile
    )
    more = bulk_tile(factory, "big", ["city"], TileConfig(entries=ENTRIES + 5))
    assert more.entries_added == 5 and more.version == ENTRIES + 5
    # a map written at once, in other batches, holds the same entries
    from monoloc.server.ingest.manage import create_map

    create_map(factory, "once", big.camera)
    bulk_tile(factory, "once", ["city"], TileConfig(entries=ENTRIES + 5, batch_rows=1000))
    assert _descriptors_by_hash(factory, "once") == _descriptors_by_hash(factory, "big")
    engine.dispose()

    # a query frame of the city, with a prior on the turned tile, localizes there
    query = read_kitti_sequence(city, "01").frames[FRAMES // 2]
    expected = planar_from_T_world_from_cam(T_tile @ query.T_world_from_cam)
    answer = _localize(settings, big.id, query.image_path, expected[:2], radius_m=15.0)
    best = max(answer["hypotheses"], key=lambda h: h["n_inliers"])
    found = np.array([best["pose"]["x_m"], best["pose"]["y_m"]])
    assert np.linalg.norm(found - expected[:2]) < 1.0, (found, expected)


def _descriptors_by_hash(factory, name: str) -> dict[str, bytes]:
    with session_scope(factory) as session:
        map_id = maps_repo.get_map_by_name(session, name).id
        rows = session.execute(
            select(Entry.source_image_hash, Entry.descriptors, Entry.T_world_from_cam).where(
                Entry.map_id == map_id
            )
        )
        return {h: bytes(d) + bytes(T) for h, d, T in rows}


def test_perturbation_rates():
    rng = np.random.default_rng(0)
    descriptors = rng.integers(0, 256, (2000, 32), dtype=np.uint8)
    donors = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    flipped = perturb_descriptors(descriptors, donors, 4, 0.0, rng)
    assert abs(np.unpackbits(flipped ^ descriptors).mean() - 1 / 16) < 0.003
    swapped = perturb_descriptors(descriptors, donors, 16, 0.25, rng)
    bits_changed = np.unpackbits(swapped ^ descriptors, axis=1).sum(axis=1)
    assert (bits_changed > 32).mean() == 0.25  # random rows differ in ~128 of 256 bits


def test_bulk_tile_cli_refuses_bad_input(tmp_path):
    from monoloc.core.camera import KITTI_CAM0
    from monoloc.server.ingest.manage import create_map

    settings = Settings(data_dir=tmp_path / "data")
    upgrade_database(settings.database_url)
    factory = make_session_factory(create_engine_for(settings))
    create_map(factory, "big", KITTI_CAM0)
    create_map(factory, "other-camera", KITTI_CAM0.scaled(0.5))
    env = {**os.environ, "MONOLOC_DATA_DIR": str(tmp_path / "data")}
    for args, message in (
        (["--from", "nowhere", "--entries", "10"], "nowhere"),
        (["--from", "big", "--entries", "10"], "its own source"),
    ):
        done = subprocess.run(
            [sys.executable, "-m", "monoloc.cli", "map", "bulk-tile", "big", *args],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 1, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], done.stderr
    with pytest.raises(InvalidInputError, match="has camera"):
        bulk_tile(factory, "big", ["other-camera"], TileConfig(entries=10))


def test_tile_config_refuses_bad_values():
    for bad in (
        dict(entries=0),
        dict(entries=5, swap_share=1.0),
        dict(entries=5, flip_halvings=0),
        dict(entries=5, columns=0),
    ):
        with pytest.raises(InvalidInputError):
            TileConfig(**bad).validate()
