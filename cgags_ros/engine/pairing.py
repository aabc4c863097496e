"""
Pairing of source and target clouds, and a tracked stream's backlog of pairs.

The one implementation the node and the offline replay tool share (ROS-free). One thread at
a time: the node's :class:`~.accounting.Accounting` calls it under its own lock, and waits
for its pairs there.

Feed it ``(stamp_ns, frame_id, payload)`` for every source and target as they arrive; take
ready :class:`Pair` objects out with :meth:`Pairer.pop`. Payloads are opaque (the node
passes numpy arrays).

The two modes (``latest_target`` for scan-to-map, ``synchronized`` for approximate-time
pairs), the bounded ready queue (the oldest pair is dropped when full: for localization a
fresh pose is worth more than a stale one) and the reset when stamps go backwards are
specified in docs/pairing.md. Nothing is dropped silently: every drop increments
``drops[reason]`` (and is handed to ``on_drop``, when set), and :meth:`Pairer.counters`
accounts for every source and target.

A tracked stream's backlog (:class:`Backlog`): a global registration takes several scan
periods. With a queue of one pair, the scan taken after it is the newest, too far from the
last pose (and with no velocity yet) to be tracked, so the stream goes global again and
never settles. A tracked stream (:func:`~cgags_ros.runtime.jobs.tracks`) therefore keeps up
to ``pairing.backlog`` pairs and registers them in stamp order, each from its predecessor's
pose: tracking a scan takes less than a scan period, so the backlog drains and the stream
keeps up. When it does not drain fast enough (the oldest waiting scan more than
``pairing.backlog_max_lag`` behind the newest) and the last scan was tracked, every other
waiting scan is dropped, as long as the next one taken is within ``tracking.max_age`` of
the last (beyond it the Tracker has no prediction); the Tracker scales the constant
velocity to the next scan's stamp. When the oldest waiting scan is already beyond
``tracking.max_age`` (the full backlog dropped the scans between), it would be registered
globally anyway: the newest is taken instead. A ``~/relocalize`` call is answered from the
newest scan, as with a queue of one pair. The accounting asks the backlog, under its lock,
how many pairs to drop (:meth:`Pairer.drop_oldest`) before the engine thread takes one.
"""

from __future__ import annotations

import collections
import dataclasses
from typing import Any, Callable, Iterable, Sequence

from ..config.node import NodeConfig
from ..config.pipeline import PipelineConfig
from ..runtime.jobs import tracks

MODES = ('latest_target', 'synchronized')
MAX_WAITING_TARGETS = 10  # synchronized mode: unmatched targets kept, the oldest dropped beyond
SKIPPED = 'source_skipped_catching_up'  # the drop reason of a scan the backlog skips


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
    :ivar on_drop: None, or called with (reason, the dropped :class:`Stamped`) at every drop
        (a dropped pair hands over its source).
    """

    @classmethod
    def from_config(cls, cfg, queue_depth: int | None = None) -> 'Pairer':
        """
        Return the Pairer a :class:`~cgags_ros.config.node.PairingConfig` describes.

        The node and the replay tool both build theirs here; ``queue_depth`` overrides
        the config's.
        """
        return cls(cfg.mode, slop=cfg.sync_slop,
                   queue_depth=queue_depth or cfg.queue_depth,
                   max_waiting_sources=cfg.max_waiting_sources)

    def __init__(self, mode: str = 'latest_target', *, slop: float = 0.05,
                 queue_depth: int = 2, max_waiting_sources: int = 1,
                 max_waiting_targets: int = MAX_WAITING_TARGETS):
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
        self.taken = 0  # pairs handed out by pop()
        self.targets_used = 0  # targets retired after serving at least one pair
        self.clock_resets: collections.Counter[str] = collections.Counter()
        self.drops: collections.Counter[str] = collections.Counter()
        self.on_drop: Callable[[str, Stamped], None] | None = None
        self._ready: collections.deque[Pair] = collections.deque()
        self._sources: list[Stamped] = []  # waiting sources, oldest first
        self._targets: list[Stamped] = []  # latest: [newest]; synchronized: unmatched
        self._target_used = False
        self._newest_source_ns: int | None = None  # newest stamps since the last reset
        self._newest_target_ns: int | None = None
        self._receipts = 0

    def set_slop(self, slop: float) -> None:
        """Set the synchronized-mode slop (seconds); applies to the next match."""
        self.slop_ns = int(round(slop * 1e9))

    # ------------------------------------------------------------------ input

    def add_source(self, stamp_ns: int, frame_id: str, payload: Any) -> None:
        """Add a source cloud; it waits, or is paired at once (then ready to pop)."""
        self.received_sources += 1
        item = self._stamped(stamp_ns, frame_id, payload)
        if self._newest_source_ns is not None and item.stamp_ns < self._newest_source_ns:
            self._clock_reset('source_stamp_backwards', item.stamp_ns)
        if self.mode == 'latest_target':
            self._newest_source_ns = _newest(self._newest_source_ns, item.stamp_ns)
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
        """Add a target cloud; waiting sources it completes become ready to pop."""
        self.received_targets += 1
        item = self._stamped(stamp_ns, frame_id, payload)
        if self.mode == 'latest_target':
            # A latched map may be re-sent with an old stamp: no clock check here.
            self._retire_target()
            self._targets = [item]
            self._target_used = False
            waiting, self._sources = self._sources, []
            for source in waiting:
                self._emit(source, item)
        else:
            if (self._newest_target_ns is not None
                    and item.stamp_ns < self._newest_target_ns):
                self._clock_reset('target_stamp_backwards', item.stamp_ns)
            self._newest_target_ns = _newest(self._newest_target_ns, item.stamp_ns)
            self._push(self._targets, item, self.max_waiting_targets, 'target_buffer_full')
            self._match()

    # ------------------------------------------------------------------ output

    def pop(self) -> Pair | None:
        """Return the oldest ready pair, or None."""
        return self._take()

    def ready_stamps(self) -> list[int]:
        """Return the source stamps (ns) of the ready pairs, oldest first."""
        return [pair.source.stamp_ns for pair in self._ready]

    def drop_oldest(self, count: int, reason: str) -> None:
        """Drop the ``count`` oldest ready pairs (their sources), counted as ``reason``."""
        for _ in range(min(count, len(self._ready))):
            self._drop(reason, [self._ready.popleft().source])

    def reset(self) -> None:
        """
        Forget waiting sources, unmatched targets (synchronized mode) and ready pairs.

        The latest target of latest_target mode is kept: a latched map is not sent again.
        Discarded items are counted as ``source_reset`` and ``target_reset``.
        """
        self._reset(keep_target_before=None)

    @property
    def pending(self) -> int:
        """Ready pairs not yet popped."""
        return len(self._ready)

    @property
    def waiting_sources(self) -> int:
        return len(self._sources)

    @property
    def has_target(self) -> bool:
        return bool(self._targets)

    def counters(self) -> dict[str, int]:
        """
        Return a consistent snapshot of the counters.

        Every source received is exactly one of: dropped (a ``source_*`` reason or
        ``queue_full``), waiting for a target, ready (``pending``) or ``taken``. Every
        target is dropped (``target_*``), held (the latest or an unmatched one) or
        ``targets_used`` (retired after serving a pair). ``clock_resets.<reason>`` counts
        the resets that stamps going backwards caused.
        """
        held = len(self._targets)
        out = {'received_sources': self.received_sources,
               'received_targets': self.received_targets,
               'paired': self.paired, 'pending': len(self._ready),
               'waiting_sources': len(self._sources), 'taken': self.taken,
               'targets_held': held, 'targets_used': self.targets_used,
               'dropped': sum(self.drops.values()),
               'dropped_sources': sum(v for k, v in self.drops.items()
                                      if is_source_drop(k)),
               'dropped_targets': sum(v for k, v in self.drops.items()
                                      if not is_source_drop(k))}
        out.update({f'dropped.{k}': v for k, v in sorted(self.drops.items())})
        out.update({f'clock_resets.{k}': v for k, v in sorted(self.clock_resets.items())})
        return out

    # ------------------------------------------------------------------ internals

    def _take(self) -> Pair | None:
        if not self._ready:
            return None
        self.taken += 1
        return self._ready.popleft()

    def _retire_target(self) -> None:
        """Count the latest target (latest_target mode) as used or dropped unused."""
        if self._targets:
            if self._target_used:
                self.targets_used += 1
            else:
                self._drop('target_replaced_unused', self._targets[-1:])
        self._target_used = False

    def _clock_reset(self, reason: str, stamp_ns: int) -> None:
        """
        Start over after a stamp went backwards (a bag replayed in a loop, a clock reset).

        Unpaired data from before the jump must not meet data from after it: waiting
        sources and unmatched targets are dropped, and the latest target (latest_target
        mode) is kept only when it is not newer than the new stamp, as a latched map is.
        Pairs already formed stay ready: each is consistent in itself.
        """
        self.clock_resets[reason] += 1
        self._reset(keep_target_before=stamp_ns, keep_ready=True)

    def _reset(self, keep_target_before: int | None, keep_ready: bool = False) -> None:
        if not keep_ready:
            self._drop('source_reset', [pair.source for pair in self._ready])
            self._ready.clear()
        self._drop('source_reset', self._sources)
        self._sources = []
        if self.mode == 'synchronized':
            self._drop('target_reset', self._targets)
            self._targets = []
        elif (self._targets and keep_target_before is not None
                and self._targets[-1].stamp_ns > keep_target_before):
            if self._target_used:
                self.targets_used += 1
            else:
                self._drop('target_reset', self._targets[-1:])
            self._targets, self._target_used = [], False
        self._newest_source_ns = self._newest_target_ns = None

    def _drop(self, reason: str, items: Iterable[Stamped]) -> None:
        for item in list(items):
            self.drops[reason] += 1
            if self.on_drop is not None:
                self.on_drop(reason, item)

    def _stamped(self, stamp_ns: int, frame_id: str, payload: Any) -> Stamped:
        self._receipts += 1
        return Stamped(int(stamp_ns), str(frame_id), payload, self._receipts)

    def _push(self, buf: list[Stamped], item: Stamped, limit: int, reason: str) -> None:
        buf.append(item)
        while len(buf) > limit:
            self._drop(reason, [buf.pop(0)])

    def _emit(self, source: Stamped, target: Stamped) -> None:
        self._target_used = True
        if self.mode == 'synchronized':
            self.targets_used += 1  # each target serves one source
        self.paired += 1
        self._ready.append(Pair(source, target))
        while len(self._ready) > self.queue_depth:
            self._drop('queue_full', [self._ready.popleft().source])

    def _match(self) -> None:
        slop = self.slop_ns
        self._sources.sort(key=lambda s: s.stamp_ns)
        newest_target = self._newest_target_ns
        kept: list[Stamped] = []
        for source in self._sources:
            candidates = [t for t in self._targets if abs(t.stamp_ns - source.stamp_ns) <= slop]
            if not candidates:
                if newest_target is not None and newest_target > source.stamp_ns + slop:
                    self._drop('source_no_target_within_slop', [source])
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
                self._drop('target_no_source_within_slop', [target])
            else:
                remaining.append(target)
        self._targets = remaining


def is_source_drop(reason: str) -> bool:
    """Tell whether a drop reason discards a source (the others discard a target)."""
    return reason.startswith('source_') or reason == 'queue_full'


def _newest(current: int | None, stamp_ns: int) -> int:
    return stamp_ns if current is None else max(current, stamp_ns)


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
