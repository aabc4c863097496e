"""
Relocalization over a few scans with odometry: poses of the odometry frame in a map, tested.

One scan of a self-similar place often cannot tell the right pose from a rival (a room
turned half onto itself); a robot moves and looks again. :class:`Relocalizer` takes scans in
time order, each with the sensor's pose in an odometry frame (``odom <- sensor``, from wheel,
IMU or LiDAR odometry: good over metres, drifting slowly), and keeps **hypotheses**: poses of
the odometry frame in the map (``map <- odom``). Every scan is registered onto the prepared
map as a single scan is (:func:`~.register.register_clouds`, the one path); each of its
ranked candidates, composed with the scan's odometry pose, proposes a hypothesis (one that
an earlier scan proposed already is merged into it). Each hypothesis is then checked on
every scan (first its own, which moves the hypothesis to where that scan settles: a
candidate is good to about the core's inlier threshold): the scan is put where the
hypothesis and the odometry predict and refined locally against the map
(point-to-plane on the map's k-d tree, cheap from a close start), and the scan
**explains** the hypothesis when the refinement stays within the drift allowance (the
odometry's drift and the error of the registration the hypothesis came from), the fitness
is at least ``min_fitness`` and the pose passes a single registration's gates on what the
scan shares with the map (free space, degeneracy, alike descriptors). A hypothesis that
explains a scan much worse than the best one does (its fitness ``refute_ratio`` times lower),
or does not explain it and fits it no better than the best, is **refuted** by that scan.

The answer is **confirmed** when one hypothesis explains every scan used and every distinct
rival is refuted, over at least ``min_scans`` scans; until then it asks for another scan,
and after ``max_scans`` it refuses with the reason. A scan that no hypothesis explains, not
even its own (taken outside the map), is not used: it speaks for or against none of them.
Odometry that contradicts the scans leaves no hypothesis explaining them all: it is refused,
never averaged. One scan without odometry is judged exactly as
:func:`~.register.register_clouds` judges it (confirmed when valid), at the same cost: the
checks run only once a second scan arrives.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .hypotheses import Answer, Check, Hypothesis, judge, make_answer, SequenceConfig
from ..config.pipeline import PipelineConfig
from ..errors import InvalidInputError
from ..frontend.features import CloudFeatures, finite_points
from ..frontend.refine import evaluate_alignment
from ..geometry import apply_transform, translation_error
from ..parallel import DEFAULT_WORKERS, map_ordered
from ..pipeline.cache import cached_features
from ..pipeline.candidates import distinct
from ..pipeline.covariance import loosest_sigma, overlap_covariance
from ..pipeline.gates import descriptor_ratio, observability
from ..pipeline.hint import Hint
from ..pipeline.map import PreparedMap
from ..pipeline.register import register_clouds
from ..pipeline.result import PipelineResult
from ..pipeline.settle import CHECK, Pair, settle
from ..pipeline.twins import local_symmetries, map_symmetries
from ..validity import uncertainty_refusal


@dataclasses.dataclass
class _Scan:
    xyz: np.ndarray  # the scan's finite points, sensor frame
    features: CloudFeatures
    odom: np.ndarray  # odom <- sensor
    travelled_m: float  # odometry path length from the first scan
    result: PipelineResult


class Relocalizer:
    """
    Scans in, with odometry poses; the map pose of the latest scan out (see the module doc).

    Feed it with :meth:`add` until the answer is ``done``, then :meth:`reset` it for the next
    relocalization (scans added after ``done`` are still taken, and judged with the rest).
    """

    def __init__(self, prepared: PreparedMap, config: PipelineConfig,
                 sequence: SequenceConfig | None = None):
        """Relocalize in ``prepared`` (:func:`~.map.load_map` with the same ``config``)."""
        self.prepared, self.config = prepared, config
        self.sequence = sequence or SequenceConfig()
        self.scans: list[_Scan] = []
        self.hypotheses: list[Hypothesis] = []
        self.submaps: dict[int, PipelineResult] = {}  # scan index -> its submap's result

    def reset(self) -> None:
        """Forget every scan and hypothesis."""
        self.scans, self.hypotheses, self.submaps = [], [], {}

    def add(self, scan_xyz: np.ndarray, odom_from_sensor: np.ndarray | None = None,
            hint: Hint | None = None) -> Answer:
        """
        Take the next scan and return the answer.

        :param scan_xyz: (N, 3) points in the sensor frame, metres.
        :param odom_from_sensor: 4x4 pose of the sensor in the odometry frame when the scan
            was taken (p_odom = T p_sensor); None: no odometry, the scan starts a new
            sequence and is judged alone (``min_scans`` does not apply).
        :param hint: where the sensor is believed to be when the scan was taken
            (:class:`~cgags_ros.pipeline.hint.Hint`, map frame; e.g. ``Hint.from_pose`` of
            ``initialpose``): the scan (and the scans so far, fused) is registered only in
            the map's places it covers. The hypotheses' checks are not restricted.
        """
        if odom_from_sensor is None:
            self.reset()
        odom = np.eye(4) if odom_from_sensor is None else _checked_pose(odom_from_sensor)
        xyz = finite_points(scan_xyz, 'scan')
        result = register_clouds(xyz, self.prepared, config=self.config, hint=hint)
        # The features register_clouds just computed (a cache hit, not recomputed).
        features = cached_features(xyz, self.config.voxel_size, self.config.frontend, 'source')
        travelled = (self.scans[-1].travelled_m + translation_error(odom, self.scans[-1].odom)
                     if self.scans else 0.0)
        self.scans.append(_Scan(xyz, features, odom, travelled, result))
        index = len(self.scans) - 1
        self._propose_all(result, index, 'scan')
        if index == 0:
            # One scan is judged as a single registration is; with odometry a confirmation
            # may ask for more (``min_scans``), without it there will be none.
            seq = (self.sequence if odom_from_sensor is not None
                   else dataclasses.replace(self.sequence, min_scans=1))
            return make_answer(result.transform, odom, result.refusal, self.hypotheses, [result],
                               seq)
        answer = self._judge()
        if self.sequence.submap and not answer.confirmed:
            # The scans alone did not settle it: the scans so far, fused with the odometry,
            # show more of the place than any one of them, and their candidates join in.
            to_latest = np.linalg.inv(odom)
            # On a micrometre grid: the voxel grid splits points at exact boundaries, so
            # odometry that differs only in its last bits (a pose sent as a quaternion) would
            # otherwise fuse a different cloud and register it differently.
            fused = np.round(np.vstack([apply_transform(to_latest @ s.odom, s.xyz)
                                        for s in self.scans]), 6)
            self.submaps[index] = register_clouds(fused, self.prepared, config=self.config,
                                                  hint=hint)
            self._propose_all(self.submaps[index], index, 'submap')
            answer = self._judge()
        return answer

    def _judge(self) -> Answer:
        """
        Decide; before confirming a pose, also check its twins under the map's symmetries.

        Scans that all see a near-square room alike cannot tell a pose from the pose turned
        about the room: each twin (:func:`~.twins.map_symmetries`,
        :func:`~.twins.local_symmetries`) is checked on every scan as a hypothesis, and one
        that explains them as well leaves the answer ambiguous. A confirmed pose must also be
        usable: its covariance over the latest scan's overlap with the map at most
        ``gates.max_position_sigma`` voxels along its loosest direction (a corridor leaves
        the pose loose along it).
        """
        answer = self._checked()
        if answer.confirmed and self._add_twins(answer.hypotheses[0]):
            answer = self._checked()
        if not answer.confirmed:
            return answer
        scan, ft, cfg = self.scans[-1], self.prepared.features, self.config
        # The map's local frame is the map frame moved: the covariance (about the scan's
        # origin) is the same in both.
        cov = overlap_covariance(scan.features.points, ft.points, ft.normals, ft.tree,
                                 self.prepared.to_local(answer.transform),
                                 cfg.refine.max_correspondence_distance_factor
                                 * cfg.voxel_size, cfg.voxel_size)
        refusal = uncertainty_refusal(loosest_sigma(cov), cfg)
        if refusal is None:
            return answer
        return make_answer(answer.transform, scan.odom, refusal, answer.hypotheses, answer.results,
                           self.sequence)

    def _add_twins(self, best: Hypothesis) -> bool:
        """
        Add ``best`` turned by each symmetry of the map; tell whether any is new.

        The whole map's symmetries, and those of the part the scans see where ``best``
        puts them (a square room inside a larger map).
        """
        added = False
        local = self.prepared.to_local(best.map_from_odom)
        placed = np.vstack([apply_transform(local @ s.odom, s.features.points)
                            for s in self.scans])
        for S in (map_symmetries(self.prepared, self.config)
                  + local_symmetries(self.prepared, self.config, placed)):
            twin = self.prepared.to_map(S @ local)
            if all(distinct(h.map_from_odom, twin, self.config) for h in self.hypotheses):
                self.hypotheses.append(Hypothesis(twin, best.scan, best.rank, 0, 'symmetry'))
                added = True
        return added

    def _checked(self) -> Answer:
        """Check every hypothesis not yet checked on every scan, then decide."""
        todo = [h for h in self.hypotheses
                if any(i not in h.checks for i in range(len(self.scans)))]
        # Hypotheses side by side, each on a thread (a check is mostly k-d tree queries and
        # numpy on the scan's points): each touches only its own checks.
        workers = 1 if len(todo) > 1 else DEFAULT_WORKERS
        map_ordered(lambda h: self._check_all(h, workers), todo, DEFAULT_WORKERS)
        return judge(self.hypotheses, [s.result for s in self.scans],
                     [s.odom for s in self.scans], self.config, self.sequence)

    def _check_all(self, h: Hypothesis, workers: int) -> None:
        """Check ``h`` on every scan it was not checked on, its own first."""
        # Its own scan first: a pose that does not explain the scan that proposed it is no
        # pose at all. Then every other scan, so that a scan no hypothesis explains (one
        # taken outside the map) is known as such (see :func:`judge`).
        for i in [h.scan] + [i for i in range(len(self.scans)) if i != h.scan]:
            if i not in h.checks:
                h.checks[i] = self._check(h, i, workers)
                if i == h.scan:
                    self._anchor(h)
            if i == h.scan and not h.checks[i].explains(self.sequence, self.config):
                break

    def _propose_all(self, result: PipelineResult, index: int, source: str) -> None:
        """
        Propose the candidates of a registration in scan ``index``'s frame as hypotheses.

        One that repeats a hypothesis (the same pose of this scan) is merged into it.
        """
        odom = self.scans[index].odom
        for rank, c in enumerate(result.candidates):
            for h in self.hypotheses:
                if not distinct(h.map_from_odom @ odom, c.transform, self.config):
                    h.inliers += c.num_inliers
                    break
            else:
                self.hypotheses.append(Hypothesis(c.transform @ np.linalg.inv(odom), index,
                                                  rank, c.num_inliers, source))

    def _anchor(self, h: Hypothesis) -> None:
        """
        Move ``h`` to where its own scan's check settled, when the scan fits there.

        A candidate is the core's estimate, good to about its inlier threshold (the best one
        refined on the whole map, the others not): the check refines it against the map
        near the scan, and the odometry has not drifted between a scan and itself. So the
        refined pose is the hypothesis, and the other scans are checked against it.
        """
        c = h.checks[h.scan]
        if (c.fitness < self.sequence.min_fitness
                or c.free_space > self.config.gates.max_free_space_violation):
            return
        h.map_from_odom = c.transform @ np.linalg.inv(self.scans[h.scan].odom)
        h.checks[h.scan] = dataclasses.replace(c, moved_deg=0.0, moved_m=0.0)

    def _check(self, h: Hypothesis, index: int, workers: int) -> Check:
        """Put scan ``index`` where ``h`` predicts it and refine it against the map."""
        scan, cfg, seq = self.scans[index], self.config, self.sequence
        ft = self.prepared.features
        steps = abs(index - h.scan)
        travelled = abs(scan.travelled_m - self.scans[h.scan].travelled_m)
        predicted = self.prepared.to_local(h.map_from_odom @ scan.odom)
        points = scan.features.points
        final = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
        reach = seq.drift_m * max(steps, 1) + seq.drift_fraction * travelled
        # Where the prediction leaves too little of the scan near the map even at the drift
        # allowance, no refinement can make the scan explain it: skip the refinement.
        loose = evaluate_alignment(points, ft.tree, predicted, reach + final, workers).fitness
        if loose < seq.min_fitness:
            return Check(self.prepared.to_map(predicted), 0.0, 0.0, steps, travelled, loose,
                         float('nan'))
        # Settled on the map's own k-d tree and normals, built once with its features: a
        # check costs its few Gauss-Newton steps, not a tree of the map near the scan.
        s = settle(Pair(scan.features, ft, cfg, map_target=True), predicted,
                   reach + final, CHECK, workers)
        # What the scan shares with the map there, as a single registration measures it.
        align = s.alignment
        return Check(self.prepared.to_map(s.transform), s.moved_deg, s.moved_m, steps,
                     travelled, s.fitness, s.free_space,
                     descriptor_ratio(scan.features.descriptors, ft.descriptors, align),
                     observability(points, ft.normals, align))


def _checked_pose(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InvalidInputError(f'odometry pose must be a finite 4x4 transform, got {T.shape}')
    if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4):
        raise InvalidInputError('odometry pose: its 3x3 block is not a rotation')
    return T
