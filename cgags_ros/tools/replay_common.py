"""
What offline and live replay share: the bag's contents, configuration, pairing, report.

:func:`read_bag_contents` decodes the bag (:mod:`cgags_ros.io.bag`,
:mod:`cgags_ros.io.pointcloud2`); :func:`resolve_configs` applies the user's parameters
(or :func:`auto_voxel_size`; with a map, :func:`map_voxel_size`); :func:`iter_pairs` forms
pairs with the node's own :class:`~cgags_ros.engine.pairing.Pairer`; :func:`finish_report`
evaluates against the ground truth and writes the poses bag and result files.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
import shutil
from typing import Any, Iterator, Sequence

import numpy as np

from .report import (BagReport, BrokenMessage, PairRow, pairs_table, SuccessCriteria,
                     summary_line, write_results)
from ..config import fields
from ..config.node import config_file_keys, configs_from_parameters, NodeConfig, ros_value
from ..config.pipeline import load_yaml, PipelineConfig
from ..engine.pairing import Pair, Pairer
from ..errors import CgagsError, InvalidInputError
from ..geometry import voxel_size_for
from ..io.bag import BagReader, BagRecord, write_poses_mcap
from ..io.pointcloud2 import pointcloud2_to_xyz, pose_to_transform
from ..refusal import Refusal, RefusalCode

DEFAULT_POSE_TOPIC = '/cgags/pose'
DEFAULT_GT_TOPIC = '/ground_truth'
POSES_DIR = 'poses'
AUTO_VOXEL_POINTS = 5000
MAP_SCAN_VOXELS = 2000  # voxels a scan keeps at the voxel chosen for a map (docs/map_voxel.md)
MAP_SCANS = 5  # scans whose median voxel is a map's
DEFAULT_MAX_RE_DEG = 5.0
DEFAULT_MAX_TE_VOXELS = 3.0


class ReplayError(CgagsError):
    """The replay cannot run (no clouds in the bag, the node did not start, ...)."""


# --- bag contents ------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class CloudMessage(BagRecord):
    """
    A source or target PointCloud2 of the bag: its record, role and decoded points.

    ``xyz`` is (N, 3) metres in ``frame_id``, or None when the message could not be decoded
    (then it is also in ``broken``); ``msg`` is None when it could not be deserialized.
    """

    role: str = 'source'  # 'source' | 'target'
    xyz: np.ndarray | None = None

    @classmethod
    def of(cls, rec: BagRecord, role: str, xyz: np.ndarray | None = None) -> 'CloudMessage':
        """Return the cloud of a record (a broken record keeps no stamp, frame or msg)."""
        if rec.error:
            return cls(rec.topic, rec.msgtype, rec.log_time_ns, None, '', None, rec.error, role)
        return cls(rec.topic, rec.msgtype, rec.log_time_ns, rec.stamp_ns, rec.frame_id,
                   rec.msg, rec.error, role, xyz)


@dataclasses.dataclass
class BagContents:
    """
    What a replay reads from a bag.

    Clouds in log-time order, ground truth by source stamp (4x4 source->target), and the
    broken messages that were skipped.
    """

    path: Path
    clouds: list[CloudMessage]
    ground_truth: dict[int, np.ndarray]
    broken: list[BrokenMessage]
    ground_truth_topic: str | None

    @property
    def sources(self) -> list[CloudMessage]:
        return [c for c in self.clouds if c.role == 'source']

    def first_target_points(self) -> np.ndarray | None:
        return next((c.xyz for c in self.clouds if c.role == 'target' and c.xyz is not None), None)


def read_bag_contents(path: str | Path, source_topic: str, target_topic: str,
                      ground_truth_topic: str | None, *,
                      require_ground_truth: bool = False,
                      max_points: int | None = None) -> BagContents:
    """
    Read and decode the clouds (and ground truth) of a bag.

    ``ground_truth_topic`` is used when the bag has it; a missing one raises
    BagTopicError only with ``require_ground_truth``. Raises BagError / BagTopicError for a
    bad path or a missing cloud topic.
    """
    kwargs = {} if max_points is None else {'max_points': max_points}
    with BagReader(path) as reader:
        gt_topic = ground_truth_topic
        if gt_topic and not require_ground_truth and not _has_topic(reader, gt_topic):
            gt_topic = None
        topics = [source_topic, target_topic] + ([gt_topic] if gt_topic else [])
        roles = {_canonical(source_topic): 'source', _canonical(target_topic): 'target'}
        clouds, gts, broken = [], {}, []
        for rec in reader.messages(topics):
            if rec.error:
                broken.append(BrokenMessage(rec.topic, rec.stamp_ns or None, rec.error))
                if rec.topic in roles:
                    clouds.append(CloudMessage.of(rec, roles[rec.topic]))
                continue
            if rec.topic not in roles:
                _add_ground_truth(rec, gts, broken)
                continue
            xyz = None
            try:
                xyz = pointcloud2_to_xyz(rec.msg, **kwargs)
            except InvalidInputError as exc:
                broken.append(BrokenMessage(rec.topic, rec.stamp_ns, str(exc)))
            clouds.append(CloudMessage.of(rec, roles[rec.topic], xyz))
    return BagContents(Path(path), clouds, gts, broken, gt_topic)


def _canonical(topic: str) -> str:
    return '/' + topic.lstrip('/')


def _has_topic(reader: BagReader, topic: str) -> bool:
    topics = reader.topics
    return topic in topics or _canonical(topic) in topics


def _add_ground_truth(rec: Any, gts: dict[int, np.ndarray], broken: list[BrokenMessage]) -> None:
    try:
        gts[int(rec.stamp_ns)] = pose_to_transform(rec.msg)
    except (AttributeError, TypeError, InvalidInputError) as exc:
        broken.append(BrokenMessage(rec.topic, rec.stamp_ns, f'bad ground truth pose: {exc}'))


def auto_voxel_size(points: np.ndarray, target_points: int = AUTO_VOXEL_POINTS) -> float:
    """Choose a voxel size (metres) that leaves ``points`` about ``target_points`` voxels."""
    try:
        return voxel_size_for(points, target_points)
    except InvalidInputError as exc:
        raise ReplayError(f'cannot choose a voxel size for the target cloud: {exc}; pass '
                          '--voxel-size') from exc


def map_voxel_size(scans: Sequence[np.ndarray], voxels: int = MAP_SCAN_VOXELS) -> float:
    """
    Choose the voxel size (metres) for a map target from the scans that will query it.

    The median over ``scans`` of the voxel that leaves each about ``voxels`` voxels: a map
    wants the voxel of its scans' scale, not of its own (a map is many scans across).
    """
    try:
        return float(f'{np.median([voxel_size_for(scan, voxels) for scan in scans]):.2g}')
    except InvalidInputError as exc:
        raise ReplayError(f'cannot choose a voxel size for the map from the scans: {exc}; '
                          'pass --voxel-size') from exc


def user_parameters(config_file: str | None, sets: Sequence[str], voxel_size: float | None,
                    pairing: str | None) -> dict[str, Any]:
    """Merge the node/pipeline parameters in priority order: YAML < --set < explicit flags."""
    values: dict[str, Any] = {}
    if config_file:
        values.update(config_keys(config_file))
    values.update(fields.parse_key_values(sets))
    if voxel_size is not None:
        values['voxel_size'] = voxel_size
    if pairing is not None:
        values['pairing.mode'] = pairing
    return values


def config_keys(path: str | Path) -> dict[str, Any]:
    """
    Return the flat keys of a ``--config`` file, read as the node reads a parameters file.

    A ``config_file`` it names is read first and the file's own keys replace its values, so
    a ``params.yaml`` whose keys that are no ROS parameters sit in its ``config_file`` (as
    ``cgags-tune`` writes them) configures a replay as it configures the node.
    """
    values = fields.flatten_mapping(load_yaml(path))
    named = values.pop('config_file', '')
    return {**config_file_keys(named), **values} if named else values


def resolve_configs(values: dict[str, Any], contents: BagContents, map_target: bool = False
                    ) -> tuple[PipelineConfig, NodeConfig, dict[str, Any], str]:
    """
    Validate the configs, choosing the voxel size when it is not given.

    ``map_target``: the sources are registered onto a map, whose voxel the first
    ``MAP_SCANS`` source scans choose (:func:`map_voxel_size`); else the first target does.

    :returns: the pipeline and node configs, the parameters to hand a node, and how the
        voxel size was chosen.
    """
    values = dict(values)
    how = 'given'
    if 'voxel_size' not in values and map_target:
        scans = [c.xyz for c in contents.sources if c.xyz is not None][:MAP_SCANS]
        if not scans:
            raise ReplayError(f'{contents.path} has no decodable source cloud')
        values['voxel_size'] = map_voxel_size(scans)
        how = f'auto for a map: ~{MAP_SCAN_VOXELS} voxels a source scan, {len(scans)} scans'
    elif 'voxel_size' not in values:
        points = contents.first_target_points()
        if points is None:
            raise ReplayError(f'{contents.path} has no decodable target cloud')
        values['voxel_size'] = auto_voxel_size(points)
        how = f'auto: ~{AUTO_VOXEL_POINTS} target points'
    pipe, node = configs_from_parameters(values)
    flat = {**fields.flatten(pipe), **fields.flatten(node)}
    return pipe, node, {k: ros_value(flat[k]) for k in values}, how


def iter_pairs(contents: BagContents, pairer: Pairer) -> Iterator[Pair]:
    """
    Yield the pairs of decodable clouds in the order the node would form them.

    Payloads are :class:`CloudMessage`. Undecodable clouds are skipped, as the node
    rejects them; ``pairer.counters()`` tells what pairing dropped.
    """
    for cloud in contents.clouds:
        if cloud.xyz is None:
            continue
        add = pairer.add_source if cloud.role == 'source' else pairer.add_target
        add(cloud.stamp_ns, cloud.frame_id, cloud)
        while (pair := pairer.pop()) is not None:
            yield pair


@dataclasses.dataclass
class ReplayOptions:
    """What to replay and where the results go (offline and live alike)."""

    bag: Path
    source_topic: str = '/source_cloud'
    target_topic: str = '/target_cloud'
    ground_truth_topic: str | None = DEFAULT_GT_TOPIC
    require_ground_truth: bool = False
    parameters: dict[str, Any] = dataclasses.field(default_factory=dict)
    output: Path | None = None
    pose_topic: str = DEFAULT_POSE_TOPIC
    max_re_deg: float = DEFAULT_MAX_RE_DEG
    max_te: float | None = None
    quiet: bool = False
    map_file: Path | None = None
    map_cache_dir: str = ''

    @property
    def out_dir(self) -> Path:
        """Return the output folder (``out/replay/<bag>`` unless given)."""
        return self.output or Path('out') / 'replay' / self.bag_name

    @property
    def bag_name(self) -> str:
        """Return the bag's name (its folder, or the .mcap file's stem)."""
        return self.bag.stem if self.bag.suffix == '.mcap' else self.bag.resolve().name


@dataclasses.dataclass
class LiveOptions:
    """Live replay only: playback rate, whether to start the node, and time limits (s)."""

    rate: float = 1.0
    spawn: bool = True
    node_name: str = 'register_node'
    timeout: float = 60.0
    startup_timeout: float = 60.0


def start_report(opts: ReplayOptions, contents: BagContents, pipe: PipelineConfig,
                 node: NodeConfig, mode: str) -> BagReport:
    """Return an empty report with the success criteria of ``opts`` (mode: offline/live)."""
    criteria = SuccessCriteria(opts.max_re_deg, opts.max_te if opts.max_te is not None
                               else DEFAULT_MAX_TE_VOXELS * pipe.voxel_size)
    return BagReport(bag=opts.bag_name, mode=mode,
                     voxel_size=pipe.voxel_size, pairing=node.pairing.mode, criteria=criteria,
                     broken=list(contents.broken))


def load_contents(opts: ReplayOptions) -> BagContents:
    """Read the bag of ``opts``; ReplayError when its source topic is empty."""
    contents = read_bag_contents(opts.bag, opts.source_topic, opts.target_topic,
                                 opts.ground_truth_topic,
                                 require_ground_truth=opts.require_ground_truth)
    if not contents.sources:
        raise ReplayError(f'{opts.bag}: topic {opts.source_topic} has no messages')
    return contents


def make_row(index: int, src: CloudMessage, tgt: CloudMessage | None,
             contents: BagContents) -> PairRow:
    """Start a row with stamps, frames and ground truth filled in; no estimate yet."""
    return PairRow(index=index, source_stamp_ns=int(src.stamp_ns),
                   target_stamp_ns=None if tgt is None else int(tgt.stamp_ns),
                   source_frame=src.frame_id, target_frame='' if tgt is None else tgt.frame_id,
                   valid=False, ground_truth=contents.ground_truth.get(int(src.stamp_ns)))


def fill_from_result(row: PairRow, result: dict[str, Any]) -> Refusal | None:
    """
    Copy what a node's ``~/result`` says of a pair into ``row``; return the refusal it gives.

    Inliers, fitness, path and pipeline seconds; the refusal is None when the result has none
    (or ``result`` is empty: no result came).
    """
    row.inliers, row.fitness = result.get('num_inliers'), result.get('fitness')
    row.path = result.get('path')
    row.time_s = result.get('timings', {}).get('total')
    said = result.get('refusal')
    return Refusal(RefusalCode(said['code']), said['message']) if said else None


def note_pairing_drops(report: BagReport, pairer: Pairer) -> None:
    """Add a note per reason for which pairing dropped messages."""
    for reason, value in sorted(pairer.drops.items()):
        if value:
            report.notes.append(f'pairing dropped {value} message(s): {reason}')


def finish_report(report: BagReport, opts: ReplayOptions, contents: BagContents) -> BagReport:
    """Evaluate against ground truth, write the poses bag and the result files, print."""
    for row in report.rows:
        row.evaluate(report.criteria)
    if contents.ground_truth_topic is None:
        report.notes.append('no ground truth topic: RE/TE and recall not computed')
    out = opts.out_dir
    out.mkdir(parents=True, exist_ok=True)
    poses_dir = out / POSES_DIR
    if poses_dir.is_dir() and (poses_dir / 'metadata.yaml').exists():
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
    """Print the pairs table, broken messages, notes and the summary line."""
    print(pairs_table(report))
    for b in report.broken:
        stamp = '' if b.stamp_ns is None else f' at {stamp_s(b.stamp_ns)}'
        print(f'broken message on {b.topic}{stamp}: {b.reason}')
    for note in report.notes:
        print(f'note: {note}')
    print(summary_line(report))
    print(f'wrote {report.output_bag} ({len([r for r in report.rows if r.valid])} poses on '
          f'{pose_topic}), ' + ', '.join(str(p) for p in paths.values()))


def stamp_s(stamp_ns: int | None) -> str:
    """Format a stamp in seconds ("?" when unknown)."""
    return '?' if stamp_ns is None else f'{stamp_ns * 1e-9:.3f} s'
