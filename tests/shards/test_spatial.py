"""monoloc.server.storage.spatial on SQLite, on PostgreSQL with PostGIS (migration
0010's GiST index, used by the planner) and on a PostgreSQL where the database's owner may
not create the extension (0010 skips it): the same entries for prior discs, tiles and
coverage, checked against the positions written."""

from __future__ import annotations

import numpy as np
import pytest
from shard_helpers import entry_at
from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url

from monoloc.core.camera import KITTI_CAM0
from monoloc.core.tiles import TileScheme
from monoloc.server.storage.db import create_engine_for_url, make_session_factory, session_scope
from monoloc.server.storage.entries import add_entry
from monoloc.server.storage.maps import create_map, get_or_create_vocabulary
from monoloc.server.storage.migrate import current_revision, upgrade_database
from monoloc.server.storage.spatial import (
    entry_ids_in_tile,
    entry_ids_within,
    has_postgis,
    tile_coverage,
)

SCHEME = TileScheme(100.0, origin_x_m=-20.0, origin_y_m=5.0)


def _fill(url: str) -> tuple[object, int, dict[int, tuple[float, float]]]:
    """A migrated database with map 'm' of 300 entries (and map 'other' of 20 in the same
    area, which no query of 'm' may return): (factory, map id, id -> position)."""
    upgrade_database(url)
    factory = make_session_factory(create_engine_for_url(url))
    rng = np.random.default_rng(4)
    xy = rng.uniform(-260.0, 260.0, (300, 2))
    xy[:6] = [[80.0, 40.0], [79.99, 40.0], [-20.0, 5.0], [-20.0, 105.0], [30, 0], [130, 0]]
    centres = rng.uniform(0, 255, (64, 32)).astype(np.float32)
    positions = {}
    with session_scope(factory) as session:
        vocab, _ = get_or_create_vocabulary(session, centres, "test vocabulary")
        map_id = create_map(session, "m", KITTI_CAM0, vocab.id).id
        other = create_map(session, "other", KITTI_CAM0, vocab.id).id
        for i, (x, y) in enumerate(xy):
            positions[add_entry(session, map_id, entry_at(f"e{i}", x, y))[0].id] = (x, y)
        for i in range(20):
            add_entry(session, other, entry_at(f"o{i}", *rng.uniform(-50, 50, 2)))
    return factory, map_id, positions


def _check_queries(factory, map_id: int, positions: dict[int, tuple[float, float]]) -> None:
    ids = np.array(sorted(positions))
    xy = np.array([positions[i] for i in ids])
    with factory() as session:
        for x, y, r in [(0.0, 0.0, 30.0), (80.0, 40.0, 0.005), (-200.0, 150.0, 75.0), (0, 0, 1e4)]:
            truth = ids[np.hypot(xy[:, 0] - x, xy[:, 1] - y) <= r].tolist()
            assert entry_ids_within(session, map_id, x, y, r) == truth
        tiles = [SCHEME.tile_of(x, y) for x, y in xy]
        for tile in ("0_0", "-1_0", "0_1", "1_0", "-3_-3", "9_9"):
            truth = [int(i) for i, t in zip(ids, tiles, strict=True) if t == tile]
            assert entry_ids_in_tile(session, map_id, SCHEME, tile) == truth
        # the entries on a west or south edge (x = -20 or y = 5 / 105) belong to the tile
        # east / north of it, on both paths
        assert ids[2] in entry_ids_in_tile(session, map_id, SCHEME, "0_0")
        assert ids[3] in entry_ids_in_tile(session, map_id, SCHEME, "0_1")
        counts = tile_coverage(session, map_id, SCHEME)
        assert counts == {t: tiles.count(t) for t in set(tiles)}
        assert sum(counts.values()) == 300


def test_sqlite_answers_from_the_btree(tmp_path):
    url = f"sqlite:///{tmp_path / 'm.db'}"
    factory, map_id, positions = _fill(url)
    assert current_revision(url) == "0010"
    with factory() as session:
        assert not has_postgis(session)
    _check_queries(factory, map_id, positions)


def test_postgis_index_answers_the_same_and_the_planner_uses_it(postgres_url):
    factory, map_id, positions = _fill(postgres_url)
    with factory() as session:
        if not has_postgis(session):
            pytest.fail("PostGIS missing on the test server (make system-deps installs it)")
        index = session.execute(
            text("SELECT indexdef FROM pg_indexes WHERE indexname = 'ix_entries_position_gist'")
        ).scalar_one()
        assert "gist" in index and "st_makepoint(x_m, y_m)" in index.lower()
        session.execute(text("SET enable_seqscan = off"))  # 320 rows: force the choice
        plan = "\n".join(
            row[0]
            for row in session.execute(
                text(
                    "EXPLAIN SELECT id FROM entries WHERE map_id = 1 AND ST_DWithin("
                    "ST_SetSRID(ST_MakePoint(x_m, y_m), 0), ST_SetSRID(ST_MakePoint(0, 0), 0), 30)"
                )
            )
        )
        assert "ix_entries_position_gist" in plan, plan
        session.rollback()
    _check_queries(factory, map_id, positions)


def test_without_the_right_to_create_postgis_0010_skips_and_queries_still_answer(
    postgres_admin_url, caplog
):
    admin = create_engine(postgres_admin_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text("DROP DATABASE IF EXISTS shard_nopostgis WITH (FORCE)"))
        connection.execute(text("DROP ROLE IF EXISTS shard_owner"))
        connection.execute(text("CREATE ROLE shard_owner LOGIN NOSUPERUSER"))
        connection.execute(text("CREATE DATABASE shard_nopostgis OWNER shard_owner"))
    url = (
        make_url(postgres_admin_url)
        .set(username="shard_owner", database="shard_nopostgis")
        .render_as_string(hide_password=False)
    )
    try:
        with caplog.at_level("WARNING"):
            factory, map_id, positions = _fill(url)
        assert current_revision(url) == "0010"
        assert any("cannot create the postgis extension" in r.getMessage() for r in caplog.records)
        with factory() as session:
            assert not has_postgis(session)
        _check_queries(factory, map_id, positions)
        factory.kw["bind"].dispose()
    finally:
        with admin.connect() as connection:
            connection.execute(text("DROP DATABASE IF EXISTS shard_nopostgis WITH (FORCE)"))
            connection.execute(text("DROP ROLE IF EXISTS shard_owner"))
        admin.dispose()


def test_shards_coverage_lists_a_groups_tiles_and_fails_on_a_stray_entry(tmp_path):
    from typer.testing import CliRunner

    from monoloc.cli import _register, app
    from monoloc.core.tiles import ShardGroup, TileTable, write_tile_table

    url = f"sqlite:///{tmp_path / 'g.db'}"
    upgrade_database(url)
    factory = make_session_factory(create_engine_for_url(url))
    centres = np.random.default_rng(0).uniform(0, 255, (64, 32)).astype(np.float32)
    with session_scope(factory) as session:
        vocab, _ = get_or_create_vocabulary(session, centres, "test vocabulary")
        map_id = create_map(session, "city", KITTI_CAM0, vocab.id).id
        for i, x in enumerate((-25.0, -5.0, 10.0, 60.0)):  # tile -1_0 west of x = -20
            add_entry(session, map_id, entry_at(f"c{i}", x, 20.0))
    groups = {"a": ShardGroup("a", "http://a"), "b": ShardGroup("b", "http://b")}
    table = TileTable(SCHEME, "city", groups, {"-1_0": "b", "0_0": "a"})
    path = write_tile_table(tmp_path / "tiles.json", table)
    _register()
    args = ["shards", "coverage", str(path), "--database-url", url]
    stray = CliRunner().invoke(app, [*args, "--group", "a"])
    assert stray.exit_code == 1, stray.output
    assert "0_0\t3\tok" in stray.output and "-1_0\t1\tbelongs to b" in stray.output
    assert "1 entries outside group a's tiles" in stray.output
    with session_scope(factory) as session:
        session.execute(text("DELETE FROM entries WHERE x_m < -20"))
    clean = CliRunner().invoke(app, [*args, "--group", "a"])
    assert clean.exit_code == 0 and clean.output == "0_0\t3\tok\n", clean.output
    unknown = CliRunner().invoke(app, [*args, "--group", "c"])
    assert unknown.exit_code != 0 and "group 'c' is not in" in str(unknown.exception)
