"""
A stream's scans through one :class:`~.tracking.Tracker`: where it lives, what it counts.

The node (continuous mode) and ``cgags-replay`` register a stream's scans through a
:class:`~.tracking.Tracker`, which falls back to :func:`~.register.register_clouds`, the one
global path. The Tracker's state must live where registration runs, beside the target and
the feature cache: :func:`register_stream` keeps one per process, so in the node's
registration process it is created with the process and forgotten when the process is
replaced; a new target or configuration drops its prior by itself. Each result carries
what its scan added to the Tracker's counts (``stats['tracking_counts']``), so that the
caller's :class:`StreamCounts` adds them up across restarts of that process.

Importing this module does not import the pipeline (Open3D): the node's own process only
counts.
"""

from __future__ import annotations

from collections import Counter
import threading
from typing import Any

import numpy as np

from .result import PipelineResult
from ..config.pipeline import PipelineConfig

COUNTS_KEY = 'tracking_counts'  # result.stats[COUNTS_KEY]: this scan's share of counts()
# The counts /diagnostics always carries (the others appear once they happen).
SHOWN = ('tracked', 'global', 'tracking_failures', 'periodic_checks')

_tracker: Any = None  # in the process that runs the pipeline: the stream's Tracker


def tracks(mode: str, config: PipelineConfig) -> bool:
    """Tell whether a stream in node mode ``mode`` is tracked (continuous, tracking on)."""
    return mode == 'continuous' and config.tracking.enabled


def register_stream(source: np.ndarray, target: Any, *, config: PipelineConfig,
                    stamp: float) -> PipelineResult:
    """
    Register the stream's next scan with this process's :class:`~.tracking.Tracker`.

    :param source: (N, 3) points, metres, the sensor's frame.
    :param target: (M, 3) points or a :class:`~.map.PreparedMap`.
    :param stamp: the scan's header stamp, seconds.
    """
    global _tracker
    if _tracker is None:
        from .tracking import Tracker

        _tracker = Tracker()
    return track(_tracker, source, target, stamp, config)


def track(tracker: Any, source: np.ndarray, target: Any, stamp: float,
          config: PipelineConfig) -> PipelineResult:
    """Run ``tracker.register`` and put what the scan added to its counts on the result."""
    before = tracker.counts()
    result = tracker.register(source, target, stamp, config=config)
    result.stats[COUNTS_KEY] = {k: v - before.get(k, 0) for k, v in tracker.counts().items()}
    return result


class StreamCounts:
    """The Tracker's counts, added up from the results (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter({name: 0 for name in SHOWN})

    def add(self, result: PipelineResult) -> None:
        """Add what ``result``'s scan counted (nothing for a result not tracked or searched)."""
        with self._lock:
            self._counts.update(result.stats.get(COUNTS_KEY, {}))

    def statistics(self) -> dict[str, int]:
        """Return ``tracking.<count>`` for /diagnostics."""
        with self._lock:
            return {f'tracking.{k}': v for k, v in sorted(self._counts.items())}
