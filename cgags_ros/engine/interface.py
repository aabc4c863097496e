"""
What the registration engine and its node exchange, without ROS.

The node decodes each message into a :class:`Cloud` (the map of ``map.file`` is a
:class:`MapCloud`, which has a frame and no header); the engine
(:class:`~.engine.RegistrationEngine`) hands back what to publish (:class:`Estimate`,
:class:`BasePose`, :class:`Calibration`, :class:`PairResult`) through :class:`EngineOutputs`,
which the node implements
(:class:`~cgags_ros.ros.outputs.Outputs`). Headers are the messages' own, opaque here: the
engine reads only their ``frame_id``. An engine that cannot start raises :class:`StartFailed`.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any, Protocol

import numpy as np

from ..errors import CgagsError
from ..pipeline.result import PipelineResult
from ..refusal import Refusal, RefusalCode


class StartFailed(CgagsError):
    """The engine cannot start registering: its process or its map is unusable."""

    code = RefusalCode.START_FAILED


class Cloud:
    """A decoded cloud: points (N, 3) metres in its frame, its message header, receipt time."""

    __slots__ = ('xyz', 'header', 'receipt_ns')

    def __init__(self, xyz: np.ndarray, header: Any, receipt_ns: int):
        self.xyz, self.header, self.receipt_ns = xyz, header, receipt_ns

    def as_target(self) -> np.ndarray:
        """Return what a registration onto this cloud takes: its points."""
        return self.xyz


class MapCloud:
    """
    The prior map (``map.file``) as the target of every scan: a reference, not points.

    The registration process loads the map and holds its features; this process passes
    only the reference (:class:`~cgags_ros.runtime.jobs.MapRef`) in the map's frame.
    """

    __slots__ = ('ref', 'frame_id', 'receipt_ns')

    def __init__(self, ref: Any, frame_id: str, receipt_ns: int):
        self.ref, self.frame_id, self.receipt_ns = ref, frame_id, receipt_ns

    def as_target(self) -> Any:
        """Return what a registration onto the map takes: its reference."""
        return self.ref


@dataclasses.dataclass(frozen=True)
class Estimate:
    """
    One registered pair, to publish as ~/pose, ~/pose_with_covariance, ~/aligned_cloud, TF.

    :ivar transform: 4x4 ``T`` with ``p_frame = R p_source + t`` (metres).
    :ivar covariance: 6x6 covariance of ``transform`` (ROS order, metres and radians).
    :ivar header: the source cloud's message header (its stamp is the outputs').
    :ivar frame_id: frame of the pose (the target's, or ``output.pose_frame_id``).
    :ivar aligned: the source points moved into ``frame_id``, or None (not published).
    :ivar tf_child_frame: child frame of the TF to broadcast; '' broadcasts none.
    """

    transform: np.ndarray
    covariance: np.ndarray
    header: Any
    frame_id: str
    aligned: np.ndarray | None
    tf_child_frame: str


@dataclasses.dataclass(frozen=True)
class BasePose:
    """
    An initial pose that passed every guard: the robot base in the map.

    :ivar transform: 4x4 ``T_map_base`` (metres). :ivar covariance: its 6x6 covariance.
    :ivar header: the scan's message header (its stamp). :ivar map_frame: frame of the pose.
    :ivar odom_frame: broadcast map -> odom from it and TF's odom -> ``base_frame`` at the
        stamp; '' broadcasts nothing.
    :ivar base_frame: the robot base frame.
    :ivar map_from_odom: 4x4 map <- odom confirmed over scans with the robot's odometry,
        broadcast as is (no TF lookup); None: from TF as above.
    """

    transform: np.ndarray
    covariance: np.ndarray
    header: Any
    map_frame: str
    odom_frame: str
    base_frame: str
    map_from_odom: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class Calibration:
    """
    A calibration that ended valid: the extrinsic parent <- child, published once, latched.

    :ivar transform: 4x4 ``T`` with ``p_parent = R p_child + t`` (metres).
    :ivar covariance: its 6x6 covariance, order (x, y, z, rx, ry, rz), metres and radians,
        rotations about the parent axes (see ``covariance_convention`` in ``report``).
    :ivar header: the last frame's parent-cloud message header (its stamp is the outputs').
    :ivar parent_frame, child_frame: the clouds' frame ids (target, source).
    :ivar report: the whole result as JSON (:func:`cgags_ros.calibration.formats.as_dict`).
    """

    transform: np.ndarray
    covariance: np.ndarray
    header: Any
    parent_frame: str
    child_frame: str
    report: str


@dataclasses.dataclass(frozen=True)
class PairResult:
    """
    What became of one source cloud the node is done with, published as ~/result (JSON).

    Every source the accounting counts as published, rejected or dropped gets one.

    :ivar source_stamp_ns: the source's stamp (0 when its header could not be read).
    :ivar source_frame: its frame ('' when unknown).
    :ivar outcome: 'published' (a pose went out), 'rejected' or 'dropped' (by pairing).
    :ivar dropped_by: the pairing reason of a dropped source (``pairing.dropped.<reason>``
        of /diagnostics), else ''.
    :ivar target_stamp_ns: the target it was paired with (None: not paired).
    :ivar target_frame: that target's frame.
    :ivar frame_id: the frame of the pose (the target's or ``output.pose_frame_id``; '' unpaired).
    :ivar valid: the registration is valid (and its transform finite).
    :ivar result: the registration's result, None when none ran.
    :ivar refusal: why the node rejected or dropped the source (a refused registration, a
        timeout, a stale scan, a message it could not decode, ...); None when published.
    :ivar latency_s: seconds from the node's receipt of the source to this result (None when
        it was not paired): what the node itself adds to a pose's delay.
    """

    source_stamp_ns: int
    source_frame: str
    outcome: str
    dropped_by: str = ''
    target_stamp_ns: int | None = None
    target_frame: str = ''
    frame_id: str = ''
    valid: bool = False
    result: PipelineResult | None = None
    refusal: Refusal | None = None
    latency_s: float | None = None

    @property
    def cause(self) -> str:
        """
        Return the key the source is counted under.

        '' when published, the refusal's code when rejected (``rejected.<code>``), the
        pairing reason when dropped (``pairing.dropped.<reason>``).
        """
        if self.outcome == 'dropped':
            return self.dropped_by
        return self.refusal.code.value if self.refusal is not None else ''

    def to_json(self) -> str:
        """
        Return the JSON of ~/result: the CLIs' per-pair result and where it came from.

        The keys of ``result.summary()`` (as ``cgags-register --json`` prints them:
        ``valid``, ``reason``, ``transform``, ``covariance``, ``num_inliers``, ``fitness``,
        ``timings``, ``candidates``, ...) when a registration ran, else ``valid`` false and
        ``reason`` the message; plus every field of this class but ``result``, ``refusal``
        and ``dropped_by``; ``cause`` (:attr:`cause`), ``message`` (why, in words, '' when
        published) and ``refusal`` as ``{"code": ..., "message": ...}`` (null when valid;
        docs/refusals.md): the result's own when it has one, else the node's.
        """
        message = self.refusal.message if self.refusal is not None else ''
        out: dict[str, Any] = (self.result.summary() if self.result is not None
                               else {'reason': message})
        out.update({f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                    if f.name not in ('result', 'refusal', 'dropped_by')})
        out['cause'], out['message'] = self.cause, message
        refusal = (self.result.refusal if self.result is not None else None) or self.refusal
        out['refusal'] = None if refusal is None else refusal.summary()
        return json.dumps(out)


class EngineOutputs(Protocol):
    """What the engine needs from its node: publishing, logging, TF and odometry."""

    def publish_estimate(self, estimate: Estimate) -> None:
        """Publish a pose (and its covariance, aligned cloud and TF as it says)."""

    def publish_candidates(self, header: Any, frame_id: str,
                           transforms: list[np.ndarray]) -> None:
        """Publish ranked candidate poses (best first) at the scan's stamp."""

    def publish_initial_pose(self, pose: BasePose) -> None:
        """Publish an initial pose that passed every guard."""

    def publish_calibration(self, calibration: Calibration) -> None:
        """Publish a valid calibration (latched) and its /tf_static transform."""

    def publish_result(self, result: PairResult) -> None:
        """Publish what became of a source (~/result), also while inactive."""

    def base_from_sensor(self, base_frame: str, sensor_frame: str) -> np.ndarray | None:
        """Return ``T_base_sensor`` from TF (identity without TF), or None when unknown."""

    def odometry(self, odom_frame: str, base_frame: str, stamp_ns: int
                 ) -> tuple[bool, np.ndarray | None]:
        """
        Return the robot's odometry at a scan's stamp (``stamp_ns``).

        :returns: (whether any odometry is known, ``T_odom_base`` (4x4, metres) at the stamp
            or None when none is near it).
        """

    def lookup(self, parent: str, child: str, stamp_ns: int | None = None
               ) -> np.ndarray | None:
        """Return ``parent <- child`` (4x4, metres) from TF at ``stamp_ns``, None if unknown."""

    def log(self, level: str, message: str) -> None:
        """Log ``message`` at ``level`` ('info', 'warning' or 'error')."""
