"""
Configuration of the regenerated correspondences (:mod:`cgags_ros.pipeline.regenerate`).

The stage's own sizes (seeds, sphere radius, its short refinement) are constants of that
module: they were measured on real RGB-D pairs (docs/method.md), not tuned per robot. What a
user chooses is whether the stage runs, on which pairs, and how much time it may take.
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
        'whose refined pose the original correspondences support best (docs/method.md). '
        'It puts low-overlap pairs right that the core alone gets wrong; false saves its '
        'time where every pair overlaps well (a stream, a calibration rig).')
    when: str = option(
        'refused', "'always': on every 6-DoF pair; 'refused': only when the core refuses its "
        'estimate (its consensus does not stand out).', choices=('always', 'refused'),
        advanced=True)
    judged: int = option(
        0, 'Proposed poses refined and judged: those that the most original correspondences '
        'support before the refinement. 0 judges every one; 10 bounds the time the stage '
        'takes on a low-overlap pair (docs/benchmarks_3dmatch.md, the speed setting).',
        low=0, high=1000)
