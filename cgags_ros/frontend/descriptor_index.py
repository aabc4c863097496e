"""
An exact nearest-neighbour index over descriptors, built once per cloud and queried many times.

Brute force compares every source descriptor with every target descriptor, so its cost
grows with source x target points. This index (k-means cells with exact pruning bounds,
compiled in :mod:`.compiled.descriptor_index`) answers the same queries, exactly, while
computing a small share of those distances; a latched target or a map builds it once and reuses it
(:meth:`~.features.CloudFeatures.descriptor_index`). Asked to, it searches only the cells
nearest each query: approximate, for a search that needs most right matches, not all (a
map's consensus search, docs/maps.md).
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

import numpy as np

from . import compiled
from ..compiled_types import c_array
from ..parallel import run_chunks

# Cells ~ sqrt(M) / 2.5, at most 256: the cost of visiting the cells' centres grows with
# their count and the cost of scanning their members with M / count; measured on the
# redkitchen and LiDAR features from 5k to 37k points (docs/design.md).
_CELLS_PER_SQRT = 0.4
_MAX_CELLS = 256
_SAMPLE_PER_CELL = 64  # k-means runs on at most this many rows a cell
_ITERATIONS = 8
_PROJECTED = 12  # principal directions of the screening distance (float32)


class DescriptorIndex:
    """
    Exact k-nearest-neighbour search (k = 1 or 2) among the rows of a reference array.

    The answer equals brute force: nearest first by Euclidean distance (float64), ties to
    the lower reference row. The k-means partition only decides how fast it is found; it is
    seeded, so building is deterministic too. :meth:`query` with ``cells`` searches only the
    nearest cells instead: approximate, and deterministic as well.
    """

    def __init__(self, reference: np.ndarray, workers: int = 1, seed: int = 0,
                 like: DescriptorIndex | None = None) -> None:
        """
        Build the index over the (M, D) ``reference`` rows (finite), on ``workers`` threads.

        ``like``: an index of similar descriptors (the other cloud's) whose cell centres
        and principal directions are reused instead of computing them (k-means) again.
        """
        ref = _reference(reference)
        if like is not None and like.dim == ref.shape[1]:
            centres, basis = like.centres, like.basis
        else:
            centres, basis = _partition(ref, _cell_count(len(ref)), seed)
        labels, ring = _assign(ref, centres, workers)
        order = _stored_order(labels, ring)
        self._store(ref[order], labels[order], ring[order], order, centres, basis)

    @classmethod
    def on_cells(cls, cells: Cells, keep: np.ndarray, descriptors: np.ndarray,
                 rows: np.ndarray) -> DescriptorIndex:
        """
        Return the index of the rows of ``cells`` where ``keep`` is True, numbered as they come.

        ``descriptors[rows]`` are the rows ``cells`` was fitted to (only the kept ones are
        read). Their cells and order are already known: building it computes no row's
        distance to a centre and sorts nothing, so an index over a few of many rows (a place
        of a map) costs little more than copying them.
        """
        keep = np.asarray(keep, dtype=bool)
        stored = cells.order[keep[cells.order]]
        if len(stored) == 0:
            raise ValueError('keep holds no row')
        index = cls.__new__(cls)
        index._store(_reference(descriptors[rows[stored]]), cells.label[stored],
                     cells.ring[stored], (np.cumsum(keep) - 1)[stored], cells.centres,
                     cells.basis)
        return index

    def _store(self, points: np.ndarray, labels: np.ndarray, ring: np.ndarray,
               order: np.ndarray, centres: np.ndarray, basis: np.ndarray) -> None:
        """
        Hold the reference rows by cell (the arrays the search reads).

        ``points``: the rows in stored order (by cell, then ring, then row); ``labels``,
        ``ring``: their cells among ``centres`` and distances to them; ``order``: their rows.
        """
        self.rows: np.ndarray | None = None  # which rows of a cloud's descriptors it holds
        self.size, self.dim = points.shape
        # Drop cells without members: a centre that duplicates another gets none (ties go
        # to the lower one), so every pair of centres left is apart and the plane bound
        # never divides by zero.
        used = np.bincount(labels, minlength=len(centres)) > 0
        labels = (np.cumsum(used) - 1)[labels]
        self.centres = np.ascontiguousarray(centres[used])
        self.basis = basis
        starts = np.searchsorted(labels, np.arange(len(self.centres) + 1))
        radius = np.ascontiguousarray(ring[starts[1:] - 1])  # the last of a cell is farthest
        slot_of = np.empty(self.size, dtype=np.int64)
        slot_of[order] = np.arange(self.size)
        diff = self.centres[:, None, :] - self.centres[None, :, :]
        self.arrays = compiled.IndexArrays(
            self.centres, np.ascontiguousarray(self.centres.T),
            c_array(np.sqrt(np.einsum('ijk,ijk->ij', diff, diff)), np.float64), radius,
            starts, c_array(ring, np.float64), points, basis,
            np.ascontiguousarray(basis @ points.T, dtype=np.float32),
            float(np.sqrt(np.einsum('ij,ij->i', points, points).max())),
            c_array(order, np.int64), slot_of)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Return the index as named arrays (:meth:`from_arrays` builds it back, as it was)."""
        out = {name: np.asarray(value) for name, value in self.arrays._asdict().items()}
        out['max_norm'] = np.array([self.arrays.max_norm])
        if self.rows is not None:
            out['rows'] = self.rows
        return out

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> DescriptorIndex:
        """
        Return the index :meth:`to_arrays` gave, on ``arrays`` as they are (no copy).

        Arrays memory-mapped from a map's cache stay so: processes that load one map share
        its index.
        """
        index = cls.__new__(cls)
        fields = {name: arrays[name] for name in compiled.IndexArrays._fields}
        fields['max_norm'] = float(np.reshape(fields['max_norm'], -1)[0])
        index.arrays = compiled.IndexArrays(**fields)
        index.size, index.dim = index.arrays.points.shape
        index.centres, index.basis = index.arrays.centres, index.arrays.basis
        index.rows = arrays.get('rows')
        return index

    def query(self, queries: np.ndarray, k: int = 1, workers: int = 1,
              cells: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the (len(queries), k) reference rows nearest each query and their distances.

        ``k`` is 1 or 2 (the index holds at least k rows); ``workers`` threads share the
        queries, with the same result for any number of them. ``cells`` > 0 makes the search
        approximate: it visits that many cells, nearest centre first (more only until it has
        ``k`` rows), and answers the nearest of their members; 0, every cell a bound does not
        rule out: exact.
        """
        if cells < 0:
            raise ValueError(f'cells must be 0 (exact) or positive, got {cells}')
        if k not in (1, 2) or k > self.size:
            raise ValueError(f'k must be 1 or 2 and at most {self.size}, got {k}')
        q = c_array(queries, np.float64).reshape(-1, self.dim)
        index = np.empty((len(q), k), dtype=np.int64)
        dist = np.empty((len(q), k))
        run_chunks(
            lambda a, b: compiled.search(self.arrays, q[a:b], k, cells, index[a:b], dist[a:b]),
            len(q), workers)
        return index, dist

    def is_nearest(self, queries: np.ndarray, rows: np.ndarray, workers: int = 1) -> np.ndarray:
        """
        Tell, for each query, whether reference row ``rows[i]`` is its nearest.

        The same as ``query(queries, 1)[0][:, 0] == rows``, at a fraction of the cost: the
        search starts from that row and stops at the first row that beats it.
        """
        q = c_array(queries, np.float64).reshape(-1, self.dim)
        rows = c_array(rows, np.int64)
        if len(rows) != len(q) or (len(rows) and not 0 <= rows.min() <= rows.max() < self.size):
            raise ValueError(f'rows must be one reference row (0 to {self.size - 1}) a query')
        out = np.empty(len(q), dtype=np.bool_)
        run_chunks(lambda a, b: compiled.nearest_is(self.arrays, q[a:b], rows[a:b], out[a:b]),
                   len(q), workers)
        return out


@dataclasses.dataclass
class Cells:
    """
    A partition of many descriptor rows, fitted once: the cells of any few of them.

    An index over a part of the rows (:meth:`DescriptorIndex.on_cells`) takes their cells
    from here instead of fitting and assigning its own.

    :ivar centres: (C, D) the cells' centres.
    :ivar basis: (P, D) the rows' leading principal directions.
    :ivar label: (M,) each row's cell (its nearest centre).
    :ivar ring: (M,) each row's distance to its centre.
    :ivar order: (M,) the rows by cell, then ring, then row: as an index stores them.
    """

    centres: np.ndarray
    basis: np.ndarray
    label: np.ndarray
    ring: np.ndarray
    order: np.ndarray

    @classmethod
    def fit(cls, reference: np.ndarray, part_rows: int, workers: int = 1,
            seed: int = 0) -> Cells:
        """
        Return cells of the (M, D) ``reference`` rows for indexes of about ``part_rows``.

        As many cells as :class:`DescriptorIndex` fits to that many rows: an index over a
        part visits all of its cells, and cells fitted to all the rows would be too many.
        """
        ref = _reference(reference)
        centres, basis = _partition(ref, _cell_count(part_rows), seed)
        labels, ring = _assign(ref, centres, workers)
        return cls(centres, basis, labels, ring, _stored_order(labels, ring))


def _reference(reference: np.ndarray) -> np.ndarray:
    ref = c_array(reference, np.float64)
    if ref.ndim != 2 or len(ref) == 0:
        raise ValueError(f'reference must be a non-empty (M, D) array, got {ref.shape}')
    return ref


def _cell_count(rows: int) -> int:
    return int(np.clip(round(_CELLS_PER_SQRT * np.sqrt(rows)), 1, _MAX_CELLS))


def _assign(ref: np.ndarray, centres: np.ndarray,
            workers: int) -> tuple[np.ndarray, np.ndarray]:
    """Return each row's nearest centre (ties to the lower) and its distance to it."""
    labels = np.empty(len(ref), dtype=np.int64)
    ring = np.empty(len(ref))
    centresT = np.ascontiguousarray(centres.T)
    run_chunks(lambda a, b: compiled.assign(ref[a:b], centresT, labels[a:b], ring[a:b]),
               len(ref), workers)
    return labels, ring


def _stored_order(labels: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Return the rows by cell, then distance to its centre, then row: as an index stores them."""
    return np.lexsort((np.arange(len(labels)), ring, labels))


def _partition(ref: np.ndarray, cells: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Return ``cells`` k-means centres of ``ref`` and its leading principal directions."""
    rng = np.random.default_rng(seed)
    pick = rng.permutation(len(ref))[:min(len(ref), _SAMPLE_PER_CELL * cells)]
    sample = ref[np.sort(pick)]
    centres = sample[rng.permutation(len(sample))[:cells]].copy()
    compiled.kmeans(sample, centres, _ITERATIONS)
    # Distances along the leading principal directions bound the full distance from
    # below and cost a fraction of it to compute.
    spread = sample - sample.mean(axis=0)
    _, vectors = np.linalg.eigh(spread.T @ spread)
    basis = np.ascontiguousarray(vectors[:, ::-1][:, :min(_PROJECTED, ref.shape[1])].T)
    return centres, basis
