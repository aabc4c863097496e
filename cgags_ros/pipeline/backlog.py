"""
A tracked stream's backlog: the scans that arrive while a registration runs.

A global registration takes several scan periods. With a queue of one pair, the scan taken
after it is the newest, too far from the last pose (and with no velocity yet) to be
tracked, so the stream goes global again and never settles. A tracked stream
(:func:`~.stream.tracks`) therefore keeps up to ``tracking.backlog`` pairs and registers
them in stamp order, each from its predecessor's pose: tracking a scan takes less than a
scan period, so the backlog drains and the stream keeps up. When it does not drain fast
enough (the oldest waiting scan more than ``tracking.max_lag`` behind the newest), every
other waiting scan is dropped while the last scan was tracked, and the Tracker scales the
constant velocity to the next scan's stamp. A ``~/relocalize`` call is answered from the
newest scan, as with a queue of one pair. ROS-free; the engine decides with it which pair
its worker takes next (:meth:`~.pairing.Pairer.drop_oldest`).
"""

from __future__ import annotations

from typing import Sequence

from .result import PipelineResult
from .stream import tracks
from ..config.pipeline import PipelineConfig

SKIPPED = 'source_skipped_catching_up'  # the pairing drop reason of a skipped scan


def queue_depth(mode: str, config: PipelineConfig, depth: int) -> int:
    """Return the pairs to keep: ``depth`` (pairing.queue_depth), or the backlog's when tracked."""
    return max(depth, config.tracking.backlog) if tracks(mode, config) else depth


class Backlog:
    """What the worker of a tracked stream skips; it remembers whether the last scan tracked."""

    def __init__(self) -> None:
        self.tracked = False  # the last registered scan was tracked (a velocity exists)

    def saw(self, result: PipelineResult) -> None:
        """Remember whether ``result`` (the last registered scan) was tracked."""
        self.tracked = result.path == 'tracked' and bool(result.valid)

    def to_skip(self, pending_ns: Sequence[int], config: PipelineConfig, called: bool) -> int:
        """
        Return how many of the oldest waiting pairs to drop before the next is taken.

        :param pending_ns: the waiting pairs' source stamps, oldest first (nanoseconds).
        :param called: a ``~/relocalize`` call waits (it is answered from the newest scan).
        """
        if len(pending_ns) < 2:
            return 0
        if called:
            return len(pending_ns) - 1
        lag = (pending_ns[-1] - pending_ns[0]) * 1e-9
        max_lag = config.tracking.max_lag
        return int(self.tracked and max_lag > 0 and lag > max_lag)
