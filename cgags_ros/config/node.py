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
from typing import Any, Mapping

from . import fields
from .fields import option
from .pipeline import PipelineConfig
from ..errors import InvalidConfigError

NODE_NAME = 'register_node'


@dataclasses.dataclass
class NodeConfig:
    """The node's own options: pairing, QoS, the registration worker and outputs."""

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


# Parameters that shape subscriptions or the pairing queue: fixed once the node runs.
READ_ONLY = frozenset({
    'pairing_mode', 'queue_depth', 'max_waiting_sources', 'max_waiting_targets',
    'source_qos', 'source_depth', 'target_durability', 'target_depth',
    'diagnostics_period', 'registration_timeout',
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
