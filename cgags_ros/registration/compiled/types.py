"""
The argument types of the compiled functions, declared once.

Every compiled function of this package is decorated with its signature built from these
aliases (``@njit(signature, cache=True, nogil=True)``): numba compiles it, or loads it from
its on-disk cache, when the module is imported, and refuses any other argument types with a
``TypeError`` instead of compiling a new specialization on a later call. Arrays are
C-contiguous and writable; :func:`c_array` gives any array that form (copying only when it
must). Functions with ``inline='always'`` carry no signature: they are compiled into their
callers.

Arguments that belong together travel as one NamedTuple of arrays (numba passes them as
tuples): the compatibility graph (:class:`GraphArrays`), the correspondences
(:class:`Correspondences`) and the rows guided sampling draws from (:class:`GuidedRows`).
"""

from __future__ import annotations

from typing import NamedTuple

from numba import types
import numpy as np


def _array(dtype, ndim: int) -> types.Array:
    return types.Array(dtype, ndim, 'C')


RNG = types.NumPyRandomGeneratorType('NumPyRandomGeneratorType')  # numpy.random.Generator
INT = types.int64
FLOAT = types.float64
BOOL = types.boolean
F64_1D, F64_2D = _array(types.float64, 1), _array(types.float64, 2)
F64_3D = _array(types.float64, 3)
F32_2D = _array(types.float32, 2)
I64_1D, I64_2D = _array(types.int64, 1), _array(types.int64, 2)
I32_2D = _array(types.int32, 2)
U64_1D, U64_2D = _array(types.uint64, 1), _array(types.uint64, 2)
BOOL_1D, BOOL_2D = _array(types.boolean, 1), _array(types.boolean, 2)


def c_array(a, dtype) -> np.ndarray:
    """Return ``a`` as a C-contiguous, aligned, writable ``dtype`` array (copied if it is not)."""
    if type(a) is np.ndarray and a.dtype == dtype:  # the usual case, without np.require's cost
        flags = a.flags
        if flags.c_contiguous and flags.aligned and flags.writeable:
            return a
    return np.require(a, dtype, 'CAW')


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
