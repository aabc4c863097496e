"""
4-DoF sampling state of Algorithm 1: edges as minimal subsets (steps 2, 5 and 7).

Adapts the paper's minimal compatible subset (METHOD.md step 2), its guided sampling
(step 5) and the stopping bound's all-inlier probability (step 7) to the yaw + translation
model of :mod:`.yaw`: two correspondences determine a hypothesis, so a minimal subset is a
compatible edge (i, j), drawn by graph edge sampling exactly as the first half of the 6-DoF
triangle (no vertex step). Guided sampling draws the seed i and its partner j by the
preference kernel, and the P1/P2 bounds count all-inlier edges.

An edge is stored as the triple (i, j, j), so the scoring, pre-screening (on
N(i) ∩ N(j)), preference lists, consensus record and the all-inlier counts of
:class:`~.search.Search` apply to it unchanged; only the chance level of the significance
test is measured apart, on uniformly drawn edges (see ``CHANCE_ROWS``).
"""

from __future__ import annotations

import numpy as np

from . import compiled
from .search import Search
from .stopping import empirical_inlier_probability
from .yaw import fit_edges, fit_yaw, horizontal_lengths


class EdgeSearch(Search):
    """Search of Algorithm 1 whose minimal subsets are compatible edges (4-DoF)."""

    SUBSET_SIZE = 2
    REFIT = (fit_yaw, 2)  # hypotheses.refit solves yaw + translation from >= 2 inliers
    # No scored row is unselected: an edge's common neighbours are nearly the consensus of
    # its yaw fit (two lengths and a height place a point up to a mirror image), so the edge
    # tournament already picks by consensus, and guided draws start from the best inliers.
    # The chance level comes from uniform edges drawn apart (_record_chance).
    CHANCE_ROWS = 0
    # Resumed after a stage two whose best model was not yet significant (the chance level
    # settles as uniform edges accumulate): from 0 its P1 bound would stay infinite until a
    # better model turned up, so one that became significant ran stage one to the cap.
    RESUME_W1 = True

    def fit(self, triples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the closed-form yaw + translation fits of edges stored as (i, j, j)."""
        return fit_edges(self.src, self.dst, triples[:, 0], triples[:, 1])

    def minimal_compatible_subsets(self, count: int) -> tuple[np.ndarray, None]:
        """
        Draw ``count`` minimal subsets of the 4-DoF model: compatible edges, as (i, j, j).

        Edges too short across the gravity axis to fix the yaw are dropped.
        """
        self._record_chance(self.cfg.exact_per_batch)
        i, j, _ = self.compatible_edges(count)
        edges = np.stack([i, j, j], axis=1)
        self.sampled.append(edges)
        return self._keep_non_collinear(edges)

    def _record_chance(self, count: int) -> None:
        """
        Score ``count`` uniformly drawn usable edges for the chance level only.

        Uniform over E (soft: by weight), as the tournament's own candidates: no selection
        by common neighbours, whose winners are to a large share all-inlier edges when the
        graph is sparse (outliers spread wider than the model) and would read as chance.
        """
        i, j = compiled.draw_edges(self.rng, self.graph.arrays(self.lists()), self.corr,
                                   self.delta, count, 1)
        ok = self._usable(i, j)
        if ok.any():
            R, t = fit_edges(self.src, self.dst, i[ok], j[ok])
            self.consensus.add_chance(compiled.residual_matrix(self.corr, R, t))

    def _usable(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Mask of the edges long enough across the gravity axis to fix the yaw."""
        min_length = self.cfg.min_edge_length_factor * self.tau
        if min_length <= 0:
            return np.ones(len(i), dtype=bool)
        return ((horizontal_lengths(self.src, i, j) >= min_length)
                & (horizontal_lengths(self.dst, i, j) >= min_length))

    def _keep_non_collinear(self, triples: np.ndarray, support: np.ndarray | None = None
                            ) -> tuple[np.ndarray, np.ndarray | None]:
        if len(triples) == 0:
            return triples, support
        ok = self._usable(triples[:, 0], triples[:, 1])
        self.stats['rejected_collinear'] += int((~ok).sum())
        return triples[ok], None if support is None else support[ok]

    def _stage_one_inlier_probability(self) -> float:
        """
        Return w1, the probability that one stage-one edge is all-inlier.

        Uniform edge sampling gives |E(I)| / |E| for the best model's inliers I; the
        'observed' estimate takes the larger of that and the share of drawn edges inside I.
        """
        e_in = self.graph.count_edges_within(self.best_inliers)
        analytic = e_in / self.graph.num_edges if self.graph.num_edges else 0.0
        if self.cfg.stage_one_estimate == 'analytic':
            return analytic
        return max(analytic, empirical_inlier_probability(self.sampled, self.best_mask))

    def draw_guided(self, rows, seed_w, count):
        """Guided edges (local indices i, j, j): j in N(i) with p ∝ K(i, j) + xi."""
        return compiled.draw_guided(self.rng, rows, seed_w, count, self.cfg.xi, True)
