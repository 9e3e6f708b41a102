"""Crash trials: SIGKILL a real map-server process in the middle of a write, restart it,
and check what it serves (issue 15, "keep it closed").

A trial starts ``monoloc serve`` on a fresh data directory, makes it write, kills it
with SIGKILL at a random moment (``rng``), restarts it on the same directory, resumes
what was interrupted, and checks:

* nothing acknowledged is lost: every upload answered 202 still has its job, which
  finishes after a resume; every entry answered 201/200 is there unless a delete of it
  was answered 204; every delete answered 204 stays deleted;
* nothing is duplicated: no two entries of the map share an image hash, and a run's
  counters add up (entries added + frames skipped = frames total);
* the served index equals the database: the map's ``indexed_entries`` equals its
  ``n_entries`` and the listed entries, and localizing a frame of the map retrieves
  only entries that exist.

Kinds: ``ingest`` (killed during an upload's ingestion job), ``entries`` (during a
stream of entry adds and deletes), ``index_write`` (at the end of an ingestion, when the
index file is persisted: the kill lands around the write, before or after it).
"""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from monoloc.local_server import free_port, kitti_archive, new_admin_key, start_server

KINDS = ("ingest", "entries", "index_write")


@dataclass
class TrialResult:
    """One trial: what was acknowledged before the kill and what the restart served."""

    kind: str
    killed_after_s: float
    acknowledged: int
    lost: int = 0
    duplicated: int = 0
    index_mismatch: int = 0
    counters_mismatch: int = 0
    job_state_at_kill: str = ""
    restart_s: float = 0.0  # SIGKILL to ready again
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not (self.lost or self.duplicated or self.index_mismatch or self.counters_mismatch)


class _Server:
    """``monoloc serve`` on one data directory, started and SIGKILLed as a child."""

    def __init__(self, data_dir: Path, log_dir: Path) -> None:
        self.data_dir, self.log_dir = data_dir, log_dir
        self.key = new_admin_key()
        self.proc: subprocess.Popen | None = None
        self.url = ""
        self.starts = 0
        self.last_start_s = 0.0

    def start(self) -> httpx.Client:
        """Start (or restart) the server; ``last_start_s`` is how long it took to be ready."""
        port = free_port()
        self.starts += 1
        log = self.log_dir / f"server-{self.starts}.log"
        began = time.monotonic()
        self.proc = start_server(self.data_dir, port, self.key, log)
        self.last_start_s = time.monotonic() - began
        self.url = f"http://127.0.0.1:{port}"
        return httpx.Client(base_url=self.url, headers={"X-API-Key": self.key}, timeout=60)

    def kill(self) -> None:
        assert self.proc is not None
        os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=30)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.kill()


def _create_map(client: httpx.Client, camera: dict) -> int:
    r = client.post("/v1/maps", json={"name": "crash", "camera": camera})
    r.raise_for_status()
    return int(r.json()["id"])


def _wait_job(client: httpx.Client, job_id: int, timeout_s: float = 300) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if job["state"] in ("done", "failed", "interrupted"):
            return job
        time.sleep(0.1)
    raise TimeoutError(f"job {job_id} did not finish in {timeout_s} s")


def _all_entries(client: httpx.Client, map_id: int) -> list[dict]:
    items, offset = [], 0
    while True:
        page = client.get(f"/v1/maps/{map_id}/entries", params={"limit": 1000, "offset": offset})
        page.raise_for_status()
        items.extend(page.json()["items"])
        if len(page.json()["items"]) < 1000:
            return items
        offset += 1000


def _check_served(client: httpx.Client, map_id: int, probe_png: bytes, result: TrialResult) -> list:
    """Duplicates and index/database agreement; returns the listed entries."""
    entries = _all_entries(client, map_id)
    hashes = [e["source_image_hash"] for e in entries]
    result.duplicated += len(hashes) - len(set(hashes))
    detail = client.get(f"/v1/maps/{map_id}").json()
    if not (detail["n_entries"] == detail["indexed_entries"] == len(entries)):
        result.index_mismatch += 1
        result.notes.append(
            f"n_entries {detail['n_entries']}, indexed {detail['indexed_entries']}, "
            f"listed {len(entries)}"
        )
    if entries:
        answer = client.post(
            f"/v1/maps/{map_id}/localize",
            files={"image": ("probe.png", probe_png, "image/png")},
            data={"k": str(min(100, len(entries)))},
        )
        answer.raise_for_status()
        ids = {e["id"] for e in entries}
        retrieved = {r["entry_id"] for r in answer.json()["retrieved"]}
        if not retrieved <= ids or len(retrieved) != min(100, len(entries)):
            result.index_mismatch += 1
            result.notes.append(f"retrieved {sorted(retrieved - ids)} not in the database")
    return entries


def _check_run(client: httpx.Client, map_id: int, job: dict, result: TrialResult) -> None:
    run = client.get(f"/v1/maps/{map_id}/runs/{job['run_id']}").json()
    if run["entries_added"] + run["frames_skipped"] != run["frames_total"]:
        result.counters_mismatch += 1
        result.notes.append(f"run counters {run}")


def _resume_to_done(client: httpx.Client, job_id: int, result: TrialResult) -> dict:
    job = client.get(f"/v1/jobs/{job_id}")
    if job.status_code == 404:
        result.lost += 1  # the upload was acknowledged: its job must survive
        result.notes.append(f"job {job_id} is gone")
        return {}
    state = job.json()["state"]
    if state in ("interrupted", "failed"):
        client.post(f"/v1/jobs/{job_id}/resume").raise_for_status()
    final = _wait_job(client, job_id)
    if final["state"] != "done":
        result.lost += 1
        result.notes.append(f"job {job_id} ended {final['state']}: {final.get('error')}")
    return final


def _ingest_trial(server, dataset, rng, workdir, result, at_end: bool) -> None:
    from monoloc.server.ingest.sources import read_kitti_sequence

    archive = kitti_archive(dataset.root, dataset.map_sequence, workdir / "map.tar")
    probe = read_kitti_sequence(dataset.root, dataset.map_sequence).frames[1].image_path
    client = server.start()
    map_id = _create_map(client, dataset.camera)
    with open(archive, "rb") as fh:
        r = client.post(
            f"/v1/maps/{map_id}/runs",
            files={"archive": ("map.tar", fh, "application/x-tar")},
            data={"format": "kitti", "kind": "map"},
        )
    r.raise_for_status()
    job_id = int(r.json()["job"]["id"])
    result.acknowledged = 1
    start = time.monotonic()
    # ingest: the kill lands once the map holds a random number of the run's entries (a
    # run ingests in about a second and progress is written every 0.5 s, so a random
    # delay would mostly land after the job); index_write: every frame built (progress
    # 1.0), the last commit and the index file write under way; the kill lands within
    # 50 ms of that, before, during or after.
    n_frames = len(read_kitti_sequence(dataset.root, dataset.map_sequence).frames)
    entries_before_kill = int(rng.integers(1, max(2, n_frames - 1)))
    while time.monotonic() - start < 120:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if job["state"] == "done":
            break
        if at_end and job["state"] != "queued" and job["progress"] > 0.99:
            break
        if not at_end:
            n_entries = client.get(f"/v1/maps/{map_id}").json()["n_entries"]
            if n_entries >= entries_before_kill:
                break
        time.sleep(0.005)
    time.sleep(float(rng.uniform(0.0, 0.05 if at_end else 0.01)))
    result.job_state_at_kill = client.get(f"/v1/jobs/{job_id}").json()["state"]
    result.killed_after_s = time.monotonic() - start
    server.kill()
    client.close()
    client = server.start()
    result.restart_s = server.last_start_s
    final = _resume_to_done(client, job_id, result)
    if final:
        _check_run(client, map_id, final, result)
        entries = _check_served(client, map_id, probe.read_bytes(), result)
        if final.get("result") and final["result"]["entries_added"] != len(entries):
            result.counters_mismatch += 1
            result.notes.append(f"job says {final['result']['entries_added']}, map {len(entries)}")
    client.close()


def _entries_trial(server, dataset, rng, workdir, result) -> None:
    from monoloc.server.ingest.sources import read_kitti_sequence

    seq = read_kitti_sequence(dataset.root, dataset.map_sequence)
    client = server.start()
    map_id = _create_map(client, dataset.camera)
    added: dict[int, str] = {}  # acknowledged entry id -> image name
    deleted: set[int] = set()  # acknowledged deletes
    in_flight: set[int] = set()  # a delete sent but not answered: its outcome is unknown
    stop = threading.Event()
    lidar_pose = ",".join(f"{v:.10g}" for v in seq.T_cam_from_lidar.reshape(-1))

    def writer() -> None:
        order = rng.permutation(len(seq.frames))
        with httpx.Client(base_url=server.url, headers={"X-API-Key": server.key}) as c:
            for step, index in enumerate(np.concatenate([order, order])):
                if stop.is_set():
                    return
                frame = seq.frames[int(index)]
                try:
                    if step % 3 == 2 and added.keys() - deleted:
                        victim = int(rng.choice(sorted(added.keys() - deleted)))
                        in_flight.add(victim)
                        if c.delete(f"/v1/maps/{map_id}/entries/{victim}").status_code == 204:
                            deleted.add(victim)
                        in_flight.discard(victim)
                        continue
                    r = c.post(
                        f"/v1/maps/{map_id}/entries",
                        data={
                            "T_world_from_cam": ",".join(
                                f"{v:.10g}" for v in frame.T_world_from_cam.reshape(-1)
                            ),
                            "T_cam_from_lidar": lidar_pose,
                        },
                        files={
                            "image": ("i.png", frame.image_path.read_bytes(), "image/png"),
                            "lidar": ("s.bin", frame.scan_path.read_bytes(), "application/x"),
                        },
                    )
                    if r.status_code in (200, 201):
                        entry_id = int(r.json()["entry"]["id"])
                        deleted.discard(entry_id)  # re-added after a delete: a new id anyway
                        added[entry_id] = frame.image_path.name
                except httpx.HTTPError:
                    return  # the server died under us: the in-flight request is unknown

    kill_after_s = float(rng.uniform(0.5, 3.0))  # drawn before the writer shares rng
    thread = threading.Thread(target=writer, daemon=True)
    start = time.monotonic()
    thread.start()
    time.sleep(kill_after_s)
    result.killed_after_s = time.monotonic() - start
    server.kill()
    stop.set()
    thread.join(60)
    client.close()
    result.acknowledged = len(added) + len(deleted)
    client = server.start()
    result.restart_s = server.last_start_s
    entries = _check_served(client, map_id, seq.frames[0].image_path.read_bytes(), result)
    present = {e["id"] for e in entries}
    for entry_id in added.keys() - in_flight:
        if (entry_id in present) == (entry_id in deleted):
            result.lost += 1
            state = "deleted (204) but present" if entry_id in deleted else "added but missing"
            result.notes.append(f"entry {entry_id} {state}")
    client.close()


@dataclass(frozen=True)
class TrialDataset:
    """A generated KITTI-layout run to write with: its root, sequence and camera."""

    root: Path
    map_sequence: str
    camera: dict


def run_trial(kind: str, dataset: TrialDataset, workdir: Path, rng: np.random.Generator):
    """One crash trial of ``kind`` in ``workdir`` (a fresh directory); a TrialResult."""
    if kind not in KINDS:
        raise ValueError(f"unknown crash trial kind {kind!r}; one of {KINDS}")
    workdir.mkdir(parents=True, exist_ok=True)
    server = _Server(workdir / "data", workdir)
    result = TrialResult(kind=kind, killed_after_s=0.0, acknowledged=0)
    try:
        if kind == "entries":
            _entries_trial(server, dataset, rng, workdir, result)
        else:
            _ingest_trial(server, dataset, rng, workdir, result, at_end=kind == "index_write")
    finally:
        server.stop()
    return result
