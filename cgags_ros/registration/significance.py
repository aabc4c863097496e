"""
Significance of a consensus (step 7): the chance level and the best distinct alternative.

A real motion's consensus must stand above what a wrong hypothesis reaches by chance
(a non-randomness bound, as in PROSAC) and well above every distinct alternative
hypothesis; :class:`ConsensusRecord` keeps what both tests need while the search scores
hypotheses.
"""

from __future__ import annotations

import numpy as np

from .stopping import poisson_isf

_TOP_MODELS = 32  # consensus sets kept for the runner-up


class ConsensusRecord:
    """The inlier counts of unselected hypotheses and the largest consensus sets seen."""

    def __init__(self, tau: float, members: int = 3):
        # members: correspondences of a minimal subset (3; 2 for 4-DoF edges), which
        # every hypothesis fits by construction and so are no chance inliers.
        self.tau, self.members = tau, members
        self.num_chance = 0  # unselected hypotheses, whose extra inliers are chance ones
        self.num_zero = 0  # of them without an extra inlier
        self.num_exact = 0
        # The largest consensus sets, largest first (older first on ties): counts (K,) and
        # inlier masks (K, N), K <= _TOP_MODELS.
        self.top_counts = np.zeros(0, np.int64)
        self.top_masks: np.ndarray | None = None
        self._level: tuple[tuple, int] | None = None  # the last chance level and its inputs

    def add(self, res: np.ndarray, unselected: int) -> None:
        """
        Record a batch of exactly scored hypotheses (residual rows, metres).

        Its first ``unselected`` rows were not chosen by any score: their inlier counts
        measure the chance consensus level.
        """
        inside = res <= self.tau
        self._add_chance(inside[:unselected])
        self.num_exact += len(res)
        counts = inside.sum(axis=1)
        full = len(self.top_counts) >= _TOP_MODELS
        new = np.flatnonzero(counts > (self.top_counts[-1] if full else -1))
        if len(new) == 0:
            return
        # One stable sort of the kept and the new sets (the new in batch order): the same
        # selection as appending each and sorting, without a Python loop over the rows.
        both = np.concatenate([self.top_counts, counts[new]])
        keep = np.argsort(-both, kind='stable')[:_TOP_MODELS]
        masks = inside[new] if self.top_masks is None else np.concatenate(
            [self.top_masks, inside[new]])
        self.top_counts, self.top_masks = both[keep], masks[keep]

    def add_chance(self, res: np.ndarray) -> None:
        """
        Record hypotheses drawn and scored only to measure the chance level (residual rows).

        For a search whose every scored hypothesis was selected (4-DoF: an edge tournament
        that ranks edges by nearly their consensus, guided draws): these rows compete for
        neither the best model nor the runner-up, and do not count in the Bonferroni
        correction, which is over the hypotheses that could have won.
        """
        self._add_chance(res <= self.tau)

    def _add_chance(self, inside: np.ndarray) -> None:
        chance = np.maximum(inside.sum(axis=1) - self.members, 0)
        self.num_chance += len(chance)
        self.num_zero += int(np.count_nonzero(chance == 0))

    def chance_level(self, p1: float) -> int:
        """
        Return the inlier count a wrong hypothesis reaches with probability below 1 - P1.

        Chance inliers of a wrong hypothesis are ~ Poisson(lambda); lambda is estimated
        from the share of zero counts among hypotheses scored without pre-selection (robust
        to the few of them that happen to be near the true motion), with a +3 pseudo-count
        so that a handful of samples cannot make a small consensus look significant.
        """
        key = (self.num_zero, self.num_chance, self.num_exact, p1)
        if self._level is None or self._level[0] != key:  # the search asks every batch
            lam = -np.log(max(float(self.num_zero), 1.0) / (self.num_chance + 3.0))
            alpha = (1.0 - p1) / max(self.num_exact, 1)
            self._level = key, self.members + poisson_isf(alpha, lam) + 1
        return self._level[1]

    def runner_up(self, inliers: np.ndarray) -> int:
        """
        Return the largest consensus that shares under half of its inliers with ``inliers``.

        A real motion stands well above every distinct alternative.
        """
        if self.top_masks is None:
            return 0
        shared = np.count_nonzero(self.top_masks[:, inliers], axis=1)
        distinct = 2 * shared < self.top_counts
        return int(self.top_counts[distinct].max()) if distinct.any() else 0
