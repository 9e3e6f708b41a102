"""Archive bombs against the real upload route (issue 50, deliverable 4): each refused
quickly, with its status and the setting that applied, and without writing more than the
limit into the uploads directory.

What reached the disk is measured, not inferred: an audit hook records every file the
process opens for writing under the uploads directory (so "refused before extracting"
means no member file was created at all), and a thread samples the bytes held there
every millisecond (the peak). The archives are built here with zipfile and tarfile, of
zeros, so they stay a few kilobytes however much they declare; the limits are small ones
set through Settings."""

from __future__ import annotations

import io
import os
import sqlite3
import struct
import sys
import tarfile
import threading
import time
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from api_helpers import create_keys, make_settings, open_client

MiB = 1 << 20
LIMIT = 32 * MiB  # max_archive_bytes of these tests
CAMERA = dict(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width_px=320, height_px=240)

# --- what reaches the disk -----------------------------------------------------------

_WATCHED: list[DiskWatch] = []


def _audit(event: str, args: tuple) -> None:
    if event != "open" or not _WATCHED:
        return
    path, mode, flags = args
    if not isinstance(path, str | bytes | os.PathLike):
        return  # an open file descriptor
    writing = (isinstance(mode, str) and any(c in mode for c in "wxa+")) or (
        isinstance(flags, int) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT)
    )
    if writing:
        name = os.fsdecode(path)
        for watch in list(_WATCHED):
            if name.startswith(watch.root_text):
                watch.created.append(name)


_HOOKED = False


def _install_hook() -> None:
    global _HOOKED
    if not _HOOKED:  # an audit hook cannot be removed: one per process, idle when unwatched
        sys.addaudithook(_audit)
        _HOOKED = True


@dataclass
class DiskWatch:
    root: Path
    created: list[str] = field(default_factory=list)
    peak_bytes: int = 0

    @property
    def root_text(self) -> str:
        return str(self.root.resolve())

    def held_bytes(self) -> int:
        total = 0
        for folder, _, names in os.walk(self.root):
            for name in names:
                try:
                    total += os.stat(os.path.join(folder, name)).st_size
                except FileNotFoundError:
                    pass  # removed while walking
        return total


@contextmanager
def watching(root: Path) -> Iterator[DiskWatch]:
    """Files created under ``root`` and the peak bytes held there while the block runs."""
    _install_hook()
    root.mkdir(parents=True, exist_ok=True)
    watch = DiskWatch(root)
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            watch.peak_bytes = max(watch.peak_bytes, watch.held_bytes())
            time.sleep(0.001)

    sampler = threading.Thread(target=sample, daemon=True)
    _WATCHED.append(watch)
    sampler.start()
    try:
        yield watch
    finally:
        stop.set()
        sampler.join()
        _WATCHED.remove(watch)
        watch.peak_bytes = max(watch.peak_bytes, watch.held_bytes())


# --- archives --------------------------------------------------------------------------


def zeros_zip(n_members: int, member_bytes: int) -> bytes:
    buffer = io.BytesIO()
    zeros = bytes(member_bytes)
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as archive:
        for i in range(n_members):
            archive.writestr(f"bomb/{i:03d}.bin", zeros)
    return buffer.getvalue()


def zeros_tar_gz(n_members: int, member_bytes: int) -> bytes:
    buffer = io.BytesIO()
    zeros = bytes(member_bytes)
    with tarfile.open(fileobj=buffer, mode="w:gz", compresslevel=9) as tar:
        for i in range(n_members):
            info = tarfile.TarInfo(f"bomb/{i:03d}.bin")
            info.size = member_bytes
            tar.addfile(info, io.BytesIO(zeros))
    return buffer.getvalue()


def lie_about_sizes(blob: bytes, file_size: int, local_too: bool) -> bytes:
    """The zip with every member's uncompressed size in its central directory entry
    (and, with ``local_too``, in its local header) overwritten by ``file_size``."""
    data = bytearray(blob)
    eocd = data.rindex(b"PK\x05\x06")
    n_entries, _, cd_offset = struct.unpack_from("<HLL", data, eocd + 10)
    at = cd_offset
    for _ in range(n_entries):
        assert data[at : at + 4] == b"PK\x01\x02"
        struct.pack_into("<L", data, at + 24, file_size)
        local = struct.unpack_from("<L", data, at + 42)[0]
        if local_too:
            assert data[local : local + 4] == b"PK\x03\x04"
            struct.pack_into("<L", data, local + 22, file_size)
        name_len, extra_len, comment_len = struct.unpack_from("<HHH", data, at + 28)
        at += 46 + name_len + extra_len + comment_len
    return bytes(data)


def kitti_run(scan_bytes: int, rng: np.random.Generator, kind: str = "tar") -> bytes:
    """A one-frame KITTI sequence the reader accepts (a noise image, a scan of random
    points of ``scan_bytes``), as a plain tar or a stored zip."""
    import cv2

    ok, png = cv2.imencode(".png", rng.integers(0, 255, (240, 320), dtype=np.uint8))
    assert ok
    pose = " ".join(str(v) for v in np.eye(4)[:3].ravel())
    files = {
        "kitti/sequences/00/calib.txt": f"P0: 300 0 159.5 0 0 300 119.5 0 0 0 1 0\nTr: {pose}\n",
        "kitti/sequences/00/times.txt": "0.0\n",
        "kitti/poses/00.txt": pose + "\n",
        "kitti/sequences/00/image_0/000000.png": png.tobytes(),
        "kitti/sequences/00/velodyne/000000.bin": rng.random(scan_bytes // 4, np.float32),
    }
    buffer = io.BytesIO()
    if kind == "zip":
        with zipfile.ZipFile(buffer, "w") as archive:
            for name, content in files.items():
                archive.writestr(name, content if isinstance(content, str) else bytes(content))
        return buffer.getvalue()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        for name, content in files.items():
            data = content.encode() if isinstance(content, str) else bytes(content)
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


# --- the server ------------------------------------------------------------------------


@dataclass
class Server:
    client: object
    keys: object
    map_id: int
    uploads: Path
    data_dir: Path

    def upload(self, blob: bytes, name: str = "run.zip"):
        start = time.perf_counter()
        r = self.client.post(  # type: ignore[attr-defined]
            f"/v1/maps/{self.map_id}/runs",
            headers=self.keys.header("write"),  # type: ignore[attr-defined]
            files={"archive": (name, blob, "application/octet-stream")},
            data={"format": "kitti"},
        )
        return r, time.perf_counter() - start

    def runs(self) -> list:
        return self.client.get(  # type: ignore[attr-defined]
            f"/v1/maps/{self.map_id}/runs",
            headers=self.keys.header("write"),  # type: ignore[attr-defined]
        ).json()


@contextmanager
def server(tmp_path: Path, **overrides) -> Iterator[Server]:
    settings = make_settings(tmp_path / "data", **{"max_archive_bytes": LIMIT, **overrides})
    with open_client(settings) as client:
        keys = create_keys(client)
        r = client.post(
            "/v1/maps", json={"name": "m", "camera": CAMERA}, headers=keys.header("admin")
        )
        assert r.status_code == 201, r.text
        uploads = Path(settings.uploads_dir)  # type: ignore[arg-type]
        yield Server(client, keys, r.json()["id"], uploads, tmp_path / "data")


def refused(r, status: int, code: str, setting: str) -> None:
    assert r.status_code == status, r.text
    error = r.json()["error"]
    assert error["code"] == code, error
    assert setting in error["message"], error


def left_nothing(srv: Server) -> None:
    assert [p.name for p in srv.uploads.iterdir()] == [], "temp files must be removed"
    assert srv.runs() == []


# --- the bombs -------------------------------------------------------------------------


def test_zip_bomb_is_refused_from_its_central_directory(tmp_path):
    bomb = zeros_zip(16, 4 * MiB)  # declares 64 MiB, twice the limit, in ~70 kB
    assert len(bomb) < 200_000
    with server(tmp_path) as srv:
        with watching(srv.uploads) as disk:
            r, elapsed_s = srv.upload(bomb)
        assert disk.created == [], "nothing may be extracted before the refusal"
        assert disk.peak_bytes == 0
        refused(r, 413, "archive_too_large", "MONOLOC_MAX_ARCHIVE_BYTES")
        assert elapsed_s < 5.0
        left_nothing(srv)


def test_zip_whose_central_directory_lies_is_refused(tmp_path):
    bomb = zeros_zip(8, 4 * MiB)  # 32 MiB of zeros, the directory saying 64 KiB each
    with server(tmp_path, max_archive_bytes=16 * MiB) as srv:
        with watching(srv.uploads) as disk:
            r, _ = srv.upload(lie_about_sizes(bomb, 64 * 1024, local_too=False))
        assert r.status_code == 400, r.text
        message = r.json()["error"]["message"]
        assert "central directory declares 65536 bytes" in message, message
        assert f"local header {4 * MiB}" in message, message
        assert disk.created == [] and disk.peak_bytes == 0
        # both headers lie alike: the copy stops at the declared size, the CRC refuses
        with watching(srv.uploads) as disk:
            r, elapsed_s = srv.upload(lie_about_sizes(bomb, 64 * 1024, local_too=True))
        assert r.status_code == 400, r.text
        assert "CRC" in r.json()["error"]["message"]
        assert disk.peak_bytes <= 64 * 1024, disk.peak_bytes
        assert len(disk.created) == 1 and elapsed_s < 5.0
        left_nothing(srv)


def test_tar_bomb_is_refused_as_it_streams(tmp_path):
    bomb = zeros_tar_gz(16, 4 * MiB)  # 64 MiB of zeros in ~70 kB of gzip
    assert len(bomb) < 200_000
    with server(tmp_path) as srv:
        with watching(srv.uploads) as disk:
            r, elapsed_s = srv.upload(bomb, "run.tar.gz")
        # the ratio stops the copy within the allowance (1 MiB) and a chunk or two, long
        # before the 32 MiB limit: a fraction of one member is written
        assert len(disk.created) <= 1, disk.created
        assert disk.peak_bytes <= 3 * MiB, disk.peak_bytes
        refused(r, 413, "compression_ratio_too_high", "MONOLOC_MAX_ARCHIVE_RATIO")
        assert elapsed_s < 5.0
        left_nothing(srv)


def test_ratio_bomb_under_the_size_limit_is_refused(tmp_path):
    with server(tmp_path) as srv:
        # 4 x 2 MiB of zeros: 8 MiB, a quarter of the limit, at ~1000x
        with watching(srv.uploads) as disk:
            r, _ = srv.upload(zeros_zip(4, 2 * MiB))
        refused(r, 413, "compression_ratio_too_high", "MONOLOC_MAX_ARCHIVE_RATIO")
        assert "member 'bomb/000.bin'" in r.json()["error"]["message"]
        assert disk.created == [] and disk.peak_bytes == 0
        with watching(srv.uploads) as disk:
            r, _ = srv.upload(zeros_tar_gz(2, 4 * MiB), "run.tgz")
        refused(r, 413, "compression_ratio_too_high", "MONOLOC_MAX_ARCHIVE_RATIO")
        assert disk.peak_bytes <= 3 * MiB, disk.peak_bytes
        # members within the allowance may compress as well as they like: this one goes
        # on to the reader, which finds no KITTI run in it
        r, _ = srv.upload(zeros_zip(2, 256 * 1024))
        assert r.status_code == 422, r.text
        left_nothing(srv)


def test_a_tar_member_bomb_behind_real_data_is_refused_by_its_own_ratio(tmp_path):
    """Random bytes (incompressible, as images are) first, then 8 MiB of zeros: the
    archive's overall ratio stays near 5x, the zeros member alone is ~1000x."""
    rng = np.random.default_rng(7)
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz", compresslevel=6) as tar:
        for name, data in (
            ("run/noise.bin", rng.bytes(2 * MiB)),
            ("run/zeros.bin", bytes(8 * MiB)),
        ):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    blob = buffer.getvalue()
    assert 10 * MiB / len(blob) < 10  # far under the overall limit of 100x
    with server(tmp_path) as srv:
        with watching(srv.uploads) as disk:
            r, _ = srv.upload(blob, "run.tar.gz")
        assert disk.peak_bytes <= 2 * MiB + 3 * MiB, disk.peak_bytes
        refused(r, 413, "compression_ratio_too_high", "MONOLOC_MAX_ARCHIVE_RATIO")
        assert "member 'run/zeros.bin'" in r.json()["error"]["message"]
        left_nothing(srv)


def test_many_small_files_exceed_the_per_upload_disk_quota(tmp_path):
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        for i in range(300):  # 300 one-byte files take 300 blocks of 4 KiB
            info = tarfile.TarInfo(f"run/{i:03d}.txt")
            info.size = 1
            tar.addfile(info, io.BytesIO(b"x"))
    blob = buffer.getvalue()
    with server(tmp_path, upload_disk_quota_bytes=len(blob) + 200 * 4096) as srv:
        with watching(srv.uploads) as disk:
            r, _ = srv.upload(blob, "run.tar")
        refused(r, 413, "upload_quota_exceeded", "MONOLOC_UPLOAD_DISK_QUOTA_BYTES")
        assert len(disk.created) == 200, len(disk.created)
        left_nothing(srv)


def test_concurrent_uploads_share_one_disk_quota(tmp_path):
    """Upload A is held inside its database transaction (the test holds SQLite's write
    lock) after unpacking, so its disk stays reserved; B, which would fit alone, is
    answered 507 with Retry-After at once, before writing a file (a zip: its whole need is
    known from its central directory); once A is stored, B fits."""
    rng = np.random.default_rng(50)
    run_a, run_b = kitti_run(6 * MiB, rng), kitti_run(6 * MiB, rng, "zip")
    # each holds its archive and its files (~12 MiB) while it is unpacked; 20 MiB fits one
    with server(tmp_path, uploads_disk_quota_bytes=20 * MiB, busy_timeout_ms=60_000) as srv:
        lock = sqlite3.connect(srv.data_dir / "monoloc.db", timeout=10, isolation_level=None)
        lock.execute("BEGIN IMMEDIATE")
        answers: dict[str, object] = {}
        thread = threading.Thread(target=lambda: answers.update(a=srv.upload(run_a, "a.tar")[0]))
        try:
            with watching(srv.uploads) as disk:
                thread.start()
                deadline = time.monotonic() + 30
                while disk.held_bytes() < 6 * MiB:  # A unpacked, now waiting for the lock
                    assert time.monotonic() < deadline and thread.is_alive(), answers
                    time.sleep(0.01)
                created_by_a = len(disk.created)
                r, elapsed_s = srv.upload(run_b, "b.zip")
            refused(r, 507, "insufficient_storage", "MONOLOC_UPLOADS_DISK_QUOTA_BYTES")
            assert int(r.headers["Retry-After"]) >= 1
            assert elapsed_s < 5.0
            assert len(disk.created) == created_by_a, "B must not write a file"
            assert disk.peak_bytes <= 20 * MiB, disk.peak_bytes
            assert thread.is_alive(), "A is still held by the lock"
        finally:
            lock.execute("ROLLBACK")
            lock.close()
            thread.join(60)
        assert answers["a"].status_code == 202, answers["a"].text  # type: ignore[attr-defined]
        r, _ = srv.upload(run_b, "b.zip")
        assert r.status_code == 202, r.text
        assert sorted(run["source_name"] for run in srv.runs()) == ["a.tar", "b.zip"]
