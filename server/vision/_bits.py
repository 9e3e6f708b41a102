"""Bit tricks shared by the compiled kernels (numba)."""

from __future__ import annotations

import numpy as np
from numba import njit

_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_H01 = np.uint64(0x0101010101010101)
# "no distance yet": above any Hamming distance of two 256-bit descriptors
FAR = np.int32(1 << 20)


@njit(inline="always")
def popcount64(x):
    """Set bits of a uint64. Written as the classic SWAR sequence, which LLVM recognises
    as ctpop: scalar popcnt, or a nibble-table popcount when the loop vectorises."""
    x = x - ((x >> np.uint64(1)) & _M1)
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    return (x * _H01) >> np.uint64(56)
