"""A map server on loopback and what feeds it: a `monoloc serve` child process, run
archives, job polling, operator uploads (the demo, the sim's closed-loop study and the
lab's crash trials drive a server through these)."""

from __future__ import annotations

import os
import secrets
import socket
import subprocess
import sys
import tarfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from monoloc.client.api import MonolocClient, ServerError, wait_until_ready
from monoloc.core.errors import MonolocError


class LocalServerError(MonolocError):
    """A local server step failed (server did not start, a job failed, ...)."""


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def new_admin_key() -> str:
    return "mlk_" + secrets.token_urlsafe(32)


def start_server(data_dir: Path, port: int, admin_key: str, log_path: Path) -> subprocess.Popen:
    """`monoloc serve` as a child process on 127.0.0.1; returns once /readyz answers 200."""
    env = dict(os.environ)
    env.update(
        MONOLOC_DATA_DIR=str(data_dir),
        MONOLOC_BOOTSTRAP_ADMIN_KEY=admin_key,
        MONOLOC_MAX_BODY_BYTES=str(4 * 1024**3),
        MONOLOC_MAX_ARCHIVE_BYTES=str(4 * 1024**3),
    )
    log = open(log_path, "w")  # noqa: SIM115 - owned by the process for its lifetime
    proc = subprocess.Popen(
        [sys.executable, "-m", "monoloc.cli", "serve", "--host", "127.0.0.1", "--port", str(port)],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        wait_until_ready(f"http://127.0.0.1:{port}", 90.0, proc, poll_s=0.3)
    except ServerError as exc:
        proc.terminate()
        raise LocalServerError(f"{exc}; see {log_path}") from exc
    return proc


def stop_server(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()


def kitti_archive(dataset_root: Path, sequence: str, out: Path) -> Path:
    """An uncompressed tar of one KITTI sequence: sequences/NN/... and poses/NN.txt."""
    with tarfile.open(out, "w") as tar:
        seq = dataset_root / "sequences" / sequence
        for name in ("calib.txt", "times.txt", "image_0", "velodyne"):
            tar.add(seq / name, arcname=f"sequences/{sequence}/{name}")
        tar.add(dataset_root / "poses" / f"{sequence}.txt", arcname=f"poses/{sequence}.txt")
    return out


def wait_job(client: MonolocClient, job_id: int, progress: Callable[[float], None]) -> dict:
    """Poll a job until it ends; returns its final JSON or raises LocalServerError."""
    while True:
        job = client.request("GET", f"/v1/jobs/{job_id}").json()
        progress(float(job["progress"]))
        if job["state"] == "done":
            return job
        if job["state"] in ("failed", "interrupted"):
            raise LocalServerError(
                f"job {job_id} ({job['kind']}) {job['state']}: {job.get('error')}"
            )
        time.sleep(0.5)


def upload_run(client: MonolocClient, map_id: int, archive: Path, path: str, **fields) -> dict:
    """POST an archive to ``path`` (runs or calibration jobs); returns the answer JSON."""
    data = {"format": "kitti", **{k: str(v) for k, v in fields.items() if v is not None}}
    with open(archive, "rb") as fh:
        response = client.request(
            "POST",
            path.format(map_id=map_id),
            data=data,
            files={"archive": (archive.name, fh, "application/x-tar")},
        )
    return response.json()


def add_entry(
    client: MonolocClient,
    map_id: int,
    image: Path,
    scan: Path,
    T_world_from_cam: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    tags: str,
    timestamp_s: float,
) -> dict:
    """The operator's admin route: one reference image with its LiDAR scan and pose."""
    data = {
        "T_world_from_cam": ",".join(f"{v:.10g}" for v in T_world_from_cam.reshape(-1)),
        "T_cam_from_lidar": ",".join(f"{v:.10g}" for v in T_cam_from_lidar.reshape(-1)),
        "tags": tags,
        "timestamp_s": repr(float(timestamp_s)),
    }
    files = {
        "image": (image.name, image.read_bytes(), "image/png"),
        "lidar": (scan.name, scan.read_bytes(), "application/octet-stream"),
    }
    return client.request("POST", f"/v1/maps/{map_id}/entries", data=data, files=files).json()
