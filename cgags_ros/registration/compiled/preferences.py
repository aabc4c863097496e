"""
Compiled functions (numba) of step 4 of Algorithm 1: preference lists and the kernel K.

Each correspondence keeps the b hypotheses with its smallest residuals
(:func:`merge_preferences`); the intersection kernel K(a, c) = |T_a ∩ T_c| / b is computed
on bit rows of those lists (:func:`preference_bits`, :func:`kernel_row`), whole
(:func:`intersection_kernel`) or, for guided sampling, row by row as draws read it
(:func:`.sampling.draw_guided`). Loops per correspondence that numpy would run as chains of
small array calls (docs/design.md).
"""

from __future__ import annotations

from numba import njit
import numpy as np

from .bits import ONE, popcount
from ...compiled_types import F32_2D, I64_1D, I64_2D, INT


@njit((F32_2D, I64_2D, F32_2D, INT), cache=True, nogil=True)
def merge_preferences(pref_res, pref_ids, res, first_id):
    """
    Merge E new hypotheses into the preference lists (step 4, top-b residual ranks).

    Each correspondence keeps the b hypotheses with its smallest residuals, sorted
    ascending (empty slots hold inf at the end; equal residuals in hypothesis order).
    The rows are streamed in memory order, each residual below its list's last entry
    (most are not, once the lists fill) inserted from the end: a new hypothesis goes after
    every equal residual, as its id is the largest. Sorted lists also give each list's
    median without a sort (:meth:`.PreferenceLists.quality`).
    ``res`` (E, N) float32; ids are ``first_id`` + row.
    """
    n, b = pref_res.shape
    last = pref_res[:, b - 1].copy()  # contiguous: the test every residual meets
    for e in range(res.shape[0]):
        h = first_id + e
        for m in range(n):
            r = res[e, m]
            if not r < last[m]:
                continue
            p = b - 1
            while p > 0 and pref_res[m, p - 1] > r:
                pref_res[m, p] = pref_res[m, p - 1]
                pref_ids[m, p] = pref_ids[m, p - 1]
                p -= 1
            pref_res[m, p] = r
            pref_ids[m, p] = h
            last[m] = pref_res[m, b - 1]


@njit((I64_2D, I64_1D, INT, INT), cache=True, nogil=True)
def preference_bits(ids, members, num_hypotheses, b):
    """
    Return the members' preference lists as bit rows (M, W) uint64 (step 4, for K).

    The hypotheses present in the members' lists are renumbered 0..H'-1 and each list
    becomes a bit row of H' bits, so a kernel entry costs H' / 64 AND + popcounts
    (:func:`kernel_row`): the dense 0/1 matrix product it replaces multiplied mostly
    zeros. ``ids`` (N, b) int64, -1 in empty slots.
    """
    m = members.shape[0]
    slot = np.full(num_hypotheses, -1, np.int64)
    used = 0
    for a in range(m):
        for p in range(b):
            h = ids[members[a], p]
            if h >= 0 and slot[h] < 0:
                slot[h] = used
                used += 1
    w = max((used + 63) >> 6, 1)
    bits = np.zeros((m, w), np.uint64)
    for a in range(m):
        for p in range(b):
            h = ids[members[a], p]
            if h >= 0:
                s = slot[h]
                bits[a, s >> 6] |= ONE << np.uint64(s & 63)
    return bits


@njit(cache=True, nogil=True, inline='always')
def kernel_row(bits, a, scale, out):
    """Write row a of the intersection kernel, K(a, c) = |T_a ∩ T_c| / b, to ``out``."""
    for c in range(bits.shape[0]):
        count = 0
        for k in range(bits.shape[1]):
            count += popcount(bits[a, k] & bits[c, k])
        out[c] = np.float32(count) / scale
    out[a] = 0.0


@njit((I64_2D, I64_1D, INT, INT), cache=True, nogil=True)
def intersection_kernel(ids, members, num_hypotheses, b):
    """
    Return the intersection kernel K (M, M) float32 of the members' preference lists.

    K(a, c) = |T_a ∩ T_c| / b, diagonal zero (step 4), every row of it; guided sampling
    computes only the rows it draws from (:func:`.sampling.draw_guided`).
    """
    bits = preference_bits(ids, members, num_hypotheses, b)
    K = np.empty((members.shape[0], members.shape[0]), np.float32)
    for a in range(members.shape[0]):
        kernel_row(bits, a, np.float32(b), K[a])
    return K
