"""The ROS-free registration core (numpy/scipy only).

>>> from cgags_ros.registration import register_correspondences
>>> result = register_correspondences(src, dst, resolution=0.05)   # doctest: +SKIP
"""

from ..errors import DegenerateCorrespondencesError, InvalidInputError
from .cgags import register_correspondences
from .config import CoreConfig
from .metrics import rotation_error_deg, translation_error
from .result import RegistrationResult

__all__ = ["register_correspondences", "CoreConfig", "RegistrationResult",
           "rotation_error_deg", "translation_error", "InvalidInputError",
           "DegenerateCorrespondencesError"]
