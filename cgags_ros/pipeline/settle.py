"""
Settle and measure: a start refined briefly against a target, then measured there.

Five stages ask one question of the poses they propose: where does this start settle, and
how well does the source fit there? They are the proposers: the correspondences' other
candidates of an ambiguous estimate (:mod:`.candidates`), the estimate's twins, turned or
slid as a symmetric scene would also accept it, and a map's symmetries (:mod:`.twins`), the
poses of the regenerated correspondences (:mod:`.regenerate`), and the relocalizer's
checks of a hypothesis on a scan (:mod:`cgags_ros.relocalization.relocalizer`). Each
proposes starts; :func:`settle` refines one and returns it :class:`Settled`, whose
measures (fitness both ways, free-space violation, support among the correspondences, how
far it moved) are taken when first read: a proposer that stops at the first failing test
pays for no more. What the measures mean for the estimate (whether it is ambiguous) is
decided in :mod:`cgags_ros.validity` only.

:class:`Settling` is the one settings object: every ``stride``-th source point refines
(fitness is judged on every point), for ``iterations`` Gauss-Newton steps a stage of
point-to-plane against the target's own k-d tree and normals (built once with its
features, so a settle pays for its few steps only), in the estimate's stages (the coarse
distance first when it is the larger, then the final correspondence distance); with
``iterations`` 0 the start is refined as the estimate is (``refine.method`` in full).
Each proposer has its preset (below); they differ where a measurement said they should:
docs/method.md, "Settle and measure".
"""

from __future__ import annotations

import dataclasses
from functools import cached_property

import numpy as np

from .free_space import measured_free_space
from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures
from ..frontend.refine import (Alignment, evaluate_alignment, refine_transform,
                               staged_point_to_plane)
from ..geometry import apply_transform, rotation_error_deg, translation_error


@dataclasses.dataclass(frozen=True)
class Settling:
    """
    How briefly a start is refined (see the module doc).

    :ivar stride: every this many source points take part in the refinement.
    :ivar iterations: Gauss-Newton steps a stage of the short point-to-plane refinement;
        0: the estimate's own refinement, in full (``refine.method``).
    """

    stride: int = 1
    iterations: int = 0


# The presets, one a proposer. A candidate of an ambiguous estimate may become the estimate:
# it is refined as the estimate is. A twin, a regenerated proposal and a check only have to
# show where they settle; a proposal's support is counted on the correspondences, so an
# eighth of the source points settles it; a map's symmetry settles a sample of the map
# (already a few thousand points) onto the whole map.
CANDIDATE = Settling()
TWIN = Settling(stride=2, iterations=5)
SYMMETRY = Settling(stride=1, iterations=10)
PROPOSAL = Settling(stride=8, iterations=5)
CHECK = Settling(stride=2, iterations=6)


def support(src: np.ndarray, dst: np.ndarray, transform: np.ndarray, tau: float) -> np.ndarray:
    """Return the mask of correspondences ``src[i] -> dst[i]`` within ``tau`` of ``transform``."""
    return np.linalg.norm(apply_transform(transform, src) - dst, axis=1) <= tau


@dataclasses.dataclass(frozen=True, eq=False)
class Pair:
    """
    What starts are settled on, and measured against.

    :ivar source: the source's features, or (N, 3) points alone (a map's sample settled onto
        the map: no fitness back, no free space then).
    :ivar target: the target's features (its k-d tree and normals serve every settle).
    :ivar map_target: the target is a map (free space is judged from the source's view).
    :ivar correspondences: (src, dst) corresponding points, for :attr:`Settled.support`.
    :ivar tau: the distance (metres) within which a correspondence supports a pose.
    """

    source: CloudFeatures | np.ndarray
    target: CloudFeatures
    cfg: PipelineConfig
    map_target: bool = False
    correspondences: tuple[np.ndarray, np.ndarray] | None = None
    tau: float = float('nan')

    @property
    def points(self) -> np.ndarray:
        """Return the source's points, metres, in its frame."""
        return self.source.points if isinstance(self.source, CloudFeatures) else self.source

    @property
    def distance(self) -> float:
        """Return the final correspondence distance, metres: fitness is counted within it."""
        return self.cfg.refine.max_correspondence_distance_factor * self.cfg.voxel_size


def settle(pair: Pair, start: np.ndarray, coarse_distance: float, settling: Settling,
           workers: int = 1) -> Settled:
    """
    Refine ``start`` (4x4 source -> target, metres) briefly and return it settled.

    ``coarse_distance`` (metres): how far the start may be off, the first stage's distance
    when it is larger than the final one (the core's inlier threshold for a pose it found,
    the drift allowance for a predicted one). ``workers``: threads of the refinement (the
    result does not depend on them).
    """
    cfg, target = pair.cfg, pair.target
    if settling.iterations == 0:
        gravity = cfg.core.gravity_axis if cfg.core.motion_model == '4dof' else None
        T = refine_transform(pair.points, target.points, start, voxel_size=cfg.voxel_size,
                             config=cfg.refine, target_normals=target.normals,
                             coarse_distance=coarse_distance, gravity=gravity,
                             workers=workers)
    else:
        T = staged_point_to_plane(pair.points[::settling.stride], target.points,
                                  target.normals, target.tree, start, coarse_distance,
                                  pair.distance, settling.iterations, workers)
    return Settled(pair, np.asarray(start, dtype=np.float64), T)


class Settled:
    """
    A start and where it settled (4x4 source -> target, metres), with its measures.

    Each measure is taken when first read and kept.
    """

    def __init__(self, pair: Pair, start: np.ndarray, transform: np.ndarray):
        """Keep the settled ``transform`` of ``start`` on ``pair``."""
        self.pair, self.start, self.transform = pair, start, transform

    @cached_property
    def alignment(self) -> Alignment:
        """Return the source points paired with their nearest target points (final distance)."""
        pair = self.pair
        return evaluate_alignment(pair.points, pair.target.tree, self.transform, pair.distance)

    @property
    def fitness(self) -> float:
        """Return the share of every source point within the final distance of the target."""
        return self.alignment.fitness

    @cached_property
    def back(self) -> float:
        """Return the share of the target's points within the final distance of the source."""
        pair = self.pair
        return evaluate_alignment(pair.target.points, pair.source.tree,
                                  np.linalg.inv(self.transform), pair.distance).fitness

    @property
    def overlap(self) -> float:
        """Return the smaller of the fitness both ways (the estimate's ``overlap``)."""
        return min(self.fitness, self.back)

    @cached_property
    def free_space(self) -> float:
        """Return the free-space violation (:func:`.free_space.measured_free_space`; NaN: none)."""
        pair = self.pair
        return measured_free_space(pair.source, pair.target, self.transform, pair.cfg,
                                   pair.map_target)

    @cached_property
    def support(self) -> int:
        """Return how many of the pair's correspondences lie within ``tau`` of the pose."""
        src, dst = self.pair.correspondences
        return int(np.count_nonzero(support(src, dst, self.transform, self.pair.tau)))

    @property
    def moved_deg(self) -> float:
        """Return how far (degrees) the refinement turned the start."""
        return rotation_error_deg(self.transform, self.start)

    @property
    def moved_m(self) -> float:
        """Return how far (metres) the refinement moved the start."""
        return translation_error(self.transform, self.start)

    def measured(self, *names: str) -> Settled:
        """Take the measures ``names`` now (a settle on a worker thread measures there)."""
        for name in names:
            getattr(self, name)
        return self
