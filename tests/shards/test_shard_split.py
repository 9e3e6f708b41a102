"""`monoloc shards split` (server/ingest/split.py): a map in one SQLite file split into
two groups' databases (SQLite and PostgreSQL). Every entry of a group's tiles lands in
that group's database and in no other, with its arrays, tags, image, run and vocabulary;
entries of tiles no group serves stay behind; each copy keeps the map's invariants (one
version and one ``add`` row per entry), `shards coverage` finds nothing misplaced, a
rerun copies nothing, an interrupted copy resumes to the full set, the refusals are one
line and write nothing; and a frame of a tiny sim street localizes on the group that
holds its tile, served by ``create_app`` from the copy."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from shard_helpers import entry_at
from sqlalchemy import func, select

from monoloc import cli
from monoloc.core.camera import KITTI_CAM0
from monoloc.core.geo import GeoOrigin, GeoReference
from monoloc.core.tiles import ShardGroup, TileScheme, TileTable, write_tile_table
from monoloc.server.ingest.split import same_database, split_map
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage import runs as runs_repo
from monoloc.server.storage.db import create_engine_for_url, make_session_factory, session_scope
from monoloc.server.storage.migrate import upgrade_database
from monoloc.server.storage.models import Entry, EntryImage, Map, MapChange, Run, Vocabulary
from monoloc.server.storage.records import EntryImageData

MAP = "city"
# tiles of 100 m with a corner at (14, -50): x < 14 is tile -1_0 (west), x >= 14 is 0_0
SCHEME = TileScheme(100.0, origin_x_m=14.0, origin_y_m=-50.0)
CALIBRATION = {
    "mu1": [0.01, -0.02, 0.001],
    "Sigma1": np.diag([0.04, 0.05, 0.001]).tolist(),
    "mu2": [0.5, 0.0, 0.0, 0.0],
    "Sigma2": np.diag([0.1, 4.0, 4.0, 0.05]).tolist(),
    "source": "test",
}
GEO = GeoReference.from_origin(GeoOrigin(37.87, -122.26, 50.0, 10.0)).to_dict()


def _table(tiles: dict[str, str] | None = None) -> TileTable:
    groups = {name: ShardGroup(name, replicas=(f"{name}-1:8000",)) for name in ("west", "east")}
    return TileTable(
        SCHEME, MAP, groups, tiles or {"-1_0": "west", "0_0": "east"}, "http://router:8080"
    )


def _url(path: Path) -> str:
    return f"sqlite:///{path}"


def _source(path: Path) -> tuple[str, dict[str, str]]:
    """A SQLite map of 60 entries: west and east of x = 14 m (one exactly on it: east's),
    4 in a tile no group serves; a run owning some, tags, images on some, a calibration, a
    geo-reference, and entries computed with an older vocabulary than the map's. Returns
    (url, hash -> tile)."""
    url = _url(path)
    upgrade_database(url)
    engine = create_engine_for_url(url)
    rng = np.random.default_rng(7)
    tiles = {}
    with session_scope(make_session_factory(engine)) as session:
        old, _ = maps_repo.get_or_create_vocabulary(
            session, rng.uniform(0, 255, (64, 32)).astype(np.float32), "old"
        )
        new, _ = maps_repo.get_or_create_vocabulary(
            session, rng.uniform(0, 255, (64, 32)).astype(np.float32), "new"
        )
        record = maps_repo.create_map(session, MAP, KITTI_CAM0, old.id)
        maps_repo.set_calibration(session, record.id, CALIBRATION)
        maps_repo.set_geo_reference(session, record.id, GEO)
        maps_repo.create_map(session, "other", KITTI_CAM0, old.id)  # never copied
        run = runs_repo.create_run(session, record.id, kind="map", source_format="kitti")
        xy = np.column_stack([rng.uniform(-80, 110, 60), rng.uniform(-45, 45, 60)])
        xy[0] = (14.0, 0.0)  # on the border: the tile east of it
        xy[1] = (13.999, 0.0)
        xy[56:] = rng.uniform(320, 380, (4, 2))  # tile 3_3: no group's
        for i, (x, y) in enumerate(xy):
            if i == 30:
                maps_repo.set_map_vocabulary(session, record.id, new.id)
            entry = entry_at(f"split-{i}", x, y, n=10 + i % 7)
            image = None
            if i % 3 == 0:
                image = EntryImageData(
                    jpeg=b"\xff\xd8\xff" + rng.bytes(40),
                    width_px=80,
                    height_px=24,
                    keypoints_without_point_px=rng.uniform(0, 300, (5, 2)).astype(np.float32),
                )
            entry = type(entry)(
                **{
                    **entry.__dict__,
                    "tags": ("night",) if i % 4 == 0 else (),
                    "image": image,
                }
            )
            summary, _ = entries_repo.add_entry(
                session, record.id, entry, run_id=run.id if i % 2 else None
            )
            tiles[summary.source_image_hash] = SCHEME.tile_of(summary.x_m, summary.y_m)
    engine.dispose()
    assert tiles[entry_at("split-0", 14.0, 0.0).source_image_hash] == "0_0"
    return url, tiles


def _contents(url: str) -> dict[str, tuple]:
    """hash -> everything of the map's entry a replica or the console reads."""
    engine = create_engine_for_url(url)
    try:
        with make_session_factory(engine)() as session:
            record = maps_repo.get_map_by_name(session, MAP)
            ids = list(session.scalars(select(Entry.id).where(Entry.map_id == record.id)))
            out = {}
            for d in entries_repo.get_entry_data(session, ids):
                s = d.summary
                image = session.get(EntryImage, d.id)
                vocab = session.get(Vocabulary, s.vocabulary_id).version_hash
                run = None if s.run_id is None else session.get(Run, s.run_id)
                out[s.source_image_hash] = (
                    d.T_world_from_cam.tobytes(),
                    d.vlad.tobytes(),
                    d.code.tobytes(),
                    d.keypoints_px.tobytes(),
                    d.descriptors.tobytes(),
                    d.points_cam.tobytes(),
                    (s.x_m, s.y_m, s.yaw_rad, s.timestamp_s, s.n_points),
                    s.tags,
                    vocab,
                    None if run is None else (run.kind, run.created_at),
                    None if image is None else (image.jpeg, image.keypoints_without_point_px),
                )
            return out
    finally:
        engine.dispose()


def _check_invariants(url: str) -> None:
    """The copy's map: one version and one 'add' change per entry, in id order."""
    engine = create_engine_for_url(url)
    try:
        with make_session_factory(engine)() as session:
            record = maps_repo.get_map_by_name(session, MAP)
            ids = list(
                session.scalars(
                    select(Entry.id).where(Entry.map_id == record.id).order_by(Entry.id)
                )
            )
            changes = session.execute(
                select(MapChange.version, MapChange.kind, MapChange.entry_id)
                .where(MapChange.map_id == record.id)
                .order_by(MapChange.version)
            ).all()
            assert record.version == len(ids) == len(changes)
            assert [c.version for c in changes] == list(range(1, len(ids) + 1))
            assert {c.kind for c in changes} == {"add"} and [c.entry_id for c in changes] == ids
            assert record.calibration == maps_repo.validate_calibration(CALIBRATION)
            assert record.geo_reference == GEO and record.camera == KITTI_CAM0
            assert session.scalar(select(func.count(Map.id))) == 1  # not 'other'
    finally:
        engine.dispose()


def _cli(monkeypatch, capsys, *argv: str) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of `monoloc *argv` run in this process."""
    monkeypatch.setattr(sys, "argv", ["monoloc", *argv])
    code = 0
    try:
        cli.main()
    except SystemExit as exited:
        code = exited.code or 0
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_split_into_sqlite_and_postgresql_covers_the_map_once(
    tmp_path, postgres_url, monkeypatch, capsys
):
    source, tiles = _source(tmp_path / "all.db")
    table_path = write_tile_table(tmp_path / "tiles.json", _table())
    west = _url(tmp_path / "west.db")
    dests = {"west": west, "east": postgres_url}
    for group, dest in dests.items():
        code, out, _ = _cli(
            monkeypatch, capsys, "shards", "split", str(table_path), "--group", group,
            "--from-database", source, "--to-database", dest, "--batch-rows", "7",
        )  # fmt: skip
        assert code == 0, out
        n = sum(t == ("-1_0" if group == "west" else "0_0") for t in tiles.values())
        assert f"{n} entries in group {group}'s tiles, copied {n}, already there 0" in out
        assert f"skipped outside {60 - n}" in out
        _check_invariants(dest)
        # coverage of the copy: every entry in the group's own tile
        code, out, err = _cli(
            monkeypatch, capsys, "shards", "coverage", str(table_path), "--group", group,
            "--database-url", dest,
        )  # fmt: skip
        assert code == 0, err
        assert out.split() == [("-1_0" if group == "west" else "0_0"), str(n), "ok"]

    everything = _contents(source)
    copies = {group: _contents(dest) for group, dest in dests.items()}
    assert not set(copies["west"]) & set(copies["east"])
    inside = {h for h, t in tiles.items() if t in ("-1_0", "0_0")}
    assert len(inside) == 56
    assert set(copies["west"]) | set(copies["east"]) == inside
    for copy in copies.values():
        for source_hash, row in copy.items():
            assert row == everything[source_hash]
    # the old vocabulary came along for the entries computed with it, the runs once each
    assert {row[8] for row in copies["west"].values()} == {row[8] for row in everything.values()}

    # a rerun copies nothing and leaves the version alone
    for group, dest in dests.items():
        again = split_map(_table(), group, source, dest, batch_rows=5)
        assert again.copied == 0 and again.already_there == again.in_group
        assert again.runs_copied == 0 and again.vocabularies_copied == 0
        assert not again.created and again.version == again.in_group
        _check_invariants(dest)


class _StopCopyError(Exception):
    pass


@pytest.mark.parametrize("dest_kind", ["sqlite", "postgresql"])
def test_an_interrupted_split_resumes_to_the_full_set(tmp_path, request, dest_kind):
    source, tiles = _source(tmp_path / "all.db")
    dest = (
        request.getfixturevalue("postgres_url")
        if dest_kind == "postgresql"
        else _url(tmp_path / "east.db")
    )
    n = sum(t == "0_0" for t in tiles.values())

    def stop_after_first_batch(done: int, total: int) -> None:
        assert total == n
        raise _StopCopyError

    with pytest.raises(_StopCopyError):
        split_map(_table(), "east", source, dest, batch_rows=4, progress=stop_after_first_batch)
    assert len(_contents(dest)) == 4
    _check_invariants(dest)
    resumed = split_map(_table(), "east", source, dest, batch_rows=4)
    assert (resumed.copied, resumed.already_there, resumed.in_group) == (n - 4, 4, n)
    assert not resumed.created and resumed.outside == 60 - n
    copy, everything = _contents(dest), _contents(source)
    assert set(copy) == {h for h, t in tiles.items() if t == "0_0"}
    assert all(copy[h] == everything[h] for h in copy)
    _check_invariants(dest)


def test_refusals_are_one_line_and_write_nothing(tmp_path, monkeypatch, capsys):
    source, _ = _source(tmp_path / "all.db")
    table_path = write_tile_table(tmp_path / "tiles.json", _table())
    dest_path = tmp_path / "dest.db"

    def refused(*args: str, table: Path = table_path, to: str = _url(dest_path)) -> str:
        code, out, err = _cli(
            monkeypatch, capsys, "shards", "split", str(table), *args,
            "--from-database", source, "--to-database", to,
        )  # fmt: skip
        assert code == 1 and not out, (code, out, err)
        assert len(err.strip().splitlines()) == 1, err
        return err

    assert "group 'north' is not in" in refused("--group", "north")
    assert not dest_path.exists()
    # the same file under another spelling
    same = _url(tmp_path / "sub" / ".." / "all.db")
    assert same_database(source, same) and not same_database(source, _url(dest_path))
    assert "same database" in refused("--group", "west", to=same)
    other_map = write_tile_table(tmp_path / "other.json", _renamed(_table(), "nowhere"))
    assert "map 'nowhere' is not in the source database" in refused(
        "--group", "west", table=other_map
    )
    assert not dest_path.exists()

    # a destination map of that name with another vocabulary: refused, nothing written
    upgrade_database(_url(dest_path))
    engine = create_engine_for_url(_url(dest_path))
    factory = make_session_factory(engine)
    with session_scope(factory) as session:
        vocab, _ = maps_repo.get_or_create_vocabulary(
            session, np.full((64, 32), 3.0, np.float32), "another"
        )
        maps_repo.create_map(session, MAP, KITTI_CAM0, vocab.id)
    assert "another vocabulary" in refused("--group", "west")
    with factory() as session:
        assert session.scalar(select(func.count(Vocabulary.id))) == 1
        assert session.scalar(select(func.count(Entry.id))) == 0
        assert session.scalar(select(func.count(Run.id))) == 0
    engine.dispose()


def _renamed(table: TileTable, name: str) -> TileTable:
    return TileTable(table.scheme, name, table.groups, table.tiles, table.router)


ADMIN_KEY = "mlk_" + "S" * 43


def test_a_frame_localizes_on_the_group_copy_served_by_create_app(tmp_path):
    """A 6-frame sim street (half-size images, LiDAR) ingested whole, split at x = 2.6 m;
    the east copy, served by create_app, localizes one of its frames at its pose."""
    from monoloc.core.geometry import planar_from_T_world_from_cam
    from monoloc.server.api.app import create_app
    from monoloc.server.ingest.manage import create_map, ingest_source
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.settings import Settings
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig
    from monoloc.sim.recording import RecordingErrors

    root = tmp_path / "street"
    generate_dataset(
        GenerateConfig(
            seed=3,
            runs=("map",),
            max_frames=6,
            image_scale=0.5,
            write_depth=False,
            errors=RecordingErrors.none(),
            lidar=LidarConfig(azimuth_steps=1000),
        ),
        root,
    )
    run = read_kitti_sequence(root, "00")
    source = _url(tmp_path / "all.db")
    upgrade_database(source)
    engine = create_engine_for_url(source)
    factory = make_session_factory(engine)
    create_map(factory, MAP, run.intrinsics)
    ingest_source(factory, MAP, run)
    engine.dispose()
    table = TileTable(
        TileScheme(100.0, origin_x_m=2.6, origin_y_m=-50.0),
        MAP,
        _table().groups,
        {"-1_0": "west", "0_0": "east"},
        "http://router:8080",
    )
    east = _url(tmp_path / "east.db")
    summary = split_map(table, "east", source, east)
    xs = [f.T_world_from_cam[0, 3] for f in run.frames]
    assert summary.copied == summary.in_group == sum(x >= 2.6 for x in xs) > 0
    assert summary.outside == len(xs) - summary.in_group

    frame = run.frames[4]
    expected = planar_from_T_world_from_cam(frame.T_world_from_cam)
    settings = Settings(
        data_dir=tmp_path / "data", database_url=east, bootstrap_admin_key=ADMIN_KEY
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from fastapi.testclient import TestClient
    with TestClient(create_app(settings)) as client:
        r = client.post(
            f"/v1/maps/{summary.map_id}/localize",
            files={"image": ("frame.png", frame.image_path.read_bytes(), "image/png")},
            data={
                "prior_x_m": repr(float(expected[0])),
                "prior_y_m": repr(float(expected[1])),
                "prior_radius_m": "8.0",
                "seed": "1",
            },
            headers={"X-API-Key": ADMIN_KEY},
        )
    assert r.status_code == 200, r.text
    best = max(r.json()["hypotheses"], key=lambda h: h["n_inliers"])
    found = np.array([best["pose"]["x_m"], best["pose"]["y_m"]])
    assert np.linalg.norm(found - expected[:2]) < 0.2, (found, expected)
