"""QoS profiles of the node's subscriptions, from its configuration."""

from __future__ import annotations

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    qos_profile_sensor_data,
    QoSProfile,
    ReliabilityPolicy,
)

from ..config.node import NodeConfig


def source_qos(cfg: NodeConfig) -> QoSProfile:
    """Return the QoS of ``source_cloud``: sensor data (best effort) or reliable."""
    if cfg.pairing.source_qos == 'sensor_data':
        qos = QoSProfile(depth=cfg.pairing.source_depth)
        qos.reliability = qos_profile_sensor_data.reliability
        qos.durability = qos_profile_sensor_data.durability
        qos.history = HistoryPolicy.KEEP_LAST
        return qos
    return QoSProfile(depth=cfg.pairing.source_depth, reliability=ReliabilityPolicy.RELIABLE)


def target_qos(cfg: NodeConfig) -> QoSProfile:
    """
    Return the QoS of ``target_cloud``: reliable, volatile or transient-local.

    In synchronized mode every target is paired with a source, so the history keeps at least
    ``source_depth`` (a second target arriving before the first was taken would otherwise
    replace it, and its source would be dropped for want of a target).
    """
    pairing = cfg.pairing
    transient = pairing.target_durability == 'transient_local'
    durability = DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE
    depth = (pairing.target_depth if pairing.mode == 'latest_target'
             else max(pairing.target_depth, pairing.source_depth))
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE, durability=durability)


def latched_qos() -> QoSProfile:
    """Return the QoS of a one-off result: reliable, transient local, the last one kept."""
    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def result_qos() -> QoSProfile:
    """Return the QoS of ~/result: reliable, so that a replay client misses no source."""
    return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
