"""
Pairing of source and target clouds.

The one implementation the node and the offline replay tool share (ROS-free, thread-safe).

Feed it ``(stamp_ns, frame_id, payload)`` for every source and target as they arrive; take
ready :class:`Pair` objects out with :meth:`Pairer.pop` (or :meth:`Pairer.wait_pop` from a
worker thread). Payloads are opaque (the node passes numpy arrays).

Modes
-----
``latest_target`` (scan-to-map)
    Every source is paired with the most recently *received* target (receipt order, not
    stamp order, so a latched map with an old stamp still counts). A target may serve any
    number of sources. A source that arrives before any target waits; at most
    ``max_waiting_sources`` sources wait (the newest ones; older ones are dropped with
    reason ``source_superseded_before_target``), and they are paired, oldest first, as
    soon as a target arrives. A target replaced before any source used it is counted as
    ``target_replaced_unused``.

``synchronized`` (approximate time)
    Each source is paired with the buffered target whose stamp is nearest to its own,
    provided ``|dt| <= slop``; each target is used by at most one source (like
    message_filters' ApproximateTime, greedy per source in stamp order). A match is
    final once a target with a stamp at or after the source's exists: with per-topic
    stamps that do not go backwards no later target can be closer. A source is dropped
    (``source_no_target_within_slop``) once the newest target is more than ``slop``
    after it without a match; a target is dropped (``target_no_source_within_slop``)
    once the newest source is more than ``slop`` after it and no waiting source can use
    it. Each side buffers at most ``max_waiting_sources`` / ``max_waiting_targets``
    messages; the oldest is dropped when full (``source_buffer_full`` /
    ``target_buffer_full``).

Ready queue
    Ready pairs wait in a FIFO of at most ``queue_depth`` pairs. When it is full the
    *oldest* pair is dropped (``queue_full``): for localization a fresh pose is worth more
    than a stale one.

Nothing is dropped silently: every drop increments ``drops[reason]``; ``received_*`` and
``paired`` count the rest.
"""

from __future__ import annotations

import collections
import dataclasses
import threading
from typing import Any

MODES = ('latest_target', 'synchronized')


@dataclasses.dataclass(frozen=True)
class Stamped:
    """A message reduced to what pairing needs: stamp (ns), frame and the payload."""

    stamp_ns: int
    frame_id: str
    payload: Any
    receipt: int = 0  # receipt order (1, 2, ...) within the Pairer


@dataclasses.dataclass(frozen=True)
class Pair:
    source: Stamped
    target: Stamped

    @property
    def dt_ns(self) -> int:
        """Source stamp minus target stamp, nanoseconds."""
        return self.source.stamp_ns - self.target.stamp_ns


class Pairer:
    """
    Pairs sources with targets (see the module docstring for the exact semantics).

    :param mode: 'latest_target' or 'synchronized'.
    :param slop: synchronized mode only, the largest |source stamp - target stamp|, seconds.
    :param queue_depth: ready pairs kept (>= 1); the oldest is dropped when full.
    :param max_waiting_sources: sources kept while waiting for a target (>= 1).
    :param max_waiting_targets: synchronized mode only, targets kept while unmatched (>= 1).
    """

    @classmethod
    def from_config(cls, cfg, queue_depth: int | None = None) -> 'Pairer':
        """
        Return the Pairer a :class:`~cgags_ros.config.node.NodeConfig` describes.

        The node and the replay tool both build theirs here; ``queue_depth`` overrides
        the config's.
        """
        return cls(cfg.pairing_mode, slop=cfg.sync_slop,
                   queue_depth=queue_depth or cfg.queue_depth,
                   max_waiting_sources=cfg.max_waiting_sources,
                   max_waiting_targets=cfg.max_waiting_targets)

    def __init__(self, mode: str = 'latest_target', *, slop: float = 0.05,
                 queue_depth: int = 2, max_waiting_sources: int = 1,
                 max_waiting_targets: int = 10):
        if mode not in MODES:
            raise ValueError(f"pairing mode {mode!r} is not one of {', '.join(MODES)}")
        if slop < 0 or queue_depth < 1 or max_waiting_sources < 1 or max_waiting_targets < 1:
            raise ValueError('slop must be >= 0 and queue/buffer sizes >= 1')
        self.mode = mode
        self.set_slop(slop)
        self.queue_depth = int(queue_depth)
        self.max_waiting_sources = int(max_waiting_sources)
        self.max_waiting_targets = int(max_waiting_targets)
        self.received_sources = 0
        self.received_targets = 0
        self.paired = 0
        self.drops: collections.Counter[str] = collections.Counter()
        self._ready: collections.deque[Pair] = collections.deque()
        self._sources: list[Stamped] = []  # waiting sources, oldest first
        self._targets: list[Stamped] = []  # latest: [newest]; synchronized: unmatched
        self._target_used = False
        self._newest_source_ns: int | None = None  # newest stamps ever seen (synchronized)
        self._newest_target_ns: int | None = None
        self._receipts = 0
        self._cond = threading.Condition()

    def set_slop(self, slop: float) -> None:
        """Set the synchronized-mode slop (seconds); applies to the next match."""
        self.slop_ns = int(round(slop * 1e9))

    # ------------------------------------------------------------------ input

    def add_source(self, stamp_ns: int, frame_id: str, payload: Any) -> None:
        with self._cond:
            self.received_sources += 1
            item = self._stamped(stamp_ns, frame_id, payload)
            if self.mode == 'latest_target':
                if self._targets:
                    self._emit(item, self._targets[-1])
                else:
                    self._push(self._sources, item, self.max_waiting_sources,
                               'source_superseded_before_target')
            else:
                self._newest_source_ns = _newest(self._newest_source_ns, item.stamp_ns)
                self._push(self._sources, item, self.max_waiting_sources, 'source_buffer_full')
                self._match()

    def add_target(self, stamp_ns: int, frame_id: str, payload: Any) -> None:
        with self._cond:
            self.received_targets += 1
            item = self._stamped(stamp_ns, frame_id, payload)
            if self.mode == 'latest_target':
                if self._targets and not self._target_used:
                    self.drops['target_replaced_unused'] += 1
                self._targets = [item]
                self._target_used = False
                waiting, self._sources = self._sources, []
                for source in waiting:
                    self._emit(source, item)
            else:
                self._newest_target_ns = _newest(self._newest_target_ns, item.stamp_ns)
                self._push(self._targets, item, self.max_waiting_targets, 'target_buffer_full')
                self._match()

    # ------------------------------------------------------------------ output

    def pop(self) -> Pair | None:
        """Return the oldest ready pair, or None."""
        with self._cond:
            return self._ready.popleft() if self._ready else None

    def wait_pop(self, timeout: float | None = None) -> Pair | None:
        """Block until a pair is ready (or ``timeout`` seconds pass, or :meth:`wake`)."""
        with self._cond:
            if not self._ready:
                self._cond.wait(timeout)
            return self._ready.popleft() if self._ready else None

    def wake(self) -> None:
        """Release threads blocked in :meth:`wait_pop` (used on shutdown)."""
        with self._cond:
            self._cond.notify_all()

    def reset(self) -> None:
        """
        Forget waiting sources, unmatched targets (synchronized mode) and ready pairs.

        Used e.g. after a clock jump. The latest target of latest_target mode is kept: a
        latched map is not sent again. Discarded items are counted as ``reset``.
        """
        with self._cond:
            self.drops['reset'] += len(self._ready) + len(self._sources)
            self._ready.clear()
            self._sources = []
            if self.mode == 'synchronized':
                self.drops['reset'] += len(self._targets)
                self._targets = []
            self._newest_source_ns = self._newest_target_ns = None

    @property
    def pending(self) -> int:
        """Ready pairs not yet popped."""
        with self._cond:
            return len(self._ready)

    @property
    def waiting_sources(self) -> int:
        with self._cond:
            return len(self._sources)

    @property
    def has_target(self) -> bool:
        with self._cond:
            return bool(self._targets)

    def counters(self) -> dict[str, int]:
        """Snapshot: received, paired, pending, and ``dropped.<reason>`` for every drop."""
        with self._cond:
            out = {'received_sources': self.received_sources,
                   'received_targets': self.received_targets,
                   'paired': self.paired, 'pending': len(self._ready),
                   'waiting_sources': len(self._sources),
                   'dropped': sum(self.drops.values())}
            out.update({f'dropped.{k}': v for k, v in sorted(self.drops.items())})
            return out

    # ------------------------------------------------------------------ internals

    def _stamped(self, stamp_ns: int, frame_id: str, payload: Any) -> Stamped:
        self._receipts += 1
        return Stamped(int(stamp_ns), str(frame_id), payload, self._receipts)

    def _push(self, buf: list[Stamped], item: Stamped, limit: int, reason: str) -> None:
        buf.append(item)
        while len(buf) > limit:
            buf.pop(0)
            self.drops[reason] += 1

    def _emit(self, source: Stamped, target: Stamped) -> None:
        self._target_used = True
        self.paired += 1
        self._ready.append(Pair(source, target))
        while len(self._ready) > self.queue_depth:
            self._ready.popleft()
            self.drops['queue_full'] += 1
        self._cond.notify()

    def _match(self) -> None:
        slop = self.slop_ns
        self._sources.sort(key=lambda s: s.stamp_ns)
        newest_target = self._newest_target_ns
        kept: list[Stamped] = []
        for source in self._sources:
            candidates = [t for t in self._targets if abs(t.stamp_ns - source.stamp_ns) <= slop]
            if not candidates:
                if newest_target is not None and newest_target > source.stamp_ns + slop:
                    self.drops['source_no_target_within_slop'] += 1
                else:
                    kept.append(source)
                continue
            if newest_target is not None and newest_target >= source.stamp_ns:
                best = min(candidates, key=lambda t: (abs(t.stamp_ns - source.stamp_ns),
                                                      t.receipt))
                self._targets.remove(best)
                self._emit(source, best)
            else:
                kept.append(source)
        self._sources = kept
        newest_source = self._newest_source_ns
        if newest_source is None:
            return
        remaining = []
        for target in self._targets:
            stale = newest_source > target.stamp_ns + slop
            usable = any(abs(s.stamp_ns - target.stamp_ns) <= slop for s in kept)
            if stale and not usable:
                self.drops['target_no_source_within_slop'] += 1
            else:
                remaining.append(target)
        self._targets = remaining


def _newest(current: int | None, stamp_ns: int) -> int:
    return stamp_ns if current is None else max(current, stamp_ns)
