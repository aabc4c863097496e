"""
The search state of Algorithm 1 (:mod:`.cgags`): the two sampling stages and scoring.

Stage one draws minimal compatible subsets (step 2) until the P1 bound; stage two is the
preference-based accelerated guided sampling (steps 4-6) until the P2 bound (step 7). Both
fit and score hypotheses (step 3) into one best model, the preference lists and the
consensus record the significance test reads. What a minimal subset is (a triangle, or a
4-DoF edge) is the search's :mod:`.motion` model.
"""

from __future__ import annotations

import time

import numpy as np

from . import compiled
from .compatibility import CompatibilityGraph
from .hypotheses import score_values
from .motion import EXACT_PER_BATCH, MotionModel
from .preference import PreferenceLists
from .significance import ConsensusRecord
from .stopping import empirical_inlier_probability, ransac_bound
from ..config.core import CoreConfig
from ..geometry import make_transform

_MIN_BATCH = 32
# Mean common-neighbourhood size (share of N) of a batch's candidates above which the
# pre-screen scores them on all N correspondences instead: with many inliers the restricted
# gather costs more than full residuals; at high outlier ratios neighbourhoods are small
# and stay restricted (docs/method.md, "Pre-screening").
_DENSE_PRESCREEN = 0.2
# Entry lists cost about a graph build; without them each draw scans a bit row (same
# draws). Build them once ~N^2/6000 subsets were drawn, about when the row scans would have
# cost as much, and only while they stay cache-sized: beyond, their cache misses cost more
# than the scans.
_LISTS_BUILD_RATIO = 6000
_LISTS_MAX_ENTRIES = 1 << 19
_GIVE_UP_DRAWS = 4096  # draws without a single usable minimal subset: give up
_CHANCE_PER_BATCH = 2  # hypotheses per batch scored exactly whatever their pre-score
PREFERENCE_LENGTH = 20  # b: the length of each correspondence's preference list (paper: 20)
P2 = 0.99  # confidence of the guided stage's bound (paper: 0.99; P1 is core.p1)
MAX_UP = 3  # max_up (paper: 3): the kernel is recomputed at a new best at most this often
KERNEL_SUBSET = 400  # correspondences (best preference lists) guided sampling draws from
# Hypotheses a vectorized batch holds at most: batches start small and double, so easy
# problems stop early.
BATCH_SIZE = 512
# INFERRED stopping rule. 'adaptive': the RANSAC bound log(1-P)/log(1-w) per stage, w
# estimated from the best model's inliers inside the compatibility graph; 'fixed': always
# max_iterations (only tests set it).
STOPPING = 'adaptive'


class Search:
    """Sampling state of Algorithm 1: best hypothesis, preference lists, counters."""

    def __init__(self, src, dst, graph: CompatibilityGraph, motion: MotionModel,
                 cfg: CoreConfig, tau: float, delta: float, rng: np.random.Generator):
        self.corr = compiled.Correspondences.of(src, dst)  # (src, dst) as compiled code takes them
        self.src, self.dst = self.corr
        self.graph, self.motion = graph, motion
        self.cfg, self.tau, self.delta, self.rng = cfg, tau, delta, rng
        self.fixed = STOPPING == 'fixed'  # no adaptive bound: draw up to max_iterations
        self.num_hypotheses = 0  # minimal subsets fitted (the pre-screen fits the best)
        self.num_drawn = 0  # sampled, including subsets rejected before fitting (the cap)
        self.best_score, self.best_T = -np.inf, np.eye(4)
        self.best_inliers: np.ndarray | None = None
        self.best_mask = np.zeros(graph.n, dtype=bool)
        self.preference = PreferenceLists(graph.n, PREFERENCE_LENGTH)
        self.sampled: list[np.ndarray] = []  # stage-one subsets, to estimate w1 empirically
        self.consensus = ConsensusRecord(tau, motion.size)
        self.start = time.perf_counter()
        self.w1 = 0.0  # all-inlier probability of a stage-one sample, at its last estimate
        self.stopped_by = 'max_iterations'
        self.futile = False  # stage one ruled out any significant model
        self.no_usable_subset = False
        self.restarts = 0  # stage one resumed after a stage two without a significant model
        self.stats = {'compatible_samples': 0, 'guided_samples': 0, 'rejected_collinear': 0,
                      'empty_common_neighbourhood': 0, 'kernel_refreshes': 0,
                      'best_updates': 0, 'best_found_at': 0, 'stage_one_bound': float('inf'),
                      'stage_two_bound': float('inf')}

    def report(self) -> dict:
        """Return the counters and how the search ended, for ``RegistrationResult.stats``."""
        return dict(self.stats, stopped_by=self.stopped_by, restarts=self.restarts)

    # --- stage one: steps 2, 3 and 7 (P1) ---------------------------------------------------
    def compatible_stage(self) -> None:
        cfg, n1, batch = self.cfg, 0, _MIN_BATCH
        w1 = (self._stage_one_inlier_probability()
              if self.motion.resume_w1 and self.best_inliers is not None else 0.0)
        while self.num_drawn < cfg.max_iterations and not self.out_of_time():
            batch = min(batch, cfg.max_iterations - self.num_drawn)
            self.num_drawn += batch
            subsets, support = self.motion.draw(self, batch)
            if self.num_hypotheses == 0 and self.num_drawn >= _GIVE_UP_DRAWS:
                self.stopped_by, self.no_usable_subset = 'no_usable_triangle', True
                break
            n1 += batch
            self.stats['compatible_samples'] += batch
            if self.evaluate(subsets, support):
                w1 = self._stage_one_inlier_probability()
            bound = ransac_bound(cfg.p1, w1)
            self.stats.update(stage_one_bound=bound, stage_one_w=w1)
            if (not self.fixed and n1 >= bound
                    and self.significant()):
                self.stopped_by = 'p1_bound'
                break
            if (not self.fixed and cfg.futility_stop and not self.significant()
                    and self.stats['compatible_samples'] >= self.motion.futility_draws(
                        self.graph, max(cfg.min_inliers, self.chance_level()), cfg.p1)):
                self.stopped_by, self.futile = 'no_significant_model', True
                break
            if self.fixed and cfg.guided_sampling and n1 >= bound:
                break
            batch = min(2 * batch, BATCH_SIZE)
        self.w1 = w1

    def _stage_one_inlier_probability(self) -> float:
        """
        Return w1, the probability that one stage-one sample is all-inlier.

        The best model's inliers are taken as the inlier set. w1 is the larger of the
        value for uniform sampling (:meth:`.MotionModel.sample_inlier_probability`) and
        the observed share of all stage-one samples drawn so far inside the set: the
        tournaments draw inliers far more often than uniform sampling.
        """
        analytic = self.motion.sample_inlier_probability(self)
        observed = empirical_inlier_probability(self.sampled, self.best_mask)
        return max(analytic, observed)

    def graph_arrays(self) -> compiled.GraphArrays:
        """Return the graph for the samplers, with its entry lists once the search is long."""
        if (self.num_drawn <= self.graph.n ** 2 // _LISTS_BUILD_RATIO
                or 2 * self.graph.num_edges > _LISTS_MAX_ENTRIES):
            return self.graph.arrays()  # the same draws, by bit-row scans
        return self.graph.arrays(self.graph.entry_lists())

    # --- step 3: hypotheses -----------------------------------------------------------------
    def evaluate(self, subsets: np.ndarray, support: np.ndarray | None = None) -> bool:
        """
        Fit and score a batch of minimal subsets; update the best model and the preferences.

        ``support`` holds the subsets' common-neighbour counts when the sampler knows them.
        Returns True when the best model improved.
        """
        if len(subsets) == 0:
            return False
        cfg, motion, chance = self.cfg, self.motion, self.motion.chance_rows
        self.num_hypotheses += len(subsets)
        if len(subsets) > EXACT_PER_BATCH:
            # Two cheap filters before exact scoring: the subset's common-neighbour count
            # (an upper bound on its restricted score), then the restricted score itself.
            # Only the subsets that pass the first filter are fitted (the others' transforms
            # would never be used), plus the first `chance_rows`: subsets arrive in random
            # order, so these are unselected hypotheses (the chance level, step 7).
            cand = np.arange(len(subsets))
            if support is None:
                support = compiled.common_support(self.graph.words, subsets)
            if len(subsets) > 4 * EXACT_PER_BATCH:
                kept = 4 * EXACT_PER_BATCH
                cand = np.argpartition(-support, kept - 1)[:kept]
            fitted = np.concatenate([np.arange(_CHANCE_PER_BATCH), cand])
            R, t = motion.fit(self.corr, subsets[fitted])
            Rc, tc = R[_CHANCE_PER_BATCH:], t[_CHANCE_PER_BATCH:]
            # Common neighbourhoods spanning much of N: score on all N (the exact score).
            dense = support[cand].mean() >= _DENSE_PRESCREEN * self.graph.n
            pre = compiled.prescreen_scores(self.graph.words, self.corr, Rc, tc, subsets[cand],
                                            self.tau, motion.score == 'truncated', dense)
            top = np.argpartition(-pre, EXACT_PER_BATCH - 1)[: EXACT_PER_BATCH]
            top = np.concatenate([np.arange(_CHANCE_PER_BATCH), _CHANCE_PER_BATCH + top])
            R, t = R[top], t[top]
        else:
            R, t = motion.fit(self.corr, subsets)
        res = compiled.residual_matrix(self.corr, R, t)
        # Random hypotheses' inlier counts measure the chance consensus level.
        self.consensus.add(res, chance)
        if cfg.guided_sampling:
            self.preference.update(res)
        scores = score_values(res, self.tau, motion.score).sum(axis=1)
        best = int(np.argmax(scores))
        if scores[best] <= self.best_score:
            return False
        self.best_score = float(scores[best])
        self.best_T = make_transform(R[best], t[best])
        self.best_inliers = np.flatnonzero(res[best] <= self.tau)
        self.best_mask[:] = False
        self.best_mask[self.best_inliers] = True
        self.stats['best_updates'] += 1
        self.stats['best_found_at'] = self.num_drawn  # the draws the best model took to find
        return True

    # --- step 7: significance and the caps ---------------------------------------------------
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
        """Tell whether the cap or time budget is used up, or sampling was given up."""
        return (self.num_drawn >= self.cfg.max_iterations or self.out_of_time()
                or self.futile or self.no_usable_subset)

    def out_of_time(self) -> bool:
        if self.cfg.time_budget > 0 and time.perf_counter() - self.start > self.cfg.time_budget:
            self.stopped_by = 'time_budget'
            return True
        return False

    # --- stage two: steps 4-6 and 7 (P2) -----------------------------------------------------
    def guided_stage(self) -> None:
        """
        Draw guided subsets until the P2 bound, counting every draw of the stage.

        As adaptive RANSAC, w2 is re-estimated over all the stage's draws against each new
        best model (never below w1); the kernel K is refreshed at a new best model at most
        :data:`MAX_UP` times (step 6).
        """
        cfg, motion = self.cfg, self.motion
        members, rows, seed_w = self._guided_rows()
        refreshes = 1
        n2 = hits = 0
        drawn: list[np.ndarray] = []  # the stage's subsets, re-counted at a new best model
        batch = _MIN_BATCH
        while self.num_drawn < cfg.max_iterations and not self.out_of_time():
            batch = min(batch, cfg.max_iterations - self.num_drawn)
            self.num_drawn += batch
            local, ok = motion.guided(self, rows, seed_w, batch)
            subsets = members[local][ok]
            usable = motion.usable(self, subsets)
            self.stats['rejected_collinear'] += int((~usable).sum())
            subsets = subsets[usable]
            self.stats['guided_samples'] += batch
            drawn.append(subsets)
            n2 += batch
            if self.evaluate(subsets):
                hits = sum(int(self.best_mask[d].all(axis=1).sum()) for d in drawn if len(d))
                if refreshes <= MAX_UP:
                    members, rows, seed_w = self._guided_rows()
                    refreshes += 1
            elif len(subsets):
                hits += int(self.best_mask[subsets].all(axis=1).sum())
            self.stats['guided_hits'], self.stats['guided_n'] = hits, n2
            w2 = max(hits / n2 if n2 else 0.0, self.w1)
            bound = ransac_bound(P2, w2)
            self.stats['stage_two_bound'] = bound
            self.stats['stage_two_w'] = w2
            if not self.fixed and n2 >= bound:
                self.stopped_by = 'p2_bound'
                break
            batch = min(2 * batch, BATCH_SIZE)
        self.stats['kernel_refreshes'] = refreshes

    def _guided_rows(self):
        """
        Return the members, their kernel and adjacency rows, and seed weights (step 5).

        The members are the correspondences guided sampling draws from: at most
        :data:`KERNEL_SUBSET` of them by their preference lists' quality, and the best
        model's inliers; their rows (:func:`.compiled.guided_rows`) hold the intersection
        kernel K (step 4) and their compatibility, each row computed when a draw first
        reads it. Seeds are drawn uniformly from the best model's inliers.
        """
        n = self.graph.n
        if n <= KERNEL_SUBSET:
            members = np.arange(n)
        else:
            order = np.argsort(self.preference.quality(), kind='stable')
            members = np.union1d(order[:KERNEL_SUBSET], self.best_inliers)
        rows = compiled.guided_rows(self.preference.kernel_bits(members), self.preference.b,
                                    self.graph.words, members)
        seed_w = np.isin(members, self.best_inliers).astype(np.float64)
        return members, rows, seed_w
