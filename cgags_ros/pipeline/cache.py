"""Feature cache: a latched map or a target shared by consecutive pairs is featurised once."""

from __future__ import annotations

from collections import OrderedDict
import dataclasses
import hashlib
import threading

import numpy as np

from ..config.frontend import FrontEndConfig
from ..frontend.features import CloudFeatures, extract_features

_CACHE_SIZE = 2  # clouds whose features are kept: a latched target plus one more
# Front-end options that only choose what is matched: features do not depend on them.
_MATCHING_ONLY = frozenset({'max_correspondences', 'max_keypoints'})
_cache: OrderedDict[tuple, CloudFeatures] = OrderedDict()
# Two threads write: a pair's source features are computed on its own, its target's beside
# it (pipeline.register).
_cache_lock = threading.Lock()


def cached_features(points: np.ndarray, voxel_size: float, config: FrontEndConfig,
                    name: str = 'cloud', timings: dict[str, float] | None = None,
                    workers: int = 1) -> CloudFeatures:
    """
    Run :func:`extract_features`, remembered for the last two clouds.

    Clouds are keyed by exact content (and voxel size and the front-end settings features
    depend on, not the matching's): a latched map target, or a target shared by consecutive
    pairs, is featurised once, which saves a large share of the front end at sensor rates.
    The front end is deterministic, so a hit returns exactly what recomputing would; the
    arrays returned are shared and must not be written to. Hashing costs far less than
    featurising.
    """
    # SHA-256: the CPU's SHA extensions make it the fastest of hashlib's here (measured in
    # docs/design.md); a cold pair pays it for both clouds.
    settings = tuple(getattr(config, f.name) for f in dataclasses.fields(config)
                     if f.name not in _MATCHING_ONLY)
    key = (hashlib.sha256(np.ascontiguousarray(points)).digest(),
           points.shape, voxel_size, settings)
    with _cache_lock:
        hit = _cache.get(key)
        if hit is not None:
            _cache.move_to_end(key)
    if hit is not None:
        for stage in ('downsample', 'normals', 'fpfh') if timings is not None else ():
            timings.setdefault(stage, 0.0)  # no time spent, but keep the keys
        return hit
    features = extract_features(points, voxel_size, config, name, timings, workers)
    with _cache_lock:
        _cache[key] = features
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)
    return features


def clear_feature_cache() -> None:
    """Forget remembered features (benchmarks timing the whole front end call this)."""
    with _cache_lock:
        _cache.clear()


def set_feature_cache_size(size: int) -> int:
    """
    Remember the features of the last ``size`` clouds (two unless set); return the old size.

    For a study that revisits many clouds (every fragment of a scene in many pairs) and
    wants each featurised once; the oldest beyond ``size`` are forgotten now.
    """
    global _CACHE_SIZE
    with _cache_lock:
        previous, _CACHE_SIZE = _CACHE_SIZE, int(size)
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)
    return previous
