"""A map in two shard groups behind the nginx router, one `monoloc serve` per group on its
own SQLite file: the router sends a request to the group of the tile its header names
(an unknown tile: 400 with a message); a frame whose prior reaches the border goes to
both groups and comes back as one answer, each hypothesis with its group; `monoloc drive
--tiles` drives across the border with one filter. The committed docker/nginx-shards.conf
is what `monoloc shards nginx-config` writes for docker/tiles.example.json, and nginx
accepts it."""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
from fleet_helpers import ADMIN_KEY, REPO, Replica, find_nginx, free_port, replica_env
from shard_helpers import GROUPS, MAP_NAME, loopback_conf, start_router, stop_process
from typer.testing import CliRunner

from monoloc.client.replay import read_run
from monoloc.client.sharded import ShardedLocalizer
from monoloc.core.prior import RetrievalPrior
from monoloc.core.tiles import TILE_HEADER, ShardGroup, TileTable, write_tile_table


@dataclass
class Shards:
    table: TileTable  # through the router
    direct: TileTable  # each group at its replica's URL
    router_url: str
    frames: dict[str, int]  # map frames ingested per group
    tmp: Path


@pytest.fixture(scope="module")
def shards(split_street, tmp_path_factory) -> Iterator[Shards]:
    tmp = tmp_path_factory.mktemp("shards")
    replicas, frames = {}, {}
    for group in GROUPS:
        data = tmp / group / "data"
        url = f"sqlite:///{data / 'monoloc.db'}"
        frames[group] = split_street.ingest_half(url, group)
        replicas[group] = Replica(group, free_port(), data, replica_env(url, tmp / group / "up"))
    router = None
    try:
        for replica in replicas.values():
            replica.start()
        for replica in replicas.values():
            replica.wait_ready()
        groups = {
            g: ShardGroup(g, replicas[g].url, (f"127.0.0.1:{replicas[g].port}",)) for g in GROUPS
        }
        port = free_port()
        table = split_street.table(groups, router=f"http://127.0.0.1:{port}")
        router = start_router(tmp, table, port)
        yield Shards(table, split_street.table(groups), table.router, frames, tmp)
    finally:
        stop_process(router)
        for replica in replicas.values():
            replica.stop()


def _entries(url: str, tile: str | None) -> httpx.Response:
    headers = {"X-API-Key": ADMIN_KEY} | ({TILE_HEADER: tile} if tile else {})
    return httpx.get(f"{url}/v1/maps", headers=headers, timeout=30)


def test_the_router_sends_a_request_to_its_tiles_group(shards):
    west, east = _entries(shards.router_url, "-1_0"), _entries(shards.router_url, "0_0")
    assert west.status_code == east.status_code == 200, (west.text, east.text)
    (west_map,) = west.json()["items"]
    (east_map,) = east.json()["items"]
    assert west_map["name"] == east_map["name"] == MAP_NAME
    assert (west_map["n_entries"], east_map["n_entries"]) == (
        shards.frames["west"],
        shards.frames["east"],
    )
    assert 0 < shards.frames["west"] < 40 and 0 < shards.frames["east"] < 40
    for tile in (None, "5_5", "west"):
        refused = _entries(shards.router_url, tile)
        assert refused.status_code == 400, refused.text
        assert refused.json()["error"]["code"] == "unknown_tile"


def test_the_router_sheds_a_full_groups_frames_and_not_the_other_groups(
    shards, split_street, tmp_path
):
    """A router whose groups hold one frame each: of west frames sent together some are
    answered 503 by nginx (never proxied), while an east frame sent with them is served:
    each group's admission counts its own frames."""
    from concurrent.futures import ThreadPoolExecutor

    port = free_port()
    router = start_router(tmp_path, shards.table, port, localize_slots=1)
    url = f"http://127.0.0.1:{port}"
    map_id = _entries(url, "-1_0").json()["items"][0]["id"]
    path = f"/v1/maps/{map_id}/localize"
    frame = _frame(split_street, 3)

    def localize(tile: str) -> httpx.Response:
        return httpx.post(
            f"{url}{path}",
            files={"image": ("f.png", frame, "image/png")},
            headers={"X-API-Key": ADMIN_KEY, TILE_HEADER: tile},
            timeout=30,
        )

    try:
        with ThreadPoolExecutor(9) as pool:
            answers = list(pool.map(localize, ["-1_0"] * 4 + ["0_0"] + ["-1_0"] * 4))
    finally:
        stop_process(router)
    east, west = answers[4], answers[:4] + answers[5:]
    assert east.status_code == 200, east.text
    codes = sorted(r.status_code for r in west)
    assert set(codes) == {200, 503}, codes
    for shed in (r for r in west if r.status_code == 503):
        assert shed.json()["error"]["code"] == "overloaded"
        assert int(shed.headers["retry-after-ms"]) > 0 and shed.headers["retry-after"] == "1"
    log = (tmp_path / "access.log").read_text().splitlines()
    shed_lines = [line for line in log if " 503 " in line]
    assert len(shed_lines) == codes.count(503), log
    # never proxied: nginx found no replica of the group with room (no address tried)
    assert all("tile=-1_0 upstream=shard_west_localize " in line for line in shed_lines), shed_lines


def _frame(split_street, i: int) -> bytes:
    return (split_street.root / "sequences" / "01" / "image_0" / f"{i:06d}.png").read_bytes()


@pytest.mark.parametrize("via", ["router", "direct"])
def test_a_border_frame_is_answered_by_both_groups_in_one_answer(shards, split_street, via):
    run = read_run(split_street.root, "01")
    table = shards.table if via == "router" else shards.direct
    # the query frame nearest the border, and one well inside the west tile
    border_i = int(np.argmin(np.abs(run.truth_world[:, 0] - split_street.border_x_m)))
    inside_i = int(np.argmin(np.abs(run.truth_world[:, 0] - 3.0)))
    with ShardedLocalizer.connect(table, ADMIN_KEY, run.intrinsics) as localizer:
        x, y, yaw = run.truth_world[border_i]
        answer = localizer.localize(_frame(split_street, border_i), RetrievalPrior(x, y, 8.0))
        assert answer.error is None and not answer.dropped, answer.raw
        assert set(answer.raw["shards"]) == {"west", "east"}
        assert {s["tile"] for s in answer.raw["shards"].values()} == {"-1_0", "0_0"}
        sources = [h["shard"] for h in answer.raw["hypotheses"]]
        assert set(sources) == {"west", "east"}, sources
        assert len(answer.hypotheses) == len(sources)
        # each group's hypotheses come from its own entries: west of the border, east of it
        entry_x = answer.hypotheses.entry_pose_world[:, 0]
        from_west = np.array(sources) == "west"
        assert (entry_x[from_west] < split_street.border_x_m).all()
        assert (entry_x[~from_west] >= split_street.border_x_m).all()
        best = answer.best_pose_world
        assert np.hypot(best[0] - x, best[1] - y) < 1.0, (best, (x, y))

        x, y, _ = run.truth_world[inside_i]
        answer = localizer.localize(_frame(split_street, inside_i), RetrievalPrior(x, y, 8.0))
        assert set(answer.raw["shards"]) == {"west"}
        assert {h["shard"] for h in answer.raw["hypotheses"]} == {"west"}
        assert localizer.routes == {"one_group": 1, "several_groups": 1}
        counts = localizer.counts
        assert (counts["west"]["answered"], counts["east"]["answered"]) == (2, 1)


def _drive(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "monoloc.cli", "drive", *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={"COLUMNS": "160", "PATH": "/usr/bin:/bin"},
        check=False,
    )


def test_monoloc_drive_tiles_crosses_the_border_with_one_filter(shards, split_street):
    tiles = write_tile_table(shards.tmp / "tiles.json", shards.table)
    out = shards.tmp / "drive" / "street"
    args = [str(split_street.root), "--sequence", "01", "--tiles", str(tiles)]
    done = _drive(*args, "--key", ADMIN_KEY, "--particles", "500", "--out", str(out))
    assert done.returncode == 0, done.stderr[-3000:]
    rmse = float(re.search(r"position RMSE\s*\W*\s*([0-9.]+) m", done.stdout).group(1))
    print(f"sharded drive across the border: position RMSE {rmse:.3f} m")
    assert rmse < 0.5, done.stdout
    sent = {
        g: int(re.search(rf"shard group {g}: sent (\d+), answered (\d+)", done.stderr).group(2))
        for g in GROUPS
    }
    assert sent["west"] > 0 and sent["east"] > 0, done.stderr
    several = int(re.search(r"to several (\d+)", done.stderr).group(1))
    assert several > 0, done.stderr
    assert "failed 0" in done.stderr and "error" not in done.stderr.lower(), done.stderr
    # a wrong table or a wrong combination: one line and a non-zero exit
    missing = _drive(*args[:4], str(shards.tmp / "nope.json"), "--key", ADMIN_KEY)
    assert missing.returncode != 0 and "nope.json: cannot read the tile table" in missing.stderr
    assert len(missing.stderr.strip().splitlines()) == 1, missing.stderr
    both = _drive(*args, "--map", MAP_NAME, "--key", ADMIN_KEY)
    assert both.returncode != 0 and "give --map or --tiles" in both.stderr


def test_the_committed_router_config_is_the_tables_and_nginx_accepts_it(tmp_path):
    from monoloc.cli import _register, app

    _register()
    out = tmp_path / "nginx-shards.conf"
    example = REPO / "docker" / "tiles.example.json"
    result = CliRunner().invoke(app, ["shards", "nginx-config", str(example), "--out", str(out)])
    assert result.exit_code == 0, result.output
    committed = (REPO / "docker" / "nginx-shards.conf").read_text()
    assert out.read_text() == committed
    assert "map $http_x_monoloc_tile $shard_upstream" in committed
    nginx = find_nginx()
    if nginx is None:
        pytest.fail("nginx is not installed (make system-deps installs Debian's nginx-light)")
    ports: dict[str, int] = {}  # each replica (named in its group's two upstreams) a port
    text = re.sub(
        r"server (monoloc-\w+-\d):8000",
        lambda m: f"server 127.0.0.1:{ports.setdefault(m[1], 18101 + len(ports))}",
        committed,
    )
    assert len(ports) == 4
    conf = loopback_conf(tmp_path, text.replace("listen 80;", "listen 127.0.0.1:18100;"))
    checked = subprocess.run(
        [nginx, "-t", "-p", str(tmp_path), "-c", str(conf)], capture_output=True, text=True
    )
    assert checked.returncode == 0, checked.stderr
    # a table without the replicas of a group cannot make a router
    bare = tmp_path / "bare.json"
    bare.write_text('{"map": "m", "groups": {"a": {"url": "http://a"}}, "tiles": {"0_0": "a"}}')
    result = CliRunner().invoke(app, ["shards", "nginx-config", str(bare)])
    assert result.exit_code != 0 and "needs the replicas of groups a" in str(result.exception)
