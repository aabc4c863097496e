"""
Preference lists and the intersection kernel K (step 4; Multi-GS / AGS style).

Each correspondence keeps the b hypotheses under which its residual is smallest (its
preference list T_i, "top-b residual ranks"). Two inliers of the same rigid motion prefer
the same good hypotheses, so the kernel K(i, j) = |T_i ∩ T_j| / b is high between inliers
and low elsewhere; guided sampling draws partners in proportion to it.
"""

from __future__ import annotations

import numpy as np

from . import compiled

_PENDING_LIMIT = 1 << 22  # residuals held back before they are merged anyway (16 MB)


class PreferenceLists:
    """
    The preference lists of N correspondences.

    New hypotheses' residuals are merged when the lists are next read (kernel, quality,
    ``ids``/``residuals``), in the order they came: the same lists, but the search's last
    batches, which nothing reads, are never merged (each merge is a pass over all N lists).
    """

    def __init__(self, n: int, b: int):
        self.b = b
        self._residuals = np.full((n, b), np.inf, dtype=np.float32)
        self._ids = np.full((n, b), -1, dtype=np.int64)
        self.num_hypotheses = 0
        self._pending: list[tuple[np.ndarray, int]] = []  # (residual rows, first id)
        self._pending_size = 0

    def update(self, residuals: np.ndarray) -> None:
        """Add the residual rows (E, N) of E new hypotheses (ids assigned in order)."""
        e = len(residuals)
        if e == 0:
            return
        self._pending.append((compiled.c_array(residuals, np.float32),
                              self.num_hypotheses))
        self._pending_size += residuals.size
        self.num_hypotheses += e
        if self._pending_size > _PENDING_LIMIT:
            self._merge()

    def _merge(self) -> None:
        for rows, first in self._pending:
            compiled.merge_preferences(self._residuals, self._ids, rows, first)
        self._pending.clear()
        self._pending_size = 0

    @property
    def residuals(self) -> np.ndarray:
        """(N, b) float32 residuals of each list, ascending; inf in empty slots."""
        self._merge()
        return self._residuals

    @property
    def ids(self) -> np.ndarray:
        """(N, b) int64 hypothesis ids of each list, in residual order; -1 in empty slots."""
        self._merge()
        return self._ids

    def quality(self) -> np.ndarray:
        """Median residual over each correspondence's list (inf while it is under half full)."""
        b = self.b  # lists are sorted ascending (merge_preferences): the middle entries
        if b % 2:
            return self.residuals[:, b // 2].copy()
        return (self.residuals[:, b // 2 - 1] + self.residuals[:, b // 2]) / np.float32(2.0)

    def kernel_bits(self, members: np.ndarray) -> np.ndarray:
        """Return the members' lists as bit rows (M, W) uint64, whose ANDs give the kernel."""
        return compiled.preference_bits(self.ids, compiled.c_array(members, np.int64),
                                        self.num_hypotheses, self.b)

    def kernel(self, members: np.ndarray) -> np.ndarray:
        """Dense intersection kernel K (M, M) float32 among ``members``; diagonal zeroed."""
        return compiled.intersection_kernel(self.ids, compiled.c_array(members, np.int64),
                                            self.num_hypotheses, self.b)
