"""
The node's accounting: every cloud it receives ends in exactly one counted bucket.

Sources: published, rejected (per cause: the cloud could not be decoded, or its pair failed
or was invalid), dropped (per pairing reason) or pending (waiting for a target, queued, or
being registered). Targets: used, rejected, dropped or held. The counters change under one
lock, together with the pairer's, so every snapshot balances exactly; /diagnostics carries
the buckets and ``accounting.ok``. Sources that never arrived are outside that balance:
``sources.lost_upstream`` counts the gaps in the received source stamps
(:class:`~cgags_ros.pipeline.upstream.UpstreamLoss`).
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any, Callable

from .transport import user_line
from ..pipeline.backlog import SKIPPED
from ..pipeline.pairing import is_source_drop, Pair, Pairer, Stamped
from ..pipeline.upstream import UpstreamLoss

LOG_REPEAT_S = 30.0  # a cause already logged is logged again at most this often


class NodeHealth:
    """Counters, the last registration and the latencies of one node."""

    def __init__(self, pairer: Pairer):
        self._lock = threading.Lock()  # held around every change of these and the pairer
        self._pairer = pairer
        self._upstream = UpstreamLoss()
        self._counts: collections.Counter[str] = collections.Counter()
        self._rejected: collections.Counter[str] = collections.Counter()
        self._last: dict[str, Any] = {}
        self._latencies: collections.deque[float] = collections.deque(maxlen=200)
        self._in_progress = 0
        self._failing = ''  # why the worker failed, until a registration succeeds again
        self._logged: dict[str, float] = {}
        self._dropped: list[tuple[str, Stamped]] = []  # sources pairing dropped, not yet told
        pairer.on_drop = self._on_drop

    def failed(self, cause: str) -> None:
        """Mark the registration worker failing (``cause``) until a registration succeeds."""
        with self._lock:
            self._failing = cause

    def registered(self, last: dict[str, Any]) -> None:
        """Record the last registration's summary (``last_*`` keys); the worker works."""
        with self._lock:
            self._failing = ''
            self._last = dict(last)

    def count(self, key: str) -> None:
        """Count one event outside the balance (e.g. ``published_invalid``)."""
        with self._lock:
            self._counts[key] += 1

    def wake(self) -> None:
        """End a :meth:`take` waiting for a pair (shutting down)."""
        self._pairer.wake()

    def set_queue_depth(self, depth: int) -> None:
        """Keep ``depth`` ready pairs from the next pair on (the oldest dropped beyond)."""
        with self._lock:
            self._pairer.queue_depth = depth

    def set_slop(self, slop: float) -> None:
        """Set the pairer's synchronization slop (seconds) for the next pairs."""
        with self._lock:
            self._pairer.set_slop(slop)

    def receive(self, role: str, stamp_ns: int, frame_id: str, payload: Any,
                rejection: str = '') -> int:
        """
        Count a received cloud: pair it, or count its ``rejection`` cause.

        :returns: how many more sources its stamp shows lost upstream (a stamp of 0, when
            the header could not be read, shows nothing).
        """
        with self._lock:
            self._counts[f'received_{role}'] += 1
            lost = self._upstream.add(stamp_ns) if role == 'source' and stamp_ns > 0 else 0
            if rejection:
                self._rejected[rejection] += 1
            elif role == 'source':
                self._pairer.add_source(stamp_ns, frame_id, payload)
            else:
                self._pairer.add_target(stamp_ns, frame_id, payload)
            return lost

    def _on_drop(self, reason: str, item: Stamped) -> None:
        if is_source_drop(reason):  # under the lock of receive(): the pairer's caller
            self._dropped.append((reason, item))

    def dropped_sources(self) -> list[tuple[str, Stamped]]:
        """Return the (reason, source) pairing dropped since the last call, oldest first."""
        with self._lock:
            dropped, self._dropped = self._dropped, []
            return dropped

    def take(self, timeout: float, skip: Callable[[list[int]], int] | None = None
             ) -> Pair | None:
        """
        Return the next ready pair (now in progress), or None after ``timeout`` s.

        ``skip``: given the ready pairs' source stamps (ns, oldest first), how many of the
        oldest to drop first (counted as ``backlog.SKIPPED``).
        """
        if not self._pairer.wait_ready(timeout):
            return None
        with self._lock:
            if skip is not None:
                self._pairer.drop_oldest(skip(self._pairer.ready_stamps()), SKIPPED)
            pair = self._pairer.pop()
            self._in_progress += pair is not None
            return pair

    def finish(self, rejection: str = '', latency_s: float | None = None) -> None:
        """End the pair in progress: published (no ``rejection``) or rejected."""
        with self._lock:
            self._in_progress -= 1
            if rejection:
                self._rejected[rejection] += 1
            else:
                self._counts['published'] += 1
                if latency_s is not None:
                    self._latencies.append(latency_s)

    def reject_count(self, cause: str) -> tuple[int, bool]:
        """Return (rejections of ``cause`` so far, whether to log this one)."""
        with self._lock:
            return self._rejected[cause], self._log_due(cause)

    def lost_upstream(self) -> tuple[int, bool]:
        """Return (sources lost upstream so far, whether to log it now)."""
        with self._lock:
            return self._upstream.lost, self._log_due('lost_upstream')

    def _log_due(self, cause: str) -> bool:
        """Tell whether ``cause`` is to be logged now (first time, then every 30 s)."""
        now = time.monotonic()
        last = self._logged.get(cause)
        due = last is None or now - last >= LOG_REPEAT_S
        if due:
            self._logged[cause] = now
        return due

    def snapshot(self) -> dict[str, Any]:
        """Return counts, rejections, last result, latencies, pairing and the balance."""
        with self._lock:
            counts, rejected = dict(self._counts), dict(self._rejected)
            pairing = self._pairer.counters()
            snap = {'counts': counts, 'rejected': rejected, 'last': dict(self._last),
                    'latencies': list(self._latencies), 'pairing': pairing,
                    'failing': self._failing}
            in_progress = self._in_progress
            lost_upstream, period_ns = self._upstream.lost, self._upstream.period_ns
        target_rejects = sum(v for k, v in rejected.items() if k.startswith('target_'))
        sources = {'received': counts.get('received_source', 0),
                   'published': counts.get('published', 0),
                   'rejected': sum(rejected.values()) - target_rejects,
                   'dropped': pairing['dropped_sources'],
                   'pending': pairing['waiting_sources'] + pairing['pending'] + in_progress,
                   'lost_upstream': lost_upstream}
        targets = {'received': counts.get('received_target', 0), 'used': pairing['targets_used'],
                   'rejected': target_rejects, 'dropped': pairing['dropped_targets'],
                   'pending': pairing['targets_held']}
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
            f'{user_line()} in its shell (docs/transport.md)')
