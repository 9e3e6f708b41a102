"""Index files: written atomically, stamped with the map version, verified on load.

A file is an uncompressed ``.npz`` (zip members carry CRC-32, so torn or flipped bytes
are detected) holding the index arrays, the map version and, for IVF indexes, the
serialised FAISS index so a large map does not re-train on start. On start the server
loads it only if it is intact and its version equals the database's; anything else is
rebuilt from the database, never served empty.
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
    import faiss

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = index.snapshot()
    payload = dict(arrays)
    payload["map_version"] = np.array(map_version, dtype=np.int64)
    payload["format_version"] = np.array(FORMAT_VERSION, dtype=np.int64)
    if index.kind in ("ivf", "hnsw"):
        with index._lock.read():
            if index._tombstones == 0:  # else rebuilt on load, without the removed nodes
                payload["faiss_large"] = faiss.serialize_index_binary(index._faiss)
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
    """Load an index file; raise IndexFileError if missing, stale or corrupt."""
    import faiss

    path = Path(path)
    if not path.exists():
        raise IndexFileError(f"index file {path} is missing")
    try:
        with np.load(path, allow_pickle=False) as data:
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
    ivf = None
    if "faiss_large" in arrays:
        try:
            ivf = faiss.deserialize_index_binary(arrays["faiss_large"])
        except RuntimeError as exc:
            raise IndexFileError(f"index file {path}: unreadable FAISS index: {exc}") from exc
    try:
        return RetrievalIndex.from_arrays(
            arrays["ids"],
            arrays["codes"],
            arrays["vlads"],
            arrays["poses"],
            config,
            ivf,
            sketches=arrays.get("sketches"),
        )
    except (ValueError, MonolocError) as exc:
        raise IndexFileError(f"index file {path} is inconsistent: {exc}") from exc
