"""
Extrinsic calibration of two sensors from several synchronized frames, with no initial guess.

Frames are pairs (parent cloud, child cloud). The result is the transform parent <- child
(``p_parent = R p_child + t``), with its covariance, the motions the scenes leave
unconstrained, and each frame's agreement (:class:`CalibrationResult`). ROS-free: the node
and ``cgags-calibrate`` both drive :class:`Calibrator` / :func:`calibrate`.
"""

from .calibrator import calibrate, Calibrator
from .frames import Frame
from .result import CalibrationResult, FrameReport, TRANSFORM_WORDS

__all__ = ['calibrate', 'CalibrationResult', 'Calibrator', 'Frame', 'FrameReport',
           'TRANSFORM_WORDS']
