"""
The node's accounting: every cloud it receives ends in exactly one counted bucket.

Sources: published, rejected (per refusal code: the cloud could not be decoded, or its pair
failed or was refused; the code is the one classification, on /diagnostics
``rejected.<code>`` and on ~/result), dropped (per pairing reason) or pending (waiting for a
target, queued, or being registered). Targets: used, rejected (``rejected_targets.<code>``),
dropped or held. The counters, the pairer, the upstream losses and the tracked stream's
backlog change under one lock, so every snapshot balances exactly; /diagnostics carries
the buckets and ``accounting.ok``. Sources that never arrived are outside that balance:
``sources.lost_upstream`` counts the gaps in the received source stamps
(:class:`~.upstream.UpstreamLoss`).
"""

from __future__ import annotations

import collections
import dataclasses
import threading
import time
from typing import Any, Callable

from .backlog import Backlog, SKIPPED
from .pairing import is_source_drop, Pair, Pairer, Stamped
from .transport import user_line
from .upstream import UpstreamLoss
from ..config.node import PairingConfig
from ..pipeline.result import PipelineResult
from ..refusal import Refusal

LOG_REPEAT_S = 30.0  # a code already logged is logged again at most this often
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
        ``backlog.SKIPPED``), decided under the lock from their stamps and the backlog.
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
