"""Pack numpy arrays into database blobs and back, with explicit dtype and shape checks.

A blob is the raw C-order bytes of the array in a fixed little-endian dtype; the shape
is implied by the column (for example a VLAD is always 2048 float32) except for a
leading row count ``N`` that is derived from the blob length. A blob whose length does
not fit its column raises :class:`InvalidInputError` naming the column and the sizes,
instead of silently yielding a wrong array.
"""

from __future__ import annotations

import math

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.sizes import CODE_BYTES, DESCRIPTOR_BYTES, N_WORDS, VLAD_DIM

# (dtype, shape) of every array column; None marks the variable row count N.
POSE = ("<f8", (4, 4))
VLAD = ("<f4", (VLAD_DIM,))
CODE = ("|u1", (CODE_BYTES,))
KEYPOINTS = ("<f4", (None, 2))
DESCRIPTORS = ("|u1", (None, DESCRIPTOR_BYTES))
POINTS = ("<f4", (None, 3))
CENTRES = ("<f4", (N_WORDS, DESCRIPTOR_BYTES))

Spec = tuple[str, tuple[int | None, ...]]


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "x".join("N" if d is None else str(d) for d in shape)


def pack_array(array: np.ndarray, spec: Spec, name: str, *, finite: bool = True) -> bytes:
    """Return the blob of ``array`` after checking it matches ``spec`` (dtype, shape).

    Integer columns accept only arrays whose values fit the dtype exactly; float columns
    accept any real array and, with ``finite``, refuse NaN and infinities.
    """
    dtype_str, shape = spec
    dtype = np.dtype(dtype_str)
    a = np.asarray(array)
    if a.ndim != len(shape) or any(
        want is not None and got != want for got, want in zip(a.shape, shape, strict=True)
    ):
        raise InvalidInputError(f"{name} must have shape ({_shape_text(shape)}), got {a.shape}")
    if dtype.kind == "u":
        if a.dtype.kind not in "ui":
            raise InvalidInputError(f"{name} must be an integer array, got dtype {a.dtype}")
        if a.size and (a.min() < 0 or a.max() > np.iinfo(dtype).max):
            raise InvalidInputError(f"{name} has values outside the range of {dtype.name}")
    elif a.dtype.kind not in "fiu":
        raise InvalidInputError(f"{name} must be a real-valued array, got dtype {a.dtype}")
    out = np.ascontiguousarray(a, dtype=dtype)
    if finite and dtype.kind == "f" and not np.all(np.isfinite(out)):
        raise InvalidInputError(f"{name} contains NaN or infinite values")
    return out.tobytes()


def unpack_array(blob: bytes | None, spec: Spec, name: str) -> np.ndarray:
    """Return the array stored in ``blob`` (read-only view), or raise if the length is wrong.

    The result has the column's dtype in native byte order and its full shape, with N
    derived from the blob length.
    """
    dtype_str, shape = spec
    dtype = np.dtype(dtype_str)
    if blob is None:
        raise InvalidInputError(f"corrupt blob {name}: missing (NULL)")
    fixed = math.prod(d for d in shape if d is not None) * dtype.itemsize
    n_bytes = len(blob)
    if None in shape:
        if n_bytes % fixed:
            raise InvalidInputError(
                f"corrupt blob {name}: {n_bytes} bytes is not a multiple of {fixed} "
                f"(rows of {_shape_text(shape)} {dtype.name})"
            )
        full = tuple(n_bytes // fixed if d is None else d for d in shape)
    else:
        if n_bytes != fixed:
            raise InvalidInputError(
                f"corrupt blob {name}: {n_bytes} bytes, expected {fixed} "
                f"({_shape_text(shape)} {dtype.name})"
            )
        full = shape
    arr = np.frombuffer(blob, dtype=dtype).reshape(full)
    return arr.astype(dtype.newbyteorder("="), copy=False)
