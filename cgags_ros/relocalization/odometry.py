"""
The robot's odometry by stamp: the base's pose in odom at a scan's stamp.

:class:`OdometryTrack` holds the odometry (``odom <- base`` by stamp, from a
``nav_msgs/Odometry`` topic or TF odom -> base) and gives each scan of a relocalization
over several scans the base's pose at its stamp: interpolated between the samples either
side, or the nearest one, each within :data:`TOLERANCE_S`. Any thread.
"""

from __future__ import annotations

import bisect
import threading

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..geometry import make_transform

# Odometry this far (seconds) from a scan's stamp may stand for the robot's pose at the
# scan: at walking speed a few centimetres, well inside the relocalizer's drift allowance.
TOLERANCE_S = 0.1
KEEP_S = 60.0  # odometry kept behind the newest sample: longer than a scan waits to register


class OdometryTrack:
    """Odometry samples ``odom <- base`` (4x4, metres) by stamp; any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self.samples = 0  # received, for /diagnostics

    @property
    def received(self) -> bool:
        """Tell whether any odometry has been received."""
        with self._lock:
            return bool(self._stamps)

    def add(self, stamp_ns: int, odom_from_base: np.ndarray) -> None:
        """Take one sample (out-of-order stamps are put in place; a repeated stamp replaces)."""
        T = np.asarray(odom_from_base, dtype=np.float64)
        with self._lock:
            self.samples += 1
            i = bisect.bisect_left(self._stamps, stamp_ns)
            if i < len(self._stamps) and self._stamps[i] == stamp_ns:
                self._poses[i] = T
            else:
                self._stamps.insert(i, stamp_ns)
                self._poses.insert(i, T)
            old = bisect.bisect_left(self._stamps, self._stamps[-1] - int(KEEP_S * 1e9))
            del self._stamps[:old], self._poses[:old]

    def at(self, stamp_ns: int, tolerance_s: float = TOLERANCE_S) -> np.ndarray | None:
        """
        Return ``odom <- base`` at ``stamp_ns``, or None when no sample is near enough.

        Interpolated (translation linearly, rotation by slerp) between the samples either
        side when both are within ``tolerance_s``; else the nearest within it.
        """
        tol = int(tolerance_s * 1e9)
        with self._lock:
            i = bisect.bisect_left(self._stamps, stamp_ns)
            near = [(abs(self._stamps[j] - stamp_ns), j) for j in (i - 1, i)
                    if 0 <= j < len(self._stamps) and abs(self._stamps[j] - stamp_ns) <= tol]
            if not near:
                return None
            if len(near) == 1 or self._stamps[i] == stamp_ns:
                return self._poses[min(near)[1]].copy()
            (t0, t1), (A, B) = self._stamps[i - 1:i + 1], self._poses[i - 1:i + 1]
        f = (stamp_ns - t0) / (t1 - t0)
        R = Slerp([0.0, 1.0], Rotation.from_matrix([A[:3, :3], B[:3, :3]]))([f]).as_matrix()[0]
        return make_transform(R, (1 - f) * A[:3, 3] + f * B[:3, 3])
