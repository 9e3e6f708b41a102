"""Helpers of the API tests (imported by conftest.py and the tests; a unique module name
because the tests directories are not packages)."""

from __future__ import annotations

import io
import tarfile
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from busy_machine import GENEROUS_DEADLINES

from monoloc.server.settings import Settings

with warnings.catch_warnings():  # starlette's notice about httpx vs httpx2
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

ADMIN_KEY = "mlk_" + "T" * 43
MAP_FRAMES = 16
# A measurement model a calibration PUT accepts (provenance names a vocabulary, as a
# calibration job's does)
CALIBRATION = dict(
    mu1=[0.02, -0.01, 0.001],
    Sigma1=[[0.04, 0.01, 0.0], [0.01, 0.05, 0.0], [0.0, 0.0, 0.0007]],
    mu2=[0.8, 0.1, -0.1, 0.0],
    Sigma2=np.diag([0.05, 49.0, 49.0, 0.3]).tolist(),
    provenance={"training_run": "sim-train", "method": "ML", "vocabulary_hash": "0123456789abcdef"},
)
SIM_SCALE = 1.0


@dataclass(frozen=True)
class Keys:
    admin: str
    localize: str
    write: str

    def header(self, which: str) -> dict[str, str]:
        return {"X-API-Key": getattr(self, which)}


def make_settings(data_dir: Path, **overrides) -> Settings:
    values = dict(data_dir=data_dir, bootstrap_admin_key=ADMIN_KEY, worker_threads=2)
    values.update(GENEROUS_DEADLINES)
    values.update(overrides)
    return Settings(**values)


def open_client(settings: Settings) -> TestClient:
    from monoloc.server.api.app import create_app

    return TestClient(create_app(settings))


def create_keys(client: TestClient) -> Keys:
    admin = {"X-API-Key": ADMIN_KEY}
    made = {}
    for name, scope in (("localize", "localize"), ("write", "map:write")):
        r = client.post("/v1/keys", json={"name": name, "scopes": [scope]}, headers=admin)
        assert r.status_code == 201, r.text
        made[name] = r.json()["key"]
    return Keys(admin=ADMIN_KEY, localize=made["localize"], write=made["write"])


def camera_of(dataset: Path) -> dict:
    from monoloc.core.camera import KITTI_CAM0

    c = KITTI_CAM0.scaled(SIM_SCALE)
    return dict(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, width_px=c.width_px, height_px=c.height_px)


def tar_sequence(dataset: Path, seq: str = "00") -> bytes:
    """A tar.gz of one sequence in the KITTI layout (sequences/NN + poses/NN.txt)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz", compresslevel=1) as tar:
        tar.add(dataset / "sequences" / seq, arcname=f"kitti/sequences/{seq}")
        tar.add(dataset / "poses" / f"{seq}.txt", arcname=f"kitti/poses/{seq}.txt")
    return buffer.getvalue()


def wait_job(client: TestClient, job_id: int, headers: dict, timeout_s: float = 600.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = client.get(f"/v1/jobs/{job_id}", headers=headers).json()
        if job["state"] in ("done", "failed", "interrupted"):
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not finish in {timeout_s} s")


def ground_truth(dataset: Path, seq: str, frame: int) -> np.ndarray:
    """T_world_from_cam (4, 4) of a frame in the z-up world."""
    from monoloc.core.geometry import kitti_to_zup

    rows = np.loadtxt(dataset / "poses" / f"{seq}.txt").reshape(-1, 3, 4)
    T = np.eye(4)
    T[:3] = rows[frame]
    return kitti_to_zup(T)


def frame_png(dataset: Path, seq: str, frame: int) -> bytes:
    return (dataset / "sequences" / seq / "image_0" / f"{frame:06d}.png").read_bytes()


def free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def live_server(settings: Settings, app=None, log_level: str = "warning") -> Iterator[int]:
    """``app`` (default: create_app(settings)) served by a real uvicorn on 127.0.0.1 in a
    thread; yields the port."""
    import threading

    import uvicorn

    from monoloc.server.api.app import create_app

    port = free_port()
    config = uvicorn.Config(
        app or create_app(settings),
        host="127.0.0.1",
        port=port,
        log_level=log_level,
        lifespan="on",
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise AssertionError("uvicorn did not start")
        time.sleep(0.02)
    try:
        yield port
    finally:
        server.should_exit = True
        thread.join(30)
