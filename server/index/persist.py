"""Index files: written atomically, stamped with the map version, verified on load.

A file is an uncompressed ``.npz`` (zip members carry CRC-32, so torn or flipped bytes
are detected) holding the index arrays and the map version. On start the server loads it
only if it is intact and its version equals the database's; anything else is rebuilt
from the database, never served empty. A file that carries a serialised FAISS index
(``faiss_large``: written by the HNSW and IVF kinds monoloc no longer has) is refused the
same way, so its map is rebuilt with the current index.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from monoloc.core.errors import MonolocError
from monoloc.server.index.retrieval import IndexConfig, RetrievalIndex

FORMAT_VERSION = 1
_REMOVED_KIND_MEMBER = "faiss_large"


class IndexFileError(MonolocError):
    """The index file is missing, stale or corrupt; rebuild it from the database."""


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def save_index(path: Path, index: RetrievalIndex, map_version: int) -> None:
    """Write ``index`` to ``path`` atomically: temp file, fsync, rename, fsync directory."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = dict(index.snapshot())
    payload["map_version"] = np.array(map_version, dtype=np.int64)
    payload["format_version"] = np.array(FORMAT_VERSION, dtype=np.int64)
    fd, tmp_name = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, path)
        _fsync_dir(path.parent)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise


def load_index(
    path: Path, expected_map_version: int, config: IndexConfig | None = None
) -> RetrievalIndex:
    """Load an index file; raise IndexFileError if missing, stale, corrupt or of a removed
    kind."""
    path = Path(path)
    if not path.exists():
        raise IndexFileError(f"index file {path} is missing")
    try:
        with np.load(path, allow_pickle=False) as data:
            if _REMOVED_KIND_MEMBER in data.files:  # not read: it can be hundreds of MB
                raise IndexFileError(
                    f"index file {path} holds a FAISS HNSW or IVF index, kinds this server "
                    "no longer has"
                )
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as exc:
        raise IndexFileError(f"index file {path} is corrupt: {exc}") from exc
    required = {"ids", "codes", "vlads", "poses", "map_version", "format_version"}
    if not required <= arrays.keys() or int(arrays["format_version"]) != FORMAT_VERSION:
        raise IndexFileError(f"index file {path} has an unknown layout")
    version = int(arrays["map_version"])
    if version != expected_map_version:
        raise IndexFileError(
            f"index file {path} is stale: map version {version}, database {expected_map_version}"
        )
    try:
        return RetrievalIndex.from_arrays(
            arrays["ids"],
            arrays["codes"],
            arrays["vlads"],
            arrays["poses"],
            config,
            sketches=arrays.get("sketches"),
        )
    except (ValueError, MonolocError) as exc:
        raise IndexFileError(f"index file {path} is inconsistent: {exc}") from exc
