"""
Places of a prepared map: where in it a scan may be, ranked before it is registered.

A scan registered against a whole map matches its descriptors against every map point, and
the other rooms' matches drown its own as the map grows (docs/maps.md). The map's
**place grid**, built once when the map is prepared and stored with its features, lets a
query look only where it may be:

- **places**: the map's points grouped on a grid of ``TILE_VOXELS`` voxels; a place is
  the centre of an occupied cell, and its submap is the map within 2.5 of the query's
  reaches of it. The reach is the query's own, not the map's: a room's RGB-D fragment reaches ~26
  voxels from its centroid, a LiDAR scan ~150 (docs/maps.md), so no one submap size
  would fit both.
- **votes**: one map point a ``VOTE_CELL_VOXELS`` cell (its informative descriptor) with
  its own descriptor index. Each of at most ``KEYPOINTS`` scan keypoints votes for the
  place of its nearest voting descriptor. A place's votes are those within 1.5 of the
  scan's reaches of it, so a scan's own place collects the votes of all its surfaces; its
  score discounts what chance gives it (most votes go to look-alike descriptors anywhere,
  the more where the map has more voting points).
- a **hint** (:class:`~.hint.Hint`: a position with a radius, e.g. ``initialpose`` with its
  covariance) leaves only the places it covers.
- **cells**: the map's descriptors partitioned once more, into cells sized for a submap
  (:class:`~..frontend.descriptor_index.Cells`), so that a submap's descriptor index is
  cut from them at query time (:meth:`PlaceIndex.submap`) instead of fitted.

Numpy and the front end only: :mod:`.locate` tests and registers the ranked places.
All positions are in the map's local frame (the features', :class:`~.map.PreparedMap`).
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

import numpy as np
from scipy.spatial import cKDTree

from .hint import Hint
from ..frontend.descriptor_index import Cells, DescriptorIndex
from ..frontend.features import CloudFeatures
from ..frontend.keypoints import select_keypoints
from ..frontend.matching import informative_rows
from ..geometry import bounds, grid_cells

TILE_VOXELS = 10.0  # the place grid's spacing: fine beside the smallest reach, ~26 voxels
VOTE_CELL_VOXELS = 3.0  # one voting point a cell: a ninth of a surface's points
KEYPOINTS = 1000  # scan keypoints that vote for places and test them
CHANCE_SHARE = 0.5  # of a place's chance votes not counted (docs/maps.md: how chosen)
REACH_QUANTILE = 90.0  # a scan's reach: this percentile of its points' distance to their centroid
SUBMAP_SHARE = 8  # the submaps' cells suit this share of the map


@dataclasses.dataclass
class Place:
    """
    One place a query ranked: its centre, score and submap (map local frame, metres).

    :ivar centre: (3,) the submap's centre.
    :ivar votes: the scan's votes within its reach of the centre.
    :ivar rows: sorted rows of the map's features in the submap.
    :ivar by: what put it there: 'votes', 'hint' (no vote where the hint is) or 'consensus'
        (:mod:`.locate`: the whole map's short search).
    """

    centre: np.ndarray
    votes: int
    rows: np.ndarray
    by: str = 'votes'


@dataclasses.dataclass
class Ranked:
    """
    What a query's ranking found: the places to test, best first, or the whole map.

    :ivar places: the ranked places (empty with ``whole`` or when a hint covers none).
    :ivar whole: the map is within one submap of the query, or its best place holds half
        of it: register against all of it.
    :ivar reach: the scan's reach (metres).
    :ivar keypoints: the scan's rows that voted (informative keypoints).
    """

    places: list[Place]
    whole: bool
    reach: float
    keypoints: np.ndarray


class PlaceIndex:
    """The place grid and the voting points of a map's features (see the module doc)."""

    PREFIX = 'places.'

    def __init__(self, centres: np.ndarray, vote_place: np.ndarray, index: DescriptorIndex,
                 spacing: float, cells: Cells) -> None:
        """Hold the arrays (as they are: memory-mapped ones stay so)."""
        self.centres, self.vote_place = centres, vote_place
        self.index, self.spacing, self.cells = index, float(spacing), cells
        self._voter_tree: cKDTree | None = None
        low, high = centres.min(axis=0), centres.max(axis=0)
        self._middle = 0.5 * (low + high)
        # Every map point lies within half a cell's diagonal of its place's cell.
        self._radius = float(np.linalg.norm(centres - self._middle, axis=1).max()
                             + np.sqrt(3.0) * self.spacing)

    def __len__(self) -> int:
        """Return the number of places."""
        return len(self.centres)

    @classmethod
    def build(cls, features: CloudFeatures, voxel_size: float,
              workers: int = 1) -> PlaceIndex | None:
        """Return the place index of a map's features; None when no descriptor can match."""
        points, map_index = features.points, features.descriptor_index(workers)
        if map_index is None:
            return None
        spacing = TILE_VOXELS * voxel_size
        low = bounds(points)[0]
        _, place_of, counts = np.unique(grid_cells(points, spacing, low), return_inverse=True,
                                        return_counts=True)
        place_of = place_of.reshape(-1)
        centres = np.stack([np.bincount(place_of, points[:, i]) for i in range(3)], axis=1)
        centres /= counts[:, None]
        cell = VOTE_CELL_VOXELS * voxel_size
        _, first = np.unique(grid_cells(points, cell, low), return_index=True)
        rows = np.sort(first)
        rows = rows[informative_rows(features.descriptors[rows])]
        index = DescriptorIndex(features.descriptors[rows], workers, like=map_index)
        cells = Cells.fit(features.descriptors[map_index.rows],
                          len(map_index.rows) // SUBMAP_SHARE, workers)
        return cls(centres, place_of[rows], index, spacing, cells)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Return the index as named arrays for the map cache (:meth:`from_arrays`)."""
        out = {'centres': self.centres, 'vote_place': self.vote_place,
               'spacing': np.array([self.spacing])}
        out.update({f'index.{k}': v for k, v in self.index.to_arrays().items()})
        out.update({f'cells.{k}': v for k, v in dataclasses.asdict(self.cells).items()})
        return {self.PREFIX + k: v for k, v in out.items()}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> PlaceIndex | None:
        """Return the index of a cache entry's arrays (None when it holds none), as they are."""
        mine = {k[len(cls.PREFIX):]: v for k, v in arrays.items() if k.startswith(cls.PREFIX)}
        if not mine:
            return None
        index = DescriptorIndex.from_arrays(
            {k[len('index.'):]: v for k, v in mine.items() if k.startswith('index.')})
        cells = Cells(**{k[len('cells.'):]: v for k, v in mine.items() if k.startswith('cells.')})
        return cls(mine['centres'], mine['vote_place'], index, float(mine['spacing'][0]), cells)

    def rank(self, scan: CloudFeatures, voxel_size: float, count: int, map_tree: cKDTree,
             hint: Hint | None = None, workers: int = 1) -> Ranked:
        """
        Rank the places ``scan`` may be in; return at most ``count``, best first.

        :param scan: the scan's features (its own frame).
        :param map_tree: the map's k-d tree (its submaps are read from it).
        :param hint: a :class:`~.hint.Hint` in the map's local frame: only the places
            within its radius and the scan's reach of its position (in x and y alone when
            planar) are ranked.
        """
        spread = np.linalg.norm(scan.points - scan.points.mean(axis=0), axis=1)
        reach = float(np.percentile(spread, REACH_QUANTILE))
        # Votes are counted within ``near`` of a place: the scan's reach and the error of a
        # centroid placed by votes; its submap reaches as far again beyond the centre.
        near = self.near(reach)
        covered = self._covered(hint, reach)
        if not covered.any() or self._radius <= reach + near:
            return Ranked([], bool(covered.any()), reach, np.zeros(0, dtype=np.int64))
        keypoints = select_keypoints(scan.points, KEYPOINTS, voxel_size)
        keypoints = keypoints[informative_rows(scan.descriptors[keypoints])]
        votes = np.zeros(len(self.centres), dtype=np.int64)
        if len(keypoints):
            nearest = self.index.query(scan.descriptors[keypoints], 1, workers)[0][:, 0]
            np.add.at(votes, self.vote_place[nearest], 1)
        voted = np.flatnonzero(votes)
        candidates = voted[covered[voted]]
        if len(candidates) == 0:  # no vote where the hint is: the hint alone places the scan
            places = [self._place(self._where(hint, covered), 0, reach + near, map_tree,
                                  'hint')]
        else:
            places = self._best(votes, voted, candidates, near, count, reach + near, map_tree,
                                len(keypoints))
        # A place that holds half the map is the map: testing it costs more than it saves.
        whole = 2 * len(places[0].rows) >= map_tree.n
        return Ranked([] if whole else places, whole, reach, keypoints)

    def _best(self, votes: np.ndarray, voted: np.ndarray, candidates: np.ndarray,
              near: float, count: int, radius: float, map_tree: cKDTree,
              cast: int) -> list[Place]:
        """
        Return the ``count`` best places, apart and each with a submap of its own.

        Each is more than ``near`` from the others, and its submap is not within theirs.

        A place's score is its votes (within ``near``) less ``CHANCE_SHARE`` of what
        ``cast`` votes for random voting points would give it: most votes are chance, so
        raw counts favour where the map has most voting points (a larger street) over where
        the scan is, yet a room's own place is where most of its chance votes land too.
        """
        pairs = cKDTree(self.centres[candidates]).sparse_distance_matrix(
            cKDTree(self.centres[voted]), near, output_type='ndarray')  # within near, 0 too
        got = np.bincount(pairs['i'], weights=votes[voted[pairs['j']]],
                          minlength=len(candidates)).astype(np.int64)
        share = self._voters().query_ball_point(self.centres[candidates], near,
                                                return_length=True) / len(self.vote_place)
        expected = cast * share
        score = got - CHANCE_SHARE * expected
        places: list[Place] = []
        for i in np.argsort(-score, kind='stable'):
            if any(np.linalg.norm(self.centres[candidates[i]] - p.centre) <= near
                   for p in places):
                continue
            # Sorted: the weighted centre sums them in one order, however the pairs come.
            members = voted[np.sort(pairs['j'][pairs['i'] == i])]
            centre = np.average(self.centres[members], axis=0, weights=votes[members])
            place = self._place(centre, int(got[i]), radius, map_tree)
            if any(_within(place.rows, p.rows) for p in places):
                continue  # testing a place ranked before it tests this submap too
            places.append(place)
            if len(places) == count:
                break
        return places

    def submap(self, features: CloudFeatures, rows: np.ndarray) -> CloudFeatures:
        """Return :func:`submap_features` of the map's ``features``, its index on our cells."""
        return submap_features(features, rows, self.cells)

    def near(self, reach: float) -> float:
        """Return how near a place a scan of ``reach`` votes for it (metres)."""
        return 1.5 * reach + self.spacing

    def place_at(self, centre: np.ndarray, reach: float, map_tree: cKDTree) -> Place:
        """Return the place centred at ``centre`` for a scan of ``reach`` (no votes)."""
        return self._place(centre, 0, reach + self.near(reach), map_tree, 'consensus')

    def _voters(self) -> cKDTree:
        """Return the k-d tree of the voting points, each at its place's centre (built once)."""
        if self._voter_tree is None:
            self._voter_tree = cKDTree(self.centres[self.vote_place])
        return self._voter_tree

    def _covered(self, hint: Hint | None, reach: float) -> np.ndarray:
        if hint is None:
            return np.ones(len(self.centres), dtype=bool)
        return self._distance(hint) <= hint.radius + reach

    def _distance(self, hint: Hint) -> np.ndarray:
        """Return each place's distance to the hint (in x and y alone when planar)."""
        return np.linalg.norm((self.centres - hint.position)[:, :2 if hint.planar else 3],
                              axis=1)

    def _where(self, hint: Hint, covered: np.ndarray) -> np.ndarray:
        """Return the hint's position; a planar one at the height of its nearest place."""
        if not hint.planar:
            return hint.position
        nearest = np.flatnonzero(covered)[np.argmin(self._distance(hint)[covered])]
        return np.array([*hint.position[:2], self.centres[nearest, 2]])

    @staticmethod
    def _place(centre: np.ndarray, votes: int, radius: float, map_tree: cKDTree,
               by: str = 'votes') -> Place:
        rows = np.asarray(map_tree.query_ball_point(centre, radius), dtype=np.int64)
        return Place(np.asarray(centre, dtype=np.float64), votes, np.sort(rows), by)


def _within(rows: np.ndarray, other: np.ndarray) -> bool:
    """Return whether the sorted ``rows`` are all among the sorted ``other``."""
    if len(rows) > len(other):
        return False
    at = np.minimum(np.searchsorted(other, rows), len(other) - 1)
    return bool(np.all(other[at] == rows))


def submap_features(features: CloudFeatures, rows: np.ndarray,
                    cells: Cells | None = None) -> CloudFeatures:
    """
    Return the features of the map's sorted ``rows`` (copied), with a descriptor index.

    ``features``: the map's. The map's resolution is kept (its gates and thresholds are the
    map's). The index takes its rows' cells from ``cells`` (:attr:`PlaceIndex.cells`, fitted
    to the map's informative rows once) instead of fitting its own for the one query it
    serves; without them it is fitted when first asked for. The k-d tree is left to
    :func:`with_tree`: only a submap that is registered needs one.
    """
    descriptors = np.ascontiguousarray(features.descriptors[rows])
    sub = CloudFeatures(np.ascontiguousarray(features.points[rows]),
                        np.ascontiguousarray(features.normals[rows]), descriptors,
                        features.resolution, None, features.sensor_at_origin)
    if cells is None:
        return sub
    whole = features.descriptor_index().rows  # the rows the cells partition
    inside = np.zeros(len(features.points), dtype=bool)
    inside[rows] = True
    keep = inside[whole]
    index = None  # nothing here can match
    if keep.any():
        index = DescriptorIndex.on_cells(cells, keep, features.descriptors, whole)
        index.rows = np.searchsorted(rows, whole[keep])
    sub._index.append(index)
    return sub


def with_tree(sub: CloudFeatures) -> CloudFeatures:
    """Return :func:`submap_features`' ``sub`` with its k-d tree (its index shared)."""
    return sub if sub.tree is not None else dataclasses.replace(sub, tree=cKDTree(sub.points))
