"""Live replay (``cgags-replay BAG --live``): the bag's clouds through a running register_node.

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

import dataclasses
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..pairing import Pairer
from ..ros.conversions import pose_to_transform, stamp_to_ns
from .replay import (BagContents, CloudMessage, ReplayError, ReplayOptions, finish_report,
                     iter_pairs, load_contents, make_row, note_pairing_drops,
                     resolve_configs, start_report)
from .report import BagReport, PairRow

DIAGNOSTICS_PERIOD_S = 0.1
SHUTDOWN_GRACE_S = 10.0
MAX_QUEUE = 1000  # node_config's upper bound for depths
# Node counters that end a source's life (see cgags_ros.ros.node and cgags_ros.pairing).
_SOURCE_DROPS = ("source_", "queue_full", "reset")


@dataclasses.dataclass
class Received:
    """A pose from the node: 4x4 source->target, its frame, and when it arrived (s)."""

    transform: np.ndarray
    frame_id: str
    receipt_s: float


class LiveSession:
    """An rclpy context with the player node: publishers, pose and diagnostics recorders."""

    def __init__(self, opts: ReplayOptions, n_sources: int):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("cgags_replay_player", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        depth = max(1, min(n_sources, MAX_QUEUE))
        self.source_pub = self.node.create_publisher(
            PointCloud2, opts.source_topic,
            QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE))
        self.target_pub = self.node.create_publisher(
            PointCloud2, opts.target_topic,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.poses: dict[int, Received] = {}
        self.details: dict[int, dict[str, str]] = {}
        self.stats: dict[str, str] = {}
        self.last_progress = time.monotonic()
        self.node_id = "/" + opts.node_name.lstrip("/")
        self.pose_sub = self.node.create_subscription(
            PoseStamped, f"{self.node_id}/pose", self._on_pose, 100)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 100)

    def _on_pose(self, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self.poses[stamp] = Received(pose_to_transform(msg), msg.header.frame_id, time.monotonic())
        self.last_progress = time.monotonic()

    def _on_diagnostics(self, msg: Any) -> None:
        for status in msg.status:
            if status.hardware_id != self.node_id:
                continue
            values = {kv.key: kv.value for kv in status.values}
            if values != self.stats:
                self.last_progress = time.monotonic()
            self.stats = values
            stamp = values.get("last_source_stamp_ns")
            if stamp:
                self.details[int(stamp)] = values

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + max(seconds, 0.0)
        while True:
            left = end - time.monotonic()
            self.executor.spin_once(timeout_sec=max(min(left, 0.02), 0.0))
            if left <= 0:
                return

    def connected(self) -> bool:
        return (self.source_pub.get_subscription_count() > 0
                and self.target_pub.get_subscription_count() > 0
                and self.pose_sub.get_publisher_count() > 0)

    def accounted_sources(self) -> int | None:
        """Sources the node is done with (published + rejected + dropped + waiting), from
        its last diagnostics; None before any diagnostics."""
        if not self.stats:
            return None
        n = 0
        for key, value in self.stats.items():
            if (key == "published"
                    or (key.startswith("rejected.") and not key.startswith("rejected.target_"))
                    or (key.startswith("pairing.dropped.") and key[16:].startswith(_SOURCE_DROPS))
                    or key == "pairing.waiting_sources"):
                n += _int(value)
        return n

    def received_sources(self) -> int:
        return _int(self.stats.get("received_source", "0"))

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def replay_live(opts: ReplayOptions) -> BagReport:
    """Replay the bag through the node; write and return the report (as offline)."""
    start = time.perf_counter()
    contents = load_contents(opts)
    pipe, node_cfg, params, how = resolve_configs(opts.parameters, contents)
    report = start_report(opts, contents, pipe, node_cfg)
    report.notes.append(f"voxel size {pipe.voxel_size:g} m ({how})")
    pairer = Pairer.from_config(node_cfg, queue_depth=MAX_QUEUE)
    expected = {p.source.stamp_ns: p for p in iter_pairs(contents, pairer)}
    note_pairing_drops(report, pairer.counters())
    playable = [c for c in contents.clouds if c.msg is not None]
    n_sources = sum(c.role == "source" for c in playable)
    out = opts.out_dir
    out.mkdir(parents=True, exist_ok=True)
    proc = spawn_node(opts, params, n_sources, out) if opts.spawn else None
    session = None
    try:
        session = LiveSession(opts, n_sources)
        wait_for_node(session, proc, opts, out)
        sent = play(session, playable, opts.rate, proc)
        finished = wait_for_results(session, proc, opts, n_sources, len(expected))
        if not finished:
            report.notes.append(f"stopped waiting: no progress from the node for "
                                f"{opts.timeout:g} s (see node.log)")
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

def spawn_node(opts: ReplayOptions, params: dict[str, Any], n_sources: int,
               out: Path) -> subprocess.Popen:
    """Start ``python -m cgags_ros.register_node`` with a generated parameter file."""
    import yaml

    depth = max(2, min(n_sources + 1, MAX_QUEUE))
    values = {"source_qos": "reliable", "source_depth": depth, "queue_depth": depth,
              "diagnostics_period": DIAGNOSTICS_PERIOD_S}
    values.update(params)  # the user's own settings win
    params_file = out / "node_params.yaml"
    params_file.write_text(yaml.safe_dump({"/**": {"ros__parameters": values}}, sort_keys=False))
    cmd = [sys.executable, "-m", "cgags_ros.register_node", "--ros-args",
           "-r", f"__node:={opts.node_name}", "--params-file", str(params_file),
           "-r", f"source_cloud:={opts.source_topic}", "-r", f"target_cloud:={opts.target_topic}"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    log = open(out / "node.log", "w", encoding="utf-8")
    try:
        return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    finally:
        log.close()  # the child keeps its own descriptor


def wait_for_node(session: LiveSession, proc: subprocess.Popen | None, opts: ReplayOptions,
                  out: Path) -> None:
    """Block until the node subscribes to both clouds and publishes its pose topic."""
    deadline = time.monotonic() + opts.startup_timeout
    while not session.connected():
        if proc is not None and proc.poll() is not None:
            raise ReplayError(f"register_node exited with code {proc.returncode} before it "
                              f"connected: {_log_tail(out / 'node.log')}")
        if time.monotonic() > deadline:
            what = "the spawned register_node" if proc is not None else (
                f"a running {session.node_id} (started with --no-spawn)")
            raise ReplayError(f"no connection to {what} within {opts.startup_timeout:g} s: "
                              f"nobody subscribes to {opts.source_topic}/{opts.target_topic} "
                              f"or publishes {session.node_id}/pose")
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
        text = path.read_text(encoding="utf-8", errors="replace").strip().splitlines()
    except OSError:
        return "(no log)"
    return " | ".join(text[-lines:]) or "(empty log)"


# --- playback and recording -----------------------------------------------------------------

def play(session: LiveSession, clouds: list[CloudMessage], rate: float,
         proc: subprocess.Popen | None) -> dict[int, float]:
    """Publish the clouds at their recorded spacing / rate; returns source stamp -> the
    monotonic time it was sent."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    sent: dict[int, float] = {}
    if not clouds:
        return sent
    t0, wall0 = clouds[0].log_time_ns, time.monotonic()
    for cloud in clouds:
        due = wall0 + (cloud.log_time_ns - t0) * 1e-9 / rate
        session.spin_for(due - time.monotonic())
        if proc is not None and proc.poll() is not None:
            raise ReplayError(f"register_node exited with code {proc.returncode} during playback")
        raw = bytes(store.serialize_cdr(cloud.msg, cloud.msgtype))
        pub = session.source_pub if cloud.role == "source" else session.target_pub
        pub.publish(raw)
        if cloud.role == "source" and cloud.stamp_ns is not None:
            sent[cloud.stamp_ns] = time.monotonic()
    return sent


def wait_for_results(session: LiveSession, proc: subprocess.Popen | None, opts: ReplayOptions,
                     n_sources: int, n_expected: int) -> bool:
    """Spin until the node is done with every source; False on ``opts.timeout`` without
    progress or when the node exited."""
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
        if time.monotonic() - session.last_progress > opts.timeout:
            return False


def _wait_for_details(session: LiveSession, grace: float = 1.0) -> None:
    """The pose of the last pair can beat its diagnostics sample; give that a moment."""
    end = time.monotonic() + grace
    while time.monotonic() < end and not set(session.poses) <= set(session.details):
        session.spin_for(0.05)


def build_rows(contents: BagContents, expected: dict[int, Any], poses: dict[int, Received],
               details: dict[int, dict[str, str]], sent: dict[int, float]) -> list[PairRow]:
    """One row per source the node should have paired (and per unexpected pose)."""
    by_stamp = {c.stamp_ns: c for c in contents.sources if c.stamp_ns is not None}
    rows = []
    for stamp in sorted(set(expected) | set(poses)):
        pair = expected.get(stamp)
        src = pair.source.payload if pair else by_stamp.get(stamp)
        if src is None:
            continue
        row = make_row(len(rows), src, pair.target.payload if pair else None, contents)
        info = details.get(stamp, {})
        row.inliers = _int(info["last_inliers"]) if "last_inliers" in info else None
        row.fitness = _float(info.get("last_fitness"))
        row.time_s = _float(info.get("last_timing.total"))
        got = poses.get(stamp)
        if got is not None:
            row.valid = info.get("last_valid", "True") == "True"
            row.transform, row.target_frame = got.transform, got.frame_id
            row.latency_s = got.receipt_s - sent[stamp] if stamp in sent else None
            row.reason = info.get("last_reason", "")
        else:
            row.reason = info.get("last_reason") or "no pose received (see node.log)"
        rows.append(row)
    return rows


def node_notes(stats: dict[str, str]) -> list[str]:
    keys = [k for k in stats if k.startswith(("rejected.", "pairing.dropped."))]
    return [f"node {k}: {stats[k]}" for k in sorted(keys) if _int(stats[k])]


def _int(value: Any) -> int:
    try:
        return int(float(value))
    except (TypeError, ValueError):
        return 0


def _float(value: Any) -> float | None:
    try:
        return float(value)
    except (TypeError, ValueError):
        return None
