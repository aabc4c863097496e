"""
A tracked stream's backlog: the scans that arrive while a registration runs.

A global registration takes several scan periods. With a queue of one pair, the scan taken
after it is the newest, too far from the last pose (and with no velocity yet) to be tracked,
so the stream goes global again and never settles. A tracked stream
(:func:`~cgags_ros.runtime.jobs.tracks`) therefore keeps up to ``pairing.backlog`` pairs
and registers them in stamp order, each from its predecessor's pose: tracking a scan takes
less than a scan period, so the backlog drains and the stream keeps up. When it does not
drain fast enough (the oldest waiting scan more than ``pairing.backlog_max_lag`` behind the
newest) and the last scan was tracked, every other waiting scan is dropped, as long as the
next one taken is within ``tracking.max_age`` of the last (beyond it the Tracker has no
prediction); the Tracker scales the constant velocity to the next scan's stamp. When the
oldest waiting scan is already beyond ``tracking.max_age`` (the full backlog dropped the
scans between), it would be registered globally anyway: the newest is taken instead. A
``~/relocalize`` call is answered from the newest scan, as with a queue of one pair.
ROS-free; the accounting decides with it, under its lock, which pair the engine thread
takes next (:meth:`~.pairing.Pairer.drop_oldest`).
"""

from __future__ import annotations

from typing import Sequence

from ..config.node import NodeConfig
from ..config.pipeline import PipelineConfig
from ..runtime.jobs import tracks

SKIPPED = 'source_skipped_catching_up'  # the pairing drop reason of a skipped scan


def queue_depth(node: NodeConfig, config: PipelineConfig) -> int:
    """Return the pairs to keep: ``pairing.queue_depth``, or ``pairing.backlog`` when tracked."""
    depth = node.pairing.queue_depth
    return max(depth, node.pairing.backlog) if tracks(node.mode, config) else depth


class Backlog:
    """What a tracked stream's engine thread skips; it remembers whether the last scan tracked."""

    def __init__(self) -> None:
        self.tracked = False  # the last registered scan was tracked (a velocity exists)
        self.stamp_ns = 0  # and its stamp

    def saw(self, tracked: bool, stamp_ns: int) -> None:
        """Remember whether the last registered scan (``stamp_ns``) was tracked and valid."""
        self.tracked = tracked
        self.stamp_ns = stamp_ns

    def to_skip(self, pending_ns: Sequence[int], max_lag: float, max_age: float,
                called: bool) -> int:
        """
        Return how many of the oldest waiting pairs to drop before the next is taken.

        :param pending_ns: the waiting pairs' source stamps, oldest first (nanoseconds).
        :param max_lag: ``pairing.backlog_max_lag``, seconds (0: never skip for lag).
        :param max_age: ``tracking.max_age``, seconds: no prediction beyond it.
        :param called: a ``~/relocalize`` call waits (it is answered from the newest scan).
        """
        if len(pending_ns) < 2:
            return 0
        if called:
            return len(pending_ns) - 1
        if not self.tracked or max_lag <= 0 or (pending_ns[-1] - pending_ns[0]) * 1e-9 <= max_lag:
            return 0
        reach = self.stamp_ns + max_age * 1e9  # the last scan's prediction reaches this far
        if pending_ns[0] > reach:
            return len(pending_ns) - 1
        return int(pending_ns[1] <= reach)
