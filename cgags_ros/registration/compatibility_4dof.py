"""
The 4-DoF compatibility graph: length and vertical-offset consistency (step 1).

Adapts the paper's compatibility graph (step 1) to yaw + translation motions,
which preserve both lengths and vertical offsets along the gravity axis: an edge (i, j)
needs ``| ||p_i - p_j|| - ||q_i - q_j|| | < delta`` and ``|dz_p - dz_q| < delta``. The
second test is 1-D: ``dz_p - dz_q = u_j - u_i`` with u_i the vertical translation that
correspondence i implies (:func:`~.yaw.vertical_offsets`). With the correspondences sorted
by u, the vertical partners of a row are one contiguous window of rows, and the length
test is only computed inside it.
"""

from __future__ import annotations

import numpy as np

from . import compiled
from .compatibility import CompatibilityGraph


def build_vertical_compatibility_graph(src: np.ndarray, dst: np.ndarray, delta: float,
                                       offsets: np.ndarray,
                                       min_pair_distance: float = 0.0) -> CompatibilityGraph:
    """
    Build the graph with edges ``d_ij < delta`` and ``|u_i - u_j| < delta``.

    One compiled pass over each row's offset window
    (:func:`.compiled.vertical_compatibility_words`): float64 squared lengths.

    :param src, dst: (N, 3) correspondences in the gravity frame, sorted by ``offsets``.
    :param offsets: (N,) u_i = z(q_i) - z(p_i), ascending.
    :param min_pair_distance: as in :func:`~.compatibility.build_compatibility_graph`.
    :raises ValueError: when ``offsets`` is not sorted.
    """
    n = len(src)
    u = compiled.c_array(offsets, np.float64)
    if n > 1 and np.any(np.diff(u) < 0):
        raise ValueError('offsets must be sorted ascending (sort the correspondences by u)')
    hi = np.searchsorted(u, u + delta, side='right').astype(np.int64)  # end of each window
    words = compiled.vertical_compatibility_words(
        compiled.Correspondences.of(src, dst), u, hi, float(delta), float(min_pair_distance) ** 2)
    return CompatibilityGraph(words.view(np.uint8), n)
