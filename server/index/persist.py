"""Index files: written atomically, stamped with the map version, verified on load.

An index is two files: ``<name>.npz``, an uncompressed ``.npz`` (zip members carry
CRC-32, so torn or flipped bytes are detected) with the arrays held in memory (ids,
codes, 4-bit VLADs, sketches, poses), the map version and the name and CRC-32 of the
second, ``<name>.<token>.vlads.npy``: the float32 VLADs in row order, opened on load
and read row by row on demand (only the page cache holds them). The float file is written and
renamed first, the ``.npz`` that names it last, so a crash between leaves the old pair
intact. On start the server loads a pair only if both are intact and the version equals
the database's; anything else is rebuilt from the database, never served empty. Files of
older formats (float VLADs inside the ``.npz``; a serialised FAISS HNSW or IVF index) are
refused the same way, so their map is rebuilt with the current index.
"""

from __future__ import annotations

import os
import secrets
import tempfile
import zipfile
import zlib
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from monoloc.core.errors import MonolocError
from monoloc.server.index.retrieval import IndexConfig, RetrievalIndex
from monoloc.server.index.vlad_store import VladFile
from monoloc.server.vision.sizes import VLAD_DIM

FORMAT_VERSION = 2
_REMOVED_KIND_MEMBER = "faiss_large"
_REQUIRED = {
    "ids",
    "codes",
    "compressed",
    "sketches",
    "poses",
    "map_version",
    "format_version",
    "vlad_file",
    "vlad_crc32",
}


class IndexFileError(MonolocError):
    """The index file is missing, stale or corrupt; rebuild it from the database."""


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def vlad_files(path: Path) -> list[Path]:
    """The float VLAD files written beside index file ``path`` (current and leftovers)."""
    path = Path(path)
    return sorted(path.parent.glob(f"{path.name}.*.vlads.npy"))


def delete_index(path: Path) -> None:
    """Remove index file ``path`` and its float VLAD files."""
    path = Path(path)
    path.unlink(missing_ok=True)
    for stale in vlad_files(path):
        stale.unlink(missing_ok=True)


def _write_atomically(path: Path, write) -> None:
    fd, tmp_name = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise


def _write_vlads(path: Path, n: int, blocks: Iterable[np.ndarray]) -> int:
    """Write (n, 2048) float32 VLADs, given in blocks, as a ``.npy`` file; returns the
    CRC-32 of the data (the header excluded)."""
    crc = 0

    def write(fh) -> None:
        nonlocal crc
        header = {"descr": "<f4", "fortran_order": False, "shape": (n, VLAD_DIM)}
        np.lib.format.write_array_header_1_0(fh, header)
        written = 0
        for block in blocks:
            data = np.ascontiguousarray(block, dtype="<f4").tobytes()
            crc = zlib.crc32(data, crc)
            fh.write(data)
            written += len(block)
        if written != n:
            raise ValueError(f"{written} VLADs written for {n} entries")

    _write_atomically(path, write)
    return crc


def write_index_files(
    path: Path, arrays: dict[str, np.ndarray], vlad_blocks: Iterable[np.ndarray], map_version: int
) -> Path:
    """Write an index pair: the float VLADs (given in row order, in blocks) then the
    ``.npz`` of ``arrays`` (ids, codes, compressed, sketches, poses) naming them; old
    float files are removed. Returns the float file's path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = len(arrays["ids"])
    vlad_path = path.with_name(f"{path.name}.{secrets.token_hex(8)}.vlads.npy")
    crc = _write_vlads(vlad_path, n, vlad_blocks)
    payload = dict(arrays)
    payload["map_version"] = np.array(map_version, dtype=np.int64)
    payload["format_version"] = np.array(FORMAT_VERSION, dtype=np.int64)
    payload["vlad_file"] = np.array(vlad_path.name)
    payload["vlad_crc32"] = np.array(crc, dtype=np.int64)
    try:
        _write_atomically(path, lambda fh: np.savez(fh, **payload))
    except BaseException:
        vlad_path.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    for stale in vlad_files(path):
        if stale != vlad_path:
            stale.unlink(missing_ok=True)  # a mapping of it stays readable until closed
    return vlad_path


def save_index(path: Path, index: RetrievalIndex, map_version: int) -> None:
    """Write ``index`` to ``path`` (and its float file) atomically; the index then reads
    its float VLADs from the new file and drops the ones it held in memory (unless it was
    edited meanwhile: then it keeps them until the next save)."""
    arrays, blocks, edits = index.persist_state()
    vlad_path = write_index_files(path, arrays, blocks, map_version)
    index.adopt_vlads(map_vlads(vlad_path), edits)


def _data_offset(vlad_path: Path) -> tuple[tuple[int, ...], int]:
    """A ``.npy`` file's shape and the offset of its data."""
    with open(vlad_path, "rb") as fh:
        major, _ = np.lib.format.read_magic(fh)
        read_header = np.lib.format.read_array_header_1_0
        if major != 1:
            read_header = np.lib.format.read_array_header_2_0
        shape, fortran_order, dtype = read_header(fh)
        if fortran_order or dtype != np.dtype("<f4"):
            raise ValueError(f"not a C-ordered float32 array ({dtype})")
        return shape, fh.tell()


def map_vlads(vlad_path: Path) -> VladFile:
    """A float VLAD file, opened for reading rows on demand."""
    shape, offset = _data_offset(vlad_path)
    if len(shape) != 2 or shape[1] != VLAD_DIM:
        raise ValueError(f"shape {shape}, not (N, {VLAD_DIM})")
    return VladFile(vlad_path, shape[0], offset)


def _file_crc32(path: Path, offset: int) -> int:
    """CRC-32 of a file's bytes from ``offset`` on, read with plain reads: the page cache
    keeps them, but this process maps none of them (its resident set stays small)."""
    crc = 0
    with open(path, "rb") as fh:
        fh.seek(offset)
        while chunk := fh.read(1 << 24):
            crc = zlib.crc32(chunk, crc)
    return crc


def _checked_vlads(path: Path, name: str, n: int, crc: int) -> np.ndarray:
    vlad_path = path.parent / name
    if Path(name).name != name or not vlad_path.exists():
        raise IndexFileError(f"index file {path}: its VLAD file {name} is missing")
    try:
        vlads = map_vlads(vlad_path)
    except (OSError, ValueError) as exc:
        raise IndexFileError(f"index file {path}: VLAD file {name} is corrupt: {exc}") from exc
    if vlads.shape != (n, VLAD_DIM):
        raise IndexFileError(f"index file {path}: VLAD file {name} has the wrong shape")
    if _file_crc32(vlad_path, _data_offset(vlad_path)[1]) != crc:
        raise IndexFileError(f"index file {path}: VLAD file {name} is corrupt (CRC-32)")
    return vlads


def load_index(
    path: Path, expected_map_version: int, config: IndexConfig | None = None
) -> RetrievalIndex:
    """Load an index file; raise IndexFileError if missing, stale, corrupt or of an older
    format."""
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
            if "vlads" in data.files:  # format 1: not read, it is N x 8 KiB
                raise IndexFileError(f"index file {path} has an older layout (format 1)")
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as exc:
        raise IndexFileError(f"index file {path} is corrupt: {exc}") from exc
    if not _REQUIRED <= arrays.keys() or int(arrays["format_version"]) != FORMAT_VERSION:
        raise IndexFileError(f"index file {path} has an unknown layout")
    version = int(arrays["map_version"])
    if version != expected_map_version:
        raise IndexFileError(
            f"index file {path} is stale: map version {version}, database {expected_map_version}"
        )
    vlads = _checked_vlads(
        path, str(arrays["vlad_file"]), len(arrays["ids"]), int(arrays["vlad_crc32"])
    )
    try:
        return RetrievalIndex.from_arrays(
            arrays["ids"],
            arrays["codes"],
            vlads,
            arrays["poses"],
            config,
            sketches=arrays["sketches"],
            compressed=arrays["compressed"],
        )
    except (ValueError, MonolocError) as exc:
        raise IndexFileError(f"index file {path} is inconsistent: {exc}") from exc


def rebuild_index(
    path: Path,
    batches: Iterable,
    map_version: int,
    config: IndexConfig | None = None,
) -> RetrievalIndex:
    """Build an index from the database's batches (``MapVectors``: entry_ids, codes,
    vlads, planar) straight into its files, then load it: the float VLADs go to the file
    as they come, never all in memory."""
    from monoloc.server.index.compressed import compress_vlads
    from monoloc.server.index.sketch import vlad_sketch

    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("ids", "codes", "compressed")}
    parts |= {"sketches": [], "poses": []}
    spool = tempfile.TemporaryFile(dir=Path(path).parent if Path(path).parent.exists() else None)
    with spool:
        for batch in batches:
            vlads = np.asarray(batch.vlads, dtype="<f4").reshape(-1, VLAD_DIM)
            parts["ids"].append(np.asarray(batch.entry_ids, dtype=np.int64).reshape(-1))
            parts["codes"].append(np.asarray(batch.codes, dtype=np.uint8))
            parts["compressed"].append(compress_vlads(vlads))
            parts["sketches"].append(vlad_sketch(vlads))
            parts["poses"].append(np.asarray(batch.planar, dtype=np.float64).reshape(-1, 3))
            spool.write(vlads.tobytes())
        arrays = {
            name: np.concatenate(chunks) if chunks else _empty(name)
            for name, chunks in parts.items()
        }
        n = len(arrays["ids"])
        spool.flush()
        spool.seek(0)

        def spooled():
            rows = 4096
            for start in range(0, n, rows):
                count = min(rows, n - start)
                data = spool.read(count * VLAD_DIM * 4)
                yield np.frombuffer(data, dtype="<f4").reshape(count, VLAD_DIM)

        Path(path).parent.mkdir(parents=True, exist_ok=True)
        write_index_files(path, arrays, spooled(), map_version)
    return load_index(path, map_version, config)


def _empty(name: str) -> np.ndarray:
    from monoloc.server.index.compressed import COMPRESSED_BYTES
    from monoloc.server.index.sketch import SKETCH_BYTES
    from monoloc.server.vision.sizes import CODE_BYTES

    widths = {"codes": CODE_BYTES, "compressed": COMPRESSED_BYTES, "sketches": SKETCH_BYTES}
    if name == "ids":
        return np.zeros(0, dtype=np.int64)
    if name == "poses":
        return np.zeros((0, 3), dtype=np.float64)
    return np.zeros((0, widths[name]), dtype=np.uint8)
