"""Helpers of the fleet suites (a unique module name: the tests directories are not
packages): `monoloc serve` replica processes, uploads, nginx on loopback."""

from __future__ import annotations

import io
import os
import signal
import socket
import subprocess
import sys
import tarfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
from busy_machine import generous_env
from nginx_loopback import loopback_paths

from monoloc.client.api import ServerError, wait_until_ready

ADMIN_KEY = "mlk_" + "F" * 43
FRAMES = 40


def tar_run(dataset: Path, seq: str = "00") -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz", compresslevel=1) as tar:
        tar.add(dataset / "sequences" / seq, arcname=f"kitti/sequences/{seq}")
        tar.add(dataset / "poses" / f"{seq}.txt", arcname=f"kitti/poses/{seq}.txt")
    return buffer.getvalue()


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@dataclass
class Replica:
    """One `monoloc serve` process."""

    name: str
    port: int
    data_dir: Path
    env: dict[str, str]
    process: subprocess.Popen | None = None
    log: Path = field(init=False)

    def __post_init__(self) -> None:
        self.log = self.data_dir.parent / f"{self.name}.log"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> None:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        cmd = [
            sys.executable,
            "-m",
            "monoloc.cli",
            "serve",
            "--port",
            str(self.port),
            "--data-dir",
            str(self.data_dir),
            "--log-level",
            "warning",
        ]
        with open(self.log, "ab") as log:
            self.process = subprocess.Popen(cmd, env=self.env, stdout=log, stderr=log)

    def wait_ready(self, timeout_s: float = 120.0) -> None:
        assert self.process is not None
        try:
            wait_until_ready(self.url, timeout_s, self.process, poll_s=0.1)
        except ServerError as exc:
            raise AssertionError(f"{self.name}: {exc}: {self.log.read_text()[-3000:]}") from exc

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
            self.process.wait(10)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(40)
            except subprocess.TimeoutExpired:
                self.kill()


def replica_env(database_url: str, uploads: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MONOLOC_")}
    env.update(generous_env())  # the lease below is short: a takeover is a suite's subject
    env.update(
        MONOLOC_DATABASE_URL=database_url,
        MONOLOC_UPLOADS_DIR=str(uploads),
        MONOLOC_BOOTSTRAP_ADMIN_KEY=ADMIN_KEY,
        MONOLOC_WORKER_THREADS="1",
        MONOLOC_JOB_LEASE_S="2",
        MONOLOC_JOB_POLL_S="0.2",
        MONOLOC_REPLICA_SYNC_S="0.2",
        **extra,
    )
    return env


@dataclass
class Fleet:
    database_url: str
    replicas: list[Replica]
    keys: dict[str, str]
    map_id: int

    def headers(self, scope: str) -> dict[str, str]:
        return {"X-API-Key": self.keys[scope]}


def wait_job(url: str, job_id: int, headers: dict, timeout_s: float = 600.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = httpx.get(f"{url}/v1/jobs/{job_id}", headers=headers, timeout=10).json()
        if job["state"] in ("done", "failed", "interrupted"):
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not finish in {timeout_s} s")


def create_map(url: str, keys: dict, name: str, dataset: Path) -> int:
    from monoloc.core.camera import KITTI_CAM0

    c = KITTI_CAM0
    camera = dict(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, width_px=c.width_px, height_px=c.height_px)
    r = httpx.post(
        f"{url}/v1/maps",
        json={"name": name, "camera": camera},
        headers={"X-API-Key": keys["admin"]},
        timeout=30,
    )
    assert r.status_code == 201, r.text
    return r.json()["id"]


def upload_run(url: str, keys: dict, map_id: int, dataset: Path, seq: str) -> int:
    r = httpx.post(
        f"{url}/v1/maps/{map_id}/runs",
        files={"archive": ("run.tar.gz", tar_run(dataset, seq), "application/gzip")},
        data={"format": "kitti", "kind": "map"},
        headers={"X-API-Key": keys["write"]},
        timeout=120,
    )
    assert r.status_code == 202, r.text
    return r.json()["job"]["id"]


REPO = Path(__file__).resolve().parents[2]


def find_nginx() -> str | None:
    import shutil

    return shutil.which("nginx") or (
        "/usr/sbin/nginx" if Path("/usr/sbin/nginx").exists() else None
    )


def loopback_nginx_conf(tmp: Path, ports: list[int], listen_port: int) -> Path:
    """docker/nginx.conf with the replicas on 127.0.0.1 and its paths under ``tmp``."""
    import re

    text = (REPO / "docker" / "nginx.conf").read_text()
    # replica monoloc-N (in every upstream that names it) -> ports[N - 1]
    text = re.sub(
        r"server monoloc-(\d+):8000", lambda m: f"server 127.0.0.1:{ports[int(m[1]) - 1]}", text
    )
    text = text.replace("listen 80;", f"listen 127.0.0.1:{listen_port};")
    return loopback_paths(tmp, text, "upstream")
