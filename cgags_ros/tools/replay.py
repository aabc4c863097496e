"""``cgags-replay``: register the clouds of a rosbag2 bag, offline or through the ROS node.

Offline (default, no ROS installation needed)::

    cgags-replay BAG [--source-topic /source_cloud] [--target-topic /target_cloud]
                 [--ground-truth-topic /ground_truth] [--voxel-size V] [--params config.yaml]
                 [--set key=value ...] [--pairing latest_target|synchronized] [--output OUT_DIR]

reads the bag (:mod:`cgags_ros.datasets.bag`), pairs sources and targets with the node's
:class:`~cgags_ros.pairing.Pairer` (same code, same parameters) and runs
:func:`cgags_ros.pipeline.register_clouds` on every pair.

Live (``--live [--rate R] [--no-spawn]``): starts ``python -m cgags_ros.register_node``
(or uses a running one), publishes the bag's clouds with their recorded timing divided by
``R`` and records the node's ``~/pose``; see :mod:`cgags_ros.tools.live_replay`.

Both write to OUT_DIR (default ``out/replay/<bag>``): ``poses/`` (rosbag2 MCAP,
``geometry_msgs/msg/PoseStamped`` on ``--pose-topic``, stamp = source stamp, frame_id =
target frame, pose = source frame in the target frame), ``results.csv``, ``results.json``
and ``errors.png`` (RE, TE and time per pair). With ground truth (PoseStamped
source->target, matched to sources by header stamp) every pair gets RE/TE and the summary
a recall: success = valid and RE <= ``--max-re-deg`` and TE <= ``--max-te``.

Voxel size (metres), first match wins: ``--voxel-size``; ``--set voxel_size=V``;
``voxel_size`` in ``--params``; otherwise :func:`auto_voxel_size` of the first target cloud:
the voxel at which it keeps about 5000 points after voxel downsampling (rounded to two
significant digits; 2.5 mm for the bunny, 5 cm for the redkitchen fragment, 0.3 m for the
LiDAR scan). The chosen value is printed.

Broken messages (undeserializable, or a PointCloud2 that cannot be decoded) are reported,
counted and skipped. A missing topic, an unreadable file or a path that is not a bag ends
the run with one ``cgags-replay: error: ...`` line and exit code 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from .. import configutil
from ..config import PipelineConfig, load_yaml
from ..datasets.bag import BagReader
from ..errors import CgagsError, InvalidConfigError, InvalidInputError
from ..node_config import NodeConfig, configs_from_parameters
from ..pairing import MODES, Pair, Pairer
from ..ros.conversions import pointcloud2_to_xyz, pose_to_transform
from .report import BagReport, BrokenMessage, PairRow, SuccessCriteria, pairs_table, \
    summary_line, write_results

PROG = "cgags-replay"
DEFAULT_POSE_TOPIC = "/cgags/pose"
DEFAULT_GT_TOPIC = "/ground_truth"
POSES_DIR = "poses"
AUTO_VOXEL_POINTS = 5000
DEFAULT_MAX_RE_DEG = 5.0
DEFAULT_MAX_TE_VOXELS = 3.0


class ReplayError(CgagsError):
    """The replay cannot run (no clouds in the bag, the node did not start, ...)."""


# --- bag contents ------------------------------------------------------------------------------

@dataclasses.dataclass
class CloudMessage:
    """A source or target PointCloud2 of the bag. ``xyz`` is (N, 3) metres in ``frame_id``,
    or None when the message could not be decoded (then it is also in ``broken``); ``msg``
    is the rosbags message (None when it could not be deserialized)."""

    role: str  # 'source' | 'target'
    topic: str
    msgtype: str
    log_time_ns: int
    stamp_ns: int | None
    frame_id: str
    msg: Any
    xyz: np.ndarray | None


@dataclasses.dataclass
class BagContents:
    """Clouds in log-time order, ground truth by source stamp (4x4 source->target), and
    the broken messages that were skipped."""

    path: Path
    clouds: list[CloudMessage]
    ground_truth: dict[int, np.ndarray]
    broken: list[BrokenMessage]
    ground_truth_topic: str | None

    @property
    def sources(self) -> list[CloudMessage]:
        return [c for c in self.clouds if c.role == "source"]

    def first_target_points(self) -> np.ndarray | None:
        return next((c.xyz for c in self.clouds if c.role == "target" and c.xyz is not None), None)


def read_bag_contents(path: str | Path, source_topic: str, target_topic: str,
                      ground_truth_topic: str | None, *,
                      require_ground_truth: bool = False,
                      max_points: int | None = None) -> BagContents:
    """Read and decode the clouds (and ground truth) of a bag.

    ``ground_truth_topic`` is used when the bag has it; a missing one raises
    BagTopicError only with ``require_ground_truth``. Raises BagError / BagTopicError for a
    bad path or a missing cloud topic.
    """
    kwargs = {} if max_points is None else {"max_points": max_points}
    with BagReader(path) as reader:
        gt_topic = ground_truth_topic
        if gt_topic and not require_ground_truth and not _has_topic(reader, gt_topic):
            gt_topic = None
        topics = [source_topic, target_topic] + ([gt_topic] if gt_topic else [])
        roles = {_canonical(source_topic): "source", _canonical(target_topic): "target"}
        clouds, gts, broken = [], {}, []
        for rec in reader.messages(topics):
            if rec.error:
                broken.append(BrokenMessage(rec.topic, rec.stamp_ns or None, rec.error))
                if rec.topic in roles:
                    clouds.append(CloudMessage(roles[rec.topic], rec.topic, rec.msgtype,
                                               rec.log_time_ns, None, "", None, None))
                continue
            if rec.topic not in roles:
                _add_ground_truth(rec, gts, broken)
                continue
            xyz = None
            try:
                xyz = pointcloud2_to_xyz(rec.msg, **kwargs)
            except InvalidInputError as exc:
                broken.append(BrokenMessage(rec.topic, rec.stamp_ns, str(exc)))
            clouds.append(CloudMessage(roles[rec.topic], rec.topic, rec.msgtype, rec.log_time_ns,
                                       rec.stamp_ns, rec.frame_id, rec.msg, xyz))
    return BagContents(Path(path), clouds, gts, broken, gt_topic)


def _canonical(topic: str) -> str:
    return "/" + topic.lstrip("/")


def _has_topic(reader: BagReader, topic: str) -> bool:
    topics = reader.topics
    return topic in topics or _canonical(topic) in topics


def _add_ground_truth(rec: Any, gts: dict[int, np.ndarray], broken: list[BrokenMessage]) -> None:
    try:
        gts[int(rec.stamp_ns)] = pose_to_transform(rec.msg)
    except (AttributeError, TypeError, InvalidInputError) as exc:
        broken.append(BrokenMessage(rec.topic, rec.stamp_ns, f"bad ground truth pose: {exc}"))


# --- configuration ------------------------------------------------------------------------------

def auto_voxel_size(points: np.ndarray, target_points: int = AUTO_VOXEL_POINTS) -> float:
    """Voxel size (metres) at which ``points`` keep about ``target_points`` occupied voxels,
    found by bisection on a log scale and rounded to two significant digits."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) <= target_points:
        raise ReplayError(f"cannot choose a voxel size: the target cloud has only {len(pts)} "
                          "points; pass --voxel-size")
    pts = pts - pts.min(axis=0)
    diag = float(np.linalg.norm(pts.max(axis=0))) or 1.0
    lo, hi = np.log(diag * 1e-5), np.log(diag)
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if _occupied_voxels(pts, np.exp(mid)) > target_points:
            lo = mid
        else:
            hi = mid
    return float(f"{np.exp(0.5 * (lo + hi)):.2g}")


def _occupied_voxels(points: np.ndarray, voxel: float) -> int:
    keys = np.floor(points / voxel).astype(np.int64)
    return len(np.unique(keys, axis=0))


def user_parameters(params_file: str | None, sets: Sequence[str], voxel_size: float | None,
                    pairing: str | None) -> dict[str, Any]:
    """Flat node/pipeline parameters in priority order: YAML < --set < explicit flags."""
    values: dict[str, Any] = {}
    if params_file:
        values.update(configutil.flatten_mapping(load_yaml(params_file)))
    values.update(configutil.parse_key_values(sets))
    if voxel_size is not None:
        values["voxel_size"] = voxel_size
    if pairing is not None:
        values["pairing_mode"] = pairing
    return values


def resolve_configs(values: dict[str, Any], contents: BagContents
                    ) -> tuple[PipelineConfig, NodeConfig, dict[str, Any], str]:
    """Validated configs plus the parameters to hand a node, and how the voxel was chosen."""
    values = dict(values)
    how = "given"
    if "voxel_size" not in values:
        points = contents.first_target_points()
        if points is None:
            raise ReplayError(f"{contents.path} has no decodable target cloud")
        values["voxel_size"] = auto_voxel_size(points)
        how = f"auto: ~{AUTO_VOXEL_POINTS} target points"
    pipe, node = configs_from_parameters(values)
    flat = {**configutil.flatten(pipe), **configutil.flatten(node)}
    return pipe, node, {k: flat[k] for k in values}, how


def iter_pairs(contents: BagContents, pairer: Pairer) -> Iterator[Pair]:
    """Pairs of decodable clouds in the order the node would form them (payload:
    :class:`CloudMessage`). Undecodable clouds are skipped, as the node rejects them;
    ``pairer.counters()`` tells what pairing dropped."""
    for cloud in contents.clouds:
        if cloud.xyz is None:
            continue
        add = pairer.add_source if cloud.role == "source" else pairer.add_target
        add(cloud.stamp_ns, cloud.frame_id, cloud)
        while (pair := pairer.pop()) is not None:
            yield pair


# --- offline replay -------------------------------------------------------------------------

@dataclasses.dataclass
class ReplayOptions:
    bag: Path
    source_topic: str = "/source_cloud"
    target_topic: str = "/target_cloud"
    ground_truth_topic: str | None = DEFAULT_GT_TOPIC
    require_ground_truth: bool = False
    parameters: dict[str, Any] = dataclasses.field(default_factory=dict)
    output: Path | None = None
    pose_topic: str = DEFAULT_POSE_TOPIC
    max_re_deg: float = DEFAULT_MAX_RE_DEG
    max_te: float | None = None
    quiet: bool = False
    # live replay only
    live: bool = False
    rate: float = 1.0
    spawn: bool = True
    node_name: str = "register_node"
    timeout: float = 60.0
    startup_timeout: float = 60.0

    @property
    def out_dir(self) -> Path:
        return self.output or Path("out") / "replay" / self.bag_name

    @property
    def bag_name(self) -> str:
        return self.bag.stem if self.bag.suffix == ".mcap" else self.bag.resolve().name


def start_report(opts: ReplayOptions, contents: BagContents, pipe: PipelineConfig,
                 node: NodeConfig) -> BagReport:
    criteria = SuccessCriteria(opts.max_re_deg, opts.max_te if opts.max_te is not None
                               else DEFAULT_MAX_TE_VOXELS * pipe.voxel_size)
    return BagReport(bag=opts.bag_name, mode="live" if opts.live else "offline",
                     voxel_size=pipe.voxel_size, pairing=node.pairing_mode, criteria=criteria,
                     broken=list(contents.broken))


def replay_offline(opts: ReplayOptions) -> BagReport:
    """Register every pair of the bag in-process; write and return the report."""
    from ..pipeline import register_clouds

    start = time.perf_counter()
    contents = load_contents(opts)
    pipe, node, _, how = resolve_configs(opts.parameters, contents)
    report = start_report(opts, contents, pipe, node)
    report.notes.append(f"voxel size {pipe.voxel_size:g} m ({how})")
    progress = Progress(len(contents.sources), enabled=not opts.quiet)
    pairer = Pairer.from_config(node)  # popped after every message: the queue never fills
    for pair in iter_pairs(contents, pairer):
        src, tgt = pair.source.payload, pair.target.payload
        progress.update(f"source {_stamp_s(src.stamp_ns)}")
        row = make_row(len(report.rows), src, tgt, contents)
        t0 = time.perf_counter()
        try:
            result = register_clouds(src.xyz, tgt.xyz, config=pipe)
        except InvalidInputError as exc:  # the node rejects these pairs too
            row.reason = f"rejected by the pipeline: {exc}"
        else:
            row.valid = bool(result.valid)
            row.reason, row.inliers = result.reason, result.num_inliers
            row.fitness = float(getattr(result, "fitness", float("nan")))
            row.transform = np.asarray(result.transform, dtype=np.float64)
        row.time_s = time.perf_counter() - t0
        report.rows.append(row)
    progress.close()
    note_pairing_drops(report, pairer.counters())
    report.wall_time_s = time.perf_counter() - start
    return finish_report(report, opts, contents)


def load_contents(opts: ReplayOptions) -> BagContents:
    contents = read_bag_contents(opts.bag, opts.source_topic, opts.target_topic,
                                 opts.ground_truth_topic,
                                 require_ground_truth=opts.require_ground_truth)
    if not contents.sources:
        raise ReplayError(f"{opts.bag}: topic {opts.source_topic} has no messages")
    return contents


def make_row(index: int, src: CloudMessage, tgt: CloudMessage | None,
             contents: BagContents) -> PairRow:
    """A row with stamps, frames and ground truth filled in; no estimate yet."""
    return PairRow(index=index, source_stamp_ns=int(src.stamp_ns),
                   target_stamp_ns=None if tgt is None else int(tgt.stamp_ns),
                   source_frame=src.frame_id, target_frame="" if tgt is None else tgt.frame_id,
                   valid=False, ground_truth=contents.ground_truth.get(int(src.stamp_ns)))


def note_pairing_drops(report: BagReport, counters: dict[str, int]) -> None:
    for key, value in counters.items():
        if key.startswith("dropped.") and value:
            report.notes.append(f"pairing dropped {value} message(s): {key[8:]}")


def finish_report(report: BagReport, opts: ReplayOptions, contents: BagContents) -> BagReport:
    """Evaluate against ground truth, write the poses bag and the result files, print."""
    from ..datasets.bag import write_poses_mcap

    for row in report.rows:
        row.evaluate(report.criteria)
    if contents.ground_truth_topic is None:
        report.notes.append("no ground truth topic: RE/TE and recall not computed")
    out = opts.out_dir
    out.mkdir(parents=True, exist_ok=True)
    poses_dir = out / POSES_DIR
    if poses_dir.is_dir() and (poses_dir / "metadata.yaml").exists():
        shutil.rmtree(poses_dir)  # our own output of a previous run
    poses = [(r.source_stamp_ns, r.target_frame, r.transform) for r in report.rows
             if r.valid and r.transform is not None]
    write_poses_mcap(poses_dir, poses, topic=opts.pose_topic)
    report.output_bag = str(poses_dir)
    paths = write_results(report, out)
    if not opts.quiet:
        print_report(report, paths, opts.pose_topic)
    return report


def print_report(report: BagReport, paths: dict[str, Path], pose_topic: str) -> None:
    print(pairs_table(report))
    for b in report.broken:
        stamp = "" if b.stamp_ns is None else f" at {_stamp_s(b.stamp_ns)}"
        print(f"broken message on {b.topic}{stamp}: {b.reason}")
    for note in report.notes:
        print(f"note: {note}")
    print(summary_line(report))
    print(f"wrote {report.output_bag} ({len([r for r in report.rows if r.valid])} poses on "
          f"{pose_topic}), " + ", ".join(str(p) for p in paths.values()))


def _stamp_s(stamp_ns: int | None) -> str:
    return "?" if stamp_ns is None else f"{stamp_ns * 1e-9:.3f} s"


class Progress:
    """A one-line ``\\r`` progress counter, only when stdout is a terminal."""

    def __init__(self, total: int, enabled: bool = True):
        self.total, self.count = total, 0
        self.enabled = enabled and sys.stdout.isatty()

    def update(self, label: str = "") -> None:
        self.count += 1
        if self.enabled:
            print(f"\r[{self.count}/{self.total}] {label:<40}", end="", flush=True)

    def close(self) -> None:
        if self.enabled:
            print("\r" + " " * 60 + "\r", end="", flush=True)


# --- command line -------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0].replace("``", ""),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", type=Path, help="rosbag2 directory or .mcap file")
    p.add_argument("--source-topic", default="/source_cloud",
                   help="PointCloud2 topic of the clouds to align (default: %(default)s)")
    p.add_argument("--target-topic", default="/target_cloud",
                   help="PointCloud2 topic of the reference clouds (default: %(default)s)")
    p.add_argument("--ground-truth-topic", default=None,
                   help=f"PoseStamped source->target, matched to sources by stamp (default: "
                        f"{DEFAULT_GT_TOPIC} when the bag has it; given explicitly, it must exist)")
    p.add_argument("--voxel-size", type=float, default=None,
                   help="metres (default: --set/--params, else chosen from the target cloud)")
    p.add_argument("--params", default=None, help="YAML of node/pipeline parameters "
                   "(ROS format or a plain mapping), e.g. config/register_node.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one parameter (repeatable), e.g. --set core.p1=0.95")
    p.add_argument("--pairing", choices=MODES, default=None,
                   help="how sources meet targets, as the node's pairing_mode (default: "
                   "the parameters', latest_target)")
    p.add_argument("--output", type=Path, default=None, help="default: out/replay/<bag>")
    p.add_argument("--pose-topic", default=DEFAULT_POSE_TOPIC, help="topic in the output bag")
    p.add_argument("--max-re-deg", type=float, default=DEFAULT_MAX_RE_DEG,
                   help="success: rotation error at most this (degrees)")
    p.add_argument("--max-te", type=float, default=None, help="success: translation error at "
                   f"most this (metres; default {DEFAULT_MAX_TE_VOXELS:g} voxel sizes)")
    p.add_argument("--quiet", action="store_true", help="no progress, no tables")
    live = p.add_argument_group("live replay through the ROS node")
    live.add_argument("--live", action="store_true",
                      help="publish the bag over DDS into a register_node and record its ~/pose")
    live.add_argument("--rate", type=float, default=1.0, help="playback speed factor (> 0)")
    live.add_argument("--no-spawn", dest="spawn", action="store_false",
                      help="use a running register_node instead of starting one")
    live.add_argument("--node-name", default="register_node",
                      help="name of the node to start or listen to (default: %(default)s)")
    live.add_argument("--timeout", type=float, default=60.0,
                      help="seconds without progress from the node before giving up")
    live.add_argument("--startup-timeout", type=float, default=60.0,
                      help="seconds to wait for the node's topics")
    return p


def options_from_args(args: argparse.Namespace) -> ReplayOptions:
    if args.rate <= 0:
        raise InvalidConfigError(f"--rate must be > 0, got {args.rate}")
    return ReplayOptions(
        bag=args.bag, source_topic=args.source_topic, target_topic=args.target_topic,
        ground_truth_topic=args.ground_truth_topic or DEFAULT_GT_TOPIC,
        require_ground_truth=args.ground_truth_topic is not None,
        parameters=user_parameters(args.params, args.set, args.voxel_size, args.pairing),
        output=args.output, pose_topic=args.pose_topic, max_re_deg=args.max_re_deg,
        max_te=args.max_te, quiet=args.quiet, live=args.live, rate=args.rate,
        spawn=args.spawn, node_name=args.node_name, timeout=args.timeout,
        startup_timeout=args.startup_timeout)


def run(opts: ReplayOptions) -> BagReport:
    if opts.live:
        from .live_replay import replay_live

        return replay_live(opts)
    return replay_offline(opts)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        run(options_from_args(args))
    except CgagsError as exc:
        message = " ".join(str(exc).split())  # one line, even for multi-line library errors
        print(f"{PROG}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
