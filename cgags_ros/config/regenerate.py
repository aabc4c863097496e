"""
Configuration of the regenerated correspondences (:mod:`cgags_ros.pipeline.regenerate`).

Lengths are in voxel sizes, as every other radius. Every option is a research switch: the
stage's settings were measured on real RGB-D pairs (docs/method.md), not tuned per robot.
"""

from __future__ import annotations

import dataclasses

from .fields import option


@dataclasses.dataclass
class RegenerateConfig:
    """Local re-matching around seed correspondences, and the poses it proposes."""

    enabled: bool = option(
        True, 'Re-match descriptors inside local spheres around the best-connected '
        'correspondences, fit a pose to each sphere, and replace the estimate with the one '
        'whose refined pose the original correspondences support best (docs/method.md).',
        advanced=True)
    when: str = option(
        'refused', "'always': on every 6-DoF pair; 'refused': only when the core refuses its "
        'estimate (its consensus does not stand out).', choices=('always', 'refused'),
        advanced=True)
    free_space_factor: float = option(
        1.0, 'A proposed pose replaces the estimate only below this times '
        'gates.max_free_space_violation.', low=0.0, high=1.0, advanced=True)
    seeds: int = option(
        60, 'Seed correspondences (highest second-order compatibility, spread apart).',
        low=1, high=1000, advanced=True)
    seed_spacing_factor: float = option(
        2.0, 'Seeds are at least this many voxel sizes apart in the source.', low=0.0,
        high=100.0, advanced=True)
    radius_factor: float = option(
        6.0, 'Radius of the local spheres, in voxel sizes.', low=0.5, high=100.0,
        advanced=True)
    candidates: int = option(
        1000, 'Correspondences (highest compatibility degree) among which seeds are ranked.',
        low=10, high=100000, advanced=True)
    judged: int = option(
        0, 'Proposed poses refined and judged: those that the most original correspondences '
        'support before the refinement. 0 judges every one.', low=0, high=1000, advanced=True)
    iterations: int = option(
        5, "Point-to-plane iterations of each proposed pose's short refinement (a stage).",
        low=1, high=1000, advanced=True)
    stride: int = option(
        8, 'Every this many source points take part in the short refinement.', low=1,
        high=100, advanced=True)
