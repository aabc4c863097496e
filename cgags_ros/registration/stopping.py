"""Adaptive stopping (step 7): the RANSAC bound, per sampling stage."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from scipy import special

if TYPE_CHECKING:  # annotations only: importing the graph would compile the numba code
    from .compatibility import CompatibilityGraph


def ransac_bound(confidence: float, w: float) -> float:
    """
    Return the RANSAC bound log(1 - P) / log(1 - w) on the number of samples.

    It is the number of samples needed to draw at least one all-inlier sample with
    probability P = ``confidence`` when a single sample is all-inlier with probability ``w``.
    """
    if w <= 0.0:
        return math.inf
    if w >= 1.0:
        return 1.0
    return math.log(1.0 - confidence) / math.log1p(-w)


def futility_draws(graph: CompatibilityGraph, smallest: int, confidence: float,
                   subset_size: int) -> float:
    """
    Return the stage-one draws after which no significant model is left to find.

    A real motion whose consensus the significance test would accept has at least
    ``smallest`` inliers, pairwise compatible: one uniform edge draw lies inside them with
    probability C(smallest, 2) / |E|. After the RANSAC bound for that probability it would
    have been drawn with probability ``confidence``. The edge tournament draws inlier
    edges more often than uniform sampling, so for edges (4-DoF, subset size 2) the bound
    is conservative; for triangles it is not (the vertex tournament can draw a small
    inlier set's triangles less often, measured in docs/method.md): inf.
    """
    if subset_size != 2 or graph.num_edges == 0:
        return math.inf
    return ransac_bound(confidence, min(1.0, smallest * (smallest - 1) / 2 / graph.num_edges))


def poisson_isf(alpha: float, lam: float) -> int:
    """
    Return the smallest k with P(X > k) <= alpha for X ~ Poisson(lam).

    Gives the same values as ``scipy.stats.poisson.isf`` (tested), but calls
    ``scipy.special.pdtrc`` directly: the significance test calls it every batch, and the
    generic ``scipy.stats`` machinery would add its per-call overhead each time.
    """
    top = int(lam + 12.0 * math.sqrt(lam) + 40.0)
    while True:
        k = np.arange(top)
        above = np.flatnonzero(special.pdtrc(k, lam) <= alpha)
        if len(above):
            return int(above[0])
        top *= 2


def compatible_sample_inlier_probability(graph: CompatibilityGraph, inliers: np.ndarray,
                                         rng: np.random.Generator, pairs: int = 64) -> float:
    """
    Return the probability that one compatible-stage sample is all-inlier.

    A compatible-stage sample is an edge drawn uniformly over E, then a uniform common
    neighbour; ``inliers`` is taken as the inlier set.

    P(edge inside I) = |E(I)| / |E|; P(k in I | edge inside I) is averaged over up to
    ``pairs`` random inlier edges as |N(i) ∩ N(j) ∩ I| / |N(i) ∩ N(j)|.
    """
    n_in = len(inliers)
    if n_in < 3 or graph.num_edges == 0:
        return 0.0
    # The inlier edges counted and picked on the bit rows: a large inlier set's dense M x M
    # adjacency costs more than the search around it (docs/design.md).
    counts = graph.later_neighbour_counts(inliers)
    e_in = int(counts.sum())
    if e_in == 0:
        return 0.0
    pick = rng.choice(e_in, size=min(pairs, e_in), replace=False)
    i, j = graph.numbered_edges(inliers, counts, pick)
    total, inside = graph.common_within(i, j, inliers)
    ratio = np.where(total > 0, inside / np.maximum(total, 1), 0.0)
    return float(e_in / graph.num_edges * ratio.mean())


def empirical_inlier_probability(samples: list[np.ndarray], inlier_mask: np.ndarray) -> float:
    """Share of the drawn triples (list of (B, 3) arrays) whose members are all inliers."""
    drawn = sum(len(s) for s in samples)
    if drawn == 0:
        return 0.0
    hits = sum(int(inlier_mask[s].all(axis=1).sum()) for s in samples if len(s))
    return hits / drawn
