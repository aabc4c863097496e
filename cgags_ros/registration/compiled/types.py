"""
The named tuples the core's compiled functions take, and their numba types.

Arguments that belong together travel as one NamedTuple of arrays (numba passes them as
tuples): the compatibility graph (:class:`GraphArrays`), the correspondences
(:class:`Correspondences`) and the rows guided sampling draws from (:class:`GuidedRows`).
Their fields, like every other argument, have the types of :mod:`cgags_ros.compiled_types`
(C-contiguous, writable arrays); functions with ``inline='always'`` carry no signature:
they are compiled into their callers.
"""

from __future__ import annotations

from typing import NamedTuple

from numba import types
import numpy as np

from ...compiled_types import BOOL_1D, BOOL_2D, c_array, F32_2D, F64_2D, I32_2D, I64_1D, U64_2D


class GraphArrays(NamedTuple):
    """The compatibility graph (step 1) as the samplers of step 2 read it."""

    words: np.ndarray  # (N, W) uint64: bit j of row i (i ~ j) in word j >> 6, bit j & 63
    indptr: np.ndarray  # (N + 1,) int64: cumulative degrees, where row i's entries start
    lists: np.ndarray  # (2|E|, 2) int32 (row, column) of every entry, or (0, 2): not built


class Correspondences(NamedTuple):
    """The putative correspondences (p_i, q_i), row i of each."""

    src: np.ndarray  # (N, 3) float64
    dst: np.ndarray  # (N, 3) float64

    @classmethod
    def of(cls, src, dst) -> Correspondences:
        """Return (src, dst) as the compiled functions take them (copied only if needed)."""
        return cls(c_array(src, np.float64), c_array(dst, np.float64))


class GuidedRows(NamedTuple):
    """
    The members' rows of the intersection kernel K and of the adjacency (step 5).

    Row a of ``kernel`` and ``adjacency`` is computed when a draw first reads it (``done``),
    from ``bits`` and ``words``; the others stay unwritten.
    """

    kernel: np.ndarray  # (M, M) float32: K(a, c) = |T_a ∩ T_c| / b
    adjacency: np.ndarray  # (M, M) bool: members a ~ c
    done: np.ndarray  # (M,) bool: rows computed
    bits: np.ndarray  # (M, H) uint64: the members' preference lists as bit rows
    scale: np.float32  # b, the preference list length
    words: np.ndarray  # (N, W) uint64: the graph's bit rows
    members: np.ndarray  # (M,) int64: the correspondences the rows are of


GRAPH_ARRAYS = types.BaseTuple.from_types([U64_2D, I64_1D, I32_2D], GraphArrays)
CORRESPONDENCES = types.BaseTuple.from_types([F64_2D, F64_2D], Correspondences)
GUIDED_ROWS = types.BaseTuple.from_types(
    [F32_2D, BOOL_2D, BOOL_1D, U64_2D, types.float32, U64_2D, I64_1D], GuidedRows)
