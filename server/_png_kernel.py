"""Compiled PNG scanline unfiltering (numba), 8 bits per sample, not interlaced (PNG spec
section 9). Imported lazily by ``monoloc.server.encoded_image``.

The five filter types undone row by row in place of libpng's: the inflated stream is
already at hand (``encoded_image`` inflates it once to bound it), so decoding it here
spares rebuilding a PNG and libpng's second pass over it.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, boundscheck=False, nogil=True)
def unfilter_rows(filtered, height, row_bytes, bpp, out):
    """Undo the filters of ``filtered`` (height * (1 + row_bytes),) uint8 into ``out``
    (height, row_bytes) uint8, ``bpp`` bytes per pixel. Returns -1, or the first row whose
    filter type is not 0-4."""
    stride = row_bytes + 1
    for y in range(height):
        kind = filtered[y * stride]
        src = y * stride + 1
        if kind == 0:
            for x in range(row_bytes):
                out[y, x] = filtered[src + x]
        elif kind == 1:
            for x in range(row_bytes):
                left = out[y, x - bpp] if x >= bpp else 0
                out[y, x] = (filtered[src + x] + left) & 0xFF
        elif kind == 2:
            for x in range(row_bytes):
                up = out[y - 1, x] if y > 0 else 0
                out[y, x] = (filtered[src + x] + up) & 0xFF
        elif kind == 3:
            for x in range(row_bytes):
                left = np.int32(out[y, x - bpp]) if x >= bpp else np.int32(0)
                up = np.int32(out[y - 1, x]) if y > 0 else np.int32(0)
                out[y, x] = (np.int32(filtered[src + x]) + ((left + up) >> 1)) & 0xFF
        elif kind == 4:
            for x in range(row_bytes):
                a = np.int32(out[y, x - bpp]) if x >= bpp else np.int32(0)
                b = np.int32(out[y - 1, x]) if y > 0 else np.int32(0)
                c = np.int32(out[y - 1, x - bpp]) if (x >= bpp and y > 0) else np.int32(0)
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                if pa <= pb and pa <= pc:
                    pred = a
                elif pb <= pc:
                    pred = b
                else:
                    pred = c
                out[y, x] = (np.int32(filtered[src + x]) + pred) & 0xFF
        else:
            return y
    return -1
