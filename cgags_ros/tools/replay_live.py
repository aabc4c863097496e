"""
Live replay (``cgags-replay BAG --live``): the bag's clouds through a running register_node.

Starts ``python -m cgags_ros.register_node`` (unless ``--no-spawn``), publishes every
deserializable cloud of the bag (raw CDR, like ``ros2 bag play``; broken ones included, the
node must reject them) with the recorded log-time spacing divided by ``--rate``, the target
on reliable transient-local QoS (latched), and records ``/<node>/pose_with_covariance``.
Per-pair details (valid, reason, inliers, pipeline time) come from the node's ``~/result``,
one JSON record for every source it is done with (published, rejected or dropped). The run
ends when every published source has its result (but those pairing leaves waiting for a
target, as the replay's own pairing of the bag shows) and every published pose arrived, or
after ``--timeout`` seconds without progress; it never hangs. The spawned node is stopped
with SIGINT (then SIGTERM, SIGKILL).

A spawned node gets the replay's parameters (voxel size, ``--config``, ``--set``,
``--pairing``) through a generated ``node_config.yaml`` (its ``config_file``) in OUT_DIR,
plus settings that make a replay lossless when the pipeline is slower than the bag:
reliable source QoS and a queue as deep as the bag (unless given). Its log is ``node.log``
in OUT_DIR.
"""

from __future__ import annotations

import collections
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
from typing import Any

from .replay_common import (
    BagContents,
    CloudMessage,
    fill_from_result,
    finish_report,
    iter_pairs,
    LiveOptions,
    load_contents,
    make_row,
    note_pairing_drops,
    ReplayError,
    ReplayOptions,
    resolve_configs,
    start_report,
)
from .replay_player import LiveSession, MAX_QUEUE, Received
from .report import BagReport, PairRow
from ..engine.pairing import Pairer
from ..refusal import Refusal, RefusalCode

SHUTDOWN_GRACE_S = 10.0


def replay_live(opts: ReplayOptions, live: LiveOptions) -> BagReport:
    """Replay the bag through the node; write and return the report (as offline)."""
    start = time.perf_counter()
    contents = load_contents(opts)
    pipe, node_cfg, params, how = resolve_configs(opts.parameters, contents)
    report = start_report(opts, contents, pipe, node_cfg, 'live')
    report.notes.append(f'voxel size {pipe.voxel_size:g} m ({how})')
    pairer = Pairer.from_config(node_cfg.pairing, queue_depth=MAX_QUEUE)
    expected = {p.source.stamp_ns: p for p in iter_pairs(contents, pairer)}
    left_waiting = pairer.waiting_sources  # the node holds these too: no result comes
    note_pairing_drops(report, pairer)
    playable = [c for c in contents.clouds if c.msg is not None]
    n_sources = sum(c.role == 'source' for c in playable)
    out = opts.out_dir
    out.mkdir(parents=True, exist_ok=True)
    proc = spawn_node(opts, live, params, n_sources, out) if live.spawn else None
    session = None
    try:
        session = LiveSession(opts.source_topic, opts.target_topic, live.node_name, n_sources)
        wait_for_node(session, proc, opts, live, out)
        sent = play(session, playable, live.rate, proc)
        finished = wait_for_results(session, proc, live, n_sources - left_waiting)
        if not finished:
            report.notes.append(f'stopped waiting: no progress from the node for '
                                f'{live.timeout:g} s (see node.log)')
    finally:
        if session is not None:
            session.close()
        if proc is not None:
            stop_node(proc)
    report.rows = build_rows(contents, expected, session.poses, session.results_by_stamp(),
                             sent)
    report.notes += node_notes(session.results)
    report.wall_time_s = time.perf_counter() - start
    return finish_report(report, opts, contents)


# --- node process --------------------------------------------------------------------------

def spawn_node(opts: ReplayOptions, live: LiveOptions, params: dict[str, Any],
               n_sources: int, out: Path) -> subprocess.Popen:
    """Start ``python -m cgags_ros.register_node`` with a generated parameter file."""
    import yaml

    depth = max(2, min(n_sources + 1, MAX_QUEUE))
    values = {'pairing.source_qos': 'reliable', 'pairing.source_depth': depth,
              'pairing.queue_depth': depth}
    values.update(params)  # the user's own settings win
    config_file = out / 'node_config.yaml'  # any key, ROS parameter or not, by its one name
    config_file.write_text(yaml.safe_dump(values, sort_keys=False))
    params_file = out / 'node_params.yaml'
    params_file.write_text(yaml.safe_dump(
        {'/**': {'ros__parameters': {'config_file': str(config_file)}}}, sort_keys=False))
    cmd = [sys.executable, '-m', 'cgags_ros.register_node', '--ros-args',
           '-r', f'__node:={live.node_name}', '--params-file', str(params_file),
           '-r', f'source_cloud:={opts.source_topic}', '-r', f'target_cloud:={opts.target_topic}']
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    log = open(out / 'node.log', 'w', encoding='utf-8')
    try:
        return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    finally:
        log.close()  # the child keeps its own descriptor


def wait_for_node(session: LiveSession, proc: subprocess.Popen | None, opts: ReplayOptions,
                  live: LiveOptions, out: Path) -> None:
    """Block until the node subscribes to both clouds and publishes its pose topic."""
    deadline = time.monotonic() + live.startup_timeout
    while not session.connected():
        if proc is not None and proc.poll() is not None:
            raise ReplayError(f'register_node exited with code {proc.returncode} before it '
                              f"connected: {_log_tail(out / 'node.log')}")
        if time.monotonic() > deadline:
            what = 'the spawned register_node' if proc is not None else (
                f'a running {session.node_id} (started with --no-spawn)')
            raise ReplayError(f'no connection to {what} within {live.startup_timeout:g} s: '
                              f'nobody subscribes to {opts.source_topic}/{opts.target_topic} '
                              f'or publishes {session.node_id}/pose_with_covariance and '
                              f'{session.node_id}/result')
        session.spin_for(0.1)
    session.spin_for(0.3)  # let the transient-local/reliable handshakes settle


def stop_node(proc: subprocess.Popen) -> int | None:
    """SIGINT (clean rclpy shutdown), then SIGTERM, then SIGKILL; returns the exit code."""
    for sig, grace in ((signal.SIGINT, SHUTDOWN_GRACE_S), (signal.SIGTERM, 5.0),
                       (signal.SIGKILL, 5.0)):
        if proc.poll() is not None:
            break
        proc.send_signal(sig)
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            continue
    return proc.poll()


def _log_tail(path: Path, lines: int = 5) -> str:
    try:
        text = path.read_text(encoding='utf-8', errors='replace').strip().splitlines()
    except OSError:
        return '(no log)'
    return ' | '.join(text[-lines:]) or '(empty log)'


# --- playback and recording -----------------------------------------------------------------

def play(session: LiveSession, clouds: list[CloudMessage], rate: float,
         proc: subprocess.Popen | None) -> dict[int, float]:
    """
    Publish the clouds at their recorded spacing / rate.

    :returns: source stamp -> the monotonic time it was sent.
    """
    from rosbags.typesys import get_typestore, Stores

    store = get_typestore(Stores.ROS2_JAZZY)
    sent: dict[int, float] = {}
    if not clouds:
        return sent
    t0, wall0 = clouds[0].log_time_ns, time.monotonic()
    for cloud in clouds:
        due = wall0 + (cloud.log_time_ns - t0) * 1e-9 / rate
        session.spin_for(due - time.monotonic())
        if proc is not None and proc.poll() is not None:
            raise ReplayError(f'register_node exited with code {proc.returncode} during playback')
        raw = bytes(store.serialize_cdr(cloud.msg, cloud.msgtype))
        pub = session.source_pub if cloud.role == 'source' else session.target_pub
        pub.publish(raw)
        if cloud.role == 'source' and cloud.stamp_ns is not None:
            sent[cloud.stamp_ns] = time.monotonic()
    return sent


def wait_for_results(session: LiveSession, proc: subprocess.Popen | None, live: LiveOptions,
                     n_results: int) -> bool:
    """
    Spin until the node has given ``n_results`` results and the pose of each published one.

    :returns: True when it has; False on ``live.timeout`` without progress or when the node
        exited.
    """
    session.last_progress = time.monotonic()
    while True:
        session.spin_for(0.1)
        results = session.results
        if len(results) >= n_results and all(
                r['source_stamp_ns'] in session.poses for r in results
                if r['outcome'] == 'published' and 'transform' in r):
            return True
        if proc is not None and proc.poll() is not None:
            return False
        if time.monotonic() - session.last_progress > live.timeout:
            return False


def build_rows(contents: BagContents, expected: dict[int, Any], poses: dict[int, Received],
               results: dict[int, dict[str, Any]], sent: dict[int, float]) -> list[PairRow]:
    """Build one row per source the node should have paired (and per unexpected pose)."""
    by_stamp = {c.stamp_ns: c for c in contents.sources if c.stamp_ns is not None}
    rows = []
    for stamp in sorted(set(expected) | set(poses)):
        pair = expected.get(stamp)
        src = pair.source.payload if pair else by_stamp.get(stamp)
        if src is None:
            continue
        row = make_row(len(rows), src, pair.target.payload if pair else None, contents)
        result = results.get(stamp, {})
        refusal = fill_from_result(row, result)
        got = poses.get(stamp)
        if got is not None:
            row.valid = result.get('valid', True)  # a pose without its result: a valid one
            row.transform, row.target_frame = got.transform, got.frame_id
            row.covariance = got.covariance
            row.latency_s = got.receipt_s - sent[stamp] if stamp in sent else None
            row.refusal = refusal
        else:
            row.refusal = refusal or Refusal(RefusalCode.NO_POSE,
                                             'no pose received (see node.log)')
        rows.append(row)
    return rows


def node_notes(results: list[dict[str, Any]]) -> list[str]:
    """Return a note per cause for which the node rejected or dropped sources."""
    causes = collections.Counter(
        ('rejected.' if r['outcome'] == 'rejected' else 'pairing.dropped.') + r['cause']
        for r in results if r['outcome'] != 'published')
    return [f'node {cause}: {n}' for cause, n in sorted(causes.items())]
