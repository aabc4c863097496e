"""
The robot's odometry by stamp where tf2 is missing: the stand-in for its buffer.

Where tf2_ros imports, its ``Buffer`` keeps the ``odom`` topic's samples and interpolates
between them (:mod:`cgags_ros.ros.transforms`); stacks without it (this package's emulated
Jazzy test stack) keep them in :class:`OdometrySamples`: ``odom <- base`` at a scan's stamp,
interpolated between the samples either side when both are within :data:`TOLERANCE_S`, else
the nearest within it.
"""

from __future__ import annotations

import bisect

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..geometry import make_transform

# Odometry this far (seconds) from a scan's stamp may stand for the robot's pose at the
# scan: at walking speed a few centimetres, well inside the relocalizer's drift allowance.
TOLERANCE_S = 0.1
KEEP_S = 60.0  # odometry kept behind the newest sample: longer than a scan waits to register


class OdometrySamples:
    """
    Odometry samples ``odom <- base`` (4x4, metres) by stamp.

    One thread adds (the node's executor), any other may read (the engine thread): the samples are
    replaced whole at each one, never changed in place, so no lock is needed.
    """

    def __init__(self) -> None:
        self._samples: tuple[list[int], list[np.ndarray]] = ([], [])

    def add(self, stamp_ns: int, odom_from_base: np.ndarray) -> None:
        """Take one sample (out-of-order stamps are put in place; a repeated stamp replaces)."""
        stamps, poses = list(self._samples[0]), list(self._samples[1])
        i = bisect.bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            del stamps[i], poses[i]
        stamps.insert(i, stamp_ns)
        poses.insert(i, np.asarray(odom_from_base, dtype=np.float64))
        old = bisect.bisect_left(stamps, stamps[-1] - int(KEEP_S * 1e9))
        self._samples = (stamps[old:], poses[old:])

    def at(self, stamp_ns: int, tolerance_s: float = TOLERANCE_S) -> np.ndarray | None:
        """
        Return ``odom <- base`` at ``stamp_ns``, or None when no sample is near enough.

        Interpolated (translation linearly, rotation by slerp) between the samples either
        side when both are within ``tolerance_s``; else the nearest within it.
        """
        stamps, poses = self._samples
        tol, i = int(tolerance_s * 1e9), bisect.bisect_left(stamps, stamp_ns)
        near = [(abs(stamps[j] - stamp_ns), j) for j in (i - 1, i)
                if 0 <= j < len(stamps) and abs(stamps[j] - stamp_ns) <= tol]
        if not near:
            return None
        if len(near) == 1 or stamps[i] == stamp_ns:
            return poses[min(near)[1]].copy()
        (t0, t1), (A, B) = stamps[i - 1:i + 1], poses[i - 1:i + 1]
        f = (stamp_ns - t0) / (t1 - t0)
        R = Slerp([0.0, 1.0], Rotation.from_matrix([A[:3, :3], B[:3, :3]]))([f]).as_matrix()[0]
        return make_transform(R, (1 - f) * A[:3, 3] + f * B[:3, 3])
