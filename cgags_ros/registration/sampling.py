"""
Minimal compatible subsets: graph edge sampling, graph vertex sampling, guided sampling.

A minimal subset is a triple (i, j, k) of correspondences: a compatible edge (i, j) and a
vertex k compatible with both (k in N(i) ∩ N(j)). Sampling only triangles of the
compatibility graph discards most outlier-contaminated triples before any model is fitted.
"""

from __future__ import annotations

import numpy as np

from .compatibility import CompatibilityGraph, length_consistency


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


def sample_edges(graph: CompatibilityGraph, rng: np.random.Generator, count: int, *,
                 src: np.ndarray, dst: np.ndarray, delta: float, soft: bool,
                 csr: tuple[np.ndarray, np.ndarray] | None = None,
                 csr_weights: np.ndarray | None = None,
                 tries: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """
    Draw ``count`` edges (i, j) uniformly from E (graph edge sampling).

    Uniform over edges equals: i with probability deg(i) / 2|E|, then j uniform in N(i).
    j is found by rejection (cheap when the graph is dense), with an exact fallback for the
    rows where all tries missed; with the neighbour lists ``csr``, an entry is drawn
    directly. With ``soft`` compatibility a uniform edge is accepted with probability
    1 - (d_ij / delta)^2 (``csr_weights``: these values per neighbour-list entry, from
    :func:`soft_edge_weights`), so edges are drawn in proportion to it.
    """
    i = np.empty(count, dtype=np.int64)
    j = np.empty(count, dtype=np.int64)
    filled = 0
    while filled < count:  # more than one round only with soft compatibility
        need = count - filled
        # Soft acceptance averages ~2/3: propose enough that one round usually suffices
        # (accepted proposals are i.i.d. from the soft distribution; the surplus is cut).
        draw = need if not soft else int(1.55 * need) + 16
        if csr is not None:  # uniform over directed adjacency entries = uniform over E
            e = rng.integers(0, len(csr[1]), draw)
            ii = np.searchsorted(csr[0], e, side='right') - 1
            jj = csr[1][e].astype(np.int64)
        else:
            ii, jj = _edges_by_rejection(graph, rng, draw, tries)
        if soft:
            w = (csr_weights[e] if csr is not None and csr_weights is not None
                 else soft_weights(src, dst, ii, jj, delta))
            keep = rng.random(draw) < w
            ii, jj = ii[keep][:need], jj[keep][:need]
        i[filled:filled + len(ii)] = ii
        j[filled:filled + len(jj)] = jj
        filled += len(ii)
    return i, j


def soft_weights(src: np.ndarray, dst: np.ndarray, i: np.ndarray, j: np.ndarray,
                 delta: float) -> np.ndarray:
    """Soft compatibility weight 1 - (d_ij / delta)^2 of edges (i, j)."""
    return 1.0 - (length_consistency(src, dst, i, j) / delta) ** 2


_WEIGHT_CHUNK = 1 << 20  # entries per chunk: ~100 MB of float64 scratch at most


def soft_edge_weights(csr: tuple[np.ndarray, np.ndarray], src: np.ndarray, dst: np.ndarray,
                      delta: float) -> np.ndarray:
    """
    Return the soft weights 1 - (d_ij / delta)^2 of the neighbour-list entries.

    They serve :func:`sample_edges` and are computed once per search, with the lists.
    """
    indptr, indices = csr
    rows = np.repeat(np.arange(len(indptr) - 1, dtype=np.int32), np.diff(indptr))
    weights = np.empty(len(indices), dtype=np.float32)
    for start in range(0, len(indices), _WEIGHT_CHUNK):  # bounded scratch memory
        part = slice(start, start + _WEIGHT_CHUNK)
        weights[part] = soft_weights(src, dst, rows[part], indices[part], delta)
    return weights


def _edges_by_rejection(graph: CompatibilityGraph, rng: np.random.Generator, count: int,
                        tries: int) -> tuple[np.ndarray, np.ndarray]:
    """
    Draw ``count`` edges (i, j) uniformly from E by rejection on the bit matrix.

    Draws i with probability deg(i) / 2|E|, then j uniform in N(i) by rejection, with an
    exact fallback for rows where all tries missed.
    """
    i = rng.choice(graph.n, size=count, p=graph.degree / graph.degree.sum())
    if graph.windows is None:
        cand = rng.integers(0, graph.n, size=(count, tries))
    else:  # every partner of i lies in its window: propose there (still uniform over N(i))
        lo, width = graph.windows[0][i], graph.windows[1][i] - graph.windows[0][i]
        cand = lo[:, None] + (rng.random((count, tries)) * width[:, None]).astype(np.int64)
    hit = graph.has_edge(np.repeat(i[:, None], tries, 1), cand)
    found = hit.any(axis=1)
    j = cand[np.arange(count), np.argmax(hit, axis=1)]
    miss = np.flatnonzero(~found)
    if len(miss):
        j[miss], _ = _uniform_member(graph.packed[i[miss]], graph.n, rng)
    return i, j


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


def sample_guided(rng: np.random.Generator, kernel: np.ndarray, adjacency: np.ndarray,
                  seed_weights: np.ndarray, count: int, xi: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """
    Preference-guided triples on a subset of M correspondences (local indices).

    Seed i with probability proportional to ``seed_weights``; then j in N(i) with
    probability proportional to K(i, j) + xi; then k in N(i) ∩ N(j) proportional to
    K(i, k) K(j, k) + xi. ``adjacency`` (M, M) bool has no self loops, so i, j, k differ.
    """
    m = len(seed_weights)
    i = rng.choice(m, size=count, p=seed_weights / seed_weights.sum())
    wj = (kernel[i] + xi) * adjacency[i]
    j, ok_j = weighted_choice_rows(wj, rng)
    wk = (kernel[i] * kernel[j] + xi) * (adjacency[i] & adjacency[j])
    k, ok_k = weighted_choice_rows(wk, rng)
    return i, j, k, ok_j & ok_k


def triangle_areas(points: np.ndarray, i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Areas of the triangles (p_i, p_j, p_k)."""
    return 0.5 * np.linalg.norm(np.cross(points[j] - points[i], points[k] - points[i]), axis=1)


def tournament(graph: CompatibilityGraph, members: tuple[np.ndarray, ...], count: int,
               size: int, ok: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """
    Keep the candidate with the most common neighbours of each group of ``size``.

    Groups are ``size`` consecutive candidates; the winner is the one whose members have
    the most common neighbours (second/third-order compatibility: inliers share the other
    inliers as neighbours, outliers only chance ones).

    ``members`` are index arrays of length count * size (an edge (i, j) or a triple
    (i, j, k)); ``ok`` marks valid candidates. Returns the winners' arrays, and their ``ok``
    mask when ``ok`` was given.
    """
    support = graph.popcount(graph.common(*members))
    if ok is not None:
        support = np.where(ok, support, -1)
    pick = np.argmax(support.reshape(count, size), axis=1) + np.arange(count) * size
    winners = tuple(m[pick] for m in members)
    return winners if ok is None else (winners[-1], ok[pick])


def sample_vertex_tournament(graph: CompatibilityGraph, rng: np.random.Generator, i: np.ndarray,
                             j: np.ndarray, size: int, *,
                             csr: tuple[np.ndarray, np.ndarray] | None = None,
                             draws: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Draw k in N(i) ∩ N(j) for each edge (i, j) by vertex tournament.

    Up to ``size`` uniform candidates k in N(i) ∩ N(j) compete; the one with the largest
    support |N(i) ∩ N(j) ∩ N(k)| wins.

    Candidates come from one batch of ``draws`` proposals per edge (from N(i) with the
    neighbour lists, else from all vertices), of which the first ``size`` members of
    N(i) ∩ N(j) compete; edges whose proposals all missed draw one k exactly (no
    tournament). Returns k, a mask of edges with a non-empty common neighbourhood, and
    the winners' support (the common-neighbour count of the triple).
    """
    count = len(i)
    if csr is not None:
        offset = np.floor(rng.random((count, draws)) * graph.degree[i][:, None]).astype(np.int64)
        cand = csr[1][csr[0][i][:, None] + offset].astype(np.int64)
        hit = graph.has_edge(np.repeat(j[:, None], draws, 1), cand)
    else:
        cand = rng.integers(0, graph.n, size=(count, draws))
        hit = graph.has_edge(np.repeat(i[:, None], draws, 1), cand)
        hit &= graph.has_edge(np.repeat(j[:, None], draws, 1), cand)
    hit &= np.cumsum(hit, axis=1) <= size
    rows, cols = np.nonzero(hit)
    common_ij = graph.common(i, j)
    support = graph.common_count(common_ij[rows], cand[rows, cols])
    # Per edge, the candidate with the largest support: sort by (row, -support).
    order = np.lexsort((-support, rows))
    first = order[np.unique(rows[order], return_index=True)[1]]
    k = np.zeros(count, dtype=np.int64)
    best = np.zeros(count, dtype=np.int64)
    ok = np.zeros(count, dtype=bool)
    winner = rows[first]
    k[winner], best[winner], ok[winner] = cand[winner, cols[first]], support[first], True
    miss = np.flatnonzero(~ok)
    if len(miss):
        k[miss], ok[miss] = _uniform_member(common_ij[miss], graph.n, rng)
        found = miss[ok[miss]]
        best[found] = graph.common_count(common_ij[found], k[found])
    return k, ok, best
