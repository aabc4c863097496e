"""
``cgags-tune --live``: trials run by a running register_node, through its ROS parameters.

Each trial sets the node's parameters through its ``set_parameters`` service (each one on
its own, as rqt_reconfigure does), then replays the bags' clouds into it over DDS and
scores the pairs from its ``~/result`` (validity, transform, pipeline time), as
``cgags-replay --live`` records them. A parameter the node refuses (out of its range,
read-only, of another type) fails the trial with the node's reason, and the same settings
are not tried on the node again.

The clouds are played in lockstep, not at the bag's pace: after a source whose target
went out before it, the player waits for the node's result before the next cloud, so no
scan queues behind a slow trial. A source that gets no result within ``--timeout`` (lost
by DDS, which a best-effort source subscription may do with a large cloud, or slower than
that) counts as not right, the replay goes on, and the report counts them (:attr:`lost`).
Every pair of the
bags goes through the node each trial, held-out ones included (the stream is the bag's);
only the tuned-on pairs' scores reach the sampler. The clouds played are those the study
read for its pairs: each bag is read once a run.

What "defaults" means here: the node's values of the searched settings before the first
trial. A setting a trial does not search (the space grows as the study goes,
:mod:`.tune_search`) is set back to that value, so no trial inherits the one before's.
When the study ends, the node is left on the settings written. The settings the user
fixed (:mod:`.tune_fixed`: runtime ROS parameters only) are set with every trial.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from . import tuning
from .replay_common import fill_from_result, iter_pairs, ReplayError
from .replay_player import LiveSession, MAX_QUEUE
from ..config.node import configs_from_parameters
from ..engine.pairing import Pairer
from ..refusal import Refusal, RefusalCode

SERVICE_TIMEOUT_S = 10.0  # the parameter services answer at once: this is a dead node
CONNECT_TIMEOUT_S = 30.0
SETTLE_S = 0.3  # after connecting: let the reliable and transient-local handshakes finish


class LiveTrials:
    """The study's trials, run by a running register_node (``opts.node``) over DDS."""

    def __init__(self, opts: Any, splits: dict[str, list], criteria: Any,
                 contents: list[tuple[str, Any]]):
        """Connect to ``opts.node``; ``contents`` are the bags as read for the pairs."""
        self.splits, self.criteria, self.timeout = splits, criteria, opts.timeout
        self.fixed = dict(opts.fixed)
        self.bags = []  # (name, playable clouds, source stamps to wait for after their target)
        for name, bag in contents:
            _, node = configs_from_parameters({})
            pairs = list(iter_pairs(bag, Pairer.from_config(node.pairing)))
            self.bags.append((name, [c for c in bag.clouds if c.msg is not None],
                              {int(p.source.payload.stamp_ns): int(p.target.payload.stamp_ns)
                               for p in pairs}))
        n_sources = sum(len(paired) for _, _, paired in self.bags)
        self.session = LiveSession(opts.source_topic, opts.target_topic,
                                   opts.node.lstrip('/'), min(n_sources, MAX_QUEUE))
        try:
            self._connect(opts)
            names = [name for name in ['voxel_size'] + [n for n, _ in tuning.FIXES.values()]
                     if name not in self.fixed]
            values = self.session.get_parameters(names, SERVICE_TIMEOUT_S)
            self.initial = {k: v for k, v in values.items() if v is not None}  # None: unset
        except BaseException:
            self.session.close()
            raise
        self._closed = False
        self.lost = 0  # pairs of all trials that got no result from the node

    def _connect(self, opts: Any) -> None:
        deadline = time.monotonic() + CONNECT_TIMEOUT_S
        while not self.session.connected():
            if time.monotonic() > deadline:
                raise ReplayError(
                    f'no running {opts.node} within {CONNECT_TIMEOUT_S:g} s: nobody '
                    f'subscribes to {opts.source_topic}/{opts.target_topic} or publishes '
                    f'{self.session.node_id}/result (start it first: --live tunes a running '
                    'node)')
            self.session.spin_for(0.1)
        self.session.spin_for(SETTLE_S)

    def defaults(self) -> dict[str, Any]:
        """Return the node's own values of the searched settings before the first trial."""
        return dict(self.initial)

    def score(self, settings: dict[str, Any], splits: tuple[str, ...]) -> dict[str, Any]:
        """
        Set ``settings`` on the node, replay every bag through it, score ``splits``' pairs.

        :raises SettingRefused: the node refused a setting (its reasons).
        """
        self._set({**self.initial, **settings, **self.fixed})  # not searched: the node's own
        results = {}
        for name, clouds, paired in self.bags:
            for stamp, result in self._play(clouds, paired).items():
                results[name, stamp] = result
        out = {}
        for split in splits:
            pairs = self.splits[split]
            if pairs:
                answers = [results.get((p.bag, p.stamp_ns)) for p in pairs]
                self.lost += sum(answer is None for answer in answers)
                rows = [_row(p, answer) for p, answer in zip(pairs, answers)]
                out[split] = tuning.score(pairs, rows, settings, self.criteria)
        return out

    def leave_on(self, best: dict[str, Any]) -> None:
        """Leave the node on the best settings."""
        self._set({**self.initial, **best, **self.fixed})

    def close(self) -> None:
        """Leave the node (running, on whatever was set last) and close the player."""
        if not self._closed:
            self._closed = True
            self.session.close()

    def _set(self, settings: dict[str, Any]) -> None:
        try:
            refused = self.session.set_parameters(settings, SERVICE_TIMEOUT_S)
        except TimeoutError as exc:
            raise ReplayError(f'the node stopped answering: {exc}') from exc
        if refused:
            raise tuning.SettingRefused('the node refused ' + '; '.join(refused))

    def _play(self, clouds: list, paired: dict[int, int]) -> dict[int, dict[str, Any]]:
        """Publish a bag's clouds in lockstep with the node; return its results by stamp."""
        from rosbags.typesys import get_typestore, Stores

        store = get_typestore(Stores.ROS2_JAZZY)
        session = self.session
        session.results.clear()
        sent_targets: set[int] = set()
        for cloud in clouds:
            raw = bytes(store.serialize_cdr(cloud.msg, cloud.msgtype))
            if cloud.role == 'target':
                session.target_pub.publish(raw)
                sent_targets.add(cloud.stamp_ns)
                continue
            session.source_pub.publish(raw)
            if paired.get(cloud.stamp_ns) in sent_targets:
                self._wait_for({cloud.stamp_ns})
        self._wait_for(set(paired))
        return session.results_by_stamp()

    def _wait_for(self, stamps: set[int]) -> None:
        """Spin until the node has answered for every stamp, or ``timeout`` without progress."""
        session = self.session
        session.last_progress = time.monotonic()
        while not stamps <= set(session.results_by_stamp()):
            if time.monotonic() - session.last_progress > self.timeout:
                return
            session.spin_for(0.01)


def _row(pair: tuning.TunePair, result: dict[str, Any] | None) -> Any:
    """Return the report row of ``pair`` from the node's ``~/result`` (None: none came)."""
    row = tuning.empty_row(pair)
    if result is None:
        row.refusal = Refusal(RefusalCode.NO_POSE, 'no result from the node (lost, or later '
                              'than --timeout)')
        return row
    row.refusal = fill_from_result(row, result)
    row.valid = bool(result.get('valid'))
    if result.get('transform') is not None:
        row.transform = np.asarray(result['transform'], dtype=np.float64)
    return row
