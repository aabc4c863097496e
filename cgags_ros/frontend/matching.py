"""
Putative correspondences: nearest neighbours in FPFH descriptor space.

Exact (Euclidean, float64 decisions) brute force by blocks of one matrix product, on
``workers`` threads; see :func:`nearest_rows` for why not a k-d tree.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import dataclasses
import threading

import numpy as np

from ..config.frontend import FrontEndConfig


@dataclasses.dataclass
class Correspondences:
    """
    Putative matches: ``source[i]`` (source frame) <-> ``target[i]`` (target frame).

    ``source_index``/``target_index`` index the downsampled clouds; ``distance`` is the FPFH
    descriptor distance, ascending (best first).
    """

    source_index: np.ndarray
    target_index: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.source_index)


def match_features(source: np.ndarray, target: np.ndarray, config: FrontEndConfig,
                   workers: int = 1) -> Correspondences:
    """
    Match descriptors by nearest neighbour, source -> target, best first.

    Keeps only mutual nearest neighbours (``mutual_filter``), then Lowe's ratio test
    (``ratio_test`` < 1), then at most ``max_correspondences`` by descriptor distance.
    Descriptors that are all zero (no neighbours within the FPFH radius) never match:
    they would all be identical and pair up at random. Neighbours are exact (Euclidean,
    float64); among exactly equidistant descriptors the lowest index wins. ``workers``
    threads share the rows (see :func:`nearest_rows`); the result does not depend on it.
    """
    src_ok = np.flatnonzero(_informative(source))
    dst_ok = np.flatnonzero(_informative(target))
    if len(src_ok) == 0 or len(dst_ok) == 0:
        return _empty_correspondences()
    src, dst = source[src_ok], target[dst_ok]
    k = 2 if config.ratio_test < 1.0 and len(dst_ok) > 1 else 1
    nn = nearest_rows(src, dst, k, workers)
    dist = np.linalg.norm(src[:, None, :] - dst[nn], axis=2)
    keep = np.ones(len(src_ok), dtype=bool)
    if config.mutual_filter:
        # Only targets that are some source's nearest can pass: ask only them back.
        hit = np.unique(nn[:, 0])
        back = np.full(len(dst), -1)
        back[hit] = nearest_rows(dst[hit], src, 1, workers)[:, 0]
        keep &= back[nn[:, 0]] == np.arange(len(src_ok))
    if k == 2:
        # Lowe: a match is distinctive when its best distance is clearly below the second.
        keep &= dist[:, 0] < config.ratio_test * dist[:, 1]
    return _best(src_ok[keep], dst_ok[nn[keep, 0]], dist[keep, 0], config.max_correspondences)


# Block sizes (entries of one distance block) that stay in cache while argmin reads them
# back; chosen by measurement (docs/implementation.md).
_BLOCK_ELEMENTS = 1 << 18  # float64
_BLOCK_ELEMENTS_F32 = 1 << 20  # float32, in _nearest_row32
_EXACT_PAIRS = 1 << 16  # candidate pairs per chunk of the exact re-ranking (<= 17 MB)


_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()


def nearest_rows(query: np.ndarray, reference: np.ndarray, k: int = 1,
                 workers: int = 1) -> np.ndarray:
    """
    Return the indices of the ``k`` rows of ``reference`` nearest to each query row.

    The result is (len(query), k), nearest first, by Euclidean distance; k is 1 or 2
    (``reference`` needs at least k rows).

    k = 1 is computed in float32 with an exact float64 decision wherever float32 rounding
    could change the answer (:func:`_nearest_row32`); k = 2 by the float64 expansion below.

    ``workers`` > 1 splits the query rows over that many threads (numpy releases the GIL
    in the products and argmins; rows are independent, so the result is the same). Meant
    for single-threaded BLAS: own threads also run the argmins in parallel, so they beat
    BLAS's threads (docs/implementation.md).

    Brute force by blocks of one matrix product: ``|q - r|^2 = |q|^2 - 2 q.r + |r|^2``, and
    ``|q|^2`` is constant along a row, so ``[q, 1] @ [-2 r, |r|^2]^T`` ranks the same. For
    33-D FPFH a k-d tree prunes little: this is faster than scipy's cKDTree at the sizes
    the pipeline matches. The expansion is exact up to ~1e-15 of the squared norms, which
    cannot tell duplicates (distance 0, common among sparse FPFH) from near-duplicates: rows
    whose second neighbour is that close are ranked again from the exact differences.
    """
    step = max(1, _BLOCK_ELEMENTS // max(len(reference), 1))
    if workers > 1 and len(query) >= 2 * step:
        global _pool, _pool_size
        with _pool_lock:
            if _pool is None or _pool_size < workers:
                _pool = ThreadPoolExecutor(workers, thread_name_prefix='cgags_match')
                _pool_size = workers
            pool = _pool
        bounds = np.linspace(0, len(query), workers + 1).astype(int)
        parts = [pool.submit(_nearest_rows_any, query[a:b], reference, k)
                 for a, b in zip(bounds[:-1], bounds[1:])]
        return np.vstack([p.result() for p in parts])
    return _nearest_rows_any(query, reference, k)


def _nearest_rows_any(query: np.ndarray, reference: np.ndarray, k: int) -> np.ndarray:
    return _nearest_row32(query, reference) if k == 1 else _nearest_rows(query, reference, k)


# Bound on |float32 - exact| of one entry of the float32 product in _nearest_row32, relative
# to |q|^2 + 2 max|r|^2: input rounding plus a 34-term dot product is <= ~37 u (u = 6e-8,
# 2.2e-6); the factor 1e-5 leaves a 4.5x margin.
_F32_TOL = 1e-5


def _nearest_row32(query: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """
    Compute ``_nearest_rows(query, reference, 1)`` from float32 products, exactly.

    The expansion in float32 (descriptors centred on the reference mean, so that the
    squared norms, hence the rounding, are smaller) moves half the bytes of float64, which
    makes the products and argmins faster. A row whose float32 runner-up is within twice
    the rounding bound of its minimum (few rows: mostly near-duplicate descriptors) is
    decided by exact float64 distances to every reference row in that window, ties to the
    lower index; so the answer never depends on float32 rounding, and near-duplicates are
    ranked more exactly than by the float64 expansion.
    """
    centre = reference.mean(axis=0)
    q, ref = query - centre, reference - centre
    norms = np.einsum('ij,ij->i', ref, ref)
    r = np.vstack([-2.0 * ref.T, norms]).astype(np.float32)
    q32 = np.hstack([q, np.ones((len(q), 1))]).astype(np.float32)
    tol = 2.0 * _F32_TOL * (np.einsum('ij,ij->i', q, q) + 2.0 * norms.max())
    out = np.empty(len(query), dtype=np.int64)
    bound = np.empty(len(query))
    step = max(1, _BLOCK_ELEMENTS_F32 // len(reference))
    unsure = []
    for s in range(0, len(query), step):
        d = q32[s:s + step] @ r
        rows = np.arange(len(d))
        out[s:s + step] = first = d.argmin(axis=1)
        bound[s:s + step] = d[rows, first] + tol[s:s + step]
        d[rows, first] = np.inf
        unsure.append(s + np.flatnonzero(d.min(axis=1) <= bound[s:s + step]))
    unsure = np.concatenate(unsure)
    # Every reference row within the window, then exact distances; by chunks of rows so
    # that near-identical descriptors (a window holding every row) stay within memory.
    chunk = max(1, _EXACT_PAIRS // len(reference))
    for c in range(0, len(unsure), chunk):
        rows = unsure[c:c + chunk]
        out[rows] = _exact_nearest(query[rows], reference, q32[rows] @ r <= bound[rows, None],
                                   1)[:, 0]
    return out[:, None]


def _nearest_rows(query: np.ndarray, reference: np.ndarray, k: int) -> np.ndarray:
    q = np.hstack([query, np.ones((len(query), 1))])
    norms = np.einsum('ij,ij->i', reference, reference)
    r = np.vstack([-2.0 * reference.T, norms])
    out = np.empty((len(query), k), dtype=np.int64)
    step = max(1, _BLOCK_ELEMENTS // len(reference))
    for s in range(0, len(query), step):
        d = q[s:s + step] @ r
        out[s:s + step, 0] = first = d.argmin(axis=1)
        if k == 2:
            rows = np.arange(len(d))
            best = d[rows, first]
            d[rows, first] = np.inf
            out[s:s + step, 1] = second = d.argmin(axis=1)
            d[rows, first] = best
            qq = np.einsum('ij,ij->i', query[s:s + step], query[s:s + step])
            tol = 1e-9 * (qq + norms.max())
            unsure = np.flatnonzero(qq + d[rows, second] <= tol)
            if len(unsure):
                out[s + unsure] = _exact_nearest(
                    query[s + unsure], reference,
                    d[unsure] + qq[unsure, None] <= 2 * tol[unsure, None], 2)
    return out


def _exact_nearest(query: np.ndarray, reference: np.ndarray, candidates: np.ndarray,
                   k: int) -> np.ndarray:
    """
    Return the (len(query), k) indices of the k nearest rows among ``candidates``.

    ``candidates`` is a mask (rows x reference; every row holds at least k); distances are
    exact, ties go to the lower index.
    """
    row, col = np.nonzero(candidates)
    dist = np.linalg.norm(query[row] - reference[col], axis=1)
    order = np.lexsort((col, dist, row))
    row, col = row[order], col[order]
    start = np.searchsorted(row, np.arange(len(query)))
    return np.stack([col[start + i] for i in range(k)], axis=1)


def _informative(descriptors: np.ndarray) -> np.ndarray:
    return np.isfinite(descriptors).all(axis=1) & (np.abs(descriptors).sum(axis=1) > 0)


def _best(src: np.ndarray, dst: np.ndarray, dist: np.ndarray, cap: int) -> Correspondences:
    order = np.argsort(dist, kind='stable')
    if cap > 0:
        order = order[:cap]
    return Correspondences(src[order].astype(np.int64), dst[order].astype(np.int64),
                           dist[order])


def _empty_correspondences() -> Correspondences:
    empty = np.zeros(0, dtype=np.int64)
    return Correspondences(empty, empty.copy(), np.zeros(0))
