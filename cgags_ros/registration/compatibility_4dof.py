"""
The 4-DoF compatibility graph: length and vertical-offset consistency (step 1).

Adapts the paper's compatibility graph (METHOD.md step 1) to yaw + translation motions,
which preserve both lengths and vertical offsets along the gravity axis: an edge (i, j)
needs ``| ||p_i - p_j|| - ||q_i - q_j|| | < delta`` and ``|dz_p - dz_q| < delta``. The
second test is 1-D: ``dz_p - dz_q = u_j - u_i`` with u_i the vertical translation that
correspondence i implies (:func:`~.yaw.vertical_offsets`). With the correspondences sorted
by u, the vertical partners of a block of rows are one contiguous column window, and the
length test is only computed inside it, and edge sampling proposes partners inside it
(:attr:`~.compatibility.CompatibilityGraph.windows`).
"""

from __future__ import annotations

import numpy as np

from .compatibility import _BLOCK_ELEMENTS, _expansion_factors, CompatibilityGraph


def build_vertical_compatibility_graph(src: np.ndarray, dst: np.ndarray, delta: float,
                                       offsets: np.ndarray,
                                       min_pair_distance: float = 0.0) -> CompatibilityGraph:
    """
    Build the graph with edges ``d_ij < delta`` and ``|u_i - u_j| < delta``.

    :param src, dst: (N, 3) correspondences in the gravity frame, sorted by ``offsets``.
    :param offsets: (N,) u_i = z(q_i) - z(p_i), ascending.
    :param min_pair_distance: as in :func:`~.compatibility.build_compatibility_graph`.
    :raises ValueError: when ``offsets`` is not sorted.
    """
    n = len(src)
    if n > 1 and np.any(np.diff(offsets) < 0):
        raise ValueError('offsets must be sorted ascending (sort the correspondences by u)')
    x = (src - src.mean(axis=0)).astype(np.float32)
    y = (dst - dst.mean(axis=0)).astype(np.float32)
    (x, xt), (y, yt) = _expansion_factors(x), _expansion_factors(y)
    u = (offsets - offsets.mean()).astype(np.float32)
    packed = np.zeros((n, (n + 7) // 8), dtype=np.uint8)
    windows = (np.searchsorted(u, u - delta, side='left'),
               np.searchsorted(u, u + delta, side='right'))
    block = max(8, min(n, _BLOCK_ELEMENTS // max(n, 1)))
    min_sq = np.float32(min_pair_distance) ** 2
    for start in range(0, n, block):
        stop = min(n, start + block)
        lo = int(np.searchsorted(u, u[start] - delta, side='left'))
        hi = int(np.searchsorted(u, u[stop - 1] + delta, side='right'))
        A = np.maximum(x[start:stop] @ xt[:, lo:hi], 0.0)
        B = np.maximum(y[start:stop] @ yt[:, lo:hi], 0.0)
        edge = A >= min_sq if min_pair_distance > 0 else None
        np.sqrt(A, out=A)
        np.sqrt(B, out=B)
        A -= B
        np.abs(A, out=A)
        ok = np.zeros((stop - start, n), dtype=bool)
        window = ok[:, lo:hi]
        np.less(A, delta, out=window)
        window &= np.abs(u[start:stop, None] - u[None, lo:hi]) < delta
        if edge is not None:
            window &= edge
        ok[np.arange(stop - start), np.arange(start, stop)] = False  # no self loops
        packed[start:stop] = np.packbits(ok, axis=1, bitorder='little')
    graph = CompatibilityGraph(packed, n)
    graph.windows = windows
    return graph
