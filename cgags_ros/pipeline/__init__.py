"""
Clouds in, result out: the one registration path of the node, the CLIs and benchmarks.

:func:`register_clouds` (``register.py``) runs the front end, the core, refinement and the
validity gates (``gates.py``); features of recent clouds are cached (``cache.py``);
``covariance.py`` turns a result into a pose covariance, ``pairing.py`` pairs sources with
targets for the node and the replay tool, ``runtime.py`` holds the thread settings.
"""

from .cache import cached_features, clear_feature_cache
from .register import register_clouds, warm_up
from .result import PipelineResult

__all__ = ['PipelineResult', 'cached_features', 'clear_feature_cache', 'register_clouds',
           'warm_up']
