"""
Putative correspondences: nearest neighbours in FPFH descriptor space.

Exact (Euclidean, float64) nearest neighbours from an index of the target's descriptors
(:mod:`.descriptor_index`), which a latched target or a map builds once; the source's own
index answers the mutual check.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import compiled
from .descriptor_index import DescriptorIndex
from ..compiled_types import c_array
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
                   workers: int = 1, target_index: DescriptorIndex | None = None, *,
                   mutual: bool = True, ratio: float = 1.0,
                   cells: int = 0) -> Correspondences:
    """
    Match descriptors by nearest neighbour, source -> target, best first.

    Keeps only mutual nearest neighbours (``mutual``: the pipeline's matching), then, with
    ``ratio`` < 1, Lowe's ratio test (the pipeline runs none: the core needs no distinctive
    matches, only some right ones), then at most ``max_correspondences`` by descriptor
    distance.
    Descriptors that are all zero (no neighbours within the FPFH radius) never match:
    they would all be identical and pair up at random. Neighbours are exact (Euclidean,
    float64); among exactly equidistant descriptors the lowest index wins. ``workers``
    threads share the rows; the result does not depend on it. ``target_index`` is
    :func:`informative_index` of ``target``, when the caller keeps one (a latched target,
    a map); it is built here otherwise. Either way the result is the same. ``cells`` > 0
    searches only that many of the target index's cells nearest each source descriptor
    (:meth:`~.descriptor_index.DescriptorIndex.query`): an approximate nearest neighbour,
    for a search that needs most right matches, not all; the mutual check stays exact.
    """
    src_ok = np.flatnonzero(_informative(source))
    # A kept index knows its target's informative rows: a map's are not scanned again.
    known = None if target_index is None else target_index.rows
    dst_ok = np.flatnonzero(_informative(target)) if known is None else known
    if len(src_ok) == 0 or len(dst_ok) == 0:
        return _empty_correspondences()
    src = source[src_ok]
    if target_index is None:
        target_index = DescriptorIndex(target[dst_ok], workers)
    elif not _indexes(target_index, target, dst_ok):
        raise ValueError(f'target_index holds {target_index.size} rows, the target '
                         f'{len(dst_ok)} informative ones: not an index of this target')
    k = 2 if ratio < 1.0 and len(dst_ok) > 1 else 1
    nn = target_index.query(src, k, workers, cells)[0]
    # The index's own distances can differ in the last bit (another summation order); these
    # keep the best-first order of equal-looking matches what it always was.
    # Rows are read where they are: a map's target is large and need not be copied whole.
    dist = np.linalg.norm(src[:, None, :] - target[dst_ok[nn]], axis=2)
    keep = np.ones(len(src_ok), dtype=bool)
    if mutual:
        # Of the sources whose nearest is a target, only the nearest of them (ties to the
        # lower row) can be that target's nearest source: ask, for it alone, whether any
        # other source is nearer the target.
        squared = np.empty(len(src_ok))
        # as the index ranks
        compiled.squared_pair_distances(c_array(src, np.float64),
                                        c_array(target[dst_ok[nn[:, 0]]], np.float64), squared)
        best = np.lexsort((np.arange(len(src_ok)), squared, nn[:, 0]))
        first = best[np.r_[True, nn[best[1:], 0] != nn[best[:-1], 0]]]
        source_index = DescriptorIndex(src, workers, like=target_index)
        keep[:] = False
        keep[first] = source_index.is_nearest(target[dst_ok[nn[first, 0]]], first, workers)
    if k == 2:
        # Lowe: a match is distinctive when its best distance is clearly below the second.
        keep &= dist[:, 0] < ratio * dist[:, 1]
    return _best(src_ok[keep], dst_ok[nn[keep, 0]], dist[keep, 0], config.max_correspondences)


def informative_index(descriptors: np.ndarray, workers: int = 1) -> DescriptorIndex | None:
    """
    Return the index :func:`match_features` searches as ``target_index``, or None.

    It holds the informative rows of ``descriptors`` (:func:`informative_rows`), in order,
    and knows which they are (``rows``; a map's cache keeps them); None when there are
    none.
    """
    rows = informative_rows(descriptors)
    if len(rows) == 0:
        return None
    index = DescriptorIndex(descriptors[rows], workers)
    index.rows = rows
    return index


def informative_rows(descriptors: np.ndarray) -> np.ndarray:
    """Return the rows of ``descriptors`` that can match: finite and not all zero."""
    return np.flatnonzero(_informative(descriptors))


def _informative(descriptors: np.ndarray) -> np.ndarray:
    return np.isfinite(descriptors).all(axis=1) & (np.abs(descriptors).sum(axis=1) > 0)


def _indexes(index: DescriptorIndex, target: np.ndarray, rows: np.ndarray) -> bool:
    """Tell whether ``index`` holds ``target``'s ``rows`` (its first, middle and last)."""
    if index.size != len(rows) or (len(rows) and rows.max() >= len(target)):
        return False
    slots = np.unique(np.linspace(0, index.size - 1, 3).astype(np.int64))
    return bool(np.array_equal(index.arrays.points[slots],
                               target[rows[index.arrays.order[slots]]]))


def _best(src: np.ndarray, dst: np.ndarray, dist: np.ndarray, cap: int) -> Correspondences:
    order = np.argsort(dist, kind='stable')
    if cap > 0:
        order = order[:cap]
    return Correspondences(src[order].astype(np.int64), dst[order].astype(np.int64),
                           dist[order])


def _empty_correspondences() -> Correspondences:
    empty = np.zeros(0, dtype=np.int64)
    return Correspondences(empty, empty.copy(), np.zeros(0))
