"""The result of a registration, shared by the core, the pipeline, the node and the CLIs."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from ..refusal import Judged, Refusal, RefusalCode, summary as refusal_summary

# A result no registration has finished yet: not valid.
NOT_RUN = Refusal(RefusalCode.NO_ESTIMATE, 'no registration was run')


@dataclasses.dataclass
class RegistrationResult(Judged):
    """
    Outcome of :func:`cgags_ros.registration.register_correspondences`.

    :ivar transform: 4x4 float64 homogeneous transform mapping source points onto target
        points (``dst ≈ R @ src + t``), metres. Identity when no estimate exists.
    :ivar inliers: indices (into the correspondences) within ``inlier_threshold`` of the
        final transform.
    :ivar refusal: None when the estimate passed every validity check
        (:mod:`cgags_ros.validity`), otherwise why it must not be trusted: a code and a
        message (:class:`~cgags_ros.refusal.Refusal`). ``valid`` and ``reason`` read it.
    :ivar num_hypotheses: minimal subsets generated (non-collinear triples); each is ranked
        by the pre-screen, the best of each batch are fitted and scored.
    :ivar num_correspondences: correspondences given (after input checks).
    :ivar inlier_threshold: tau in metres used for scoring.
    :ivar compatibility_threshold: delta in metres used for the compatibility graph.
    :ivar chance_level: the inlier count a wrong hypothesis reaches by chance (step 7).
    :ivar runner_up: inliers of the largest consensus sharing under half of the final
        inliers (the best distinct alternative).
    :ivar inlier_spread: metres: the inliers' RMS spread across their main axis (4-DoF:
        across the gravity axis); below tau they leave a rotation undetermined. NaN with
        fewer than 3 inliers.
    :ivar tilt_deg: 4-DoF mode only (else NaN): the tilt between the clouds' gravity axes
        that the best 6-DoF fit of the inliers shows (the pipeline measures it again over
        the refined overlap).
    :ivar stats: per-stage counters (graph edges, samples per stage, stopping bounds, ...).
    :ivar timings: seconds per named stage, plus ``total``.
    """

    transform: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    inliers: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    refusal: Refusal | None = NOT_RUN
    num_hypotheses: int = 0
    num_correspondences: int = 0
    inlier_threshold: float = float('nan')
    compatibility_threshold: float = float('nan')
    chance_level: int = 0
    runner_up: int = 0
    inlier_spread: float = float('nan')
    tilt_deg: float = float('nan')
    stats: dict[str, Any] = dataclasses.field(default_factory=dict)
    timings: dict[str, float] = dataclasses.field(default_factory=dict)

    @property
    def rotation(self) -> np.ndarray:
        return self.transform[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        return self.transform[:3, 3]

    @property
    def num_inliers(self) -> int:
        return int(len(self.inliers))

    @property
    def inlier_ratio(self) -> float:
        return self.num_inliers / self.num_correspondences if self.num_correspondences else 0.0

    def finish(self, start: float, refusal: Refusal | None = None) -> 'RegistrationResult':
        """
        Set ``refusal`` (None: valid) and ``timings['total']``; return self.

        ``start`` is the ``time.perf_counter()`` value at which the registration began.
        """
        self.refusal = refusal
        self.timings['total'] = time.perf_counter() - start
        return self

    def summary(self) -> dict[str, Any]:
        """JSON-friendly dict (lists instead of arrays)."""
        return {
            'valid': bool(self.valid),
            'reason': self.reason,
            'refusal': refusal_summary(self.refusal),
            'transform': np.asarray(self.transform, dtype=float).tolist(),
            'num_inliers': self.num_inliers,
            'num_correspondences': int(self.num_correspondences),
            'inlier_ratio': float(self.inlier_ratio),
            'num_hypotheses': int(self.num_hypotheses),
            'inlier_threshold': float(self.inlier_threshold),
            'compatibility_threshold': float(self.compatibility_threshold),
            'chance_level': int(self.chance_level), 'runner_up': int(self.runner_up),
            'inlier_spread': float(self.inlier_spread), 'tilt_deg': float(self.tilt_deg),
            'stats': _jsonable(self.stats),
            'timings': {k: float(v) for k, v in self.timings.items()},
        }


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
