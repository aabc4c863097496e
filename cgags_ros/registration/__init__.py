"""
The ROS-free registration core (numpy/scipy only): Algorithm 1 and its steps.

>>> from cgags_ros.registration import register_correspondences
>>> result = register_correspondences(src, dst, resolution=0.05)   # doctest: +SKIP

Public API: :func:`register_correspondences`, :class:`CoreConfig`,
:class:`RegistrationResult`, the RE/TE metrics, :func:`poisson_isf` (the chance-level
quantile the pipeline's gate shares with the core) and :func:`single_blas_thread`.
"""

from .blas import blas_controller, single_blas_thread
from .cgags import register_correspondences
from .result import RegistrationResult
from .stopping import poisson_isf
from ..config.core import CoreConfig
from ..errors import DegenerateCorrespondencesError, InvalidInputError
from ..geometry import rotation_error_deg, translation_error

__all__ = ['register_correspondences', 'CoreConfig', 'RegistrationResult',
           'rotation_error_deg', 'translation_error', 'InvalidInputError',
           'DegenerateCorrespondencesError', 'poisson_isf', 'single_blas_thread',
           'blas_controller']
