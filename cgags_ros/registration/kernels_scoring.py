"""
Compiled kernels (numba) of hypotheses and preferences: steps 3 and 4 of Algorithm 1.

The 3-point fits, the pre-screen on common neighbourhoods, the residuals of all N under the
selected hypotheses and the merge into the preference lists, each a loop per hypothesis
(or per correspondence) that numpy would run as a chain of small array calls
(docs/implementation.md, "Compiled kernels").
"""

from __future__ import annotations

import math

from numba import njit
import numpy as np

from .kernels_graph import lowest_bit

_ONE = np.uint64(1)


@njit(cache=True, nogil=True)
def fit_triples(src, dst, triples):
    """
    Return the closed-form rigid fits (step 3) of minimal subsets (rows of ``triples``).

    Kabsch / Arun on the three pairs, equal weights, reflection-safe: the same solution as
    :func:`~.rigid.kabsch_batch` (dst ≈ R src + t).

    :returns: R (B, 3, 3), t (B, 3).
    """
    count = triples.shape[0]
    R = np.empty((count, 3, 3))
    t = np.empty((count, 3))
    H = np.empty((3, 3))
    for b in range(count):
        cp = np.zeros(3)
        cq = np.zeros(3)
        for m in range(3):
            for a in range(3):
                cp[a] += src[triples[b, m], a] / 3.0
                cq[a] += dst[triples[b, m], a] / 3.0
        H[:] = 0.0
        for m in range(3):
            for a in range(3):
                for c in range(3):
                    H[a, c] += ((src[triples[b, m], a] - cp[a])
                                * (dst[triples[b, m], c] - cq[c]) / 3.0)
        U, _, Vt = np.linalg.svd(H)
        Rb = Vt.T @ U.T
        if np.linalg.det(Rb) < 0:  # reflection: flip the last singular vector
            Vt[2, :] = -Vt[2, :]
            Rb = Vt.T @ U.T
        R[b] = Rb
        for a in range(3):
            t[b, a] = cq[a] - (Rb[a, 0] * cp[0] + Rb[a, 1] * cp[1] + Rb[a, 2] * cp[2])
    return R, t


@njit(cache=True, nogil=True, inline='always')
def _score(src, dst, R, t, b, m, tau, truncated):
    """Score contribution of correspondence m under hypothesis b (inlier count or MSAC)."""
    r2 = 0.0
    for a in range(3):
        d = (R[b, a, 0] * src[m, 0] + R[b, a, 1] * src[m, 1] + R[b, a, 2] * src[m, 2]
             + t[b, a] - dst[m, a])
        r2 += d * d
    r = math.sqrt(r2)
    if truncated:
        return max(0.0, 1.0 - (r / tau) ** 2)
    return 1.0 if r <= tau else 0.0


@njit(cache=True, nogil=True)
def prescreen_scores(words, src, dst, R, t, triples, tau, truncated, dense):
    """
    Score each hypothesis on {i, j, k} ∪ (N(i) ∩ N(j) ∩ N(k)) (pre-screen of step 3).

    With ``dense``, on all N instead (the exact score). A subset stored as (i, j, j) (the
    4-DoF edge) counts j once.
    """
    count = triples.shape[0]
    n, w = words.shape
    out = np.zeros(count)
    for b in range(count):
        i, j, k = triples[b, 0], triples[b, 1], triples[b, 2]
        s = 0.0
        if dense:
            for m in range(n):
                s += _score(src, dst, R, t, b, m, tau, truncated)
        else:
            s = _score(src, dst, R, t, b, i, tau, truncated)
            s += _score(src, dst, R, t, b, j, tau, truncated)
            if k != j and k != i:
                s += _score(src, dst, R, t, b, k, tau, truncated)
            for c in range(w):
                word = words[i, c] & words[j, c] & words[k, c]
                while word:
                    s += _score(src, dst, R, t, b, (c << 6) + lowest_bit(word), tau, truncated)
                    word &= word - _ONE
        out[b] = s
    return out


@njit(cache=True, nogil=True)
def residual_matrix(src, dst, R, t):
    """Residuals ||q_m - (R_e p_m + t_e)|| of all N under E hypotheses: (E, N) float32."""
    e_count, n = R.shape[0], src.shape[0]
    out = np.empty((e_count, n), np.float32)
    for e in range(e_count):
        for m in range(n):
            r2 = 0.0
            for a in range(3):
                d = (R[e, a, 0] * src[m, 0] + R[e, a, 1] * src[m, 1] + R[e, a, 2] * src[m, 2]
                     + t[e, a] - dst[m, a])
                r2 += d * d
            out[e, m] = math.sqrt(r2)
    return out


@njit(cache=True, nogil=True)
def merge_preferences(pref_res, pref_ids, res, first_id):
    """
    Merge E new hypotheses into the preference lists (step 4, top-b residual ranks).

    Each correspondence keeps the b hypotheses with its smallest residuals, sorted
    ascending (empty slots hold inf at the end): a new one enters when it beats the last
    entry, by one insertion shift, and most are rejected by that single comparison. Sorted
    lists also give each list's median without a sort (:meth:`.PreferenceLists.quality`).
    ``res`` (E, N) float32; ids are ``first_id`` + row.
    """
    n, b = pref_res.shape
    for m in range(n):
        for e in range(res.shape[0]):
            r = res[e, m]
            if not r < pref_res[m, b - 1]:
                continue
            p = b - 1
            while p > 0 and pref_res[m, p - 1] > r:
                pref_res[m, p], pref_ids[m, p] = pref_res[m, p - 1], pref_ids[m, p - 1]
                p -= 1
            pref_res[m, p], pref_ids[m, p] = r, first_id + e
