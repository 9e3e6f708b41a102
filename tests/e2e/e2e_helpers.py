"""Helpers of the end-to-end tests: a real uvicorn on 127.0.0.1 in a thread, a sim city
uploaded through the HTTP API as a vehicle operator would, and a consistent copy of a
live server's database (a module name of its own: tests directories are not packages)."""

from __future__ import annotations

import io
import os
import re
import socket
import sqlite3
import subprocess
import sys
import tarfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from busy_machine import GENEROUS_DEADLINES

ADMIN_KEY = "mlk_" + "E" * 43
MAP_SEQ, QUERY_SEQ = "00", "01"  # the sim's map and query runs
SIM_FRAMES = 40  # per run; full KITTI resolution (half size gives too few 3D points)


@dataclass(frozen=True)
class Keys:
    admin: str
    localize: str
    write: str


@dataclass(frozen=True)
class LiveMap:
    """A live server holding map ``map_name`` built from the sim's map run."""

    url: str
    app: object  # the FastAPI app, for in-process instrumentation
    map_id: int
    map_name: str
    keys: Keys
    data_dir: Path
    dataset: Path


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def live_server(settings) -> Iterator[tuple[str, object]]:
    """create_app(settings) under a real uvicorn on 127.0.0.1; yields (base URL, app)."""
    import uvicorn

    from monoloc.server.api.app import create_app

    app = create_app(settings)
    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise AssertionError("uvicorn did not start")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}", app
    finally:
        server.should_exit = True
        thread.join(30)


def make_settings(data_dir: Path, **overrides):
    from monoloc.server.settings import Settings

    values = dict(data_dir=data_dir, bootstrap_admin_key=ADMIN_KEY, worker_threads=1)
    values.update(GENEROUS_DEADLINES)
    values.update(overrides)
    return Settings(**values)


def tar_sequence(dataset: Path, seq: str) -> bytes:
    """tar.gz of one sequence in the KITTI layout (sequences/NN + poses/NN.txt)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz", compresslevel=1) as tar:
        tar.add(dataset / "sequences" / seq, arcname=f"kitti/sequences/{seq}")
        tar.add(dataset / "poses" / f"{seq}.txt", arcname=f"kitti/poses/{seq}.txt")
    return buffer.getvalue()


def camera_json(intrinsics) -> dict:
    c = intrinsics
    return dict(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, width_px=c.width_px, height_px=c.height_px)


def create_keys(client) -> Keys:
    """A localize key and a map:write key, made with the bootstrap admin key."""
    made = {}
    for name, scope in (("car", "localize"), ("operator", "map:write")):
        made[name] = client.request(
            "POST", "/v1/keys", json={"name": name, "scopes": [scope]}
        ).json()["key"]
    return Keys(admin=ADMIN_KEY, localize=made["car"], write=made["operator"])


def upload_map_run(client, name: str, dataset: Path, seq: str, timeout_s: float = 600) -> int:
    """Create map ``name`` (admin client) and ingest sequence ``seq`` through the API."""
    from monoloc.core.camera import KITTI_CAM0

    created = client.request(
        "POST", "/v1/maps", json={"name": name, "camera": camera_json(KITTI_CAM0)}
    ).json()
    archive = tar_sequence(dataset, seq)
    accepted = client.request(
        "POST",
        f"/v1/maps/{created['id']}/runs",
        files={"archive": ("map.tar.gz", archive, "application/gzip")},
        data={"format": "kitti", "kind": "map"},
    ).json()
    job_id = accepted["job"]["id"]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = client.request("GET", f"/v1/jobs/{job_id}").json()
        if job["state"] in ("done", "failed", "interrupted"):
            assert job["state"] == "done", job
            return int(created["id"])
        time.sleep(0.1)
    raise AssertionError(f"ingestion job {job_id} did not finish in {timeout_s} s")


def copy_database(src_data_dir: Path, dst_data_dir: Path) -> None:
    """A consistent copy of a live server's SQLite database (the backup API); the copy's
    server rebuilds its retrieval indexes from it."""
    dst_data_dir.mkdir(parents=True, exist_ok=True)
    src = sqlite3.connect(src_data_dir / "monoloc.db")
    dst = sqlite3.connect(dst_data_dir / "monoloc.db")
    try:
        src.backup(dst)
    finally:
        dst.close()
        src.close()


@contextmanager
def mapped_loop_server(world, root: Path, map_frames: int, name: str, timeout_s: float = 60.0):
    """A closed-loop world's mapping drive (``map_frames`` centre-line frames recorded by
    the sim's vehicle under ``root/map``) uploaded to a live server's new map ``name``;
    yields (client, map_id, run_dir, lap)."""
    from monoloc.client.api import MonolocClient
    from monoloc.sim.closed_loop import LoopConfig
    from monoloc.sim.closed_loop_study import MAP_LAP, create_map, record_lap, upload

    run_dir, lap = record_lap(
        world, root, "map", LoopConfig(mode="open", max_frames=map_frames, lap=MAP_LAP, seed=1)
    )
    with live_server(make_settings(root / "data")) as (url, _app):
        with MonolocClient(url, ADMIN_KEY, timeout_s=timeout_s) as client:
            map_id = create_map(client, world, name)
            job = upload(client, map_id, world, run_dir, "/v1/maps/{map_id}/runs", kind="map")
            assert job["state"] == "done"
            yield client, map_id, run_dir, lap


def localize_frames(url: str, key: str, map_id: int, images: list[bytes], seed: int) -> list:
    """Each image localized over HTTP with the same seed (the answers of one server)."""
    from monoloc.client.api import MonolocClient

    with MonolocClient(url, key) as client:
        return [client.localize(map_id, image, seed=seed) for image in images]


def localize_frames_on_copy(live_map, data_dir: Path, images, seed: int, **overrides) -> list:
    """The same frames localized by a second server on a copy of ``live_map``'s database
    with these settings overridden (to compare a setting against the default)."""
    copy_database(live_map.data_dir, data_dir)
    with live_server(make_settings(data_dir, **overrides)) as (url, _):
        return localize_frames(url, live_map.keys.localize, live_map.map_id, images, seed)


def query_drive_args(live_map, out: Path, *, key: bool = True) -> list[str]:
    """`monoloc drive` arguments (after the command) of the query run's frames 10..29
    against ``live_map``, writing under ``out``; ``key``: pass the localize key (else the
    caller sets MONOLOC_API_KEY)."""
    args = [str(live_map.dataset), "--sequence", QUERY_SEQ, "--server", live_map.url]
    args += ["--map", live_map.map_name, "--frames", "10:30", "--particles", "500"]
    if key:
        args += ["--key", live_map.keys.localize]
    return [*args, "--out", str(out)]


def printed_rmse_m(stdout: str) -> float:
    """The position RMSE of a drive's printed table (AssertionError with the output when
    the table has none)."""
    found = re.search(r"position RMSE\s*\W*\s*([0-9.]+) m", stdout)
    assert found, stdout[-3000:]
    return float(found.group(1))


def run_monoloc(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """The full install's `monoloc` CLI in a subprocess, one line per table row."""
    env = dict(os.environ, COLUMNS="160")
    return subprocess.run(
        [sys.executable, "-m", "monoloc.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        check=False,
    )
