"""
Synthetic putative correspondences built from a real scanned model (numpy/scipy only).

Used by the core's tests, the core benchmark and the ablation. Convention everywhere:
``dst = R @ src + t`` for inliers (source -> target), units of the model (the Stanford
bunny model is unit-scaled by :func:`unit_scale`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from cgags_ros.io.clouds import read_cloud
from cgags_ros.io.shared_data import shared_data_dir
import numpy as np
from scipy.spatial.transform import Rotation


BUNNY_MODEL = 'objects/teaser/bun_zipper_res3.ply'


def unit_scale(points: np.ndarray) -> np.ndarray:
    """Centre the points and scale them so the largest bounding-box extent is 1."""
    centred = points - points.mean(axis=0)
    return centred / np.ptp(centred, axis=0).max()


def load_bunny(data_dir: str | Path | None = None) -> np.ndarray:
    """Load the Stanford bunny model (1889 points), unit-scaled."""
    return unit_scale(read_cloud(Path(data_dir or shared_data_dir()) / BUNNY_MODEL))


def random_transform(rng: np.random.Generator, max_translation: float = 1.0) -> np.ndarray:
    """Draw a uniformly random rotation (any angle) and a translation in [-t, t]^3."""
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-max_translation, max_translation, 3)
    return T


OUTLIER_LAYOUTS = ('uniform', 'surface', 'cube', 'cube-surface')
_WIDE = 3.0  # how much wider than the model the 'cube' layouts spread their outliers


@dataclasses.dataclass
class SyntheticProblem:
    src: np.ndarray
    dst: np.ndarray
    transform: np.ndarray  # ground truth, src -> dst
    inlier_mask: np.ndarray
    noise_sigma: float


def make_correspondences(model: np.ndarray, n: int, outlier_ratio: float, *,
                         noise_sigma: float = 0.01, rng: np.random.Generator | int = 0,
                         outliers: str = 'uniform',
                         transform: np.ndarray | None = None) -> SyntheticProblem:
    """
    Build N putative correspondences of which round((1 - outlier_ratio) N) are inliers.

    Inliers: ``src`` a model point, ``dst = R src + t + N(0, sigma^2 I)``.
    Outliers (``outliers``, one of :data:`OUTLIER_LAYOUTS`): ``'uniform'`` puts ``dst``
    uniformly in the bounding box of the transformed model (TEASER++'s protocol);
    ``'surface'`` puts it on another transformed model point plus noise, like a wrong feature
    match (harder: outliers are structured). ``'cube'`` and ``'cube-surface'`` spread them
    wider than the model, as matches into a larger scene: uniformly in a cube three times the
    model's largest extent, and on the transformed model scaled three times (plus noise),
    both centred on the transformed model's centroid. Rows are shuffled so inliers are not
    first.
    """
    rng = np.random.default_rng(rng)
    n_in = int(round((1.0 - outlier_ratio) * n))
    n_out = n - n_in
    T = random_transform(rng) if transform is None else np.asarray(transform, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    moved = model @ R.T + t

    idx_in = rng.choice(len(model), n_in, replace=n_in > len(model))
    src = np.empty((n, 3))
    dst = np.empty((n, 3))
    src[:n_in] = model[idx_in]
    dst[:n_in] = moved[idx_in] + rng.normal(0.0, noise_sigma, (n_in, 3))
    src[n_in:] = model[rng.integers(0, len(model), n_out)]
    centre, extent = moved.mean(axis=0), np.ptp(model, axis=0).max()
    if outliers == 'uniform':
        lo, hi = moved.min(axis=0), moved.max(axis=0)
        dst[n_in:] = rng.uniform(lo, hi, (n_out, 3))
    elif outliers == 'surface':
        dst[n_in:] = (moved[rng.integers(0, len(model), n_out)]
                      + rng.normal(0.0, noise_sigma, (n_out, 3)))
    elif outliers == 'cube-surface':
        dst[n_in:] = (centre + _WIDE * (moved[rng.integers(0, len(model), n_out)] - centre)
                      + rng.normal(0.0, noise_sigma, (n_out, 3)))
    elif outliers == 'cube':
        dst[n_in:] = centre + rng.uniform(-0.5, 0.5, (n_out, 3)) * _WIDE * extent
    else:
        raise ValueError(f'outliers must be one of {OUTLIER_LAYOUTS}, got {outliers!r}')
    mask = np.zeros(n, dtype=bool)
    mask[:n_in] = True
    perm = rng.permutation(n)
    return SyntheticProblem(src[perm], dst[perm], T, mask[perm], noise_sigma)
