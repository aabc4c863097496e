"""
Graph vertex sampling in numpy: k in N(i) ∩ N(j), uniform or by weight.

The search's own draws (edge and vertex tournaments, guided subsets) and the collinearity
test are compiled (:mod:`.compiled.sampling`); this module serves the non-default
vertex samplers (``core.vertex_sampling`` 'uniform' and 'degree').
"""

from __future__ import annotations

import numpy as np

from .compatibility import CompatibilityGraph


def weighted_choice_rows(weights: np.ndarray,
                         rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """
    One index per row of ``weights`` (B, M), with probability proportional to the row.

    Returns the indices and a mask of rows whose total weight was positive.
    """
    cum = np.cumsum(weights, axis=1, dtype=np.float64)
    total = cum[:, -1]
    ok = total > 0
    u = rng.random(len(weights)) * total
    idx = np.argmax(cum > u[:, None], axis=1)
    return idx, ok


def _uniform_member(rows_packed: np.ndarray, n: int, rng: np.random.Generator,
                    weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact draw of one set bit per packed row (optionally weighted per column)."""
    rows = np.unpackbits(rows_packed, axis=1, count=n, bitorder='little')
    if weights is not None:
        return weighted_choice_rows(rows * weights[None, :], rng)
    # Uniform: pick a random position among each row's set bits (no cumulative sums).
    r, c = np.nonzero(rows)
    counts = np.bincount(r, minlength=len(rows))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ok = counts > 0
    pick = starts + np.floor(rng.random(len(rows)) * counts).astype(np.int64)
    idx = np.zeros(len(rows), dtype=np.int64)
    idx[ok] = c[pick[ok]]
    return idx, ok


def sample_common_vertex(graph: CompatibilityGraph, rng: np.random.Generator, i: np.ndarray,
                         j: np.ndarray, *, weights: np.ndarray | None = None,
                         csr: tuple[np.ndarray, np.ndarray] | None = None,
                         tries: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """
    Draw k from N(i) ∩ N(j) (graph vertex sampling), uniformly or by ``weights``.

    Returns k and a mask of pairs with a non-empty common neighbourhood (others must be
    resampled by the caller).
    """
    count = len(i)
    if csr is not None:  # candidates from N(i): only the edge to j remains to be tested
        offset = np.floor(rng.random((count, tries)) * graph.degree[i][:, None]).astype(np.int64)
        cand = csr[1][csr[0][i][:, None] + offset].astype(np.int64)
        hit = graph.has_edge(np.repeat(j[:, None], tries, 1), cand)
    else:
        cand = rng.integers(0, graph.n, size=(count, tries))
        hit = graph.has_edge(np.repeat(i[:, None], tries, 1), cand)
        hit &= graph.has_edge(np.repeat(j[:, None], tries, 1), cand)
    if weights is not None:
        hit &= rng.random(cand.shape) < weights[cand] / weights.max()
    found = hit.any(axis=1)
    k = cand[np.arange(count), np.argmax(hit, axis=1)]
    ok = found.copy()
    miss = np.flatnonzero(~found)
    if len(miss):
        k[miss], ok[miss] = _uniform_member(graph.common(i[miss], j[miss]), graph.n, rng, weights)
    return k, ok
