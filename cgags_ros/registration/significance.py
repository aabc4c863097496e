"""
Significance of a consensus: the chance level and the best distinct alternative.

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
        self.top_models: list[tuple[int, np.ndarray]] = []  # (count, inlier mask (N,))
        self._level: tuple[tuple, int] | None = None  # the last chance level and its inputs

    def add(self, res: np.ndarray, unselected: int) -> None:
        """
        Record a batch of exactly scored hypotheses (residual rows, metres).

        Its first ``unselected`` rows were not chosen by any score: their inlier counts
        measure the chance consensus level.
        """
        inside = res <= self.tau
        chance = np.maximum(inside[:unselected].sum(axis=1) - self.members, 0)
        self.num_chance += len(chance)
        self.num_zero += int(np.count_nonzero(chance == 0))
        self.num_exact += len(res)
        counts = inside.sum(axis=1)
        floor = self.top_models[-1][0] if len(self.top_models) >= _TOP_MODELS else -1
        for e in np.flatnonzero(counts > floor):
            self.top_models.append((int(counts[e]), inside[e].copy()))  # not the batch
        self.top_models.sort(key=lambda m: -m[0])
        del self.top_models[_TOP_MODELS:]

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
        best = 0
        for count, mask in self.top_models:
            if count > best and 2 * np.count_nonzero(mask[inliers]) < count:
                best = count
        return best
