"""
The search state of Algorithm 1 (:mod:`.cgags`): the two sampling stages and scoring.

Stage one draws minimal compatible subsets (a compatible edge, then a common-neighbour
vertex) until the P1 bound; stage two is the preference-based accelerated guided sampling
until the P2 bound. Both feed one best model, the preference lists and the counters the
stopping rules and the significance test read.
"""

from __future__ import annotations

import time

import numpy as np

from . import compiled
from .compatibility import CompatibilityGraph
from .hypotheses import refit, score_values
from .preference import PreferenceLists
from .rigid import residuals
from .sampling import sample_common_vertex
from .significance import ConsensusRecord
from .stopping import (compatible_sample_inlier_probability, empirical_inlier_probability,
                       futility_draws, ransac_bound)
from ..config.core import CoreConfig
from ..geometry import make_transform

_MIN_BATCH = 32
# Mean common-neighbourhood size (share of N) of a batch's candidates above which the
# pre-screen scores them on all N correspondences instead: with many inliers the restricted
# gather costs more than full residuals; at high outlier ratios neighbourhoods are small
# and stay restricted (docs/implementation.md).
_DENSE_PRESCREEN = 0.2
# Entry lists cost about a graph build; without them each draw scans a bit row (same
# draws). Build them once ~N^2/6000 triples were drawn, about when the row scans would have
# cost as much, and only while they stay cache-sized: beyond, their cache misses cost more
# than the scans (docs/implementation.md).
_LISTS_BUILD_RATIO = 6000
_LISTS_MAX_ENTRIES = 1 << 19
_GIVE_UP_DRAWS = 4096  # draws without a single usable (non-collinear) triangle: give up
_CHANCE_PER_BATCH = 2  # hypotheses per batch scored exactly whatever their pre-score


class Search:
    """Sampling state of Algorithm 1: best hypothesis, preference lists, counters."""

    SUBSET_SIZE = 3  # correspondences per minimal subset (a triangle)
    REFIT = ()  # extra arguments of hypotheses.refit: the 6-DoF defaults (Kabsch)
    CHANCE_ROWS = _CHANCE_PER_BATCH  # of those rows, the ones counted for the chance level
    RESUME_W1 = False  # stage one resumed after stage two: from w1 = 0, not the best's

    def __init__(self, src, dst, graph: CompatibilityGraph, cfg: CoreConfig, tau: float,
                 delta: float, rng: np.random.Generator):
        self.corr = compiled.Correspondences.of(src, dst)  # (src, dst) as compiled code takes them
        self.src, self.dst = self.corr
        self.graph, self.cfg = graph, cfg
        self.tau, self.delta, self.rng = tau, delta, rng
        self.num_hypotheses = 0  # minimal subsets generated (the pre-screen fits the best)
        self.num_drawn = 0  # sampled, including triples rejected before fitting (the cap)
        self.best_score, self.best_T = -np.inf, np.eye(4)
        self.best_inliers: np.ndarray | None = None
        self.best_mask = np.zeros(graph.n, dtype=bool)
        self.improvements = 0
        self.preference = PreferenceLists(graph.n, cfg.preference_length)
        self.vertex_weights = (graph.degree.astype(np.float64)
                               if cfg.vertex_sampling == 'degree' else None)
        self.sampled: list[np.ndarray] = []  # stage-one triples, to estimate w1 empirically
        self.consensus = ConsensusRecord(tau, self.SUBSET_SIZE)
        self.start = time.perf_counter()
        self.no_lists = np.zeros((0, 2), np.int32)
        self.stats = {'compatible_samples': 0, 'guided_samples': 0, 'rejected_collinear': 0,
                      'empty_common_neighbourhood': 0, 'kernel_refreshes': 0,
                      'best_updates': 0, 'stage_one_bound': float('inf'),
                      'stage_two_bound': float('inf'), 'stopped_by': 'max_iterations'}

    # --- stage one ------------------------------------------------------------------------
    def compatible_stage(self) -> None:
        cfg, n1, batch = self.cfg, 0, _MIN_BATCH
        w1 = (self._stage_one_inlier_probability()
              if self.RESUME_W1 and self.best_inliers is not None else 0.0)
        while self.num_drawn < cfg.max_iterations and not self.out_of_time():
            batch = min(batch, cfg.max_iterations - self.num_drawn)
            self.num_drawn += batch
            triples, support = self.minimal_compatible_subsets(batch)
            if self.num_hypotheses == 0 and self.num_drawn >= _GIVE_UP_DRAWS:
                self.stats['stopped_by'] = 'no_usable_triangle'
                break
            n1 += batch
            self.stats['compatible_samples'] += batch
            if self.evaluate(triples, support):
                w1 = self._stage_one_inlier_probability()
            bound = ransac_bound(cfg.p1, w1)
            self.stats.update(stage_one_bound=bound, stage_one_w=w1)
            if (cfg.stopping == 'adaptive' and n1 >= max(bound, cfg.min_iterations)
                    and self.significant()):
                self.stats['stopped_by'] = 'p1_bound'
                break
            if (cfg.stopping == 'adaptive' and cfg.futility_stop and not self.significant()
                    and self.stats['compatible_samples'] >= futility_draws(
                        self.graph, max(cfg.min_inliers, self.chance_level()), cfg.p1,
                        self.SUBSET_SIZE)):
                self.stats['stopped_by'] = 'no_significant_model'
                break
            if (cfg.guided_sampling and cfg.guided_start == 'after_b_hypotheses'
                    and self.preference.num_hypotheses >= cfg.preference_length
                    and self.best_inliers is not None):
                break
            if cfg.stopping == 'fixed' and cfg.guided_sampling and n1 >= bound:
                break
            batch = min(2 * batch, cfg.batch_size)
        self.w1 = w1

    def _stage_one_inlier_probability(self) -> float:
        """
        Return w1, the probability that one stage-one sample is all-inlier.

        The best model's inliers are taken as the inlier set. w1 is the larger of the
        analytic value for uniform edge and vertex sampling and the observed share of all
        stage-one samples drawn so far that lie inside the set (which also covers the
        tournament samplers).
        """
        analytic = compatible_sample_inlier_probability(self.graph, self.best_inliers, self.rng)
        if self.cfg.stage_one_estimate == 'analytic':
            return analytic
        observed = empirical_inlier_probability(self.sampled, self.best_mask)
        return max(analytic, observed)

    def minimal_compatible_subsets(self, count: int) -> tuple[np.ndarray, np.ndarray | None]:
        """
        Draw ``count`` minimal compatible subsets, the triples (i, j, k).

        Each is a compatible edge (graph edge sampling), then a vertex k in N(i) ∩ N(j)
        (graph vertex sampling), each uniform or by tournament (see config). Returns the
        non-collinear triples and, when known, their common-neighbour counts.
        """
        cfg = self.cfg
        if cfg.vertex_sampling != 'tournament':
            i, j, csr = self.compatible_edges(count)
            k, ok = sample_common_vertex(self.graph, self.rng, i, j,
                                         weights=self.vertex_weights, csr=csr)
            self.stats['empty_common_neighbourhood'] += int((~ok).sum())
            triples = np.stack([i, j, k], axis=1)[ok]
            self.sampled.append(triples)
            return self._keep_non_collinear(triples)
        i, j, k, support, status = compiled.draw_triples(
            self.rng, self.graph.arrays(self.lists()), self.corr, self.delta, count,
            self.edge_tournament_size(), cfg.vertex_tournament, compiled.VERTEX_PROPOSALS,
            cfg.min_triangle_area_factor * self.tau ** 2)
        self.stats['empty_common_neighbourhood'] += int((status == compiled.EMPTY).sum())
        self.stats['rejected_collinear'] += int((status == compiled.COLLINEAR).sum())
        triples = np.stack([i, j, k], axis=1)
        self.sampled.append(triples[status != compiled.EMPTY])
        keep = status == 0
        return triples[keep], support[keep]

    def edge_tournament_size(self) -> int:
        return self.cfg.edge_tournament if self.cfg.edge_sampling == 'tournament' else 1

    def lists(self) -> np.ndarray:
        """Return the CSR neighbour indices once the search is long, else empty (same draws)."""
        if (self.num_drawn <= self.graph.n ** 2 // _LISTS_BUILD_RATIO
                or 2 * self.graph.num_edges > _LISTS_MAX_ENTRIES):
            return self.no_lists
        pairs = self.graph.entry_lists()
        return self.no_lists if pairs is None else pairs

    def compatible_edges(self, count: int):
        """Draw ``count`` compatible edges i, j (graph edge sampling); the lists used or None."""
        lists = self.lists()
        i, j = compiled.draw_edges(self.rng, self.graph.arrays(lists), self.corr, self.delta,
                                   count, self.edge_tournament_size())
        return i, j, ((self.graph.indptr, lists[:, 1]) if len(lists) else None)

    def _keep_non_collinear(self, triples: np.ndarray, support: np.ndarray | None = None
                            ) -> tuple[np.ndarray, np.ndarray | None]:
        min_area = self.cfg.min_triangle_area_factor * self.tau ** 2
        if min_area <= 0 or len(triples) == 0:
            return triples, support
        ok = compiled.usable_triangles(self.corr, triples, min_area)
        self.stats['rejected_collinear'] += int((~ok).sum())
        return triples[ok], None if support is None else support[ok]

    # --- hypotheses -------------------------------------------------------------------------
    def fit(self, triples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the closed-form fits R (B, 3, 3), t (B, 3) of minimal subsets (rows)."""
        return compiled.fit_triples(self.corr, triples)

    def evaluate(self, triples: np.ndarray, support: np.ndarray | None = None) -> bool:
        """
        Fit and score a batch of triples; update the best model and the preference lists.

        ``support`` holds the triples' common-neighbour counts when the sampler knows them.
        Returns True when the best model improved.
        """
        if len(triples) == 0:
            return False
        cfg = self.cfg
        self.num_hypotheses += len(triples)
        if cfg.prescreen and len(triples) > cfg.exact_per_batch:
            # Two cheap filters before exact scoring: the triple's common-neighbour count
            # (an upper bound on its restricted score), then the restricted score itself.
            # Only the triples that pass the first filter are fitted (the others' transforms
            # would never be used), plus the first _CHANCE_PER_BATCH: triples arrive in
            # random order, so these are unselected hypotheses (the chance level).
            cand = np.arange(len(triples))
            subsets = np.ascontiguousarray(triples[:, :self.SUBSET_SIZE])  # 4-DoF: edges (i, j)
            if support is None:
                support = compiled.common_support(self.graph.words, subsets)
            if len(triples) > 4 * cfg.exact_per_batch:
                kept = 4 * cfg.exact_per_batch
                cand = np.argpartition(-support, kept - 1)[:kept]
            fitted = np.concatenate([np.arange(_CHANCE_PER_BATCH), cand])
            R, t = self.fit(triples[fitted])
            Rc, tc = R[_CHANCE_PER_BATCH:], t[_CHANCE_PER_BATCH:]
            # Common neighbourhoods spanning much of N: score on all N (the exact score).
            dense = support[cand].mean() >= _DENSE_PRESCREEN * self.graph.n
            pre = compiled.prescreen_scores(self.graph.words, self.corr, Rc, tc, subsets[cand],
                                            self.tau, cfg.score == 'truncated', dense)
            top = np.argpartition(-pre, cfg.exact_per_batch - 1)[: cfg.exact_per_batch]
            top = np.concatenate([np.arange(_CHANCE_PER_BATCH), _CHANCE_PER_BATCH + top])
            R, t = R[top], t[top]
        else:
            R, t = self.fit(triples)
        res = compiled.residual_matrix(self.corr, R, t)
        # Random hypotheses' inlier counts measure the chance consensus level.
        self.consensus.add(res, self.CHANCE_ROWS)
        if cfg.guided_sampling:
            self.preference.update(res)
        scores = score_values(res, self.tau, cfg.score).sum(axis=1)
        best = int(np.argmax(scores))
        if scores[best] <= self.best_score:
            return False
        self.best_score = float(scores[best])
        self.best_T = make_transform(R[best], t[best])
        if cfg.max_up_mode == 'local_refits' and cfg.max_up > 0:
            T, _, _ = refit(self.src, self.dst, self.best_T, self.tau, cfg.max_up,
                            *self.REFIT)
            self.best_T = T
            res_best = residuals(T, self.src, self.dst)
            self.best_score = float(score_values(res_best, self.tau, cfg.score).sum())
            self.best_inliers = np.flatnonzero(res_best <= self.tau)
        else:
            self.best_inliers = np.flatnonzero(res[best] <= self.tau)
        self.best_mask[:] = False
        self.best_mask[self.best_inliers] = True
        self.improvements += 1
        self.stats['best_updates'] += 1
        return True

    def chance_level(self) -> int:
        """Return the inlier count a wrong hypothesis reaches by chance (see significance)."""
        return self.consensus.chance_level(self.cfg.p1)

    def runner_up(self, inliers: np.ndarray) -> int:
        """Return the largest consensus distinct from ``inliers`` (see significance)."""
        return self.consensus.runner_up(inliers)

    def significant(self, inliers: np.ndarray | None = None) -> bool:
        inliers = self.best_inliers if inliers is None else inliers
        if inliers is None or len(inliers) < self.chance_level():
            return False
        return len(inliers) >= self.cfg.distinct_ratio * self.runner_up(inliers)

    def exhausted(self) -> bool:
        """Tell whether the hypothesis cap or time budget is used up, or no triangle is usable."""
        return (self.num_drawn >= self.cfg.max_iterations or self.out_of_time()
                or self.futile or self.stats['stopped_by'] == 'no_usable_triangle')

    @property
    def futile(self) -> bool:
        """Tell whether stage one ruled out any significant model (futility_draws)."""
        return self.stats['stopped_by'] == 'no_significant_model'

    def out_of_time(self) -> bool:
        if self.cfg.time_budget > 0 and time.perf_counter() - self.start > self.cfg.time_budget:
            self.stats['stopped_by'] = 'time_budget'
            return True
        return False

    # --- stage two --------------------------------------------------------------------------
    def guided_stage(self) -> None:
        cfg = self.cfg
        members, rows, seed_w = self._kernel()
        refreshes = 1
        start_improvements = self.improvements
        n2 = hits = 0
        drawn: list[np.ndarray] = []  # all_draws: the stage's triples, re-counted at a new best
        batch = _MIN_BATCH
        while self.num_drawn < cfg.max_iterations and not self.out_of_time():
            batch = min(batch, cfg.max_iterations - self.num_drawn)
            self.num_drawn += batch
            li, lj, lk, ok = self.draw_guided(rows, seed_w, batch)
            drawn_now = np.stack([members[li], members[lj], members[lk]], 1)[ok]
            triples, _ = self._keep_non_collinear(drawn_now)
            self.stats['guided_samples'] += batch
            if cfg.guided_count == 'all_draws':
                drawn.append(triples)
            n2 += batch
            improved = self.evaluate(triples)
            if cfg.guided_count == 'since_improvement' and improved:
                n2 = hits = 0
            elif improved:  # as adaptive RANSAC: all draws count, w2 from the new best
                hits = sum(int(self.best_mask[d].all(axis=1).sum()) for d in drawn if len(d))
            else:
                hits += int(self.best_mask[triples].all(axis=1).sum()) if len(triples) else 0
            if improved:
                updates = self.improvements - start_improvements
                if cfg.max_up_mode == 'best_updates' and updates >= cfg.max_up:
                    self.stats['stopped_by'] = 'max_up_best_updates'
                    break
                if cfg.max_up_mode != 'preference_refreshes' or refreshes <= cfg.max_up:
                    members, rows, seed_w = self._kernel()
                    refreshes += 1
            self.stats['guided_hits'], self.stats['guided_n'] = hits, n2
            w2 = max(hits / n2 if n2 else 0.0, getattr(self, 'w1', 0.0))
            bound = ransac_bound(cfg.p2, w2)
            self.stats['stage_two_bound'] = bound
            self.stats['stage_two_w'] = w2
            if cfg.stopping == 'adaptive' and n2 >= max(bound, cfg.min_iterations):
                self.stats['stopped_by'] = 'p2_bound'
                break
            batch = min(2 * batch, cfg.batch_size)
        self.stats['kernel_refreshes'] = refreshes

    def draw_guided(self, rows, seed_w, count):
        """Draw ``count`` guided minimal subsets (local indices i, j, k and an ok mask)."""
        return compiled.draw_guided(self.rng, rows, seed_w, count, self.cfg.xi, False)

    def _kernel(self):
        """
        Return the members, their kernel and adjacency rows, and seed weights.

        The members are the M correspondences guided sampling draws from; the rows
        (:func:`.compiled.guided_rows`) hold their intersection kernel K and their
        compatibility adjacency, each row computed when a draw first reads it.
        """
        cfg, n = self.cfg, self.graph.n
        if cfg.kernel_subset == 0 or n <= cfg.kernel_subset:
            members = np.arange(n)
        else:
            order = np.argsort(self.preference.quality(), kind='stable')
            members = np.union1d(order[: cfg.kernel_subset], self.best_inliers)
        rows = compiled.guided_rows(self.preference.kernel_bits(members), self.preference.b,
                                    self.graph.words, members)
        if cfg.guided_seed == 'best_inliers':
            seed_w = np.isin(members, self.best_inliers).astype(np.float64)
        else:
            kernel, adjacency = self.preference.kernel(members), self.graph.adjacency(members)
            seed_w = ((kernel * adjacency).sum(axis=1) + cfg.xi).astype(np.float64)
        return members, rows, seed_w
