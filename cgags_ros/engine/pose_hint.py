"""
Pose hints (the node's ``~/hint``): where the robot roughly is, for a relocalization in the map.

ROS-free. The node hands each hint message (geometry_msgs/PoseWithCovarianceStamped: the robot
base's pose with its covariance, as RViz's "2D Pose Estimate" sends it) to
:meth:`PoseHints.receive` as numbers. An accepted hint is a relocalization request (as
``reinitialize_global_localization`` is) that says where to look: the scans that answer it
(one without odometry, up to ``relocalization.max_scans`` with it) are registered only in the
map's places it covers (:class:`~cgags_ros.pipeline.hint.Hint`: ``HINT_SIGMAS`` standard
deviations of the position; planar for a pose with no height variance, as RViz sends), and
a hint that covers none refuses at once (``no_shared_surface``). It ends with its request:
answered (a pose found, or refused for good), or failed past ``relocalization.timeout``. A
``~/relocalize`` call pending at the same time is answered by the same scans, with the
newest pending hint.

A rejected hint is counted (``hint.rejected.<why>``) and logged, never raised:

- ``inactive``: the node is not active (lifecycle).
- ``frame``: its ``header.frame_id`` is not ``map.frame`` and TF has no ``map.frame`` <- it
  at its stamp (with a transform, the hint is moved into the map frame, its covariance
  turned).
- ``not_finite``: a NaN or infinite value; ``zero_quaternion``.
- ``negative_covariance``: a negative variance, or a covariance that is not positive
  semidefinite.

At each scan it answers (:meth:`PoseHints.at_scan`), the hint's base pose is carried to the
scan's stamp by the odometry when it is known at both stamps (``T_map_base(scan) = T_hint
inv(T_odom_base(hint)) T_odom_base(scan)``: a robot that moves while it relocalizes), then to
the sensor by the extrinsic (the base's position stands for the sensor's when none is known),
its covariance moved along the lever arm.
"""

from __future__ import annotations

import collections
import dataclasses
import threading
from typing import Any, Callable

import numpy as np

from ..errors import InvalidInputError
from ..geometry import make_transform, quaternion_to_matrix
from ..pipeline.covariance import moved_covariance
from ..pipeline.hint import Hint

# (parent, child, stamp ns) -> parent <- child (4x4, metres) from TF, or None
Lookup = Callable[[str, str, int], 'np.ndarray | None']


@dataclasses.dataclass(frozen=True)
class PoseHint:
    """
    An accepted hint: the robot base in the map frame, as received.

    :ivar pose: 4x4 ``T_map_base`` (metres). :ivar covariance: its 6x6 covariance (ROS
    order, metres and radians). :ivar stamp_ns: its header stamp (0: unstamped).
    """

    pose: np.ndarray
    covariance: np.ndarray
    stamp_ns: int


class PoseHints:
    """
    Checks hints, turns them into the :class:`Hint` of a scan, counts them (``hint.*``).

    The node's executor receives, the engine thread uses: the counts change under a lock.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: collections.Counter[str] = collections.Counter(received=0, used=0)

    def receive(self, stamp_ns: int, frame_id: str, pose: Any, covariance: Any,
                map_frame: str, lookup: Lookup, log: Callable[[str, str], None],
                refused: str = '') -> PoseHint | None:
        """
        Return the hint of one message in the map frame, or None when it is rejected.

        :param pose: ``[x, y, z, qx, qy, qz, qw]``, the base in ``frame_id`` (metres).
        :param covariance: its 36 values (PoseWithCovariance order).
        :param lookup: TF, for a hint in another frame than ``map_frame``.
        :param log: ``log(level, message)``: a rejection is logged with why.
        :param refused: why the node takes no hint now (``inactive``), '' when it does.
        """
        self._count('received')
        why, message = refused, f'the node takes no hint now ({refused})'
        if not why:
            try:
                return self._checked(stamp_ns, frame_id, pose, covariance, map_frame, lookup)
            except _Rejected as exc:
                why, message = exc.why, str(exc)
        self._count(f'rejected.{why}')
        log('warning', f'~/hint rejected ({why}): {message}')
        return None

    def _checked(self, stamp_ns: int, frame_id: str, pose: Any, covariance: Any,
                 map_frame: str, lookup: Lookup) -> PoseHint:
        values = np.asarray(pose, dtype=np.float64).reshape(7)
        cov = np.asarray(covariance, dtype=np.float64).reshape(6, 6)
        if not (np.isfinite(values).all() and np.isfinite(cov).all()):
            raise _Rejected('not_finite', 'its pose or covariance holds a NaN or infinity')
        try:
            T = make_transform(quaternion_to_matrix(values[3:]), values[:3])
        except InvalidInputError as exc:
            raise _Rejected('zero_quaternion', str(exc)) from None
        sym = 0.5 * (cov + cov.T)
        if (np.diag(cov) < 0).any() or np.linalg.eigvalsh(sym).min() < -1e-9 * max(
                1.0, float(np.abs(sym).max())):
            raise _Rejected('negative_covariance', 'its covariance has a negative variance or '
                            'is not positive semidefinite')
        if frame_id.lstrip('/') != map_frame.lstrip('/'):
            moved = lookup(map_frame, frame_id, stamp_ns)
            if moved is None:
                raise _Rejected('frame', f"it is in frame '{frame_id}', not map.frame "
                                f"'{map_frame}', and TF has no {map_frame} <- {frame_id}")
            J = np.kron(np.eye(2), moved[:3, :3])  # the covariance turned into the map frame
            T, sym = moved @ T, J @ sym @ J.T
        return PoseHint(T, sym, int(stamp_ns))

    def at_scan(self, hint: PoseHint, moved: np.ndarray | None,
                base_from_sensor: np.ndarray | None) -> Hint:
        """
        Return the :class:`Hint` of a scan that answers the request ``hint`` made (counted).

        :param moved: ``inv(T_odom_base(hint)) T_odom_base(scan)``, the base's motion since the
            hint (None: unknown, the hint stands as received).
        :param base_from_sensor: 4x4 ``T_base_sensor`` (None: unknown; the base's position
            stands for the sensor's).
        """
        T = hint.pose if moved is None else hint.pose @ moved
        base = np.eye(4) if base_from_sensor is None else np.asarray(base_from_sensor)
        self._count('used')
        return Hint.from_pose(T @ base, moved_covariance(hint.covariance, T, base))

    def _count(self, key: str) -> None:
        with self._lock:
            self._counts[key] += 1

    def statistics(self) -> dict[str, int]:
        """Return ``hint.received``, ``hint.used`` and ``hint.rejected.<why>``."""
        with self._lock:
            return {f'hint.{k}': v for k, v in sorted(self._counts.items())}


class _Rejected(Exception):
    """Why a hint is rejected: ``why`` (its counter's name) and the message."""

    def __init__(self, why: str, message: str):
        super().__init__(message)
        self.why = why
