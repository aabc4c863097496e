"""
Bounded matching: match at most ``max_keypoints`` source points against the whole target.

Matching costs one search of the target's descriptor index per source point; matching a
bounded, spatially even subset of the source (keypoints) bounds the number of searches.
The subset is a coarser voxel grid over the downsampled source, one point a cell (the one
nearest the cell's centroid), with the cell size grown until at most ``max_keypoints``
cells are occupied: reproducible for the same input (no randomness). Not independent of
the input row order: a permuted LiDAR scan picked 58 of 965 keypoints differently.
"""

from __future__ import annotations

import numpy as np

from .descriptor_index import DescriptorIndex
from .matching import Correspondences, match_features
from ..config.frontend import FrontEndConfig
from ..geometry import grid_cells

_GROWTH = 1.05  # cell size margin per step of the search, above the area scaling


def select_keypoints(points: np.ndarray, max_keypoints: int,
                     voxel_size: float) -> np.ndarray:
    """
    Return the sorted indices of at most ``max_keypoints`` rows of ``points``.

    :param points: (M, 3) downsampled points, metres.
    :param max_keypoints: the bound; 0 or at least M returns every index.
    :param voxel_size: the points' voxel size, metres (the search starts from it).
    """
    n = len(points)
    if max_keypoints <= 0 or n <= max_keypoints:
        return np.arange(n)
    cell = voxel_size * np.sqrt(n / max_keypoints)  # surfaces: count ~ 1 / cell^2
    while True:
        _, inverse, counts = np.unique(grid_cells(points, cell), return_inverse=True,
                                       return_counts=True)
        if len(counts) <= max_keypoints:
            break
        cell *= _GROWTH * np.sqrt(len(counts) / max_keypoints)
    inverse = inverse.reshape(-1)
    centroids = np.stack([np.bincount(inverse, points[:, i]) for i in range(3)], axis=1)
    centroids /= counts[:, None]
    dist = np.linalg.norm(points - centroids[inverse], axis=1)
    order = np.lexsort((np.arange(n), dist, inverse))  # per cell: nearest, then lowest index
    first = order[np.searchsorted(inverse[order], np.arange(len(counts)))]
    return np.sort(first)


def match_keypoints(source_points: np.ndarray, source_descriptors: np.ndarray,
                    target_descriptors: np.ndarray, voxel_size: float,
                    config: FrontEndConfig, workers: int = 1,
                    target_index: DescriptorIndex | None = None) -> Correspondences:
    """
    Run :func:`match_features` from the source's keypoints to every target point.

    With ``config.max_keypoints`` = 0, or a source no larger, this is
    :func:`match_features` on every point, unchanged. Indices of the result index the
    whole downsampled clouds. Mutual matching is then between the keypoints and the
    target: a target point's nearest source is sought among the keypoints only.
    ``target_index`` as in :func:`match_features`.
    """
    keep = select_keypoints(source_points, config.max_keypoints, voxel_size)
    if len(keep) == len(source_points):
        return match_features(source_descriptors, target_descriptors, config, workers,
                              target_index)
    corr = match_features(source_descriptors[keep], target_descriptors, config, workers,
                          target_index)
    return Correspondences(keep[corr.source_index], corr.target_index, corr.distance)
