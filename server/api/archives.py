"""Safe unpacking of uploaded mapping runs (a tar or zip archive, or a set of files).

Every member name is checked before anything is written: relative, no ``..``, no
backslash, no drive letter, no NUL, no duplicates (400). Only regular files and
directories are written; symlinks, hard links and device files are refused (400).
The member count and the total uncompressed size are limited (413); sizes are the
declared ones, and the copy never writes more than declared, so a lying header cannot
exceed the limit either. Archives are recognised by their magic bytes (415 otherwise).
Nothing is extracted with ``extractall``: each file is created by this module under
the destination directory, which the caller deletes on any error.
"""

from __future__ import annotations

import stat
import tarfile
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from monoloc.server.api.errors import (
    BadRequestError,
    PayloadTooLargeError,
    UnsupportedMediaTypeError,
)

_COPY_CHUNK = 1 << 20


@dataclass(frozen=True)
class ArchiveLimits:
    max_members: int
    max_total_bytes: int


@dataclass(frozen=True)
class Unpacked:
    """What landed in the destination: file count and bytes written."""

    n_files: int
    total_bytes: int


class _Writer:
    """Writes members under ``dest`` while enforcing the limits and name rules."""

    def __init__(self, dest: Path, limits: ArchiveLimits, what: str) -> None:
        self.dest = dest.resolve()
        self.limits = limits
        self.what = what
        self.n_members = 0
        self.n_files = 0
        self.total_bytes = 0
        self.seen: set[str] = set()

    def check_name(self, raw_name: str) -> PurePosixPath:
        self.n_members += 1
        if self.n_members > self.limits.max_members:
            raise PayloadTooLargeError(
                f"{self.what} has more than {self.limits.max_members} members"
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

    def add_dir(self, path: PurePosixPath) -> None:
        (self.dest / path).mkdir(parents=True, exist_ok=True)

    def add_file(self, path: PurePosixPath, declared_size: int, source: BinaryIO) -> None:
        if declared_size < 0:
            raise BadRequestError(f"{self.what}: member {str(path)!r} has a negative size")
        if self.total_bytes + declared_size > self.limits.max_total_bytes:
            raise PayloadTooLargeError(
                f"{self.what} unpacks to more than {self.limits.max_total_bytes} bytes"
            )
        target = self.dest / path
        target.parent.mkdir(parents=True, exist_ok=True)
        written = 0
        with open(target, "xb") as out:
            while written < declared_size:
                chunk = source.read(min(_COPY_CHUNK, declared_size - written))
                if not chunk:
                    break
                out.write(chunk)
                written += len(chunk)
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


def _unpack_tar(fileobj: BinaryIO, writer: _Writer) -> None:
    try:
        with tarfile.open(fileobj=fileobj, mode="r:*") as tar:
            for member in tar:  # streamed: the member limit applies before reading on
                path = writer.check_name(member.name)
                if member.issym() or member.islnk():
                    raise BadRequestError(
                        f"{writer.what}: member {member.name!r} is a link; links are refused"
                    )
                if member.isdir():
                    writer.add_dir(path)
                elif member.isfile():
                    source = tar.extractfile(member)
                    assert source is not None
                    writer.add_file(path, member.size, source)
                else:
                    raise BadRequestError(
                        f"{writer.what}: member {member.name!r} is not a regular file or directory"
                    )
    except (tarfile.TarError, EOFError, OSError) as exc:
        raise BadRequestError(f"{writer.what}: unreadable tar archive: {exc}") from exc


def _unpack_zip(fileobj: BinaryIO, writer: _Writer) -> None:
    try:
        with zipfile.ZipFile(fileobj) as archive:
            infos = archive.infolist()
            if len(infos) > writer.limits.max_members:
                raise PayloadTooLargeError(
                    f"{writer.what} has {len(infos)} members; the limit is "
                    f"{writer.limits.max_members}"
                )
            for info in infos:
                path = writer.check_name(info.filename)
                mode = info.external_attr >> 16
                if stat.S_ISLNK(mode):
                    raise BadRequestError(
                        f"{writer.what}: member {info.filename!r} is a link; links are refused"
                    )
                if info.flag_bits & 0x1:
                    raise BadRequestError(f"{writer.what}: member {info.filename!r} is encrypted")
                if info.is_dir():
                    writer.add_dir(path)
                    continue
                with archive.open(info) as source:
                    writer.add_file(path, info.file_size, source)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError) as exc:
        raise BadRequestError(f"{writer.what}: unreadable zip archive: {exc}") from exc


def unpack_archive(fileobj: BinaryIO, dest: Path, limits: ArchiveLimits, what: str) -> Unpacked:
    """Unpack a tar (plain or compressed) or zip ``fileobj`` (seekable) into ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    writer = _Writer(dest, limits, what)
    if _kind(fileobj) == "zip":
        _unpack_zip(fileobj, writer)
    else:
        _unpack_tar(fileobj, writer)
    return Unpacked(writer.n_files, writer.total_bytes)


def save_file_set(
    files: Iterable[tuple[str, BinaryIO]], dest: Path, limits: ArchiveLimits, what: str
) -> Unpacked:
    """Write uploaded files named by relative paths (``image_0/000000.png``) into ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    writer = _Writer(dest, limits, what)
    for name, fileobj in files:
        path = writer.check_name(name)
        fileobj.seek(0, 2)
        size = fileobj.tell()
        fileobj.seek(0)
        writer.add_file(path, size, fileobj)
    return Unpacked(writer.n_files, writer.total_bytes)
