"""
Clouds in, result out: the one registration path of the node, the CLIs and benchmarks.

:func:`register_clouds` (``register.py``) runs the front end, the core, refinement and the
validity gates (``gates.py``), settles the correspondences' other candidates
(``candidates.py``) and the estimate's twins (``twins.py``) with one primitive
(``settle.py``) and rates the estimate (``confidence.py``); features of recent clouds are
cached (``cache.py``); ``covariance.py`` turns a result into a pose covariance; ``map.py``
prepares a map file's features and places (``places.py``) once, and a scan onto a map is
registered in its best places (``locate.py``). A stream's scans (:mod:`cgags_ros.tracking`) and a
relocalization over several scans (:mod:`cgags_ros.relocalization`) build on this one pair.

``register_clouds``, ``warm_up`` and the cache functions are imported on first use: they
bring in Open3D, which the node's own process (covariance, unpickling results from its
registration process) never needs.
"""

import importlib
from typing import Any

from .result import PipelineResult

_LAZY = {'register_clouds': 'register', 'warm_up': 'register',
         'cached_features': 'cache', 'clear_feature_cache': 'cache',
         'set_feature_cache_size': 'cache'}

__all__ = ['PipelineResult', 'cached_features', 'clear_feature_cache',
           'register_clouds', 'set_feature_cache_size', 'warm_up']


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(f'.{_LAZY[name]}', __name__), name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
