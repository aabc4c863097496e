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
from typing import Any

from ..pipeline.pairing import Pair, Pairer
from ..pipeline.upstream import UpstreamLoss

LOG_REPEAT_S = 30.0  # a cause already logged is logged again at most this often


class NodeHealth:
    """Counters, the last registration and the latencies of one node."""

    def __init__(self, pairer: Pairer):
        self.lock = threading.Lock()  # held around every change of these and the pairer
        self.pairer = pairer
        self.upstream = UpstreamLoss()
        self.counts: collections.Counter[str] = collections.Counter()
        self.rejected: collections.Counter[str] = collections.Counter()
        self.last: dict[str, Any] = {}
        self.latencies: collections.deque[float] = collections.deque(maxlen=200)
        self.in_progress = 0
        self.failing = ''  # why the worker failed, until a registration succeeds again
        self._logged: dict[str, float] = {}

    def receive(self, role: str, stamp_ns: int, frame_id: str, payload: Any,
                rejection: str = '') -> int:
        """
        Count a received cloud: pair it, or count its ``rejection`` cause.

        :returns: how many more sources its stamp shows lost upstream (a stamp of 0, when
            the header could not be read, shows nothing).
        """
        with self.lock:
            self.counts[f'received_{role}'] += 1
            lost = self.upstream.add(stamp_ns) if role == 'source' and stamp_ns > 0 else 0
            if rejection:
                self.rejected[rejection] += 1
            elif role == 'source':
                self.pairer.add_source(stamp_ns, frame_id, payload)
            else:
                self.pairer.add_target(stamp_ns, frame_id, payload)
            return lost

    def take(self, timeout: float) -> Pair | None:
        """Return the next ready pair (now in progress), or None after ``timeout`` s."""
        if not self.pairer.wait_ready(timeout):
            return None
        with self.lock:
            pair = self.pairer.pop()
            self.in_progress += pair is not None
            return pair

    def finish(self, rejection: str = '', latency_s: float | None = None) -> None:
        """End the pair in progress: published (no ``rejection``) or rejected."""
        with self.lock:
            self.in_progress -= 1
            if rejection:
                self.rejected[rejection] += 1
            else:
                self.counts['published'] += 1
                if latency_s is not None:
                    self.latencies.append(latency_s)

    def reject_count(self, cause: str) -> tuple[int, bool]:
        """Return (rejections of ``cause`` so far, whether to log this one)."""
        with self.lock:
            return self.rejected[cause], self._log_due(cause)

    def lost_upstream(self) -> tuple[int, bool]:
        """Return (sources lost upstream so far, whether to log it now)."""
        with self.lock:
            return self.upstream.lost, self._log_due('lost_upstream')

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
        with self.lock:
            counts, rejected = dict(self.counts), dict(self.rejected)
            pairing = self.pairer.counters()
            snap = {'counts': counts, 'rejected': rejected, 'last': dict(self.last),
                    'latencies': list(self.latencies), 'pairing': pairing,
                    'failing': self.failing}
            in_progress = self.in_progress
            lost_upstream, period_ns = self.upstream.lost, self.upstream.period_ns
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
