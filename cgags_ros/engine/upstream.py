"""
Source scans lost before the node, counted from the gaps in their stamps.

A scan that the transport drops never reaches the node, so no bucket of its accounting can
hold it. What the node does see is the hole it leaves: a LiDAR stamps its scans at a
regular period, so a stamp ``k`` periods after the previous one means ``k - 1`` scans went
missing upstream (in the driver, the network or DDS; docs/transport.md). Scans lost before
the first or after the last received one leave no hole and are not counted, so the count
is a lower bound.

The period is learnt from the stamps themselves: the median of the shortest intervals that
agree within 25 % (at least two of them, so a single odd interval, e.g. a duplicated scan,
does not set it), or a half, third or quarter of it when nearly all intervals are whole
multiples of that (under heavy loss no two scans may arrive back to back); it is then
refined over the longer intervals. The stamps' jitter must stay well below a quarter
period, as a LiDAR's does. Losses that leave only even multiples of the period look like a
slower sensor, another reason the count is a lower bound; it never goes down.
Stamps that go backwards (a bag restarted, a clock reset) start a new stream; a gap longer
than ``pause_s`` is a pause of the sensor, not a loss.
"""

from __future__ import annotations

import collections
import statistics

GAP_PERIODS = 1.5  # an interval above this many periods is a gap
CLUSTER = 1.25  # intervals within this factor of the shortest are single periods
MIN_AGREEING = 2  # single-period intervals needed before the period is trusted
MAX_DIVISOR = 4  # the shortest agreeing intervals may be up to this many periods long
ON_GRID = 0.2  # an interval within this many periods of a whole number fits a period
FIT = 0.9  # fraction of intervals that must fit a shorter candidate period
MIN_FOR_DIVISOR = 5  # intervals needed before a shorter period than the shortest is tried


class UpstreamLoss:
    """
    Count scans missing between received source stamps (not thread-safe: hold a lock).

    :param window: intervals remembered to learn the period and re-count with it.
    :param pause_s: gaps longer than this (seconds) are pauses, never counted.
    """

    def __init__(self, window: int = 64, pause_s: float = 10.0):
        if window < MIN_AGREEING or pause_s <= 0:
            raise ValueError('window must be >= 2 and pause_s > 0')
        self._intervals: collections.deque[int] = collections.deque(maxlen=window)
        self._pause_ns = int(pause_s * 1e9)
        self._last_ns: int | None = None
        self._committed = 0  # losses of intervals that left the window
        self.period_ns: int | None = None
        self.lost = 0

    def add(self, stamp_ns: int) -> int:
        """Note a received source stamp (ns); return how many more scans are now lost."""
        last, self._last_ns = self._last_ns, int(stamp_ns)
        if last is None or stamp_ns <= last or stamp_ns - last > self._pause_ns:
            return 0  # the first stamp of a stream, a reset, or a pause
        if len(self._intervals) == self._intervals.maxlen:
            self._committed += self._missing(self._intervals[0])
        self._intervals.append(stamp_ns - last)
        self._learn_period()
        before = self.lost
        self.lost = max(self.lost, self._committed + sum(map(self._missing, self._intervals)))
        return self.lost - before

    def _learn_period(self) -> None:
        ordered = sorted(self._intervals)
        for i, shortest in enumerate(ordered[:1 - MIN_AGREEING]):
            single = [iv for iv in ordered[i:] if iv <= CLUSTER * shortest]
            if len(single) >= MIN_AGREEING:
                rough = self._divide(statistics.median(single), ordered[i:])
                # Refined over the longer intervals as whole numbers of periods: long gaps
                # average the stamps' jitter out of the period.
                periods = sum(round(iv / rough) for iv in ordered[i:])
                self.period_ns = int(round(sum(ordered[i:]) / periods))
                return

    @staticmethod
    def _divide(shortest: float, intervals: list[int]) -> float:
        """
        Return the longest period, ``shortest / k``, that the intervals are multiples of.

        When scans are lost at random, no two may arrive back to back for a while: the
        shortest intervals are then two or three periods, and intervals of 3 and 5 periods
        betray the true one.
        """
        if len(intervals) < MIN_FOR_DIVISOR:
            return shortest
        for k in range(1, MAX_DIVISOR + 1):
            period = shortest / k
            fits = sum(abs(iv / period - round(iv / period)) <= ON_GRID for iv in intervals)
            if fits >= FIT * len(intervals):
                return period
        return shortest

    def _missing(self, interval_ns: int) -> int:
        """Return the scans missing in one interval (0 until the period is known)."""
        if self.period_ns is None or interval_ns <= GAP_PERIODS * self.period_ns:
            return 0
        return max(round(interval_ns / self.period_ns) - 1, 1)
