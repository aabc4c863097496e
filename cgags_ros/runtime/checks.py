"""
The second lane: a tracked stream's periodic global checks, beside the stream.

A tracked stream is checked by a global registration every ``tracking.global_check_period``
seconds (or ``global_check_interval`` scans): the tracked poses may have slid into a wrong
minimum. A global registration takes several scan periods, so in the stream's own lane the
scans behind it wait. :class:`CheckLane` runs the check in a process of its own at a lower
OS priority (:data:`NICENESS`): on a machine whose cores the stream, its publisher and the
node share, it uses what they leave idle, and the stream never waits for it. The stream's
Tracker tracks the checked scan as any other and says the check is due
(:class:`~.jobs.Tracked`); the engine offers it here and hands the verdict that lands to the
stream's next scan (:class:`~.jobs.CheckVerdict`), where a disagreement resets the motion.
A check offered while the last one still runs is skipped (counted): the next one comes one
period later. A scan that cannot be tracked (the first, a jump, a lost stream) is not a
check: it goes global in the stream's own lane.
"""

from __future__ import annotations

import collections
from typing import Any

import numpy as np

from .jobs import CheckScan, CheckVerdict, MapReady, MapRef, PrepareMap, Target
from .process import spill_folder
from .supervisor import Supervisor
from ..config.pipeline import PipelineConfig
from ..errors import CgagsError

NICENESS = 15  # the check process's niceness: it yields the CPU to the stream's lane


class CheckLane:
    """A supervised process for periodic checks: offer one, collect its verdict later."""

    def __init__(self, timeout_s: float):
        # Its clouds go through files: reading a pipe at this priority would hold the sender.
        self.supervisor = Supervisor(timeout_s, 'cgags-checks', NICENESS, spill_folder())
        self.counts: collections.Counter[str] = collections.Counter()
        self._stamp: float | None = None  # the scan in flight, None for a map load
        self._map: tuple[PrepareMap, float] | None = None  # a map to load before any check

    def prepare_map(self, ref: MapRef, config: PipelineConfig, timeout_s: float) -> None:
        """Load a map here first, within ``timeout_s``, once the process is warm."""
        self._map = (PrepareMap(ref, config), timeout_s)

    def offer(self, source: np.ndarray, target: Target, config: PipelineConfig,
              stamp: float) -> bool:
        """Start checking the scan ``source`` stamped ``stamp`` (s); False: the lane is busy."""
        lane = self.supervisor
        # Never wait here: a process still warming up, or dead (supervise() replaces it),
        # skips the check as a busy one does.
        if lane.in_flight or not lane.ready or not lane.alive:
            self.counts['skipped_busy'] += 1
            return False
        if self._map is not None:  # the map loads first; this check is skipped for it
            (job, timeout_s), self._map = self._map, None
            self._stamp = None
            lane.submit(job, timeout_s)
            self.counts['skipped_busy'] += 1
            return False
        self.counts['offered'] += 1
        self._stamp = stamp
        self.supervisor.submit(CheckScan(source, target, config, stamp))
        return True

    def landed(self) -> CheckVerdict | None:
        """Return the check's verdict once it landed; None (at once) until then."""
        if not self.supervisor.in_flight:
            return None
        stamp = self._stamp
        try:
            answer = self.supervisor.collect(0.0)
        except CgagsError as exc:  # a timeout, a crash or a failed pair: no verdict
            self.counts[f'failed.{exc.code.value}'] += 1
            return None if stamp is None else CheckVerdict(stamp, None)
        if answer is None or isinstance(answer, MapReady) or stamp is None:
            return None
        assert isinstance(answer, CheckVerdict)
        self.counts['valid' if answer.transform is not None else f'refused.{answer.code}'] += 1
        return answer

    def statistics(self) -> dict[str, Any]:
        """Return ``checks.*`` and the lane's process keys for /diagnostics."""
        stats = {f'checks.{k}': v for k, v in sorted(self.counts.items())}
        stats.update(self.supervisor.health('checks'))
        return stats

    def close(self) -> None:
        """End the lane's process for good."""
        self.supervisor.close()
