"""Safe unpacking of uploaded mapping runs (a tar or zip archive, or a set of files).

Every member name is checked before anything is written: relative, no ``..``, no
backslash, no drive letter, no NUL, no duplicates (400). Only regular files and
directories are written; symlinks, hard links and device files are refused (400).
Archives are recognised by their magic bytes (415 otherwise). Nothing is extracted with
``extractall``: each file is created by this module under the destination directory,
which the caller deletes on any error.

Bounds, and the answer each gives (a zip bomb of 80 x 64 MiB of zeros in 5 MB was
unpacked to the 4 GiB limit before this module refused it; issue 50):

* **Declared size** (413 ``archive_too_large``, ``MONOLOC_MAX_ARCHIVE_BYTES``) and
  **member count** (413, ``MONOLOC_MAX_ARCHIVE_MEMBERS``). A zip is checked whole from its
  central directory before the first file is created, and each member's local header
  must agree with the central directory (400 otherwise: a lying archive). A tar is
  checked header by header as it streams, before the member's data is written.
* **Compression ratio** (413 ``compression_ratio_too_high``, ``MONOLOC_MAX_ARCHIVE_RATIO``,
  default 100x): per member and for the whole archive; a zip from its declared sizes, a
  tar (gzip/bzip2/xz) while copying, the bytes unpacked against the archive bytes read
  (so far, and while the member was copied); a tar's declared total against its size.
  Members up to ``MONOLOC_ARCHIVE_RATIO_ALLOWANCE_BYTES`` (1 MiB), and as much of the
  total, are exempt: small text files (calib.txt, times.txt) compress far better than
  images. Real runs
  (PNG images, LiDAR floats) compress about 1-3x. Zip members are stored or deflated
  (415 for bzip2/lzma: Python decompresses those without an output bound).
* **Running total**: every copy counts the bytes it writes and stops at the member's
  declared size and at the archive limit, whatever a header says.
* **Disk quotas**: one upload may occupy ``MONOLOC_UPLOAD_DISK_QUOTA_BYTES`` while it is
  unpacked (the received archive plus its files, each file and directory in whole 4 KiB
  blocks; 413 ``upload_quota_exceeded``: the upload itself is too big for this server),
  and all the uploads this server process unpacks at the same time together
  ``MONOLOC_UPLOADS_DISK_QUOTA_BYTES`` (507 ``insufficient_storage`` with Retry-After:
  the upload is fine, the space is taken by others now; retry later). Space is
  reserved before it is written (a zip's whole need before extracting) and given back
  when the upload is stored or refused.
"""

from __future__ import annotations

import math
import stat
import struct
import tarfile
import threading
import zipfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO

from monoloc.core.errors import MonolocError
from monoloc.server.api.errors import (
    BadRequestError,
    PayloadTooLargeError,
    UnsupportedMediaTypeError,
)

_COPY_CHUNK = 1 << 20
BLOCK_BYTES = 4096
_ZIP_LOCAL_HEADER = struct.Struct("<4s5H3L2H")  # PK\3\4 ... name length, extra length
_ZIP_METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate"}


class ArchiveTooLargeError(PayloadTooLargeError):
    """The archive declares, or unpacks to, more than ``max_archive_bytes`` (413)."""


class CompressionRatioTooHighError(PayloadTooLargeError):
    """A member or the archive unpacks to more than ``max_archive_ratio`` times its
    compressed size (413: what the request would become is too large for what it is)."""


class UploadQuotaExceededError(PayloadTooLargeError):
    """One upload needs more disk than ``upload_disk_quota_bytes`` (413)."""


class InsufficientStorageError(MonolocError):
    """The uploads unpacking at the same time hold ``uploads_disk_quota_bytes``: this
    upload would fit alone; retry after ``Retry-After`` seconds (507)."""

    http_status = 507

    def __init__(self, message: str, retry_after_s: int = 10) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s

    @property
    def headers(self) -> dict[str, str]:
        return {"Retry-After": str(self.retry_after_s)}


def on_disk_bytes(n_bytes: int) -> int:
    """What a file of ``n_bytes`` (or a directory: 0) occupies: whole blocks, at least one."""
    return BLOCK_BYTES * max(1, math.ceil(n_bytes / BLOCK_BYTES))


@dataclass(frozen=True)
class ArchiveLimits:
    max_members: int
    max_total_bytes: int
    max_ratio: float = 100.0
    ratio_allowance_bytes: int = 1 << 20


@dataclass(frozen=True)
class Unpacked:
    """What landed in the destination: file count and bytes written."""

    n_files: int
    total_bytes: int


class UploadSpace:
    """The disk promised to the uploads one process is unpacking into one directory,
    against a quota shared by all of them (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._in_use = 0

    @property
    def in_use_bytes(self) -> int:
        with self._lock:
            return self._in_use

    def take(self, n_bytes: int, quota_bytes: int, what: str) -> None:
        with self._lock:
            if self._in_use + n_bytes > quota_bytes:
                in_use = self._in_use
            else:
                self._in_use += n_bytes
                return
        raise InsufficientStorageError(
            f"{what} needs {n_bytes} more bytes of disk, but the uploads being unpacked now "
            f"hold {in_use} of MONOLOC_UPLOADS_DISK_QUOTA_BYTES={quota_bytes}; retry after "
            "the Retry-After seconds"
        )

    def give(self, n_bytes: int) -> None:
        with self._lock:
            self._in_use -= n_bytes


class Reservation:
    """One upload's share of an :class:`UploadSpace`: grows before bytes are written,
    bounded by the per-upload quota; :meth:`release` gives it all back."""

    def __init__(self, space: UploadSpace, upload_quota_bytes: int, all_quota_bytes: int) -> None:
        self.space = space
        self.upload_quota_bytes = upload_quota_bytes
        self.all_quota_bytes = all_quota_bytes
        self.held_bytes = 0

    def take(self, n_bytes: int, what: str) -> None:
        if self.held_bytes + n_bytes > self.upload_quota_bytes:
            raise UploadQuotaExceededError(
                f"{what} needs more than {self.upload_quota_bytes} bytes of disk while it is "
                "unpacked (the archive and its files in 4 KiB blocks); the limit is "
                f"MONOLOC_UPLOAD_DISK_QUOTA_BYTES={self.upload_quota_bytes}"
            )
        self.space.take(n_bytes, self.all_quota_bytes, what)
        self.held_bytes += n_bytes

    def release(self) -> None:
        self.space.give(self.held_bytes)
        self.held_bytes = 0


class _Writer:
    """Writes members under ``dest`` while enforcing the limits and name rules."""

    def __init__(
        self, dest: Path, limits: ArchiveLimits, what: str, reservation: Reservation | None
    ) -> None:
        self.dest = dest.resolve()
        self.limits = limits
        self.what = what
        self.reservation = reservation
        self.n_members = 0
        self.n_files = 0
        self.total_bytes = 0
        self.declared_bytes = 0
        self.seen: set[str] = set()

    def reserve(self, n_bytes: int) -> None:
        if self.reservation is not None:
            self.reservation.take(n_bytes, self.what)

    def check_name(self, raw_name: str) -> PurePosixPath:
        self.n_members += 1
        if self.n_members > self.limits.max_members:
            raise PayloadTooLargeError(
                f"{self.what} has more than {self.limits.max_members} members; the limit is "
                f"MONOLOC_MAX_ARCHIVE_MEMBERS={self.limits.max_members}"
            )
        name = raw_name.rstrip("/")
        while name.startswith("./"):
            name = name[2:]
        bad = (
            not name
            or "\\" in name
            or "\x00" in name
            or name.startswith("/")
            or (len(name) > 1 and name[1] == ":")
        )
        path = PurePosixPath(name)
        if bad or any(part in ("..", "") for part in path.parts):
            raise BadRequestError(
                f"{self.what}: member name {raw_name!r} is absolute or leaves the upload "
                "directory; refused"
            )
        key = str(path)
        if key in self.seen:
            raise BadRequestError(f"{self.what}: member {raw_name!r} appears twice")
        self.seen.add(key)
        target = (self.dest / path).resolve()
        if not target.is_relative_to(self.dest):
            raise BadRequestError(f"{self.what}: member {raw_name!r} leaves the upload directory")
        return path

    def declare(self, name: str, size: int) -> None:
        """Count a member's declared size against the archive limit (before its data)."""
        if size < 0:
            raise BadRequestError(f"{self.what}: member {name!r} has a negative size")
        self.declared_bytes += size
        if self.declared_bytes > self.limits.max_total_bytes:
            raise ArchiveTooLargeError(
                f"{self.what} declares more than {self.limits.max_total_bytes} bytes "
                f"unpacked (at member {name!r}); the limit is "
                f"MONOLOC_MAX_ARCHIVE_BYTES={self.limits.max_total_bytes}"
            )

    def check_ratio(self, unpacked: int, packed: int, which: str) -> None:
        allowance = self.limits.ratio_allowance_bytes
        if unpacked > allowance + self.limits.max_ratio * max(packed, 1):
            raise CompressionRatioTooHighError(
                f"{which} unpacks {unpacked} bytes from {packed}, more than "
                f"{self.limits.max_ratio:g}x; the limit is MONOLOC_MAX_ARCHIVE_RATIO="
                f"{self.limits.max_ratio:g} (the first MONOLOC_ARCHIVE_RATIO_ALLOWANCE_BYTES="
                f"{allowance} are exempt)"
            )

    def add_dir(self, path: PurePosixPath, reserved: bool = False) -> None:
        if not reserved:
            self.reserve(on_disk_bytes(0))
        (self.dest / path).mkdir(parents=True, exist_ok=True)

    def add_file(
        self,
        path: PurePosixPath,
        declared_size: int,
        source: BinaryIO,
        reserved: bool = False,
        on_chunk: Callable[[int], None] | None = None,
    ) -> None:
        """Copy ``source`` to ``path``: at most ``declared_size`` bytes (more is a lie,
        400) and never past the archive limit; ``on_chunk(total so far)`` after each
        chunk read (the running ratio). ``reserved``: its disk is already reserved."""
        if declared_size < 0:
            raise BadRequestError(f"{self.what}: member {str(path)!r} has a negative size")
        if self.total_bytes + declared_size > self.limits.max_total_bytes:
            raise ArchiveTooLargeError(
                f"{self.what} unpacks to more than {self.limits.max_total_bytes} bytes; the "
                f"limit is MONOLOC_MAX_ARCHIVE_BYTES={self.limits.max_total_bytes}"
            )
        if not reserved:
            self.reserve(on_disk_bytes(declared_size))
        target = self.dest / path
        target.parent.mkdir(parents=True, exist_ok=True)
        written = 0
        with open(target, "xb") as out:
            while True:
                chunk = source.read(min(_COPY_CHUNK, declared_size - written + 1))
                if not chunk:
                    break
                written += len(chunk)
                if written > declared_size:
                    raise BadRequestError(
                        f"{self.what}: member {str(path)!r} holds more than the "
                        f"{declared_size} bytes its header declares; refused"
                    )
                if self.total_bytes + written > self.limits.max_total_bytes:
                    raise ArchiveTooLargeError(  # unreachable unless a header lied
                        f"{self.what} unpacks to more than {self.limits.max_total_bytes} "
                        f"bytes; the limit is MONOLOC_MAX_ARCHIVE_BYTES="
                        f"{self.limits.max_total_bytes}"
                    )
                if on_chunk is not None:
                    on_chunk(self.total_bytes + written)
                out.write(chunk)
        self.total_bytes += written
        self.n_files += 1


def _kind(fileobj: BinaryIO) -> str:
    head = fileobj.read(512)
    fileobj.seek(0)
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return "zip"
    if head.startswith((b"\x1f\x8b", b"BZh", b"\xfd7zXZ\x00")):
        return "tar"  # compressed tar (gzip, bzip2, xz)
    if len(head) >= 262 and head[257:262] == b"ustar":
        return "tar"
    raise UnsupportedMediaTypeError(
        "the upload is neither a zip nor a (gzip/bzip2/xz-compressed) tar archive"
    )


def _size_of(fileobj: BinaryIO) -> int:
    fileobj.seek(0, 2)
    size = fileobj.tell()
    fileobj.seek(0)
    return size


class _Metered:
    """A file object that remembers how far into it anything has read (the compressed
    bytes a tar stream consumed), passing everything else through."""

    def __init__(self, raw: BinaryIO) -> None:
        self._raw = raw
        self.read_bytes = 0

    def read(self, n: int = -1) -> bytes:
        data = self._raw.read(n)
        self.read_bytes = max(self.read_bytes, self._raw.tell())
        return data

    def seek(self, *args: Any) -> int:
        return self._raw.seek(*args)

    def tell(self) -> int:
        return self._raw.tell()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._raw, name)


def _unpack_tar(fileobj: BinaryIO, writer: _Writer, packed_bytes: int) -> None:
    metered = _Metered(fileobj)
    member_start = {"written": 0, "read": 0, "name": ""}

    def running_ratio(unpacked: int) -> None:
        writer.check_ratio(unpacked, metered.read_bytes, writer.what)
        # the member alone (a bomb behind enough real data passes the overall ratio): the
        # archive bytes read while it is copied, read-ahead included, so never too few
        in_member = unpacked - member_start["written"]
        if in_member > writer.limits.ratio_allowance_bytes:
            read = metered.read_bytes - member_start["read"]
            writer.check_ratio(in_member, read, f"{writer.what}: member {member_start['name']!r}")

    try:
        with tarfile.open(fileobj=metered, mode="r:*") as tar:  # type: ignore[call-overload]
            for member in tar:  # streamed: each header is checked before its data is read
                path = writer.check_name(member.name)
                if member.issym() or member.islnk():
                    raise BadRequestError(
                        f"{writer.what}: member {member.name!r} is a link; links are refused"
                    )
                if member.isdir():
                    writer.add_dir(path)
                elif member.isfile():
                    writer.declare(member.name, member.size)
                    writer.check_ratio(writer.declared_bytes, packed_bytes, writer.what)
                    source = tar.extractfile(member)
                    assert source is not None
                    member_start.update(
                        written=writer.total_bytes, read=metered.read_bytes, name=member.name
                    )
                    writer.add_file(path, member.size, source, on_chunk=running_ratio)
                else:
                    raise BadRequestError(
                        f"{writer.what}: member {member.name!r} is not a regular file or directory"
                    )
    except (tarfile.TarError, EOFError, OSError) as exc:
        raise BadRequestError(f"{writer.what}: unreadable tar archive: {exc}") from exc


def _local_header_sizes(fileobj: BinaryIO, info: zipfile.ZipInfo) -> tuple[int, int] | None:
    """(compressed, uncompressed) sizes in a member's local header, or None where the
    local header does not hold them (a data descriptor follows the data; zip64)."""
    fileobj.seek(info.header_offset)
    raw = fileobj.read(_ZIP_LOCAL_HEADER.size)
    if len(raw) != _ZIP_LOCAL_HEADER.size:
        raise zipfile.BadZipFile(f"member {info.filename!r}: truncated local header")
    signature, _, flags, _, _, _, _, packed, unpacked, _, _ = _ZIP_LOCAL_HEADER.unpack(raw)
    if signature != b"PK\x03\x04":
        raise zipfile.BadZipFile(f"member {info.filename!r}: no local header at its offset")
    if flags & 0x08 or 0xFFFFFFFF in (packed, unpacked):
        return None
    return packed, unpacked


def _check_zip(
    fileobj: BinaryIO, infos: list[zipfile.ZipInfo], writer: _Writer, packed: int
) -> tuple[int, list[PurePosixPath]]:
    """Everything about a zip that its directory tells, before any file is created:
    names, types, sizes against the limit and the ratio, local headers against the
    central directory. Returns the disk the members will take and their paths."""
    if len(infos) > writer.limits.max_members:
        raise PayloadTooLargeError(
            f"{writer.what} has {len(infos)} members; the limit is "
            f"MONOLOC_MAX_ARCHIVE_MEMBERS={writer.limits.max_members}"
        )
    need, paths, members = 0, [], []
    for info in infos:  # names, types and the declared total first: the size limit rules
        paths.append(writer.check_name(info.filename))
        if stat.S_ISLNK(info.external_attr >> 16):
            raise BadRequestError(
                f"{writer.what}: member {info.filename!r} is a link; links are refused"
            )
        if info.flag_bits & 0x1:
            raise BadRequestError(f"{writer.what}: member {info.filename!r} is encrypted")
        if info.is_dir():
            need += on_disk_bytes(0)
            continue
        if info.compress_type not in _ZIP_METHODS:
            raise UnsupportedMediaTypeError(
                f"{writer.what}: member {info.filename!r} uses zip compression method "
                f"{info.compress_type}; only stored and deflate members are accepted"
            )
        writer.declare(info.filename, info.file_size)
        need += on_disk_bytes(info.file_size)
        members.append(info)
    for info in members:
        if info.file_size > writer.limits.ratio_allowance_bytes:
            writer.check_ratio(
                info.file_size, info.compress_size, f"{writer.what}: member {info.filename!r}"
            )
    writer.check_ratio(writer.declared_bytes, packed, writer.what)
    for info in members:
        local = _local_header_sizes(fileobj, info)
        if local is not None and local != (info.compress_size, info.file_size):
            raise BadRequestError(
                f"{writer.what}: member {info.filename!r}: the central directory declares "
                f"{info.file_size} bytes ({info.compress_size} compressed), its local header "
                f"{local[1]} ({local[0]}); refused before extracting"
            )
    return need, paths


def _unpack_zip(fileobj: BinaryIO, writer: _Writer, packed_bytes: int) -> None:
    try:
        with zipfile.ZipFile(fileobj) as archive:
            infos = archive.infolist()
            need, paths = _check_zip(fileobj, infos, writer, packed_bytes)
            writer.reserve(need)
            for info, path in zip(infos, paths, strict=True):
                if info.is_dir():
                    writer.add_dir(path, reserved=True)
                    continue
                with archive.open(info) as source:
                    writer.add_file(path, info.file_size, source, reserved=True)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError) as exc:
        raise BadRequestError(f"{writer.what}: unreadable zip archive: {exc}") from exc


def unpack_archive(
    fileobj: BinaryIO,
    dest: Path,
    limits: ArchiveLimits,
    what: str,
    reservation: Reservation | None = None,
) -> Unpacked:
    """Unpack a tar (plain or compressed) or zip ``fileobj`` (seekable) into ``dest``,
    taking its disk from ``reservation`` (the received archive first)."""
    kind = _kind(fileobj)
    packed_bytes = _size_of(fileobj)
    writer = _Writer(dest, limits, what, reservation)
    writer.reserve(packed_bytes)  # the received archive is on disk while it is unpacked
    dest.mkdir(parents=True, exist_ok=True)
    if kind == "zip":
        _unpack_zip(fileobj, writer, packed_bytes)
    else:
        _unpack_tar(fileobj, writer, packed_bytes)
    return Unpacked(writer.n_files, writer.total_bytes)


def save_file_set(
    files: Iterable[tuple[str, BinaryIO]],
    dest: Path,
    limits: ArchiveLimits,
    what: str,
    reservation: Reservation | None = None,
) -> Unpacked:
    """Write uploaded files named by relative paths (``image_0/000000.png``) into ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    writer = _Writer(dest, limits, what, reservation)
    for name, fileobj in files:
        path = writer.check_name(name)
        size = _size_of(fileobj)
        writer.declare(name, size)
        writer.reserve(size)  # the received copy, spooled by the multipart parser
        writer.add_file(path, size, fileobj)
    return Unpacked(writer.n_files, writer.total_bytes)
