"""
Configuration of the ROS node (pairing, map, relocalization, outputs), and its full key set.

ROS-free. The node's configuration keys are the dotted paths of :class:`PipelineConfig`
(``voxel_size``, ``core.gravity``, ``gates.min_fitness``...) and of :class:`NodeConfig`
(``mode``, ``pairing.mode``, ``map.file``...); they share one namespace. The fields declared
``ros=True`` are the node's ROS parameters, under the same names; every key (ROS parameter
or not) may also be set in the YAML file named by ``config_file``. ``config/register_node.yaml``
and docs/parameters.md are generated from these dataclasses (:mod:`cgags_ros.config.files`),
so no default is written twice.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

from . import fields
from .calibration import CalibrationConfig
from .fields import option, section
from .frontend import MAP_TARGET_SENSOR
from .pipeline import load_yaml, PipelineConfig
from ..errors import InvalidConfigError

NODE_NAME = 'register_node'
# Keys of config_file under this prefix configure calibrate mode (CalibrationConfig keys).
CALIBRATION_PREFIX = 'calibration.'


@dataclasses.dataclass
class PairingConfig:
    """The two input topics, their QoS, and how sources meet targets."""

    mode: str = option(
        'latest_target', "How sources meet targets: 'latest_target' pairs each source with "
        "the newest target received (scan-to-map); 'synchronized' pairs source and target "
        'whose header stamps differ by at most sync_slop.',
        choices=('latest_target', 'synchronized'), ros=True, read_only=True)
    sync_slop: float = option(
        0.05, 'synchronized mode: largest |source stamp - target stamp|, seconds.',
        low=0.0, high=3600.0, ros=True)
    queue_depth: int = option(
        1, 'Pairs waiting for the engine thread; when full the oldest pair is dropped '
        '(counted in /diagnostics). 1 gives the lowest latency (a new source waits only '
        'behind the pair in progress); more buffers bursts at the cost of latency.',
        low=1, high=1000, ros=True, read_only=True)
    backlog: int = option(
        20, 'Continuous mode with tracking.enabled: pairs kept while a registration runs, in '
        'place of queue_depth when larger (the oldest dropped beyond). The scans that arrived '
        'during a global registration are then tracked in stamp order, each from its '
        "predecessor's pose, instead of restarting from the newest scan, too far from the "
        'last pose to be tracked.', low=1, high=1000, read_only=True)
    backlog_max_lag: float = option(
        1.0, 'Continuous mode with tracking.enabled: while the newest waiting scan is more than '
        'this (seconds, header stamps) ahead of the oldest and the last scan was tracked, every '
        'other waiting scan within tracking.max_age is dropped (source_skipped_catching_up), so '
        'that the backlog drains; a scan beyond it would go global: the newest is taken. 0 '
        'tracks every scan in order.', low=0.0, high=3600.0)
    max_waiting_sources: int = option(
        1, 'Sources kept while no target (latest_target) or no matching target '
        '(synchronized) has arrived; the oldest is dropped beyond this.', low=1, high=1000,
        read_only=True)
    source_qos: str = option(
        'sensor_data', "QoS of source_cloud: 'sensor_data' (best effort) or 'reliable', "
        'each keeping the last source_depth scans.', choices=('sensor_data', 'reliable'),
        ros=True, read_only=True)
    source_depth: int = option(
        30, 'History depth of the source_cloud subscription: the scans DDS holds until the '
        "node's executor takes them. Scans beyond it are lost before the node sees them "
        '(counted only as sources.lost_upstream), so it covers the longest a loaded machine '
        'keeps the executor from taking one (30: 3 s of a 10-Hz LiDAR); which scans are '
        'registered is for pairing and the queue to decide, and they count what they drop.',
        low=1, high=1000, read_only=True)
    target_durability: str = option(
        'volatile', "Durability of target_cloud: 'transient_local' also receives a "
        'latched map published before the node started, but connects only to '
        "transient-local publishers; 'volatile' connects to every publisher, new messages "
        'only. Reliable either way.', choices=('volatile', 'transient_local'), ros=True,
        read_only=True)
    target_depth: int = option(
        1, 'History depth of the target_cloud subscription (the newest target is the one '
        'used in latest_target mode); synchronized mode keeps at least source_depth, since '
        'every target is paired.', low=1, high=1000, read_only=True)
    max_cloud_points: int = option(
        20_000_000, 'A PointCloud2 claiming more points than this is rejected as malformed.',
        low=1)


@dataclasses.dataclass
class RuntimeConfig:
    """The registration process: where each pair's registration runs, and for how long."""

    registration_timeout: float = option(
        30.0, 'Seconds one registration may take. > 0 runs the pipeline in a child process '
        'that is killed and restarted past this limit (the pair is rejected as '
        "'timeout'), so a pathological cloud cannot stall the node; 0 runs it in the "
        "node's engine thread with no limit.", low=0.0, high=3600.0, ros=True, read_only=True)


@dataclasses.dataclass
class MapConfig:
    """A prior map loaded from a file instead of the target_cloud topic."""

    file: str = option(
        '', 'Prior map (PLY, PCD, NPY, XYZ/CSV/TXT; metres, in map.frame) every source scan '
        "is registered onto; target_cloud is then not subscribed. '' uses the target_cloud "
        'topic as the map (or reference).', ros=True, read_only=True)
    frame: str = option(
        'map', 'Frame of map.file, of ~/candidates and of the initial pose (with map.file; '
        "without it the target cloud's frame is used).", ros=True, read_only=True)
    cache_dir: str = option(
        '~/.cache/cgags_ros/maps', 'Directory of the map feature cache (keyed by the map '
        "file's content and every setting that changes the features); '' disables it.",
        ros=True, read_only=True)
    load_timeout: float = option(
        600.0, 'Seconds loading map.file (features computed or read from the cache) may '
        'take in the registration process before the attempt is abandoned and configure '
        'fails.', low=1.0, high=86400.0, read_only=True)


@dataclasses.dataclass
class RelocalizationConfig:
    """The ~/relocalize requests and the guarded initial pose for Nav2/AMCL."""

    publish_initial_pose: bool = option(
        False, 'Publish the robot base pose on initialpose (geometry_msgs/'
        'PoseWithCovarianceStamped, frame map.frame, for Nav2/AMCL) when every guard '
        '(min_inliers, min_ratio, min_fitness, cooldown, max_auto) passes.', ros=True)
    base_from_sensor: tuple[float, ...] = option(
        (0.0,) * 7, 'Sensor pose in the robot base frame, [x, y, z, qx, qy, qz, qw] (metres, '
        'unit quaternion): p_base = T p_sensor. The initial pose is that of the base: '
        'T_map_base = T_map_sensor inv(T). Seven zeros (the default) take it from TF '
        '(base_frame <- sensor frame) when tf2_ros is importable, else the identity.',
        ros=True)
    min_inliers: int = option(
        20, 'Initial-pose guard: fewest inlier correspondences of the estimate.', low=0)
    min_ratio: float = option(
        2.0, 'Initial-pose guard: smallest best / runner-up candidate inlier ratio (how '
        'clearly the pose beats every distinct alternative).', low=1.0, high=1e6, ros=True)
    min_fitness: float = option(
        0.3, 'Initial-pose guard: smallest fitness (share of scan points with a map point '
        'within the refinement distance).', low=0.0, high=1.0)
    cooldown: float = option(
        5.0, 'Initial-pose guard: seconds between two publishes.', low=0.0, high=86400.0)
    max_auto: int = option(
        1, 'Initial-pose guard: most publishes in continuous mode (each ~/relocalize call '
        'may publish once more); 0 publishes only on ~/relocalize.', low=0)
    base_frame: str = option(
        'base_link', 'Robot base frame (TF lookup of the extrinsic when base_from_sensor is '
        'seven zeros, and of odom -> base for broadcast_map_to_odom).', read_only=True)
    broadcast_map_to_odom: bool = option(
        False, "With each published initial pose, broadcast Nav2's map -> odom on /tf from "
        'it and the odom -> base transform at the scan stamp (needs tf2_ros; without it the '
        'node says so once and broadcasts nothing).')
    odom_frame: str = option('odom', 'Odometry frame of broadcast_map_to_odom.')
    max_scan_age: float = option(
        1.0, 'on_demand mode: a ~/relocalize call uses the latest scan if it was received at '
        'most this many seconds before the call; otherwise it waits for the next scan.',
        low=0.0, high=3600.0)
    timeout: float = option(
        10.0, 'Seconds a ~/relocalize call may take (waiting for a scan and, with odometry, '
        'the scans of a relocalization) before it answers failure.', low=0.1, high=3600.0)
    max_scans: int = option(
        3, 'With map.file and odometry (the odom topic): scans a relocalization takes until '
        'a pose is confirmed over them before it answers failure.', low=1, high=100)

    def check(self) -> None:
        """Refuse a base_from_sensor with a zero quaternion (seven zeros: unset)."""
        if any(self.base_from_sensor) and math.hypot(*self.base_from_sensor[3:]) < 1e-9:
            raise InvalidConfigError(
                'relocalization.base_from_sensor must be [x, y, z, qx, qy, qz, qw] with a '
                f'nonzero quaternion (or seven zeros), got {list(self.base_from_sensor)}')

    @property
    def sensor_pose(self) -> tuple[float, ...] | None:
        """Return base_from_sensor, None while unset (seven zeros)."""
        return self.base_from_sensor if any(self.base_from_sensor) else None


@dataclasses.dataclass
class OutputConfig:
    """What the node publishes besides ~/pose, and how it names frames."""

    pose_frame_id: str = option(
        '', "frame_id of ~/pose; '' uses the target cloud's frame_id.", ros=True)
    publish_invalid: bool = option(
        False, 'Also publish ~/pose and TF for results the pipeline marked invalid.',
        ros=True)
    publish_aligned_cloud: bool = option(
        False, 'Publish the source cloud transformed into the target frame on ~/aligned_cloud '
        '(for RViz).', ros=True)
    broadcast_tf: bool = option(
        False, 'Broadcast the estimate on /tf (parent: target frame, child: tf_child_frame); '
        'needs tf2_ros.', ros=True)
    tf_child_frame: str = option(
        '', "Child frame of the broadcast TF; '' uses the source cloud's frame_id. Set it "
        'when that frame already has a parent in your TF tree.')
    diagnostics_period: float = option(
        1.0, 'Seconds between /diagnostics messages.', low=0.05, high=3600.0, ros=True,
        read_only=True)


@dataclasses.dataclass
class NodeConfig:
    """The node's own options: what it does, its inputs, its runtime, the map and outputs."""

    mode: str = option(
        'continuous', "'continuous' registers every source scan; 'on_demand' registers "
        'nothing until the ~/relocalize service (std_srvs/Trigger) is called, then the '
        'latest scan received within relocalization.max_scan_age, or else the next one; '
        "'calibrate' calibrates target frame <- source frame (source = child sensor, "
        'target = parent) from synchronized pairs: docs/calibration.md.',
        choices=('continuous', 'on_demand', 'calibrate'), ros=True, read_only=True)
    autostart: bool = option(
        True, 'Configure and activate the lifecycle node at start-up, so that it runs alone '
        '(ros2 run); a failed configure (e.g. an unusable map.file) leaves it unconfigured, '
        'still running. false leaves it unconfigured for a lifecycle manager '
        '(nav2_lifecycle_manager) to drive.', ros=True, read_only=True)
    config_file: str = option(
        '', 'YAML of configuration keys (the format of --params-file and of cgags-register '
        '--config: flat or nested keys, docs/parameters.md), read at start-up: its values '
        "replace the defaults, and ROS parameters given to the node replace its values. '' "
        'reads none.', ros=True, read_only=True)
    pairing: PairingConfig = section(PairingConfig)
    runtime: RuntimeConfig = section(RuntimeConfig)
    map: MapConfig = section(MapConfig)  # noqa: A003 - the ROS parameters map.*
    relocalization: RelocalizationConfig = section(RelocalizationConfig)
    output: OutputConfig = section(OutputConfig)


def check_no_collisions() -> None:
    """Node and pipeline keys share one parameter namespace; they must not overlap."""
    node = {f.name for f in dataclasses.fields(NodeConfig)}
    both = node & {f.name for f in dataclasses.fields(PipelineConfig)}
    if both:
        raise InvalidConfigError(f'keys in both NodeConfig and PipelineConfig: {sorted(both)}')


def parameter_descriptions() -> dict[str, dict[str, Any]]:
    """Flat ``{key: {description, low, high, choices, default, ros, read_only...}}``."""
    check_no_collisions()
    return {**fields.describe(PipelineConfig), **fields.describe(NodeConfig)}


def ros_parameter_descriptions() -> dict[str, dict[str, Any]]:
    """Return the descriptions of the keys that are ROS parameters, pipeline keys first."""
    return {k: meta for k, meta in parameter_descriptions().items() if meta['ros']}


def split_parameters(values: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """Split flat (or nested) keys into (pipeline keys, node keys) by their first part."""
    node_sections = {f.name for f in dataclasses.fields(NodeConfig)}
    pipe, node = {}, {}
    for key, value in fields.flatten_mapping(values).items():
        (node if key.split('.')[0] in node_sections else pipe)[key] = value
    return pipe, node


def configs_from_parameters(values: Mapping[str, Any], *,
                            base: tuple[PipelineConfig, NodeConfig] | None = None
                            ) -> tuple[PipelineConfig, NodeConfig]:
    """
    Return a validated (PipelineConfig, NodeConfig) from flat or nested keys.

    The keys are applied over ``base`` (the defaults when None). Raises InvalidConfigError
    with the offending key (an unknown one too).
    """
    pipe_base, node_base = base or (PipelineConfig(), NodeConfig())
    pipe, node = split_parameters(values)
    pipe_cfg = fields.update_from_flat(pipe_base, pipe)
    node_cfg = fields.update_from_flat(node_base, node)
    if node_cfg.mode == 'calibrate' and node_cfg.map.file:
        raise InvalidConfigError('mode calibrate takes two live sensors (source_cloud = child, '
                                 'target_cloud = parent); map.file must be empty')
    if node_cfg.map.file and pipe_cfg.frontend.target_sensor is not None:
        raise InvalidConfigError(MAP_TARGET_SENSOR)
    return pipe_cfg, node_cfg


def config_file_keys(path: str) -> dict[str, Any]:
    """Return the flat keys of the YAML ``path`` ({} for ''), ``calibration.*`` ones included."""
    return fields.flatten_mapping(load_yaml(path)) if path else {}


def configs_from_file(path: str) -> tuple[PipelineConfig, NodeConfig]:
    """Return the defaults with the keys of ``config_file`` applied (calibration keys aside)."""
    keys = config_file_keys(path)
    return configs_from_parameters(
        {k: v for k, v in keys.items() if not k.startswith(CALIBRATION_PREFIX)})


def pipeline_from_keys(values: Mapping[str, Any]) -> PipelineConfig:
    """
    Return the PipelineConfig of keys in the node's format (what ``--config`` reads).

    The node's own keys are checked, then left out; so are the ``calibration.`` ones.
    """
    return configs_from_parameters(
        {k: v for k, v in fields.flatten_mapping(values).items()
         if not k.startswith(CALIBRATION_PREFIX)})[0]


def calibration_from_keys(values: Mapping[str, Any],
                          pipeline: PipelineConfig | None = None) -> CalibrationConfig:
    """
    Return the :class:`CalibrationConfig` of keys in the node's format.

    The pipeline keys are at the top level (``voxel_size``), applied over ``pipeline`` (the
    calibration's default pipeline when None); the calibration keys are under
    ``calibration.`` (``calibration.max_frames: 5``); a ``calibration.pipeline.*`` key is
    refused, as the top-level keys set the pipeline.
    """
    flat = fields.flatten_mapping(values)
    keys = {k[len(CALIBRATION_PREFIX):]: v for k, v in flat.items()
            if k.startswith(CALIBRATION_PREFIX)}
    nested = sorted(k for k in keys if k.startswith('pipeline.'))
    if nested:
        raise InvalidConfigError(f'calibration.{nested[0]}: set the pipeline keys at the top '
                                 'level (the node and the calibration share them)')
    rest = {k: v for k, v in flat.items() if not k.startswith(CALIBRATION_PREFIX)}
    pipe, _ = configs_from_parameters(
        rest, base=(pipeline or CalibrationConfig().pipeline, NodeConfig()))
    return fields.update_from_flat(CalibrationConfig(pipeline=pipe), keys)


def calibration_config(pipeline: PipelineConfig, config_file: str) -> CalibrationConfig:
    """
    Return the :class:`CalibrationConfig` of calibrate mode.

    Its pipeline is the node's (``voxel_size`` and every pipeline key); the other
    calibration keys come from ``config_file`` under ``calibration.``
    (:func:`calibration_from_keys`).
    """
    keys = {k: v for k, v in config_file_keys(config_file).items()
            if k.startswith(CALIBRATION_PREFIX)}
    try:
        return calibration_from_keys(keys, pipeline)
    except InvalidConfigError as exc:
        raise InvalidConfigError(f'config_file {config_file}: {exc}') from None


def ros_value(value: Any) -> Any:
    """Return a configuration value as a ROS parameter value (a vector as a new list)."""
    return list(value) if isinstance(value, (tuple, list)) else value
