"""
Compiled functions (numba) of step 7 of Algorithm 1, stopping: the edges among an inlier set.

The P1 bound's all-inlier probability needs the edges among the best model's inliers and
a few of them drawn at random. Counted on the graph's bit rows they cost M x W words; the
dense M x M adjacency of a large inlier set cost more than the search around it
(docs/design.md).
"""

from __future__ import annotations

from numba import njit
import numpy as np

from .bits import LOW6, lowest_bit, ONE, popcount
from ...compiled_types import I64_1D, INT, U64_1D, U64_2D


@njit(cache=True, nogil=True, inline='always')
def _later_members(words, mask, i, k):
    """Word k of row i restricted to the members (``mask``) above column i."""
    word = words[i, k] & mask[k]
    if k == i >> 6:
        word &= ~((np.uint64(2) << (np.uint64(i) & LOW6)) - ONE)
    return word


@njit((I64_1D, INT), cache=True, nogil=True)
def member_mask(members, w):
    """Return ``members`` (indices) as one bit row of W words, like a row of ``words``."""
    mask = np.zeros(w, np.uint64)
    for a in range(members.shape[0]):
        mask[members[a] >> 6] |= ONE << (np.uint64(members[a]) & LOW6)
    return mask


@njit((U64_2D, I64_1D, U64_1D), cache=True, nogil=True)
def later_member_counts(words, members, mask):
    """
    Return, per member, its neighbours among the members with a larger index.

    Row a of the upper triangle of the members' adjacency, counted on the bit rows (M x W
    popcounts, not the M x M matrix of :func:`sub_adjacency`); ``members`` sorted
    ascending, ``mask`` their :func:`member_mask`. Their sum is the edges among them.
    """
    out = np.zeros(members.shape[0], np.int64)
    for a in range(members.shape[0]):
        i = members[a]
        s = 0
        for k in range(i >> 6, words.shape[1]):
            s += popcount(_later_members(words, mask, i, k))
        out[a] = s
    return out


@njit((U64_2D, I64_1D, U64_1D, I64_1D, I64_1D), cache=True, nogil=True)
def later_member_pairs(words, members, mask, starts, picks):
    """
    Return the edges (i, j), i < j, among ``members`` numbered by ``picks``.

    Edges are numbered in row-major order of the upper triangle (as ``np.nonzero`` of
    ``np.triu`` of the members' adjacency lists them); ``starts`` is the exclusive cumulative
    sum of :func:`later_member_counts`.
    """
    ii = np.empty(picks.shape[0], np.int64)
    jj = np.empty(picks.shape[0], np.int64)
    for m in range(picks.shape[0]):
        a = np.searchsorted(starts, picks[m], side='right') - 1
        i, r = members[a], picks[m] - starts[a]
        ii[m] = i
        for k in range(i >> 6, words.shape[1]):
            word = _later_members(words, mask, i, k)
            c = popcount(word)
            if r < c:
                for _ in range(r):
                    word &= word - ONE
                jj[m] = (k << 6) + lowest_bit(word)
                break
            r -= c
    return ii, jj
