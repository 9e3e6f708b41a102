"""The visual vocabulary: k-means centres of ORB descriptors (docs/method.md section 3).

A vocabulary is versioned data. Its version is a hash of the centres' float32 bytes, so
two vocabularies with the same version give the same VLADs, and a map entry records the
version its VLAD was computed with.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.resources
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.sizes import DESCRIPTOR_BYTES, N_WORDS

DEFAULT_VOCABULARY_FILE = "default_vocabulary.npz"


@dataclass(frozen=True)
class VocabularyConfig:
    """k-means settings. ``max_descriptors`` (None = all) subsamples the training set with
    ``seed``; ``n_threads`` is the OpenMP thread count FAISS uses while training (fixed so
    that a retrain on the same machine reproduces the centres bit for bit)."""

    n_words: int = N_WORDS
    n_iter: int = 20
    seed: int = 0
    max_descriptors: int | None = None
    n_threads: int = 1

    def __post_init__(self) -> None:
        if self.n_words < 1 or self.n_iter < 1 or self.n_threads < 1:
            raise InvalidInputError(f"invalid VocabularyConfig {self}")
        if self.max_descriptors is not None and self.max_descriptors < self.n_words:
            raise InvalidInputError(
                f"VocabularyConfig.max_descriptors ({self.max_descriptors}) is below "
                f"n_words ({self.n_words})"
            )


def vocabulary_hash(centres: np.ndarray) -> str:
    """Version string of a vocabulary: first 16 hex digits of sha256 over the float32
    C-order bytes of ``centres`` (K, 32); K follows from the byte count, so no prefix."""
    data = np.ascontiguousarray(centres, dtype=np.float32)
    return hashlib.sha256(data.tobytes()).hexdigest()[:16]


@dataclass(frozen=True, eq=False)
class Vocabulary:
    """K visual words. centres: (K, 32) float32 in descriptor byte space (0..255 per
    entry), read-only; version: :func:`vocabulary_hash` of the centres; description: how
    it was made. docs/method.md uses K = 64; any K >= 1 works with VLAD (output K * 32)."""

    centres: np.ndarray
    version: str
    description: str = ""

    def __post_init__(self) -> None:
        centres = np.array(self.centres, dtype=np.float32, order="C")
        if centres.ndim != 2 or centres.shape[1] != DESCRIPTOR_BYTES or centres.shape[0] < 1:
            raise InvalidInputError(f"vocabulary centres must be (K, 32), got {centres.shape}")
        if not np.all(np.isfinite(centres)):
            raise InvalidInputError("vocabulary centres contain NaN or infinite values")
        centres.setflags(write=False)
        object.__setattr__(self, "centres", centres)
        if self.version != vocabulary_hash(centres):
            raise InvalidInputError(
                f"vocabulary version {self.version!r} does not match its centres "
                f"({vocabulary_hash(centres)!r})"
            )

    @classmethod
    def from_centres(cls, centres: np.ndarray, description: str = "") -> Vocabulary:
        """Build a vocabulary from (K, 32) centres, computing its version."""
        centres = np.asarray(centres, dtype=np.float32)
        return cls(centres=centres, version=vocabulary_hash(centres), description=description)

    @property
    def n_words(self) -> int:
        return int(self.centres.shape[0])


def train_vocabulary(
    descriptors: np.ndarray, config: VocabularyConfig = VocabularyConfig(), description: str = ""
) -> Vocabulary:
    """k-means (FAISS, L2 on byte values) of (N, 32) uint8 ORB descriptors -> Vocabulary.

    Reproducible: the same descriptors, config and machine give the same centres. FAISS
    is told to use every point (no internal subsampling); subsampling, if any, is ours
    (``config.max_descriptors``, seeded).
    """
    import faiss

    descriptors = np.asarray(descriptors)
    if descriptors.dtype != np.uint8 or descriptors.ndim != 2 or descriptors.shape[1] != 32:
        raise InvalidInputError(
            f"training descriptors must be (N, 32) uint8, got {descriptors.shape} "
            f"{descriptors.dtype}"
        )
    if len(descriptors) < config.n_words:
        raise InvalidInputError(
            f"{len(descriptors)} training descriptors are too few for {config.n_words} words"
        )
    if config.max_descriptors is not None and len(descriptors) > config.max_descriptors:
        rng = np.random.default_rng(config.seed)
        rows = np.sort(rng.choice(len(descriptors), config.max_descriptors, replace=False))
        descriptors = descriptors[rows]
    points = np.ascontiguousarray(descriptors, dtype=np.float32)
    kmeans = faiss.Kmeans(
        DESCRIPTOR_BYTES,
        config.n_words,
        niter=config.n_iter,
        seed=config.seed,
        verbose=False,
        min_points_per_centroid=1,
        max_points_per_centroid=len(points) // config.n_words + 1,
    )
    previous_threads = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(config.n_threads)
    try:
        kmeans.train(points)
    finally:
        faiss.omp_set_num_threads(previous_threads)
    return Vocabulary.from_centres(np.asarray(kmeans.centroids), description=description)


def save_vocabulary(path: str | Path, vocabulary: Vocabulary) -> None:
    """Write ``vocabulary`` to an .npz (centres, version, description)."""
    with open(path, "wb") as handle:
        np.savez_compressed(
            handle,
            centres=vocabulary.centres,
            version=np.array(vocabulary.version),
            description=np.array(vocabulary.description),
        )


def load_vocabulary(path: str | Path, expected_n_words: int | None = N_WORDS) -> Vocabulary:
    """Read a vocabulary written by :func:`save_vocabulary`.

    Checks the shape ((expected_n_words, 32); any K if None), finiteness and the stored
    version against the centres; raises InvalidInputError naming ``path`` otherwise.
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            centres = np.asarray(data["centres"])
            version = str(data["version"]) if "version" in data else None
            description = str(data["description"]) if "description" in data else ""
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise InvalidInputError(f"cannot read vocabulary file {path}: {exc}") from exc
    if (
        centres.ndim != 2
        or centres.shape[1] != DESCRIPTOR_BYTES
        or (expected_n_words is not None and centres.shape[0] != expected_n_words)
    ):
        want = f"({expected_n_words}, 32)" if expected_n_words is not None else "(K, 32)"
        raise InvalidInputError(f"vocabulary file {path}: centres are {centres.shape}, want {want}")
    if not np.issubdtype(centres.dtype, np.floating) or not np.all(np.isfinite(centres)):
        raise InvalidInputError(f"vocabulary file {path}: centres are not finite floats")
    computed = vocabulary_hash(centres)
    if version is not None and version != computed:
        raise InvalidInputError(
            f"vocabulary file {path}: stored version {version} does not match its centres "
            f"({computed}); the file is corrupt or was edited"
        )
    return Vocabulary(centres=centres.astype(np.float32), version=computed, description=description)


def default_vocabulary_path() -> Path:
    """Path of the vocabulary shipped in ``server/vision/data``."""
    data_dir = importlib.resources.files("monoloc.server.vision") / "data"
    return Path(str(data_dir / DEFAULT_VOCABULARY_FILE))


@functools.cache
def load_default_vocabulary() -> Vocabulary:
    """The shipped 64-word vocabulary (loaded once per process; see data/*.md)."""
    return load_vocabulary(default_vocabulary_path())
