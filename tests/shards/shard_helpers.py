"""Helpers of the shard suites (a unique module name: the tests directories are not
packages): synthetic map entries at given positions, the split street, nginx as the
shard router on loopback."""

from __future__ import annotations

import dataclasses
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from fake_entries import fake_entry
from nginx_loopback import loopback_paths

from monoloc.core.tiles import ShardGroup, TileScheme, TileTable
from monoloc.server.storage.records import NewEntry


def entry_at(name: str, x_m: float, y_m: float, n: int = 12) -> NewEntry:
    """A valid entry (random features) whose camera stands at (x_m, y_m)."""
    return fake_entry(name, x_m, y_m, n=n, timestamp_s=0.0)


MAP_NAME = "street"
GROUPS = ("west", "east")


@dataclass(frozen=True)
class SplitStreet:
    """A sim street (KITTI layout: map run 00, query run 01) and the tile border that
    splits it: tiles of 100 m, origin at (border_x_m, -50), so that the street's west part
    lies in tile '-1_0' and its east part in '0_0'."""

    root: Path
    border_x_m: float

    @property
    def scheme(self) -> TileScheme:
        return TileScheme(100.0, origin_x_m=self.border_x_m, origin_y_m=-50.0)

    def table(self, groups: dict[str, ShardGroup], router: str | None = None) -> TileTable:
        return TileTable(self.scheme, MAP_NAME, groups, {"-1_0": "west", "0_0": "east"}, router)

    def ingest_half(self, database_url: str, group: str) -> int:
        """Migrate ``database_url`` and ingest the map run's frames of ``group``'s tile
        into its map 'street'; the number of frames ingested."""
        from monoloc.server.ingest.manage import create_map, ingest_source
        from monoloc.server.ingest.sources import read_kitti_sequence
        from monoloc.server.storage.db import create_engine_for_url, make_session_factory
        from monoloc.server.storage.migrate import upgrade_database

        run = read_kitti_sequence(self.root, "00")
        tile = "-1_0" if group == "west" else "0_0"
        frames = [
            f
            for f in run.frames
            if self.scheme.tile_of(f.T_world_from_cam[0, 3], f.T_world_from_cam[1, 3]) == tile
        ]
        upgrade_database(database_url)
        engine = create_engine_for_url(database_url)
        try:
            factory = make_session_factory(engine)
            create_map(factory, MAP_NAME, run.intrinsics)
            ingest_source(factory, MAP_NAME, dataclasses.replace(run, frames=frames))
        finally:
            engine.dispose()
        return len(frames)


def start_router(
    tmp: Path, table: TileTable, listen_port: int, localize_slots: int = 4
) -> subprocess.Popen:
    """nginx in the foreground on 127.0.0.1:``listen_port`` with the config
    `monoloc shards nginx-config --localize-slots N` writes for ``table`` (its paths
    under ``tmp``)."""
    from fleet_helpers import find_nginx

    from monoloc.server.shards_cli import render_nginx_config

    nginx = find_nginx()
    if nginx is None:
        pytest.fail("nginx is not installed (make system-deps installs Debian's nginx-light)")
    conf = loopback_conf(
        tmp, render_nginx_config(table, f"127.0.0.1:{listen_port}", localize_slots)
    )
    process = subprocess.Popen(
        [nginx, "-p", str(tmp), "-c", str(conf), "-g", "daemon off;"],
        stdout=subprocess.DEVNULL,
        stderr=open(tmp / "nginx.stderr", "wb"),  # noqa: SIM115 - the process keeps it
    )
    deadline = time.monotonic() + 30
    while True:
        try:
            httpx.get(f"http://127.0.0.1:{listen_port}/healthz", timeout=2)
            return process
        except httpx.TransportError:
            if process.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(
                    f"nginx did not start: {(tmp / 'nginx.stderr').read_text()[-2000:]}"
                ) from None
            time.sleep(0.1)


def loopback_conf(tmp: Path, text: str) -> Path:
    """An nginx config ``text`` with its pid, logs and temporary files under ``tmp``."""
    return loopback_paths(tmp, text, "shard")


def stop_process(process: subprocess.Popen | None) -> None:
    if process is not None and process.poll() is None:
        process.terminate()
        try:
            process.wait(20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)
