"""
Configuration of the temporal prior: a stream's next scan refined from its last pose.

Used by :class:`cgags_ros.tracking.Tracker`, which a stream's caller (the node in
continuous mode, ``cgags-replay``) holds per source/target pair; ``register_clouds`` never
reads it. Lengths are in voxel sizes, so that one number tunes them as every other radius.
"""

from __future__ import annotations

import dataclasses

from .fields import option


@dataclasses.dataclass
class TrackingConfig:
    """When a scan is refined from the predicted pose instead of searched for globally."""

    enabled: bool = option(
        True, 'Continuous mode (the node, cgags-replay): refine each scan from the pose '
        "predicted from the pair's last valid poses (constant velocity, or the odometry given) "
        'and keep it when it passes the same gates as a global result; else, and for the first '
        'scan, run the global search. false registers every scan globally.', ros=True)
    max_age: float = option(
        0.5, 'Seconds (header stamps) since the last valid pose of the same pair beyond which '
        'no prediction is made (the scan is registered globally).', low=0.0, high=3600.0)
    global_check_interval: int = option(
        50, 'Every this many scans of a tracked stream the global search runs instead (it '
        'wins over the prediction when they disagree); 0 never by count.', low=0,
        high=10**6)
    global_check_period: float = option(
        5.0, 'Seconds (header stamps) after which the global search runs again on a tracked '
        'stream, as global_check_interval; 0 never by time.', low=0.0, high=3600.0)
    min_fitness_ratio: float = option(
        0.85, "A tracked pose's fitness must be at least this times the fitness of the pair's "
        'last accepted pose: a jump or a kidnap leaves the refinement in a minimum that '
        'explains far fewer points, while smooth motion changes fitness little. Lower it '
        'where the scene itself changes between scans (crowds, traffic) and tracked scans '
        'go global too often.', low=0.0, high=1.0)
    max_correction_factor: float = option(
        6.0, 'A refinement that moves the prediction by more than this many voxel sizes '
        '(or max_correction_deg) is not a tracked pose: the scan is searched globally. '
        'Raise it when the motion between scans is jerkier than the prediction (no '
        'odometry, hard braking) and tracked scans go global too often.', low=0.0, high=1e6)
    max_correction_deg: float = option(
        10.0, 'Rotation bound (degrees) of max_correction_factor; raise it as that one, for '
        'a sensor that turns fast between scans.', low=0.0, high=180.0)
