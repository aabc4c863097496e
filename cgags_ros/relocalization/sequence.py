"""
Relocalization over the next few scans with the robot's odometry, as the node runs it.

ROS-free and light (numpy and scipy). With a map and the robot's odometry (the node's ``odom``
topic or TF, looked up by the node: :mod:`cgags_ros.ros.transforms`), a relocalization (a
``~/relocalize`` call, ``reinitialize_global_localization``, or continuous mode while an
automatic initial pose may still go out) takes scans until the
:class:`~.relocalizer.Relocalizer` in the registration process confirms a pose or the scans
(``relocalization.max_scans``) or the time (``relocalization.timeout``) run out:

- A scan with no odometry near its stamp cannot be tied to the others: it is judged alone,
  as a single scan is, and the sequence starts over from the next scan. It still counts
  towards the scans of the relocalization.
- :class:`SequenceRun` gives each scan its pose in odom and whether the sequence restarts
  (:meth:`~SequenceRun.step`, what a ``SequenceScan`` job carries) and decides on the
  answer (:meth:`~SequenceRun.judge`): a pose confirmed over two scans or more is answered
  (the relocalizer's checks stand in for the single-scan guards); a pose confirmed by one
  scan alone must also pass the initial-pose quality guards, else another scan is taken;
  an unconfirmed one takes another scan until the scans run out, then it is refused with
  the relocalizer's reason.

Without any odometry received, none of this runs: one scan at a time.

Where tf2_ros imports, its ``Buffer`` keeps the ``odom`` topic's samples and interpolates
between them; stacks without it (this package's emulated Jazzy test stack) keep them in
:class:`OdometrySamples`: ``odom <- base`` at a scan's stamp, interpolated between the
samples either side when both are within :data:`TOLERANCE_S`, else the nearest within it.
"""

from __future__ import annotations

import bisect
import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .service_calls import localized, not_localized
from ..geometry import make_transform
from ..pipeline.result import PipelineResult
from ..refusal import Judged, Refusal

# Odometry this far (seconds) from a scan's stamp may stand for the robot's pose at the
# scan: at walking speed a few centimetres, well inside the relocalizer's drift allowance.
TOLERANCE_S = 0.1
KEEP_S = 60.0  # odometry kept behind the newest sample: longer than a scan waits to register


@dataclasses.dataclass
class StepAnswer(Judged):
    """
    The relocalizer's answer after one scan, without clouds (what the process sends back).

    :ivar refusal: why not confirmed (None: confirmed).
    :ivar result: the scan's own registration.
    :ivar confirmed, done, transform, map_from_odom, scans_used: as in
        :class:`~.relocalizer.Answer`.
    :ivar hypotheses: how many hypotheses the sequence holds.
    """

    refusal: Refusal | None
    result: PipelineResult
    confirmed: bool
    done: bool
    transform: np.ndarray
    map_from_odom: np.ndarray
    scans_used: int
    hypotheses: int


@dataclasses.dataclass
class Verdict:
    """
    What the node does after a scan of a sequence.

    :ivar finished: answer the pending calls now (confirmed, or refused for good).
    :ivar refusal: why the pose is not confirmed (None: confirmed).
    :ivar transform: 4x4 map <- the scan's sensor (metres): the best hypothesis's pose.
    :ivar map_from_odom: 4x4 map <- odom, or None when the scan had no odometry.
    :ivar scans: scans taken by this relocalization; ``used``: of them in the relocalizer's
        current sequence.
    """

    finished: bool
    refusal: Refusal | None
    transform: np.ndarray
    map_from_odom: np.ndarray | None
    scans: int
    used: int

    def line(self, published: bool, why: str) -> str:
        """Return the one-line answer of a call: the pose and the scans, or why not."""
        scans = f'{self.used} scan(s) with odometry, {self.scans} taken'
        if self.refusal is not None:
            return f'{not_localized(self.refusal)}; {scans}'
        return localized(self.transform, f'confirmed over {scans}', published, why)


class SequenceRun:
    """The relocalization in progress: its scans, its last verdict."""

    def __init__(self) -> None:
        self.last: Verdict | None = None  # the last verdict of an unfinished relocalization
        self._why: Refusal | None = None  # why that one was not confirmed
        self._taken = 0
        self._restart = True
        self._with_odom = False  # the last step had the sensor's pose in odom

    def reset(self) -> None:
        """Forget the relocalization in progress (the next scan starts a new one)."""
        self.last, self._why, self._taken, self._restart = None, None, 0, True

    def step(self, odom_base: np.ndarray | None, base_from_sensor: np.ndarray | None
             ) -> tuple[np.ndarray | None, bool]:
        """
        Return (the sensor's pose in odom, restart) of a scan, a step of the sequence.

        :param odom_base: 4x4 ``T_odom_base`` at the scan's stamp (None: no odometry near it).
        :param base_from_sensor: 4x4 ``T_base_sensor`` (None: unknown, the scan has no
            pose in odom).
        :returns: the 4x4 ``odom <- sensor`` (None: no odometry near the stamp or no
            extrinsic) and whether the relocalizer forgets the scans so far first.
        """
        odom = (None if odom_base is None or base_from_sensor is None
                else odom_base @ base_from_sensor)
        restart = self._restart
        self._with_odom = odom is not None
        self._restart = odom is None  # the next scan cannot continue a scan without odometry
        return odom, restart

    def judge(self, answer: StepAnswer, guard: Refusal | None, max_scans: int) -> Verdict:
        """
        Decide on the relocalization after the answer to one scan (see the module doc).

        :param guard: the initial-pose quality guards' verdict on the scan's own registration,
            which a pose confirmed by that scan alone must pass.
        """
        self._taken += 1
        refusal = answer.refusal if not answer.confirmed else (
            guard if answer.scans_used == 1 else None)
        finished = refusal is None or self._taken >= max_scans
        if refusal is not None and not finished:
            refusal = Refusal(refusal.code, f'{refusal.message} (scan {self._taken} of at most '
                              f'{max_scans}: taking the next one)')
        verdict = Verdict(finished, refusal, np.asarray(answer.transform, dtype=np.float64),
                          np.asarray(answer.map_from_odom) if self._with_odom else None,
                          self._taken, answer.scans_used)
        if finished:
            self.reset()
        else:
            self.last, self._why = verdict, answer.refusal if not answer.confirmed else guard
        return verdict

    def timed_out(self, timeout_s: float) -> Refusal | None:
        """Return why a call whose time ran out mid-relocalization fails (None: none ran)."""
        last, why = self.last, self._why
        if last is None or why is None:
            return None
        return Refusal(why.code, f'{why.message}; relocalization.timeout = {timeout_s:g} s '
                       f'ran out after {last.scans} scan(s)')


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
