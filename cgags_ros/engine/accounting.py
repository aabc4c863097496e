"""
The node's accounting: every cloud it receives ends in exactly one counted bucket.

Sources: published, rejected (per refusal code: the cloud could not be decoded, or its pair
failed or was refused; the code is the one classification, on /diagnostics
``rejected.<code>`` and on ~/result), dropped (per pairing reason) or pending (waiting for a
target, queued, or being registered). Targets: used, rejected (``rejected_targets.<code>``),
dropped or held. The counters, the pairer, the upstream losses and the tracked stream's
backlog change under one lock, so every snapshot balances exactly; /diagnostics carries
the buckets and ``accounting.ok``.

Sources that never arrived are outside that balance: ``sources.lost_upstream`` counts the
gaps in the received source stamps (:class:`UpstreamLoss`). A scan that the transport drops
never reaches the node, so no bucket can hold it. What the node does see is the hole it
leaves: a LiDAR stamps its scans at a regular period, so a stamp ``k`` periods after the
previous one means ``k - 1`` scans went missing upstream (in the driver, the network or DDS;
docs/transport.md). Scans lost before the first or after the last received one leave no
hole and are not counted, so the count is a lower bound.

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
import dataclasses
import statistics
import threading
import time
from typing import Any, Callable

from .pairing import Backlog, is_source_drop, Pair, Pairer, SKIPPED, Stamped
from .transport import user_line
from ..config.node import PairingConfig
from ..pipeline.result import PipelineResult
from ..refusal import Refusal

LOG_REPEAT_S = 30.0  # a code already logged is logged again at most this often
# Learning a LiDAR's scan period from its stamps (UpstreamLoss):
GAP_PERIODS = 1.5  # an interval above this many periods is a gap
CLUSTER = 1.25  # intervals within this factor of the shortest are single periods
MIN_AGREEING = 2  # single-period intervals needed before the period is trusted
MAX_DIVISOR = 4  # the shortest agreeing intervals may be up to this many periods long
ON_GRID = 0.2  # an interval within this many periods of a whole number fits a period
FIT = 0.9  # fraction of intervals that must fit a shorter candidate period
MIN_FOR_DIVISOR = 5  # intervals needed before a shorter period than the shortest is tried
# Given the ready pairs' source stamps (ns, oldest first) and the backlog, how many of the
# oldest to drop before the next is taken.
Skip = Callable[[list[int], Backlog], int]


@dataclasses.dataclass(frozen=True)
class LastRegistration:
    """
    The last registration, as /diagnostics shows it (``last_<field>``, ``last_timing.*``).

    :ivar valid: the node took it (valid, finite). :ivar reason, refusal_code: why not ('').
    :ivar voxel_size: the pipeline's, metres. :ivar path: 'global' or 'tracked'.
    :ivar timings: its stages' times, seconds. :ivar source_stamp_ns: the scan's stamp.
    """

    valid: bool
    reason: str
    refusal_code: str
    inliers: int
    fitness: float
    voxel_size: float
    path: str
    timings: dict[str, float]
    source_stamp_ns: int

    @classmethod
    def of(cls, result: PipelineResult, refusal: Refusal | None, voxel_size: float,
           stamp_ns: int) -> LastRegistration:
        """Return the record of ``result``, refused by the node for ``refusal`` (None: taken)."""
        return cls(refusal is None, refusal.message if refusal else '',
                   refusal.code.value if refusal else '', result.num_inliers,
                   float(result.fitness), voxel_size, result.path, dict(result.timings),
                   stamp_ns)


class Accounting:
    """
    The counters, the pairer, the upstream losses and the backlog of one node.

    Two threads write: the node's executor (clouds received, the pairing's settings) and the
    engine thread (pairs taken and finished); all of it changes under one condition,
    which the engine thread also waits on for the next pair.
    """

    def __init__(self, pairing: PairingConfig, queue_depth: int):
        self._lock = threading.Condition()  # the engine thread waits on it for a ready pair
        self._pairer = Pairer.from_config(pairing, queue_depth)
        self._pairer.on_drop = self._on_drop
        self._upstream = UpstreamLoss()
        self.backlog = Backlog()  # a tracked stream's last scan (read under the lock)
        self._counts: collections.Counter[str] = collections.Counter()
        self._rejected: dict[str, collections.Counter[str]] = {
            'source': collections.Counter(), 'target': collections.Counter()}
        self._last: LastRegistration | None = None
        self._latencies: collections.deque[float] = collections.deque(maxlen=200)
        self._in_progress = 0
        self._failing = ''  # why the engine thread failed, until a registration succeeds again
        self._logged: dict[str, float] = {}
        self._dropped: list[tuple[str, Stamped]] = []  # sources pairing dropped, not yet told

    def failed(self, code: str) -> None:
        """Mark registration failing (``code``) until a registration succeeds."""
        with self._lock:
            self._failing = code

    def registered(self, last: LastRegistration) -> None:
        """
        Record the last registration (the engine thread's failure, if any, is over).

        The backlog keeps whether it was tracked and valid (a velocity exists).
        """
        with self._lock:
            self._failing = ''
            self._last = last
            self.backlog.saw(last.path == 'tracked' and last.valid, last.source_stamp_ns)

    def count(self, key: str) -> None:
        """Count one event outside the balance (e.g. ``published_invalid``)."""
        with self._lock:
            self._counts[key] += 1

    def wake(self) -> None:
        """End a :meth:`take` waiting for a pair (shutting down)."""
        with self._lock:
            self._lock.notify_all()

    def set_queue_depth(self, depth: int) -> None:
        """Keep ``depth`` ready pairs from the next pair on (the oldest dropped beyond)."""
        with self._lock:
            self._pairer.queue_depth = depth

    def set_slop(self, slop: float) -> None:
        """Set the pairer's synchronization slop (seconds) for the next pairs."""
        with self._lock:
            self._pairer.set_slop(slop)

    def receive(self, role: str, stamp_ns: int, frame_id: str, payload: Any,
                rejection: Refusal | None = None) -> int:
        """
        Count a received cloud: pair it, or count its ``rejection`` by code.

        :returns: how many more sources its stamp shows lost upstream (a stamp of 0, when
            the header could not be read, shows nothing).
        """
        with self._lock:
            self._counts[f'received_{role}'] += 1
            lost = self._upstream.add(stamp_ns) if role == 'source' and stamp_ns > 0 else 0
            if rejection is not None:
                self._rejected[role][rejection.code.value] += 1
            elif role == 'source':
                self._pairer.add_source(stamp_ns, frame_id, payload)
            else:
                self._pairer.add_target(stamp_ns, frame_id, payload)
            if self._pairer.pending:
                self._lock.notify()
            return lost

    def _on_drop(self, reason: str, item: Stamped) -> None:
        if is_source_drop(reason):  # under the lock: the pairer's caller holds it
            self._dropped.append((reason, item))

    def dropped_sources(self) -> list[tuple[str, Stamped]]:
        """Return the (reason, source) pairing dropped since the last call, oldest first."""
        with self._lock:
            dropped, self._dropped = self._dropped, []
            return dropped

    def take(self, timeout: float, skip: Skip | None = None) -> Pair | None:
        """
        Return the next ready pair (now in progress), or None after ``timeout`` s.

        ``skip``: how many of the oldest ready pairs to drop first (counted as
        ``pairing.SKIPPED``), decided under the lock from their stamps and the backlog.
        """
        with self._lock:
            if not self._pairer.pending:
                self._lock.wait(timeout)
            if not self._pairer.pending:
                return None
            if skip is not None:
                self._pairer.drop_oldest(skip(self._pairer.ready_stamps(), self.backlog),
                                         SKIPPED)
            pair = self._pairer.pop()
            self._in_progress += pair is not None
            return pair

    def finish(self, refusal: Refusal | None = None, latency_s: float | None = None) -> None:
        """End the pair in progress: published (no ``refusal``) or rejected by its code."""
        with self._lock:
            self._in_progress -= 1
            if refusal is not None:
                self._rejected['source'][refusal.code.value] += 1
            else:
                self._counts['published'] += 1
                if latency_s is not None:
                    self._latencies.append(latency_s)

    def log_due(self, role: str, code: str) -> tuple[int, bool]:
        """Return (``role`` clouds rejected with ``code`` so far, whether to log this one)."""
        with self._lock:
            return self._rejected[role][code], self._log_due(f'{role}.{code}')

    def lost_upstream(self) -> tuple[int, bool]:
        """Return (sources lost upstream so far, whether to log it now)."""
        with self._lock:
            return self._upstream.lost, self._log_due('lost_upstream')

    def _log_due(self, key: str) -> bool:
        """Tell whether ``key`` is to be logged now (first time, then every 30 s)."""
        now = time.monotonic()
        last = self._logged.get(key)
        due = last is None or now - last >= LOG_REPEAT_S
        if due:
            self._logged[key] = now
        return due

    def snapshot(self) -> dict[str, Any]:
        """Return counts, rejections, last result, latencies, pairing and the balance."""
        with self._lock:
            counts = dict(self._counts)
            rejected = dict(self._rejected['source'])
            rejected_targets = dict(self._rejected['target'])
            pairing = self._pairer.counters()
            snap = {'counts': counts, 'rejected': rejected,
                    'rejected_targets': rejected_targets,
                    'last': dataclasses.asdict(self._last) if self._last else {},
                    'latencies': list(self._latencies), 'pairing': pairing,
                    'failing': self._failing}
            in_progress = self._in_progress
            lost_upstream, period_ns = self._upstream.lost, self._upstream.period_ns
        sources = {'received': counts.get('received_source', 0),
                   'published': counts.get('published', 0),
                   'rejected': sum(rejected.values()),
                   'dropped': pairing['dropped_sources'],
                   'pending': pairing['waiting_sources'] + pairing['pending'] + in_progress,
                   'lost_upstream': lost_upstream}
        targets = {'received': counts.get('received_target', 0), 'used': pairing['targets_used'],
                   'rejected': sum(rejected_targets.values()),
                   'dropped': pairing['dropped_targets'], 'pending': pairing['targets_held']}
        snap['source_period_s'] = period_ns * 1e-9 if period_ns else None
        snap['accounting'] = {
            'sources': sources, 'targets': targets,
            'ok': (sources['received'] == sources['published'] + sources['rejected']
                   + sources['dropped'] + sources['pending']
                   and targets['received'] == targets['used'] + targets['rejected']
                   + targets['dropped'] + targets['pending'])}
        return snap


def lost_upstream_message(lost: Any) -> str:
    """Return the warning for source scans lost before the node, naming the fix."""
    return (f'{lost} source scans lost before reaching the node (gaps in their stamps); '
            f'large clouds need the Fast DDS profile in the publishing process too: '
            f'{user_line()} in its shell; on a loaded machine a deeper '
            f'pairing.source_depth keeps those the node is late to take (docs/transport.md)')


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
