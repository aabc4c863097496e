"""The result of a registration, shared by the core, the pipeline, the node and the CLIs."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np


@dataclasses.dataclass
class RegistrationResult:
    """
    Outcome of :func:`cgags_ros.registration.register_correspondences`.

    :ivar transform: 4x4 float64 homogeneous transform mapping source points onto target
        points (``dst ≈ R @ src + t``), metres. Identity when no estimate exists.
    :ivar inliers: indices (into the correspondences) within ``inlier_threshold`` of the
        final transform.
    :ivar valid: True only when the estimate passed every validity gate.
    :ivar reason: empty when valid, otherwise why the estimate must not be trusted.
    :ivar num_hypotheses: minimal subsets generated (non-collinear triples); each is ranked
        by the pre-screen, the best of each batch are fitted and scored.
    :ivar num_correspondences: correspondences given (after input checks).
    :ivar inlier_threshold: tau in metres used for scoring.
    :ivar compatibility_threshold: delta in metres used for the compatibility graph.
    :ivar stats: per-stage counters (graph edges, samples per stage, stopping bounds, ...).
    :ivar timings: seconds per named stage, plus ``total``.
    """

    transform: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    inliers: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    valid: bool = False
    reason: str = ''
    num_hypotheses: int = 0
    num_correspondences: int = 0
    inlier_threshold: float = float('nan')
    compatibility_threshold: float = float('nan')
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

    def finish(self, start: float, reason: str = '') -> 'RegistrationResult':
        """
        Set ``valid``/``reason`` and ``timings['total']``; return self.

        ``start`` is the ``time.perf_counter()`` value at which the registration began.
        """
        self.valid = not reason
        self.reason = reason
        self.timings['total'] = time.perf_counter() - start
        return self

    def summary(self) -> dict[str, Any]:
        """JSON-friendly dict (lists instead of arrays)."""
        return {
            'valid': bool(self.valid),
            'reason': self.reason,
            'transform': np.asarray(self.transform, dtype=float).tolist(),
            'num_inliers': self.num_inliers,
            'num_correspondences': int(self.num_correspondences),
            'inlier_ratio': float(self.inlier_ratio),
            'num_hypotheses': int(self.num_hypotheses),
            'inlier_threshold': float(self.inlier_threshold),
            'compatibility_threshold': float(self.compatibility_threshold),
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
