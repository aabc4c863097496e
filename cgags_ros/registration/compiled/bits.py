"""
The bit rows every step reads: their word layout and the word operations on it.

A row of N bits is W = ceil(N / 64) uint64 words, bit j in word j >> 6 at position
j & 63 (:data:`LOW6`): the compatibility graph's rows (step 1), the preference lists' bit
rows (step 4) and the mask of an inlier set (step 7). The helpers are inlined into their
callers.
"""

from __future__ import annotations

from numba import njit, types
from numba.extending import intrinsic
import numpy as np

ONE = np.uint64(1)
LOW6 = np.uint64(63)  # a column's bit within its word: j & LOW6


@intrinsic
def _ctpop(typingctx, word):
    """LLVM ``ctpop`` of a uint64 (the popcnt instruction where the CPU has one)."""
    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])
    return types.uint64(types.uint64), codegen


@intrinsic
def _cttz(typingctx, word):
    """LLVM ``cttz`` of a uint64: index of the lowest set bit (64 for zero)."""
    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], context.get_constant(types.boolean, False))
    return types.uint64(types.uint64), codegen


@njit(cache=True, nogil=True, inline='always')
def popcount(word):
    """Return the set bits of a uint64 word."""
    return np.int64(_ctpop(word))


@njit(cache=True, nogil=True, inline='always')
def lowest_bit(word):
    """Return the index of the lowest set bit of a nonzero uint64 word."""
    return np.int64(_cttz(word))
