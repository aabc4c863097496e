"""
Compiled functions (numba) of step 1 of Algorithm 1, the compatibility graph.

The graph is the bit matrix of :class:`.CompatibilityGraph` as 64-bit words (the layout
of :mod:`.bits`: on a little-endian machine the same bytes as its uint8 rows). Loops over
pairs and set bits run here because in numpy each would be a pass over the whole N x N
matrix per call (docs/design.md). Besides the graph's build
(:func:`compatibility_words`, 4-DoF :func:`vertical_compatibility_words`) and its entry
lists, the bit-row queries the later steps make of it: the common neighbourhoods of
minimal subsets (step 3's pre-screen, :func:`common_support`), the adjacency among guided
sampling's members (step 5, :func:`sub_adjacency`) and the common neighbours inside an
inlier set (step 7's all-inlier probability, :func:`common_within`).
"""

from __future__ import annotations

from numba import njit
import numpy as np

from .bits import LOW6, lowest_bit, ONE, popcount
from .types import CORRESPONDENCES
from ...compiled_types import F64_1D, F64_2D, FLOAT, I64_1D, I64_2D, INT, U64_1D, U64_2D


@njit(cache=True, nogil=True, inline='always')
def has_edge(words, i, j):
    """Return True when bit j of row i is set (i ~ j)."""
    return (words[i, j >> 6] >> (np.uint64(j) & LOW6)) & ONE != 0


@njit(cache=True, nogil=True, inline='always')
def _length_word(cols, k, i, d2, min_sq):
    """
    Return the bits j = 64 k .. 64 k + 63 of row i of the length test (see below).

    ``cols`` (6, W * 64): separate, NaN-padded coordinate columns px, py, pz, qx, qy, qz,
    so the loop vectorizes and padding is never an edge. The 64 columns are sliced first:
    indexed as cols[a, 64 k + b], LLVM cannot see the loads are contiguous and gathers
    them (docs/design.md, "Compiled code").
    """
    lo, hi = k << 6, (k << 6) + 64
    px, py, pz = cols[0, lo:hi], cols[1, lo:hi], cols[2, lo:hi]
    qx, qy, qz = cols[3, lo:hi], cols[4, lo:hi], cols[5, lo:hi]
    x0, y0, z0 = cols[0, i], cols[1, i], cols[2, i]
    u0, v0, s0 = cols[3, i], cols[4, i], cols[5, i]
    word = np.uint64(0)
    for b in range(64):
        ax, ay, az = px[b] - x0, py[b] - y0, pz[b] - z0
        bx, by, bz = qx[b] - u0, qy[b] - v0, qz[b] - s0
        a2 = ax * ax + ay * ay + az * az
        b2 = bx * bx + by * by + bz * bz
        c = a2 + b2 - d2
        edge = ((c < 0.0) | (4.0 * a2 * b2 > c * c)) & (a2 >= min_sq)
        word |= np.uint64(edge) << np.uint64(b)
    if k == i >> 6:  # keep j > i only
        word &= ~((np.uint64(2) << (np.uint64(i) & LOW6)) - ONE)
    return word


@njit((CORRESPONDENCES, INT), cache=True, nogil=True)
def columns(corr, w):
    """Return the coordinate columns of :func:`_length_word`, NaN-padded to W * 64."""
    n = corr.src.shape[0]
    cols = np.full((6, w * 64), np.nan)
    cols[:3, :n] = corr.src.T
    cols[3:, :n] = corr.dst.T
    return cols


@njit((F64_2D, U64_2D, INT, INT, FLOAT, FLOAT), cache=True, nogil=True)
def length_rows(cols, words, a, b, d2, min_sq):
    """
    Fill rows a..b-1 of the upper triangle of :func:`compatibility_words` (its first pass).

    Rows are independent, so row ranges may run on separate threads.
    """
    w = words.shape[1]
    for i in range(a, b):
        for k in range(i >> 6, w):
            words[i, k] = _length_word(cols, k, i, d2, min_sq)


@njit((U64_1D,), cache=True, nogil=True)
def _transpose64(x):
    """Transpose a 64 x 64 bit block in place (bit b of x[r] is entry (r, b))."""
    j = np.uint64(32)
    m = np.uint64(0x00000000FFFFFFFF)
    while j != 0:
        k = 0
        while k < 64:
            t = ((x[k] >> j) ^ x[k + j]) & m
            x[k] ^= t << j
            x[k + j] ^= t
            k = (k + j + 1) & ~j
        j >>= ONE
        m ^= m << j


@njit((U64_2D, INT, INT), cache=True, nogil=True)
def or_transpose_blocks(words, b0, b1):
    """
    Set bit (j, i) wherever bit (i, j) is set, for the source rows of blocks b0..b1-1.

    By 64 x 64 block transposes. Block row bi reads words (bi, bj >= bi) and writes only
    word column bi, so ranges of block rows may run on separate threads once the upper
    triangle is complete.
    """
    n, w = words.shape
    x = np.empty(64, np.uint64)
    for bi in range(b0, b1):  # rows 64 bi .. 64 bi + 63 hold the source bits (j > i)
        for bj in range(bi, w):
            any_bit = np.uint64(0)
            for r in range(64):
                row = (bi << 6) + r
                x[r] = words[row, bj] if row < n else np.uint64(0)
                any_bit |= x[r]
            if any_bit == 0:  # nothing to mirror (most blocks of a banded 4-DoF graph)
                continue
            _transpose64(x)
            for r in range(64):
                row = (bj << 6) + r
                if row < n:
                    words[row, bi] |= x[r]


@njit((CORRESPONDENCES, FLOAT, FLOAT), cache=True, nogil=True)
def compatibility_words(corr, delta, min_sq):
    """
    Build the compatibility graph (step 1): edge iff | |p_i - p_j| - |q_i - q_j| | < delta.

    Also requires |p_i - p_j|^2 >= ``min_sq`` (min_pair_distance squared; 0 keeps all).
    With squared lengths A, B and c = A + B - delta^2, |a - b| < delta iff c < 0 or
    4 A B > c^2 (square both sides of 2 a b > c): float64 products only, no square root,
    so the loop vectorizes; the test flips only within ~1e-15 (relative) of the threshold.
    The upper triangle is computed, the lower one is its bit transpose.

    :param corr: the correspondences, metres.
    :returns: (N, ceil(N / 64)) uint64 words, symmetric, no self loops.
    """
    n = corr.src.shape[0]
    w = (n + 63) // 64
    words = np.zeros((n, w), np.uint64)
    length_rows(columns(corr, w), words, 0, n, delta * delta, min_sq)
    or_transpose_blocks(words, 0, w)
    return words


@njit((CORRESPONDENCES, F64_1D, I64_1D, FLOAT, FLOAT), cache=True, nogil=True)
def vertical_compatibility_words(corr, u, hi, delta, min_sq):
    """
    Build the 4-DoF compatibility graph (step 1 for yaw + translation motions).

    Edge iff | |p_i - p_j| - |q_i - q_j| | < delta (tested as in
    :func:`compatibility_words`), |u_i - u_j| < delta and |p_i - p_j|^2 >= ``min_sq``. The
    correspondences are sorted by their vertical offset u, so the partners j > i of row i
    lie in i < j < ``hi[i]``: only the words covering that window are tested, 64 columns
    at a time as in :func:`compatibility_words` (plus the offset test), then mirrored.

    :param corr: the correspondences in the gravity frame, metres, sorted by ``u``.
    :param u: (N,) ascending vertical offsets.
    :param hi: (N,) one past the last j with u_j < u_i + delta.
    :returns: (N, ceil(N / 64)) uint64 words, symmetric, no self loops.
    """
    n = corr.src.shape[0]
    w = (n + 63) // 64
    words = np.zeros((n, w), np.uint64)
    cols = columns(corr, w)
    uu = np.full(w * 64, np.nan)
    uu[:n] = u
    d2 = delta * delta
    for i in range(n):
        if hi[i] <= i + 1:
            continue
        for k in range(i >> 6, ((hi[i] - 1) >> 6) + 1):
            near = np.uint64(0)
            block = uu[k << 6:(k << 6) + 64]
            for b in range(64):  # NaN padding is never near
                near |= np.uint64(abs(block[b] - u[i]) < delta) << np.uint64(b)
            words[i, k] = _length_word(cols, k, i, d2, min_sq) & near
    or_transpose_blocks(words, 0, w)
    return words


@njit(cache=True, nogil=True, inline='always')
def adjacency_row(words, members, a, out):
    """Write row a of the adjacency among ``members`` (indices) to ``out`` (bool, M)."""
    for c in range(members.shape[0]):
        out[c] = has_edge(words, members[a], members[c])


@njit((U64_2D, I64_1D), cache=True, nogil=True)
def sub_adjacency(words, members):
    """Return the (M, M) boolean adjacency among ``members`` (guided sampling, step 5)."""
    m = members.shape[0]
    out = np.empty((m, m), np.bool_)
    for a in range(m):
        adjacency_row(words, members, a, out[a])
    return out


@njit((U64_2D, I64_1D), cache=True, nogil=True)
def neighbour_lists(words, indptr):
    """
    Return the entries of the bit matrix as (2|E|, 2) int32 (row, column) pairs.

    Rows in order, columns ascending: column 1 is the CSR index array of ``indptr``, and
    entry e's row is at hand without a bisection of ``indptr``.
    """
    n, w = words.shape
    pairs = np.empty((indptr[n], 2), np.int32)
    for i in range(n):
        pos = indptr[i]
        for k in range(w):
            word = words[i, k]
            while word:
                pairs[pos, 0] = i
                pairs[pos, 1] = (k << 6) + lowest_bit(word)
                pos += 1
                word &= word - ONE
    return pairs


@njit((U64_2D, I64_2D), cache=True, nogil=True)
def common_support(words, subsets):
    """
    Return the size of the common neighbourhood of each minimal subset (a row of ``subsets``).

    Rows are triangles (i, j, k), |N(i) ∩ N(j) ∩ N(k)|, or edges (i, j), |N(i) ∩ N(j)|.
    """
    if subsets.shape[1] not in (2, 3):
        raise ValueError('minimal subsets are rows (i, j, k) or (i, j)')
    out = np.empty(len(subsets), np.int64)
    last = subsets.shape[1] - 1
    for m in range(len(subsets)):
        i, j, c = subsets[m, 0], subsets[m, 1], subsets[m, last]  # an edge: c = j
        s = 0
        for k in range(words.shape[1]):
            s += popcount(words[i, k] & words[j, k] & words[c, k])
        out[m] = s
    return out


@njit((U64_1D, INT), cache=True, nogil=True)
def nth_set_bit(row, r):
    """Return the column of the r-th (0-based) set bit of a word row (-1 if fewer)."""
    for k in range(len(row)):
        c = popcount(row[k])
        if r < c:
            word = row[k]
            for _ in range(r):
                word &= word - ONE
            return (k << 6) + lowest_bit(word)
        r -= c
    return -1


@njit((U64_2D, I64_1D, I64_1D, U64_1D), cache=True, nogil=True)
def common_within(words, i, j, subset):
    """
    Return |N(i) ∩ N(j)| and |N(i) ∩ N(j) ∩ S| per pair (i[m], j[m]).

    ``subset`` holds S as one bit row (W uint64 words), like a row of ``words``; the
    stage-one inlier probability (stopping) reads both counts.
    """
    total = np.zeros(len(i), np.int64)
    inside = np.zeros(len(i), np.int64)
    for m in range(len(i)):
        for k in range(words.shape[1]):
            both = words[i[m], k] & words[j[m], k]
            total[m] += popcount(both)
            inside[m] += popcount(both & subset[k])
    return total, inside
