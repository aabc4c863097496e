"""
The ROS-free registration core (numpy/scipy, numba): Algorithm 1 and its steps.

>>> from cgags_ros.registration import register_correspondences
>>> result = register_correspondences(src, dst, resolution=0.05)   # doctest: +SKIP

Public API: :func:`register_correspondences`, :class:`CoreConfig`,
:class:`RegistrationResult`, the RE/TE metrics, :func:`poisson_isf` (the chance-level
quantile the pipeline's gate shares with the core) and :func:`single_blas_thread`.

``register_correspondences`` is imported on first use: it brings in numba and the compiled
functions, which a process that only handles results (the node's, unpickling them from its
registration process) never needs.
"""

import importlib
from typing import Any

from .blas import single_blas_thread
from .result import RegistrationResult
from .stopping import poisson_isf
from ..config.core import CoreConfig
from ..errors import DegenerateCorrespondencesError, InvalidInputError
from ..geometry import rotation_error_deg, translation_error

__all__ = ['register_correspondences', 'CoreConfig', 'RegistrationResult',
           'rotation_error_deg', 'translation_error', 'InvalidInputError',
           'DegenerateCorrespondencesError', 'poisson_isf', 'single_blas_thread']


def __getattr__(name: str) -> Any:
    if name == 'register_correspondences':
        return importlib.import_module('.cgags', __name__).register_correspondences
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
