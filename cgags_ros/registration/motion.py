"""
The motion model of a search: what a minimal subset is, how it is drawn and fitted.

Algorithm 1 is written once (:mod:`.cgags`, :class:`~.search.Search`); what depends on
the unknowns of the transform is a strategy object of this module:

- :class:`Triangles`, 6-DoF (the paper): a minimal subset is three pairwise compatible
  correspondences, a compatible edge and a common-neighbour vertex (step 2), fitted in
  closed form (step 3); scored by inlier count.
- :class:`Edges`, 4-DoF (clouds already levelled, :mod:`.yaw`): yaw about gravity and a
  translation, so one compatible edge is a minimal subset (step 2 without the vertex),
  fitted by the closed-form yaw (step 3); the compatibility graph also checks vertical
  offsets (step 1); scored by the truncated quadratic (MSAC). Its chance level is measured
  on uniformly drawn edges apart from the search's own (step 7): an edge tournament ranks
  edges by nearly their consensus, so its winners are no chance sample.

A minimal subset is a row of correspondence indices, (B, 3) triangles or (B, 2) edges.
"""

from __future__ import annotations

import numpy as np

from . import compiled
from .compatibility import build_compatibility_graph
from .compatibility_4dof import build_vertical_compatibility_graph
from .rigid import kabsch
from .stopping import compatible_sample_inlier_probability, futility_draws
from .yaw import fit_edges, fit_yaw, horizontal_lengths, vertical_offsets

# INFERRED (4-DoF): an edge shorter than this many tau across the gravity axis in either
# cloud is no minimal subset, its yaw poorly determined
MIN_EDGE_LENGTH = 1.0
# INFERRED (6-DoF): a triangle spanning less than this many tau^2 in the source is
# near-collinear, no minimal subset
MIN_TRIANGLE_AREA = 0.5
XI = 1e-6  # xi (paper: 1e-6): the floor added to the kernel's sampling weights
# Hypotheses of a batch scored on all N and fed to the preference lists (the others are
# pre-screened on their common neighbourhood only); 4-DoF: also the uniform edges a batch
# measures the chance level on.
EXACT_PER_BATCH = 16


class MotionModel:
    """What a search needs to know of its motion model (see the module docstring)."""

    size: int  # correspondences per minimal subset

    def futility_draws(self, graph, smallest: int, confidence: float) -> float:
        """Stage-one draws after which no significant model is left (step 7)."""
        return futility_draws(graph, smallest, confidence, self.size)


class Triangles(MotionModel):
    """6-DoF: minimal subsets are compatible triangles (the paper's)."""

    size = 3  # correspondences per minimal subset
    score = 'inlier_count'
    refit_solver = (kabsch, 3)  # least-squares fit of step 8 and the points it needs
    chance_rows = 2  # first rows of each exactly scored batch, drawn unselected (step 7)
    resume_w1 = False  # a resumed stage one starts from w1 = 0 (its P1 bound: infinite)

    def compatibility_graph(self, src, dst, delta, min_pair_distance, workers):
        """Step 1: edges between length-consistent correspondences."""
        return build_compatibility_graph(src, dst, delta, min_pair_distance, workers)

    def draw(self, search, count: int) -> tuple[np.ndarray, np.ndarray]:
        """
        Step 2: ``count`` compatible triangles by edge and vertex tournament.

        Returns the usable triangles and their common-neighbour counts.
        """
        cfg = search.cfg
        i, j, k, support, status = compiled.draw_triples(
            search.rng, search.graph_arrays(), search.corr, search.delta, count,
            cfg.edge_tournament, cfg.vertex_tournament, compiled.VERTEX_PROPOSALS,
            MIN_TRIANGLE_AREA * search.tau ** 2)
        search.stats['empty_common_neighbourhood'] += int((status == compiled.EMPTY).sum())
        search.stats['rejected_collinear'] += int((status == compiled.COLLINEAR).sum())
        triples = np.stack([i, j, k], axis=1)
        search.sampled.append(triples[status != compiled.EMPTY])
        keep = status == 0
        return triples[keep], support[keep]

    def usable(self, search, subsets: np.ndarray) -> np.ndarray:
        """Mask of the triangles spanning :data:`MIN_TRIANGLE_AREA` tau^2 in both clouds."""
        min_area = MIN_TRIANGLE_AREA * search.tau ** 2
        if min_area <= 0 or len(subsets) == 0:
            return np.ones(len(subsets), dtype=bool)
        return compiled.usable_triangles(search.corr, subsets, min_area)

    def fit(self, corr, subsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Step 3: closed-form rigid fits R (B, 3, 3), t (B, 3) of the triangles."""
        return compiled.fit_triples(corr, subsets)

    def sample_inlier_probability(self, search) -> float:
        """Step 7: w1 for uniform edge and vertex sampling inside the best inliers."""
        return compatible_sample_inlier_probability(search.graph, search.best_inliers,
                                                    search.rng)

    def guided(self, search, rows, seed_weights, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Step 5: guided triangles (local indices of the members, (B, 3)) and an ok mask."""
        i, j, k, ok = compiled.draw_guided(search.rng, rows, seed_weights, count,
                                           XI, False)
        return np.stack([i, j, k], axis=1), ok


class Edges(MotionModel):
    """4-DoF: minimal subsets are compatible edges; the fit is a yaw and a translation."""

    size = 2
    score = 'truncated'
    refit_solver = (fit_yaw, 2)
    # No scored row is unselected: the chance level comes from uniform edges drawn apart
    # (:meth:`_record_chance`).
    chance_rows = 0
    # Resumed after a stage two whose model was not yet significant (the chance level
    # settles as uniform edges accumulate): from 0 its P1 bound would stay infinite until a
    # better model turned up, so one that became significant ran stage one to the cap.
    resume_w1 = True

    def compatibility_graph(self, src, dst, delta, min_pair_distance, workers):
        """Step 1: length-consistent edges whose vertical offsets agree within delta."""
        return build_vertical_compatibility_graph(src, dst, delta, vertical_offsets(src, dst),
                                                  min_pair_distance)

    def draw(self, search, count: int) -> tuple[np.ndarray, None]:
        """
        Step 2: ``count`` compatible edges by edge tournament.

        Edges too short across the gravity axis to fix the yaw are dropped.
        """
        self._record_chance(search, EXACT_PER_BATCH)
        i, j = compiled.draw_edges(search.rng, search.graph_arrays(), search.corr, search.delta,
                                   count, search.cfg.edge_tournament)
        edges = np.stack([i, j], axis=1)
        search.sampled.append(edges)
        ok = self.usable(search, edges)
        search.stats['rejected_collinear'] += int((~ok).sum())
        return edges[ok], None

    def _record_chance(self, search, count: int) -> None:
        """
        Score ``count`` uniformly drawn usable edges for the chance level only.

        Uniform over E (by soft weight), as the tournament's own candidates: no selection
        by common neighbours, whose winners are to a large share all-inlier edges when the
        graph is sparse (outliers spread wider than the model) and would read as chance.
        """
        i, j = compiled.draw_edges(search.rng, search.graph_arrays(), search.corr, search.delta,
                                   count, 1)
        ok = self.usable(search, np.stack([i, j], axis=1))
        if ok.any():
            R, t = fit_edges(search.src, search.dst, i[ok], j[ok])
            search.consensus.add_chance(compiled.residual_matrix(search.corr, R, t))

    def usable(self, search, subsets: np.ndarray) -> np.ndarray:
        """Mask of the edges at least :data:`MIN_EDGE_LENGTH` tau long across gravity."""
        min_length = MIN_EDGE_LENGTH * search.tau
        if min_length <= 0:
            return np.ones(len(subsets), dtype=bool)
        i, j = subsets[:, 0], subsets[:, 1]
        return ((horizontal_lengths(search.src, i, j) >= min_length)
                & (horizontal_lengths(search.dst, i, j) >= min_length))

    def fit(self, corr, subsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Step 3: closed-form yaw + translation fits of the edges."""
        return fit_edges(corr.src, corr.dst, subsets[:, 0], subsets[:, 1])

    def sample_inlier_probability(self, search) -> float:
        """Step 7: w1 = |E(I)| / |E| for uniform edge sampling inside the best inliers I."""
        graph = search.graph
        inside = graph.count_edges_within(search.best_inliers)
        return inside / graph.num_edges if graph.num_edges else 0.0

    def guided(self, search, rows, seed_weights, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Step 5: guided edges, j in N(i) with p ∝ K(i, j) + xi (no vertex step)."""
        i, j, _, ok = compiled.draw_guided(search.rng, rows, seed_weights, count,
                                           XI, True)
        return np.stack([i, j], axis=1), ok


def motion_model(name: str) -> MotionModel:
    """Return the strategy of ``CoreConfig.motion_model`` ('6dof' or '4dof')."""
    return Edges() if name == '4dof' else Triangles()
