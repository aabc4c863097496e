"""
What a stream's Tracker counts, added up where the stream is reported.

The Tracker lives where registration runs (the node's registration process, beside the
target), and a replaced process starts a fresh one. So each scan's answer carries what the
scan added to its Tracker's counts (:func:`track`), and the caller's :class:`StreamCounts`
adds them up across restarts. Importing this module does not import the pipeline (Open3D):
the node's own process only counts.
"""

from __future__ import annotations

from collections import Counter
from typing import Any, Callable

from ..config.pipeline import PipelineConfig

# The counts /diagnostics always carries (the others appear once they happen).
SHOWN = ('tracked', 'global', 'tracking_failures', 'periodic_checks')


def tracks(mode: str, config: PipelineConfig) -> bool:
    """Tell whether a stream in node mode ``mode`` is tracked (continuous, tracking on)."""
    return mode == 'continuous' and config.tracking.enabled


def track(tracker: Any, run: Callable[[], Any]) -> tuple[Any, dict[str, int]]:
    """Run ``run()`` (a call of ``tracker``); return its value and what it added to the counts."""
    before = tracker.counts()
    value = run()
    return value, {k: v - before.get(k, 0) for k, v in tracker.counts().items()
                   if v != before.get(k, 0)}


class StreamCounts:
    """
    The Tracker's counts, added up from each scan's share.

    One thread adds (the engine thread); :meth:`statistics` may be read from any: the
    counts are replaced whole, never changed in place, so no lock is needed.
    """

    def __init__(self) -> None:
        self._counts: Counter[str] = Counter({name: 0 for name in SHOWN})

    def add(self, counts: dict[str, int]) -> None:
        """Add what one scan counted."""
        total = self._counts.copy()
        total.update(counts)
        self._counts = total

    def statistics(self) -> dict[str, int]:
        """Return ``tracking.<count>`` for /diagnostics."""
        return {f'tracking.{k}': v for k, v in sorted(self._counts.items())}
