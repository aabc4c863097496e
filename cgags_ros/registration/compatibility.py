"""
Compatibility graph over putative correspondences (step 1: rigid length consistency).

Correspondences i and j are compatible when ``| ||p_i - p_j|| - ||q_i - q_j|| | < delta``:
a rigid motion preserves lengths, so two inliers are always compatible (up to noise), while
an outlier is compatible with a given correspondence only by chance.

The graph is stored as a bit-packed N x N adjacency matrix (N^2 / 8 bytes: 50 MB at
N = 20 000), built by a compiled function, so no N x N float matrix is ever held in memory.
"""

from __future__ import annotations

import numpy as np

from . import compiled
from ..parallel import run_split

# Correspondences below which the graph is built on one thread: below it, waking idle pool
# threads costs more than the split saves (docs/design.md, "Compiled code").
_SPLIT_MIN = 4000
_NO_LISTS = np.zeros((0, 2), np.int32)  # entry lists not built: the samplers scan bit rows


# Set bits of every byte value, for numpy 1.x (Jazzy's apt numpy), which has no bitwise_count.
_BYTE_POPCOUNT = np.array([bin(b).count('1') for b in range(256)], dtype=np.uint8)


def popcount_rows(rows: np.ndarray) -> np.ndarray:
    """Set bits per row of a 2-D array of whole 64-bit words (any integer view of them)."""
    if hasattr(np, 'bitwise_count'):
        return np.bitwise_count(rows.view(np.uint64)).sum(axis=1, dtype=np.int64)
    return _BYTE_POPCOUNT[rows.view(np.uint8)].sum(axis=1, dtype=np.int64)


class CompatibilityGraph:
    """
    Bit-packed undirected compatibility graph (no self loops).

    :ivar packed: (N, W) uint8, W = ceil(N/8) rounded up to whole 64-bit words; bit j of
        row i (little bit order) set iff i ~ j.
    :ivar degree: (N,) int64 number of compatible partners of each correspondence.
    :ivar num_edges: undirected edge count |E|.
    """

    def __init__(self, packed: np.ndarray, n: int):
        # Rows padded to whole 64-bit words: ANDs and popcounts then run on uint64.
        pad = -packed.shape[1] % 8
        self.packed = np.ascontiguousarray(np.pad(packed, ((0, 0), (0, pad))) if pad else packed)
        self._flat = self.packed.reshape(-1)
        self._words = self.packed.view(np.uint64)
        self.words = self._words  # (N, W) uint64: the compiled functions' view
        self.n = n
        self.degree = self.popcount(self.packed)
        self.num_edges = int(self.degree.sum() // 2)

    _MAX_LIST_ENTRIES = 20_000_000  # (row, column) int32 pairs up to 160 MB

    def neighbour_lists(self) -> tuple[np.ndarray, np.ndarray] | None:
        """
        Return the CSR neighbour lists (indptr, indices), built on first use.

        None if they would exceed the memory cap; samplers then draw on the bit matrix.
        """
        pairs = self.entry_lists()
        return None if pairs is None else (self.indptr, pairs[:, 1])

    def entry_lists(self) -> np.ndarray | None:
        """Return every directed adjacency entry as a (2|E|, 2) int32 (row, column) pair."""
        if not hasattr(self, '_pairs'):
            self._pairs = (None if 2 * self.num_edges > self._MAX_LIST_ENTRIES
                           else compiled.neighbour_lists(self._words, self.indptr))
        return self._pairs

    def arrays(self, lists: np.ndarray | None = None) -> compiled.GraphArrays:
        """Return the graph as the compiled samplers take it, with ``lists`` when given."""
        return compiled.GraphArrays(self._words, self.indptr,
                                    _NO_LISTS if lists is None else lists)

    @property
    def indptr(self) -> np.ndarray:
        """Cumulative degrees (N + 1,): row i's entries of the directed adjacency start here."""
        if not hasattr(self, '_indptr'):
            self._indptr = np.concatenate([[0], np.cumsum(self.degree)])
        return self._indptr

    @property
    def density(self) -> float:
        return 2.0 * self.num_edges / max(self.n * (self.n - 1), 1)

    def rows(self, idx: np.ndarray) -> np.ndarray:
        """Return the unpacked boolean rows of ``idx``, shaped (len(idx), N)."""
        return np.unpackbits(self.packed[idx], axis=1, count=self.n, bitorder='little').view(bool)

    def has_edge(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Vectorized edge test for index arrays of equal shape."""
        byte = np.take(self._flat, i * self.packed.shape[1] + (j >> 3))
        return ((byte >> (j & 7).astype(np.uint8)) & 1).astype(bool)

    def common(self, *idx: np.ndarray) -> np.ndarray:
        """Packed rows (uint8) of the common neighbourhood N(a) ∩ N(b) ∩ ... per item."""
        out = self._words[idx[0]]
        for k in idx[1:]:
            out &= self._words[k]
        return out.view(np.uint8)

    def popcount(self, rows: np.ndarray) -> np.ndarray:
        """Set bits per packed row (rows shaped like ``packed``: whole words)."""
        return popcount_rows(rows)

    def common_within(self, i: np.ndarray, j: np.ndarray, members: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Return |N(i) ∩ N(j)| and |N(i) ∩ N(j) ∩ members| per pair (index arrays)."""
        return compiled.common_within(self._words, compiled.c_array(i, np.int64),
                                      compiled.c_array(j, np.int64), self._mask(members))

    def count_edges_within(self, members: np.ndarray) -> int:
        """Return the number of undirected edges among ``members`` (indices)."""
        return int(self.later_neighbour_counts(members).sum())

    def later_neighbour_counts(self, members: np.ndarray) -> np.ndarray:
        """
        Return, per member, its neighbours among the members with a larger index.

        ``members``: distinct indices in ascending order (sorted here if they are not).
        Counted on the bit rows: M x W words, not the M x M adjacency.
        """
        members = _ascending(members)
        return compiled.later_member_counts(self._words, members, self._mask(members))

    def numbered_edges(self, members: np.ndarray, counts: np.ndarray,
                       numbers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the edges (i, j), i < j, among ``members`` with the given ``numbers``.

        Edges are numbered in the order ``np.nonzero(np.triu(self.adjacency(members)))``
        lists them (row-major), 0 to ``counts.sum()`` - 1; ``counts`` is
        :meth:`later_neighbour_counts` of the same ``members``.
        """
        members = _ascending(members)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        return compiled.later_member_pairs(self._words, members, self._mask(members),
                                           starts, compiled.c_array(numbers, np.int64))

    def _mask(self, members: np.ndarray) -> np.ndarray:
        """Return ``members`` (indices) as one bit row of words, like a row of the graph."""
        return compiled.member_mask(compiled.c_array(members, np.int64), self._words.shape[1])

    def adjacency(self, members: np.ndarray) -> np.ndarray:
        """Return the (M, M) boolean adjacency among ``members`` (indices)."""
        return compiled.sub_adjacency(self._words, compiled.c_array(members, np.int64))


def _ascending(members: np.ndarray) -> np.ndarray:
    """Return ``members`` as distinct int64 indices in ascending order."""
    members = compiled.c_array(members, np.int64)
    if len(members) > 1 and not (members[1:] > members[:-1]).all():
        members = np.unique(members)
    return members


def length_consistency(src: np.ndarray, dst: np.ndarray, i: np.ndarray,
                       j: np.ndarray) -> np.ndarray:
    """d_ij = | ||p_i - p_j|| - ||q_i - q_j|| | for index arrays i, j (any shape)."""
    a = src[i] - src[j]
    b = dst[i] - dst[j]
    return np.abs(np.sqrt(np.einsum('...k,...k->...', a, a))
                  - np.sqrt(np.einsum('...k,...k->...', b, b)))


def build_compatibility_graph(src: np.ndarray, dst: np.ndarray, delta: float,
                              min_pair_distance: float = 0.0,
                              workers: int = 1) -> CompatibilityGraph:
    """
    Build the graph with edges ``d_ij < delta`` (and ``||p_i - p_j|| >= min_pair_distance``).

    One compiled pass over the pairs (:func:`.compiled.compatibility_words`): float64
    squared lengths, no N x N scratch. With ``workers`` > 1 (and N >= ``_SPLIT_MIN``) its
    two passes are split into ranges of equal work, one thread each; the bits are the same.
    """
    corr = compiled.Correspondences.of(src, dst)
    d2, min_sq = float(delta) ** 2, float(min_pair_distance) ** 2
    n = len(src)
    if workers <= 1 or n < _SPLIT_MIN:
        words = compiled.compatibility_words(corr, float(delta), min_sq)
        return CompatibilityGraph(words.view(np.uint8), n)
    w = (n + 63) // 64
    words = np.zeros((n, w), np.uint64)
    cols = compiled.columns(corr, w)
    # Row i of the upper triangle tests w - i // 64 words; block row b transposes w - b blocks.
    run_split(lambda a, b: compiled.length_rows(cols, words, a, b, d2, min_sq),
              _equal_work(w - np.arange(n) // 64, workers))
    run_split(lambda a, b: compiled.or_transpose_blocks(words, a, b),
              _equal_work(w - np.arange(w), workers))
    return CompatibilityGraph(words.view(np.uint8), n)


def _equal_work(work: np.ndarray, parts: int) -> list[int]:
    """Return bounds splitting the items into ``parts`` consecutive ranges of equal ``work``."""
    total = np.cumsum(work)
    cuts = np.searchsorted(total, total[-1] * np.arange(1, parts) / parts)
    return sorted({0, *cuts.tolist(), len(work)})
