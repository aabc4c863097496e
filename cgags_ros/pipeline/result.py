"""The result of the whole pipeline: the core's result plus refinement and gate values."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .covariance import moved_covariance
from ..coordinates import moved, to_caller, translation
from ..registration import RegistrationResult


@dataclasses.dataclass
class Candidate:
    """
    One candidate pose of the source in the target frame, with its support.

    :ivar transform: 4x4 source->target (refined when refinement is on), metres.
    :ivar num_inliers: putative correspondences within tau of the candidate's coarse
        (core) transform.
    :ivar fitness: share of downsampled source points with a target point within the
        refinement distance under ``transform``.
    :ivar ratio: ``num_inliers`` / the best candidate's (1 for the best).
    """

    transform: np.ndarray
    num_inliers: int
    fitness: float
    ratio: float = 1.0

    def summary(self) -> dict[str, Any]:
        """Return a JSON-friendly dict of the candidate."""
        return {'transform': np.asarray(self.transform, dtype=float).tolist(),
                'num_inliers': int(self.num_inliers), 'fitness': float(self.fitness),
                'ratio': float(self.ratio)}


@dataclasses.dataclass
class PipelineResult(RegistrationResult):
    """
    :class:`RegistrationResult` of the whole pipeline.

    ``transform`` is the final estimate (refined when refinement is on); ``inliers`` index
    the putative correspondences given to the core. Extra attributes:

    :ivar coarse_transform: the core's global estimate (4x4 source->target, metres).
    :ivar refined: whether a refinement ran (``refine.method != 'none'``).
    :ivar fitness: share of downsampled source points with a target point within the
        refinement distance (``refine.max_correspondence_distance_factor * v``) under
        ``transform``.
    :ivar inlier_rmse: RMS distance (metres) of those points to their nearest target point.
    :ivar overlap: min of the source-side and target-side shares of points with a neighbour
        in the other cloud within the refinement distance (a symmetric overlap ratio); NaN on
        the tracked path, which measures the source side (``fitness``) only.
    :ivar shared_area: the surface (square metres) the clouds share under ``transform``:
        the smaller side's count of downsampled points with a neighbour in the other cloud
        within the refinement distance, times the voxel size squared (one point a surface
        cell); NaN where ``overlap`` is.
    :ivar descriptor_ratio: over that overlap, the median descriptor (FPFH) distance of its
        point pairs over that of a random pairing (:func:`~.gates.descriptor_ratio`): near
        1 where different surfaces only meet; NaN when not measured.
    :ivar observability: smallest/largest eigenvalue of the point-to-plane information
        matrix of the overlap (0: some motion is unconstrained, e.g. plane on plane).
    :ivar chance_inliers: inliers the estimate would collect if every correspondence were
        an outlier (expected value under a random pairing).
    :ivar chance_bound: the inlier count the best of ``num_hypotheses`` such estimates
        exceeds with probability ``gates.significance`` (NaN when that gate is off).
    :ivar inlier_source_points: (K, 3) source side of the core's inlier correspondences
        (downsampled keypoints, source frame, metres).
    :ivar inlier_target_points: (K, 3) target side of the same correspondences (target
        frame, metres).
    :ivar num_source_points: source points after voxel downsampling.
    :ivar num_target_points: target points after voxel downsampling.
    :ivar voxel_size: voxel size v, metres.
    :ivar resolution: point resolution pr (metres) given to the core.
    :ivar tilt_deg: 4-DoF mode only (else NaN): the tilt (degrees) between the clouds'
        gravity axes measured by one 6-DoF point-to-plane step from the final estimate over
        the overlap (the core's, on its inliers, when the pipeline stopped before the
        refinement); above ``core.max_tilt_deg`` the result is invalid.
    :ivar free_space_violation: share of aligned points lying in front of the other
        cloud's observed surface (see :func:`~.free_space.free_space_violation`); NaN when not
        measured (clouds not in sensor frames, or the gate disabled).
    :ivar free_space_surface: share of the compared points the estimate puts in the other
        cloud's free space as pieces of surface, the smaller of the two views
        (:func:`~.free_space.free_space_surface`); NaN unless both clouds are in their
        sensor frames (never against a map).
    :ivar candidates: up to ``num_candidates`` distinct :class:`Candidate` poses, best
        first (the first is ``transform``); empty when the core gave no estimate.
    :ivar ambiguous: True when the runner-up candidate is nearly as well supported as the
        best (best/runner-up inliers below ``ambiguity_ratio``), or when a twin of the
        estimate (:mod:`.twins`: turned or slid) fits about as well, as
        :mod:`cgags_ros.validity` decides; the result is then invalid.
    :ivar runner_up_ratio: best / runner-up inlier count (inf without a runner-up).
    :ivar covariance: 6x6 covariance of ``transform``, row-major in geometry_msgs/
        PoseWithCovariance order (x, y, z in metres; rotation about the target frame's X, Y,
        Z in radians, through the source origin), from the point-to-plane fit of the whole
        overlap (:func:`~.covariance.overlap_covariance`); variances of 1e6 when fewer than
        three correspondences support the estimate. docs/confidence.md says how to read it.
    :ivar confidence: the probability that ``transform`` is right (within 15 degrees and 30
        cm) given what the pipeline measured (:mod:`.confidence`); 0 without an estimate.
        ``valid`` needs it at least ``min_confidence``.
    :ivar path: what produced the result: 'global' (the guess-free search of
        :func:`~.register.register_clouds`) or 'tracked' (refined from the pose predicted
        from a stream's last poses and judged by the same overlap gates,
        :class:`~.tracking.Tracker`; no correspondences, core or candidates then).
    :ivar map_info: the summary of the map registered onto
        (:meth:`~.map.PreparedMap.info`: file, cache hit or miss, points, load time); None
        when the target was a cloud.
    """

    coarse_transform: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    refined: bool = False
    fitness: float = 0.0
    inlier_rmse: float = float('nan')
    overlap: float = 0.0
    shared_area: float = float('nan')
    descriptor_ratio: float = float('nan')
    observability: float = float('nan')
    chance_inliers: float = float('nan')
    chance_bound: float = float('nan')
    inlier_source_points: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    inlier_target_points: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    num_source_points: int = 0
    num_target_points: int = 0
    voxel_size: float = float('nan')
    resolution: float = float('nan')
    free_space_violation: float = float('nan')
    free_space_surface: float = float('nan')
    candidates: list[Candidate] = dataclasses.field(default_factory=list)
    ambiguous: bool = False
    runner_up_ratio: float = float('inf')
    covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.diag([1e6] * 6))
    confidence: float = 0.0
    path: str = 'global'
    map_info: dict[str, Any] | None = None

    def in_caller_frames(self, source_origin: np.ndarray,
                         target_origin: np.ndarray) -> PipelineResult:
        """
        Move what this result says of clouds worked on around local origins to their frames.

        The origins (:func:`~cgags_ros.coordinates.local_origin`, metres, each in its cloud's
        frame) were subtracted before registration: the transforms, the inlier points and the
        covariance (whose rotation turns about the source origin) are given back as the
        caller's clouds have them. Returns ``self``, changed in place (nothing moves when both
        origins are zero).
        """
        if not (np.any(source_origin) or np.any(target_origin)):
            return self
        local = self.transform
        self.transform = to_caller(local, source_origin, target_origin)
        self.coarse_transform = to_caller(self.coarse_transform, source_origin, target_origin)
        for c in self.candidates:
            c.transform = to_caller(c.transform, source_origin, target_origin)
        self.inlier_source_points = moved(self.inlier_source_points, -source_origin)
        self.inlier_target_points = moved(self.inlier_target_points, -target_origin)
        self.covariance = moved_covariance(self.covariance, local, translation(-source_origin))
        return self

    def summary(self) -> dict[str, Any]:
        out = super().summary()
        out.update(
            coarse_transform=np.asarray(self.coarse_transform, dtype=float).tolist(),
            refined=bool(self.refined), fitness=float(self.fitness),
            inlier_rmse=float(self.inlier_rmse), overlap=float(self.overlap),
            shared_area=float(self.shared_area), descriptor_ratio=float(self.descriptor_ratio),
            observability=float(self.observability),
            chance_inliers=float(self.chance_inliers), chance_bound=float(self.chance_bound),
            num_source_points=int(self.num_source_points),
            num_target_points=int(self.num_target_points),
            voxel_size=float(self.voxel_size), resolution=float(self.resolution),
            free_space_violation=float(self.free_space_violation),
            free_space_surface=float(self.free_space_surface),
            candidates=[c.summary() for c in self.candidates], ambiguous=bool(self.ambiguous),
            runner_up_ratio=float(self.runner_up_ratio),
            covariance=np.asarray(self.covariance, dtype=float).tolist(),
            confidence=float(self.confidence), path=self.path,
            map=None if self.map_info is None else dict(self.map_info))
        return out
