"""What a calibration reports: the joint estimate, its uncertainty and every frame's say."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..geometry import rotation_error_deg, translation_error
from ..refusal import Judged, Refusal, RefusalCode, summary as refusal_summary

TRANSFORM_WORDS = 'transform parent <- child (p_parent = R p_child + t)'


@dataclasses.dataclass
class FrameReport:
    """
    One frame's part in the calibration.

    :ivar name: the frame's label (file names or stamps).
    :ivar time_offset_s: child stamp minus parent stamp, seconds (NaN when unknown).
    :ivar agrees: whether the frame supports the joint pose (see :mod:`.consensus`).
    :ivar reason: why it does not ('' when it agrees).
    :ivar single_frame_valid: whether the pipeline alone, on this frame, gave a valid pose.
    :ivar single_frame_reason: the pipeline's reason when it did not.
    :ivar candidate_rank: rank (0 = best) of the frame's own candidate that is the joint
        pose, or -1 when none of its candidates is.
    :ivar fitness: share of the frame's child points within the refinement distance of a
        parent point under the joint pose.
    :ivar overlap: min of that and the parent-side share.
    :ivar shift_m: RMS motion, along the parent normals, of the frame's overlapping child
        points when the joint pose is refined on this frame alone (metres).
    :ivar transform: that single-frame refinement (4x4 parent <- child), or the pose the
        frame prefers when it disagrees.
    """

    name: str
    time_offset_s: float = float('nan')
    agrees: bool = False
    reason: str = ''
    single_frame_valid: bool = False
    single_frame_reason: str = ''
    candidate_rank: int = -1
    fitness: float = 0.0
    overlap: float = 0.0
    shift_m: float = float('nan')
    transform: np.ndarray | None = None

    def summary(self, joint: np.ndarray | None = None) -> dict[str, Any]:
        """Return a JSON-friendly dict; with ``joint``, the frame's distance from it."""
        out = {'name': self.name, 'time_offset_s': _num(self.time_offset_s),
               'agrees': bool(self.agrees), 'reason': self.reason,
               'single_frame_valid': bool(self.single_frame_valid),
               'single_frame_reason': self.single_frame_reason,
               'candidate_rank': int(self.candidate_rank), 'fitness': _num(self.fitness),
               'overlap': _num(self.overlap), 'shift_m': _num(self.shift_m),
               'transform': None if self.transform is None else self.transform.tolist()}
        if joint is not None and self.transform is not None:
            out['rotation_from_joint_deg'] = rotation_error_deg(self.transform, joint)
            out['translation_from_joint_m'] = translation_error(self.transform, joint)
        return out


@dataclasses.dataclass
class CalibrationResult(Judged):
    """
    The extrinsic parent <- child from several frames, or why there is none.

    :ivar refusal: None when the frames agree on one observable pose, else why not (a code
        and a message); ``valid`` and ``reason`` read it.
    :ivar transform: 4x4 parent <- child (``p_parent = R p_child + t``, metres); None when
        no pose was found; present but not to be used when ``valid`` is False.
    :ivar covariance: 6x6 (see :mod:`.uncertainty` for the convention), or None.
    :ivar std: per-axis standard deviations (``x_m .. z_m``, ``rx_deg .. rz_deg``).
    :ivar observability: smallest / largest eigenvalue of the scaled joint information.
    :ivar unobservable: the motions the frames do not constrain, named.
    :ivar frames: one :class:`FrameReport` per frame taken, in order.
    :ivar converged: whether the last frame moved the estimate by less than one standard
        deviation on every axis (False with fewer than ``min_frames``, or when the last
        frame disagrees).
    :ivar birge_ratio: the covariance's scale from the frames' scatter (>= 1).
    :ivar num_pairs: point-to-plane pairs in the joint problem.
    :ivar rms_m: RMS point-to-plane residual, metres.
    :ivar parent_frame, child_frame: frame ids, for the outputs.
    :ivar seconds: wall time of the whole calibration.
    """

    refusal: Refusal | None = Refusal(RefusalCode.NO_ESTIMATE, 'not solved yet')
    transform: np.ndarray | None = None
    covariance: np.ndarray | None = None
    std: dict[str, float] = dataclasses.field(default_factory=dict)
    observability: float = float('nan')
    unobservable: list[str] = dataclasses.field(default_factory=list)
    frames: list[FrameReport] = dataclasses.field(default_factory=list)
    converged: bool = False
    birge_ratio: float = float('nan')
    num_pairs: int = 0
    rms_m: float = float('nan')
    parent_frame: str = 'parent'
    child_frame: str = 'child'
    seconds: float = 0.0

    @property
    def num_agreeing(self) -> int:
        return sum(f.agrees for f in self.frames)

    def summary(self) -> dict[str, Any]:
        """Return a JSON-friendly dict of everything above."""
        T = self.transform
        return {
            'valid': bool(self.valid), 'reason': self.reason,
            'refusal': refusal_summary(self.refusal), 'transform_meaning': TRANSFORM_WORDS,
            'parent_frame': self.parent_frame, 'child_frame': self.child_frame,
            'transform': None if T is None else T.tolist(),
            'covariance': None if self.covariance is None else self.covariance.tolist(),
            'covariance_convention': (
                "row-major 6x6, order (x, y, z, rx, ry, rz); t' = t + dt (metres, parent "
                "frame), R' = exp([dphi]x) R (radians, about the parent axes through the "
                'child origin)'),
            'std': self.std, 'observability': _num(self.observability),
            'unobservable': list(self.unobservable), 'converged': bool(self.converged),
            'birge_ratio': _num(self.birge_ratio), 'num_pairs': int(self.num_pairs),
            'rms_m': _num(self.rms_m), 'num_frames': len(self.frames),
            'num_agreeing': self.num_agreeing, 'seconds': float(self.seconds),
            'frames': [f.summary(T) for f in self.frames]}


def _num(value: float) -> float | None:
    value = float(value)
    return value if np.isfinite(value) else None
