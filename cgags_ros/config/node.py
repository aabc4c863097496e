"""
Configuration of the ROS node (pairing, QoS, outputs), and the node's full parameter set.

ROS-free. The node's ROS parameters are the flattened keys of :class:`PipelineConfig`
(``voxel_size``, ``core.p1``, ``frontend.fpfh_radius_factor``...) plus those of
:class:`NodeConfig` (``pairing_mode``, ``sync_slop``...); ``config/register_node.yaml`` is
generated from the same dataclasses (:mod:`cgags_ros.config.files`), so no default is
written twice.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

from . import fields
from .core import CoreConfig
from .fields import option
from .pipeline import PipelineConfig
from ..errors import InvalidConfigError

NODE_NAME = 'register_node'


@dataclasses.dataclass
class NodeConfig:
    """The node's own options: pairing, QoS, the registration worker and outputs."""

    autostart: bool = option(
        True, 'Configure and activate the lifecycle node at start-up, so that it runs alone '
        '(ros2 run); a failed configure (e.g. an unusable map_file) leaves it unconfigured, '
        'still running. false leaves it unconfigured for a lifecycle manager '
        '(nav2_lifecycle_manager) to drive.')
    config_file: str = option(
        '', 'YAML of further configuration keys (the format of cgags-register --config: the '
        'research switches of the method and rarely changed node options, '
        'docs/parameters.md), applied under the ROS parameters; none of its keys may be a '
        "ROS parameter's. '' sets none.")
    pairing_mode: str = option(
        'latest_target', "How sources meet targets: 'latest_target' pairs each source with "
        "the newest target received (scan-to-map); 'synchronized' pairs source and target "
        'whose header stamps differ by at most sync_slop.',
        choices=('latest_target', 'synchronized'))
    sync_slop: float = option(
        0.05, 'synchronized mode: largest |source stamp - target stamp|, seconds.',
        low=0.0, high=3600.0)
    queue_depth: int = option(
        1, 'Pairs waiting for the registration worker; when full the oldest pair is dropped '
        '(counted in /diagnostics). 1 gives the lowest latency (a new source waits only '
        'behind the pair in progress); more buffers bursts at the cost of latency.',
        low=1, high=1000)
    backlog: int = option(
        20, 'Continuous mode with tracking.enabled: pairs kept while a registration runs, in '
        'place of queue_depth when larger (the oldest dropped beyond). The scans that arrived '
        'during a global registration are then tracked in stamp order, each from its '
        "predecessor's pose, instead of restarting from the newest scan, too far from the "
        'last pose to be tracked.', low=1, high=1000)
    backlog_max_lag: float = option(
        1.0, 'Continuous mode with tracking.enabled: while the newest waiting scan is more than '
        'this (seconds, header stamps) ahead of the oldest and the last scan was tracked, every '
        'other waiting scan within tracking.max_age is dropped (source_skipped_catching_up), so '
        'that the backlog drains; a scan beyond it would go global: the newest is taken. 0 '
        'tracks every scan in order.',
        low=0.0, high=3600.0)
    max_waiting_sources: int = option(
        1, 'Sources kept while no target (latest_target) or no matching target '
        '(synchronized) has arrived; the oldest is dropped beyond this.', low=1, high=1000)
    max_waiting_targets: int = option(
        10, 'synchronized mode: unmatched targets kept; the oldest is dropped beyond this.',
        low=1, high=1000)
    source_qos: str = option(
        'sensor_data', "QoS of source_cloud: 'sensor_data' (best effort, keep last 5) or "
        "'reliable' (keep last source_depth).", choices=('sensor_data', 'reliable'))
    source_depth: int = option(5, 'History depth of the source_cloud subscription.',
                               low=1, high=1000)
    target_durability: str = option(
        'volatile', "Durability of target_cloud: 'transient_local' also receives a "
        'latched map published before the node started, but connects only to '
        "transient-local publishers; 'volatile' connects to every publisher, new messages "
        'only. Reliable either way.', choices=('volatile', 'transient_local'))
    target_depth: int = option(1, 'History depth of the target_cloud subscription.',
                               low=1, high=1000)
    registration_timeout: float = option(
        30.0, 'Seconds one registration may take. > 0 runs the pipeline in a child process '
        'that is killed and restarted past this limit (the pair is rejected as '
        "'timeout'), so a pathological cloud cannot stall the node; 0 runs it in the "
        "node's worker thread with no limit.", low=0.0, high=3600.0)
    max_cloud_points: int = option(
        20_000_000, 'A PointCloud2 claiming more points than this is rejected as malformed.',
        low=1)
    publish_invalid: bool = option(
        False, 'Also publish ~/pose and TF for results the pipeline marked invalid.')
    publish_aligned_cloud: bool = option(
        False, 'Publish the source cloud transformed into the target frame on ~/aligned_cloud '
        '(for RViz).')
    broadcast_tf: bool = option(
        False, 'Broadcast the estimate on /tf (parent: target frame, child: tf_child_frame); '
        'needs tf2_ros.')
    pose_frame_id: str = option(
        '', "frame_id of ~/pose; '' uses the target cloud's frame_id.")
    tf_child_frame: str = option(
        '', "Child frame of the broadcast TF; '' uses the source cloud's frame_id. Set it "
        'when that frame already has a parent in your TF tree.')
    diagnostics_period: float = option(
        1.0, 'Seconds between /diagnostics messages.', low=0.05, high=3600.0)
    mode: str = option(
        'continuous', "'continuous' registers every source scan; 'on_demand' registers "
        'nothing until the ~/relocalize service (std_srvs/Trigger) is called, then the '
        "latest scan received within max_scan_age, or else the next one; 'calibrate' "
        'calibrates target frame <- source frame (source = child sensor, target = parent) '
        'from synchronized pairs: docs/calibration.md.',
        choices=('continuous', 'on_demand', 'calibrate'))
    map_file: str = option(
        '', 'Prior map (PLY, PCD, NPY, XYZ/CSV/TXT; metres, in map_frame) every source scan '
        "is registered onto; target_cloud is then not subscribed. '' uses the target_cloud "
        'topic as the map (or reference).')
    map_frame: str = option(
        'map', 'Frame of map_file, of ~/candidates and of the initial pose (with map_file; '
        "without it the target cloud's frame is used).")
    map_cache_dir: str = option(
        '~/.cache/cgags_ros/maps', 'Directory of the map feature cache (keyed by the map '
        "file's content and every setting that changes the features); '' disables it.")
    map_load_timeout: float = option(
        600.0, 'Seconds loading map_file (features computed or read from the cache) may '
        'take in the registration process before the attempt is abandoned and configure '
        'fails.', low=1.0, high=86400.0)
    max_scan_age: float = option(
        1.0, 'on_demand mode: a ~/relocalize call uses the latest scan if it was received at '
        'most this many seconds before the call; otherwise it waits for the next scan.',
        low=0.0, high=3600.0)
    relocalize_timeout: float = option(
        10.0, 'on_demand mode: seconds a ~/relocalize call waits for a scan before it '
        'answers failure.', low=0.1, high=3600.0)
    publish_initial_pose: bool = option(
        False, 'Publish the robot base pose on initialpose (geometry_msgs/'
        'PoseWithCovarianceStamped, frame map_frame, for Nav2/AMCL) when every initial_pose_* '
        'guard passes.')
    initial_pose_min_inliers: int = option(
        20, 'Initial-pose guard: fewest inlier correspondences of the estimate.', low=0)
    initial_pose_min_ratio: float = option(
        2.0, 'Initial-pose guard: smallest best / runner-up candidate inlier ratio (how '
        'clearly the pose beats every distinct alternative).', low=1.0, high=1e6)
    initial_pose_min_fitness: float = option(
        0.3, 'Initial-pose guard: smallest fitness (share of scan points with a map point '
        'within the refinement distance).', low=0.0, high=1.0)
    initial_pose_cooldown: float = option(
        5.0, 'Initial-pose guard: seconds between two publishes.', low=0.0, high=86400.0)
    initial_pose_max_auto: int = option(
        1, 'Initial-pose guard: most publishes in continuous mode (each ~/relocalize call '
        'may publish once more); 0 publishes only on ~/relocalize.', low=0)
    base_from_sensor: str = option(
        '', "Sensor pose in the robot base frame, 'x y z qx qy qz qw' (metres, unit "
        'quaternion): p_base = T p_sensor. The initial pose is that of the base: '
        "T_map_base = T_map_sensor inv(T). '' takes it from TF (base_frame <- sensor frame) "
        'when tf2_ros is importable, else the identity (sensor = base).')
    base_frame: str = option(
        'base_link', 'Robot base frame (TF lookup of the extrinsic when base_from_sensor is '
        "'', and of odom -> base for broadcast_map_to_odom).")
    broadcast_map_to_odom: bool = option(
        False, "With each published initial pose, broadcast Nav2's map -> odom on /tf from "
        'it and the odom -> base transform at the scan stamp (needs tf2_ros; without it the '
        'node says so once and broadcasts nothing).')
    odom_frame: str = option('odom', 'Odometry frame of broadcast_map_to_odom.')

    def check(self) -> None:
        """Validate the values that need more than a range (base_from_sensor)."""
        parse_pose7(self.base_from_sensor)


def parse_pose7(text: str) -> tuple[float, ...] | None:
    """
    Parse 'x y z qx qy qz qw' (spaces or commas) into seven floats (None for '').

    :raises InvalidConfigError: for anything but seven finite numbers with a nonzero
        quaternion.
    """
    if not text.strip():
        return None
    try:
        values = tuple(float(v) for v in text.replace(',', ' ').split())
    except ValueError:
        values = ()
    if (len(values) != 7 or not all(math.isfinite(v) for v in values)
            or math.hypot(*values[3:]) < 1e-9):
        raise InvalidConfigError(f"base_from_sensor must be 'x y z qx qy qz qw' (seven "
                                 f'numbers, a nonzero quaternion), got {text!r}')
    return values


# Parameters that shape subscriptions or the pairing queue: fixed once the node runs.
READ_ONLY = frozenset({
    'autostart', 'config_file',
    'pairing_mode', 'queue_depth', 'backlog', 'max_waiting_sources', 'max_waiting_targets',
    'source_qos', 'source_depth', 'target_durability', 'target_depth',
    'diagnostics_period', 'registration_timeout', 'mode', 'map_file', 'map_frame',
    'map_cache_dir', 'map_load_timeout', 'base_frame',
})


def check_no_collisions() -> None:
    """Node and pipeline keys share one parameter namespace; they must not overlap."""
    both = set(fields.flatten(NodeConfig())) & set(fields.flatten(PipelineConfig()))
    if both:
        raise InvalidConfigError(f'keys in both NodeConfig and PipelineConfig: {sorted(both)}')


def default_parameters() -> dict[str, Any]:
    """Flat ``{parameter name: default}`` of the whole node, pipeline keys first."""
    check_no_collisions()
    return {**fields.flatten(PipelineConfig()), **fields.flatten(NodeConfig())}


def parameter_descriptions() -> dict[str, dict[str, Any]]:
    """Flat ``{name: {description, low, high, choices, default, read_only}}``."""
    check_no_collisions()
    out = {**fields.describe(PipelineConfig), **fields.describe(NodeConfig)}
    for name, meta in out.items():
        meta['read_only'] = name in READ_ONLY
    return out


def split_parameters(values: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """Split flat parameters into (pipeline keys, node keys); unknown keys raise."""
    node_keys = set(fields.flatten(NodeConfig()))
    pipeline_keys = set(fields.flatten(PipelineConfig()))
    pipe, node = {}, {}
    for key, value in values.items():
        if key in node_keys:
            node[key] = value
        elif key in pipeline_keys:
            pipe[key] = value
        elif key.startswith('core.') and key[5:] in CoreConfig.REMOVED:
            raise InvalidConfigError(f'parameter {key!r} was {CoreConfig.REMOVED[key[5:]]}')
        else:
            raise InvalidConfigError(f'unknown parameter {key!r}')
    return pipe, node


def configs_from_parameters(values: Mapping[str, Any], *,
                            base: tuple[PipelineConfig, NodeConfig] | None = None
                            ) -> tuple[PipelineConfig, NodeConfig]:
    """
    Return a validated (PipelineConfig, NodeConfig) from flat parameters.

    The parameters are applied over ``base`` (the defaults when None). Raises
    InvalidConfigError with the offending key.
    """
    pipe_base, node_base = base or (PipelineConfig(), NodeConfig())
    pipe, node = split_parameters(values)
    return (fields.update_from_flat(pipe_base, pipe),
            fields.update_from_flat(node_base, node))
