"""
A scan in a prepared map with places: the places ranked, the best few tested, one registered.

:func:`~.register.register_clouds` runs :func:`locate` for a map with places
(:mod:`.places`). Matching a scan against the whole map costs as much as the map is large,
and the other places' matches drown its own; here:

1. **rank**: the scan's keypoints vote for places (:meth:`~.places.PlaceIndex.rank`), at
   most ``TESTED`` of them, the hint's only when one is given. Without a hint, the
   keypoints are also matched against the whole map and searched briefly: where that
   consensus puts the scan is the first place, the best voted not near it follow (votes
   alone miss a scan's place among look-alikes, docs/maps.md);
2. **test**: each is matched against the scan's keypoints and searched by the core for at
   most ``TEST_ITERATIONS`` hypotheses (the places side by side, a thread each): its own
   place gives a consensus within a few hundred, a wrong one none that stands out. The
   consensus place is tested only when another scores more than the whole map's search
   found in it, which its own test reaches anyway (or nearly: that search matches each
   keypoint in the nearest few of the map's descriptor cells, ``CONSENSUS_CELLS``, not
   exactly). A hint that leaves one place leaves nothing to test;
3. **register**: the place with the largest consensus goes through the whole pipeline as
   a map of its own (its submap, in the map's local frame), matching at most
   ``PLACE_KEYPOINTS`` of the scan's points (unless ``frontend.max_keypoints`` bounds them:
   matching a LiDAR scan's every point cost more than the rest of its registration). The
   result is that registration's, in the map frame as against the whole map; its
   ``map_info`` is the whole map's with the place's beside it, its ``stats['places']`` what
   was ranked and tested (``tested_inliers`` None: not tested; ``consensus_inliers`` the
   whole map's search's in the consensus place, None without one);
4. **judge elsewhere**: the place's registration sees no other place, and a scan that fits
   a look-alike surface in a wrong one passes every gate there. The whole map's matches
   (the consensus search's) count the support of the pose: no more than chance gives it
   (``gates.significance``), while their consensus, a distinct pose, has more, it is
   ambiguous (``stats['places']['whole_map_support']``: the counts, the chance bound and
   whether the poses are distinct; None with a hint, which searches no consensus).

A map within one submap of the scan, or whose best place holds half its points, is
registered whole, as without places: testing would cost more than it saves. So is a scan too
small to be featurised (it is refused as the whole map refuses it).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import numpy as np

from .cache import cached_features
from .candidates import distinct
from .confidence import capped
from .gates import chance_bound, chance_inliers
from .hint import Hint
from .map import PreparedMap
from .places import Place, Ranked, with_tree
from .result import PipelineResult
from .settle import support
from ..config.pipeline import PipelineConfig
from ..coordinates import local_origin, moved, to_local
from ..errors import DegenerateCorrespondencesError, EmptyCloudError
from ..frontend.features import CloudFeatures
from ..frontend.matching import match_features
from ..geometry import apply_transform, rotation_error_deg, translation_error
from ..parallel import DEFAULT_WORKERS, map_ordered
from ..refusal import Refusal, RefusalCode
from ..registration import register_correspondences, single_blas_thread
from ..timing import timed
from ..validity import elsewhere_refusal

TESTED = 3  # places tested a query: its own is among the first three ranked, mostly
TEST_ITERATIONS = 10_000  # the core's hypotheses a test draws at most
PLACE_KEYPOINTS = 5000  # scan points matched against the registered place (docs/maps.md)
# The cells of the whole map's descriptor index a keypoint's consensus match visits, nearest
# centre first: nearly every exact match for a fraction of the exact search (docs/maps.md).
CONSENSUS_CELLS = 8

Register = Callable[[PreparedMap, PipelineConfig], PipelineResult]


@dataclasses.dataclass(frozen=True)
class ShortSearch:
    """
    A short search of the scan's keypoints matched against a map or a submap.

    :ivar inliers: the consensus's size; ``transform`` its pose (scan -> map, local
        frames), ``rows`` the map rows of its inliers.
    :ivar source, target: the matched keypoints and their map points (local frames), and
        ``tau`` the search's inlier threshold: what :meth:`support` counts on.
    """

    inliers: int
    transform: np.ndarray
    rows: np.ndarray
    source: np.ndarray
    target: np.ndarray
    tau: float

    def support(self, transform: np.ndarray) -> int:
        """Return how many of the matches ``transform`` brings within ``tau``."""
        return int(np.count_nonzero(support(self.source, self.target, transform, self.tau)))


def locate(src: np.ndarray, prepared: PreparedMap, cfg: PipelineConfig, hint: Hint | None,
           source_sensor: np.ndarray | None, register: Register) -> PipelineResult:
    """
    Register the finite scan ``src`` (sensor frame) in ``prepared`` through its places.

    ``register(part, config)`` registers the scan against a map without places (the whole
    map or a place's submap) as :func:`~.register.register_clouds` does; ``source_sensor``
    as there.
    """
    start = time.perf_counter()
    timings: dict[str, float] = {}
    local_hint = (None if hint is None
                  else dataclasses.replace(hint, position=hint.position - prepared.origin))
    try:
        with timed(timings, 'places_rank'), single_blas_thread():
            origin = local_origin(src, source_sensor)
            scan = cached_features(moved(src, origin), cfg.voxel_size, cfg.frontend, 'source',
                                   workers=DEFAULT_WORKERS)
            ranked = prepared.places.rank(scan, cfg.voxel_size, TESTED,
                                          prepared.features.tree, local_hint, DEFAULT_WORKERS)
    except EmptyCloudError:
        return register(prepared.whole(), cfg)  # refused as the whole map refuses it
    if ranked.whole:
        return register(prepared.whole(), cfg)
    if not ranked.places:
        return _uncovered(prepared, cfg, hint, start)
    with timed(timings, 'places_test'), single_blas_thread():
        places, bound, whole = (_with_consensus(scan, ranked, prepared, cfg) if hint is None
                                else (ranked.places, None, None))
        if len(places) == 1:  # a hint covering one place: nothing to rank, nothing to test
            parts = [prepared.places.submap(prepared.features, places[0].rows)]
            scores = [None]
        else:
            parts, scores = _test_all(scan, ranked.keypoints, prepared, places, bound, cfg)
    # An untested consensus place scores its bound; ties go to the first.
    best = (int(np.argmax([bound if s is None else s for s in scores])) if len(parts) > 1
            else 0)
    result = register(prepared.part(with_tree(parts[best])), _bounded(cfg))
    said = (None if whole is None or whole.inliers == 0
            else _judged_elsewhere(result, whole, to_local(result.transform, origin,
                                                           prepared.origin), cfg))
    result.stats['places'] = {'ranked': [_summary(prepared, p, s)
                                         for p, s in zip(places, scores)],
                              'consensus_inliers': bound, 'registered': best,
                              'whole_map_support': said}
    return _noted(result, prepared, places[best], scores[best], timings, start)


def _judged_elsewhere(result: PipelineResult, whole: ShortSearch, pose: np.ndarray,
                      cfg: PipelineConfig) -> dict:
    """
    Refuse ``result`` when the whole map's matches back its ``pose`` no more than chance.

    ``pose``: the result's, in the local frames. Returns what the whole map's matches
    said: their support of the pose, the most chance gives it
    (:func:`~.gates.chance_bound` of one pose), their consensus's support, and whether
    the two poses are distinct (:func:`~.candidates.distinct`); only a valid result is
    judged (:func:`~cgags_ros.validity.elsewhere_refusal`), and only with the chance gate
    on (``gates.significance`` 0: no bound, None). A refused result's confidence is capped
    as the gates' refusals' are (:func:`~.confidence.capped`).
    """
    gated = cfg.gates.significance > 0
    said = {'pose': whole.support(pose),
            'chance_bound': (chance_bound(chance_inliers(whole.source, whole.target, pose,
                                                         whole.tau),
                                          1, cfg.gates.significance, members=0)
                             if gated else None),
            'consensus': whole.support(whole.transform),
            'distinct': distinct(pose, whole.transform, cfg)}
    if gated and result.valid and said['distinct']:
        refusal = elsewhere_refusal(said['pose'], said['chance_bound'], said['consensus'],
                                    rotation_error_deg(pose, whole.transform),
                                    translation_error(pose, whole.transform), cfg)
        if refusal is not None:  # its confidence then says no more, as for the gates' refusals
            result.refusal, result.ambiguous = refusal, True
            result.confidence = capped(result.confidence, refusal.code.value)
    return said


def _bounded(cfg: PipelineConfig) -> PipelineConfig:
    """Return ``cfg`` matching at most ``PLACE_KEYPOINTS`` scan points, unless it bounds them."""
    return dataclasses.replace(cfg, frontend=dataclasses.replace(
        cfg.frontend, max_keypoints=cfg.frontend.max_keypoints or PLACE_KEYPOINTS))


def _with_consensus(scan: CloudFeatures, ranked: Ranked, prepared: PreparedMap,
                    cfg: PipelineConfig) -> tuple[list[Place], int | None, ShortSearch]:
    """
    Return the places to test, the whole map's consensus place first, its bound, the search.

    The scan's keypoints matched against the whole map and searched briefly put it where
    the most of them agree; that place is tested with the best voted ones not near it. Its
    bound is the consensus's inliers that lie in it: its own test scores about as many or
    more (the whole map's mutual matches that land in a submap are among the submap's, but
    for the few whose nearest row the approximate search, ``CONSENSUS_CELLS``, missed), so
    it needs no test unless another place scores more. No consensus: the voted places, None.
    """
    whole = _tested(scan, ranked.keypoints, prepared.features, cfg, cells=CONSENSUS_CELLS)
    if whole.inliers == 0:
        return ranked.places, None, whole
    centre = apply_transform(whole.transform, scan.points.mean(axis=0)[None])[0]
    near = prepared.places.near(ranked.reach)
    voted = [p for p in ranked.places if np.linalg.norm(p.centre - centre) > near]
    place = prepared.places.place_at(centre, ranked.reach, prepared.features.tree)
    bound = int(np.count_nonzero(np.isin(whole.rows, place.rows)))
    return [place, *voted][:TESTED], bound, whole


def _test_all(scan: CloudFeatures, keypoints: np.ndarray, prepared: PreparedMap,
              places: list[Place], bound: int | None,
              cfg: PipelineConfig) -> tuple[list[CloudFeatures], list[int | None]]:
    """
    Return the places' submaps and what their tests scored (None: not tested).

    Each place on a thread of its own: building its index is mostly serial. With a
    ``bound``, the first place is the consensus place: its submap is built beside the
    others' tests and tested only when one of them scores more than the bound.
    """
    def test(place: Place) -> tuple[CloudFeatures, int | None]:
        part = prepared.places.submap(prepared.features, place.rows)
        if bound is not None and place is places[0]:
            return part, None
        return part, _tested(scan, keypoints, part, cfg, 1).inliers

    tested = map_ordered(test, places, DEFAULT_WORKERS)
    parts, scores = [t[0] for t in tested], [t[1] for t in tested]
    if bound is not None and max(scores[1:]) > bound:
        scores[0] = _tested(scan, keypoints, parts[0], cfg).inliers
    return parts, scores


def _tested(scan: CloudFeatures, keypoints: np.ndarray, part: CloudFeatures,
            cfg: PipelineConfig, workers: int = DEFAULT_WORKERS, cells: int = 0) -> ShortSearch:
    """
    Return a short search of the keypoints' matches in ``part``.

    ``cells`` > 0: the matches are approximate nearest neighbours, each searched in that
    many of the part's descriptor cells (:func:`~..frontend.matching.match_features`).
    """
    corr = match_features(scan.descriptors[keypoints], part.descriptors, cfg.frontend,
                          workers, part.descriptor_index(workers), cells=cells)
    core = dataclasses.replace(cfg.core,
                               max_iterations=min(cfg.core.max_iterations, TEST_ITERATIONS))
    source, target = scan.points[keypoints[corr.source_index]], part.points[corr.target_index]
    try:
        found = register_correspondences(
            source, target, inlier_threshold=cfg.core.inlier_threshold or None,
            resolution=0.5 * (scan.resolution + part.resolution), config=core, seed=cfg.seed,
            workers=workers)
    except DegenerateCorrespondencesError:
        return ShortSearch(0, np.eye(4), np.zeros(0, dtype=np.int64), source, target, 0.0)
    return ShortSearch(int(found.num_inliers), found.transform,
                       corr.target_index[found.inliers], source, target,
                       float(found.inlier_threshold))


def _summary(prepared: PreparedMap, place: Place, score: int | None) -> dict:
    return {'centre': [float(x) for x in place.centre + prepared.origin],
            'points': int(len(place.rows)), 'by': place.by, 'votes': place.votes,
            'tested_inliers': score}


def _noted(result: PipelineResult, prepared: PreparedMap, place: Place, score: int | None,
           timings: dict[str, float], start: float) -> PipelineResult:
    """Return ``result`` with the whole map's info and its place's, and the total time."""
    result.map_info = {**prepared.info(), 'place': _summary(prepared, place, score)}
    result.timings.update(timings)
    result.timings['total'] = time.perf_counter() - start
    return result


def _uncovered(prepared: PreparedMap, cfg: PipelineConfig, hint: Hint,
               start: float) -> PipelineResult:
    """Return the refusal of a scan whose hint covers no place of the map."""
    where = ' '.join(f'{x:.3f}' for x in hint.position)
    refusal = Refusal(RefusalCode.NO_SHARED_SURFACE,
                      f'the hint ({hint.radius:.2f} m around {where}) covers no place of '
                      f'the map {prepared.path}')
    result = PipelineResult(voxel_size=cfg.voxel_size, map_info=prepared.info())
    return result.finish(start, refusal)
