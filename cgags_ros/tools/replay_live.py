"""
Live replay (``cgags-replay BAG --live``): the bag's clouds through a running register_node.

Starts ``python -m cgags_ros.register_node`` (unless ``--no-spawn``), publishes every
deserializable cloud of the bag (raw CDR, like ``ros2 bag play``; broken ones included, the
node must reject them) with the recorded log-time spacing divided by ``--rate``, the target
on reliable transient-local QoS (latched), and records ``/<node>/pose``. Per-pair details
(valid, reason, inliers, pipeline time) come from the node's ``/diagnostics``
(``last_*`` keys, sampled every 0.1 s for a spawned node). The run ends when the node has
accounted for every published source (published, rejected or dropped, per its
diagnostics) or every expected pose arrived, or after ``--timeout`` seconds without
progress; it never hangs. The spawned node is stopped with SIGINT (then SIGTERM, SIGKILL).

A spawned node gets the replay's parameters (voxel size, ``--params``, ``--set``,
``--pairing``) through a generated ``node_params.yaml`` in OUT_DIR, plus settings that make
a replay lossless when the pipeline is slower than the bag: reliable source QoS and a
queue as deep as the bag (unless given). Its log is ``node.log`` in OUT_DIR.
"""

from __future__ import annotations

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
from .report import BagReport, PairRow
from ..config.ros_parameters import keys_to_ros
from ..pipeline.pairing import Pairer
from ..refusal import Refusal, RefusalCode
from ..ros import diagnostics
from ..ros.player import LiveSession, MAX_QUEUE, Received

DIAGNOSTICS_PERIOD_S = 0.1
SHUTDOWN_GRACE_S = 10.0


def replay_live(opts: ReplayOptions, live: LiveOptions) -> BagReport:
    """Replay the bag through the node; write and return the report (as offline)."""
    start = time.perf_counter()
    contents = load_contents(opts)
    pipe, node_cfg, params, how = resolve_configs(opts.parameters, contents)
    report = start_report(opts, contents, pipe, node_cfg, 'live')
    report.notes.append(f'voxel size {pipe.voxel_size:g} m ({how})')
    pairer = Pairer.from_config(node_cfg, queue_depth=MAX_QUEUE)
    expected = {p.source.stamp_ns: p for p in iter_pairs(contents, pairer)}
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
        finished = wait_for_results(session, proc, live, n_sources, len(expected))
        if not finished:
            report.notes.append(f'stopped waiting: no progress from the node for '
                                f'{live.timeout:g} s (see node.log)')
    finally:
        if session is not None:
            session.close()
        if proc is not None:
            stop_node(proc)
    report.rows = build_rows(contents, expected, session.poses, session.details, sent)
    report.notes += node_notes(session.stats)
    report.wall_time_s = time.perf_counter() - start
    return finish_report(report, opts, contents)


# --- node process --------------------------------------------------------------------------

def spawn_node(opts: ReplayOptions, live: LiveOptions, params: dict[str, Any],
               n_sources: int, out: Path) -> subprocess.Popen:
    """Start ``python -m cgags_ros.register_node`` with a generated parameter file."""
    import yaml

    depth = max(2, min(n_sources + 1, MAX_QUEUE))
    values = {'source_qos': 'reliable', 'source_depth': depth, 'queue_depth': depth,
              'diagnostics_period': DIAGNOSTICS_PERIOD_S}
    values.update(params)  # the user's own settings win
    ros, rest = keys_to_ros(values)
    if rest:  # the keys that are no ROS parameter: the node's config_file
        config_file = out / 'node_config.yaml'
        config_file.write_text(yaml.safe_dump(rest, sort_keys=False))
        ros['config_file'] = str(config_file)
    params_file = out / 'node_params.yaml'
    params_file.write_text(yaml.safe_dump({'/**': {'ros__parameters': ros}}, sort_keys=False))
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
                              f'or publishes {session.node_id}/pose_with_covariance')
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
                     n_sources: int, n_expected: int) -> bool:
    """
    Spin until the node is done with every source.

    :returns: True when it is done; False on ``live.timeout`` without progress or when the
        node exited.
    """
    session.last_progress = time.monotonic()
    while True:
        session.spin_for(0.1)
        if len(session.poses) >= n_expected > 0:
            _wait_for_details(session)
            return True
        accounted = session.accounted_sources()
        if (accounted is not None and session.received_sources() >= n_sources
                and accounted >= n_sources):
            session.spin_for(0.3)  # a pose published just before the diagnostics
            return True
        if proc is not None and proc.poll() is not None:
            return False
        if time.monotonic() - session.last_progress > live.timeout:
            return False


def _wait_for_details(session: LiveSession, grace: float = 1.0) -> None:
    """Wait briefly: the pose of the last pair can beat its diagnostics sample."""
    end = time.monotonic() + grace
    while time.monotonic() < end and not set(session.poses) <= set(session.details):
        session.spin_for(0.05)


def build_rows(contents: BagContents, expected: dict[int, Any], poses: dict[int, Received],
               details: dict[int, dict[str, str]], sent: dict[int, float]) -> list[PairRow]:
    """Build one row per source the node should have paired (and per unexpected pose)."""
    by_stamp = {c.stamp_ns: c for c in contents.sources if c.stamp_ns is not None}
    rows = []
    for stamp in sorted(set(expected) | set(poses)):
        pair = expected.get(stamp)
        src = pair.source.payload if pair else by_stamp.get(stamp)
        if src is None:
            continue
        row = make_row(len(rows), src, pair.target.payload if pair else None, contents)
        info = details.get(stamp)
        last = diagnostics.last_result(info or {})
        row.inliers, row.fitness, row.time_s = last['inliers'], last['fitness'], last['time_s']
        refusal = Refusal(RefusalCode(last['code']), last['reason']) if last['code'] else None
        got = poses.get(stamp)
        if got is not None:
            row.valid = last['valid']
            row.transform, row.target_frame = got.transform, got.frame_id
            row.covariance = got.covariance
            row.latency_s = got.receipt_s - sent[stamp] if stamp in sent else None
            row.refusal = refusal
        else:
            row.refusal = refusal or Refusal(RefusalCode.NO_POSE,
                                             'no pose received (see node.log)')
        rows.append(row)
    return rows


def node_notes(stats: dict[str, str]) -> list[str]:
    """Return a note per rejection and drop reason the node counted."""
    return [f'node {line}' for line in diagnostics.nonzero_drops(stats)]
