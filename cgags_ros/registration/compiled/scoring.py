"""
Compiled functions (numba) of the hypotheses: steps 3 and 8 of Algorithm 1.

Step 3, hypotheses: the minimal fits (:func:`fit_triples`), the pre-screen on common
neighbourhoods (:func:`prescreen_scores`) and the residuals the scores are taken from
(:func:`residual_matrix`). Step 8, the final re-fit's weighted fit and residuals
(:func:`fit_weighted`, :func:`point_residuals`, through :mod:`.rigid`). Each is a loop per
hypothesis (or per correspondence) that numpy would run as a chain of small array calls
(docs/design.md).
"""

from __future__ import annotations

import math

from numba import njit
import numpy as np

from .bits import lowest_bit, ONE
from .types import CORRESPONDENCES
from ...compiled_types import BOOL, F64_1D, F64_2D, F64_3D, FLOAT, I64_2D, U64_2D


@njit(cache=True, nogil=True, inline='always')
def _jacobi_top_eigenvector(N, V, v):
    """
    Write the eigenvector of the largest eigenvalue of the symmetric 4x4 ``N`` into ``v``.

    Cyclic Jacobi rotations until the off-diagonal part is at rounding level (``N`` and
    the scratch ``V`` are overwritten): a handful of sweeps of 6 rotations, no allocation,
    accurate to machine precision whatever the eigenvalue spread.
    """
    V[:] = 0.0
    for p in range(4):
        V[p, p] = 1.0
    for _ in range(32):
        off = 0.0
        scale = 0.0
        for p in range(4):
            scale += N[p, p] * N[p, p]
            for q in range(p + 1, 4):
                off += N[p, q] * N[p, q]
        if off <= 1e-30 * scale:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                if N[p, q] == 0.0:
                    continue
                theta = (N[q, q] - N[p, p]) / (2.0 * N[p, q])
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for r in range(4):  # N <- N J (columns p, q)
                    a, b = N[r, p], N[r, q]
                    N[r, p], N[r, q] = c * a - s * b, s * a + c * b
                for r in range(4):  # N <- J^T N (rows p, q)
                    a, b = N[p, r], N[q, r]
                    N[p, r], N[q, r] = c * a - s * b, s * a + c * b
                for r in range(4):
                    a, b = V[r, p], V[r, q]
                    V[r, p], V[r, q] = c * a - s * b, s * a + c * b
    top = 0
    for p in range(1, 4):
        if N[p, p] > N[top, top]:
            top = p
    for r in range(4):
        v[r] = V[r, top]


@njit(cache=True, nogil=True, inline='always')
def _horn_rotation(H, N, V, q, R):
    """
    Write into ``R`` the proper rotation maximising sum q . R p = trace(R H) (Horn).

    The unit quaternion is the top eigenvector of Horn's 4x4 matrix. ``H`` is the
    cross-covariance sum p q^T of centred pairs (q ≈ R p); ``N``, ``V`` (4x4) and ``q``
    (4) are scratch.
    """
    sxx, sxy, sxz = H[0, 0], H[0, 1], H[0, 2]
    syx, syy, syz = H[1, 0], H[1, 1], H[1, 2]
    szx, szy, szz = H[2, 0], H[2, 1], H[2, 2]
    N[0, 0], N[1, 1] = sxx + syy + szz, sxx - syy - szz
    N[2, 2], N[3, 3] = -sxx + syy - szz, -sxx - syy + szz
    N[0, 1] = N[1, 0] = syz - szy
    N[0, 2] = N[2, 0] = szx - sxz
    N[0, 3] = N[3, 0] = sxy - syx
    N[1, 2] = N[2, 1] = sxy + syx
    N[1, 3] = N[3, 1] = szx + sxz
    N[2, 3] = N[3, 2] = syz + szy
    _jacobi_top_eigenvector(N, V, q)
    w, x, y, z = q[0], q[1], q[2], q[3]
    R[0, 0] = w * w + x * x - y * y - z * z
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = w * w - x * x + y * y - z * z
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = w * w - x * x - y * y + z * z


@njit((CORRESPONDENCES, I64_2D), cache=True, nogil=True)
def fit_triples(corr, triples):
    """
    Return the closed-form rigid fits (step 3) of minimal subsets (rows of ``triples``).

    The least-squares rotation of the three pairs (equal weights) by Horn's unit
    quaternion: the eigenvector of the largest eigenvalue of his 4x4 matrix built from the
    cross-covariance H. It is the proper rotation Kabsch / Arun with the reflection fix
    return (:func:`~.rigid.kabsch_batch`, equal to 1e-9: test), without a LAPACK SVD per
    fit (whose workspace and copies cost several times the arithmetic).

    :returns: R (B, 3, 3), t (B, 3).
    """
    if triples.shape[1] != 3:
        raise ValueError('fit_triples fits triangles: rows (i, j, k)')
    src, dst = corr
    count = triples.shape[0]
    R = np.empty((count, 3, 3))
    t = np.empty((count, 3))
    H = np.empty((3, 3))
    N = np.empty((4, 4))
    V = np.empty((4, 4))
    q = np.empty(4)
    cp = np.empty(3)
    cq = np.empty(3)
    for b in range(count):
        for a in range(3):
            cp[a] = (src[triples[b, 0], a] + src[triples[b, 1], a] + src[triples[b, 2], a]) / 3.0
            cq[a] = (dst[triples[b, 0], a] + dst[triples[b, 1], a] + dst[triples[b, 2], a]) / 3.0
        H[:] = 0.0
        for m in range(3):
            for a in range(3):
                for c in range(3):
                    H[a, c] += ((src[triples[b, m], a] - cp[a])
                                * (dst[triples[b, m], c] - cq[c]))
        _horn_rotation(H, N, V, q, R[b])
        for a in range(3):
            t[b, a] = cq[a] - (R[b, a, 0] * cp[0] + R[b, a, 1] * cp[1] + R[b, a, 2] * cp[2])
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


@njit((U64_2D, CORRESPONDENCES, F64_3D, F64_2D, I64_2D, FLOAT, BOOL, BOOL), cache=True,
      nogil=True)
def prescreen_scores(words, corr, R, t, subsets, tau, truncated, dense):
    """
    Score each hypothesis on its minimal subset and their common neighbourhood (step 3).

    On {i, j, k} ∪ (N(i) ∩ N(j) ∩ N(k)) for a triangle (i, j, k), on
    {i, j} ∪ (N(i) ∩ N(j)) for an edge (i, j): the pre-screen. With ``dense``, on all N
    instead (the exact score). Row b of ``subsets`` is hypothesis b's subset.
    """
    if subsets.shape[1] not in (2, 3):
        raise ValueError('minimal subsets are rows (i, j, k) or (i, j)')
    src, dst = corr
    count = subsets.shape[0]
    last = subsets.shape[1] - 1
    n, w = words.shape
    out = np.zeros(count)
    for b in range(count):
        i, j, k = subsets[b, 0], subsets[b, 1], subsets[b, last]  # an edge: k = j
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
                    word &= word - ONE
        out[b] = s
    return out


@njit((CORRESPONDENCES, F64_3D, F64_2D), cache=True, nogil=True)
def residual_matrix(corr, R, t):
    """Residuals ||q_m - (R_e p_m + t_e)|| of all N under E hypotheses: (E, N) float32."""
    src, dst = corr
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


@njit((CORRESPONDENCES, F64_1D), cache=True, nogil=True)
def fit_weighted(corr, weights):
    """
    Return the weighted least-squares rigid transform (4x4) with dst ≈ R src + t.

    Weighted centroids and cross-covariance, then Horn's quaternion as in
    :func:`fit_triples`: the re-fits of step 8 without numpy's per-call overhead.
    """
    src, dst = corr
    total = 0.0
    cp = np.zeros(3)
    cq = np.zeros(3)
    for m in range(src.shape[0]):
        total += weights[m]
        for a in range(3):
            cp[a] += weights[m] * src[m, a]
            cq[a] += weights[m] * dst[m, a]
    for a in range(3):
        cp[a] /= total
        cq[a] /= total
    H = np.zeros((3, 3))
    for m in range(src.shape[0]):
        for a in range(3):
            for c in range(3):
                H[a, c] += weights[m] * (src[m, a] - cp[a]) * (dst[m, c] - cq[c])
    T = np.eye(4)
    R = np.empty((3, 3))
    _horn_rotation(H, np.empty((4, 4)), np.empty((4, 4)), np.empty(4), R)
    for a in range(3):
        for c in range(3):
            T[a, c] = R[a, c]
        T[a, 3] = cq[a] - (R[a, 0] * cp[0] + R[a, 1] * cp[1] + R[a, 2] * cp[2])
    return T


@njit((F64_2D, CORRESPONDENCES), cache=True, nogil=True)
def point_residuals(T, corr):
    """Return ||dst_m - (R src_m + t)|| per row (float64), T a 4x4 rigid transform."""
    src, dst = corr
    out = np.empty(src.shape[0])
    for m in range(src.shape[0]):
        r2 = 0.0
        for a in range(3):
            d = (T[a, 0] * src[m, 0] + T[a, 1] * src[m, 1] + T[a, 2] * src[m, 2] + T[a, 3]
                 - dst[m, a])
            r2 += d * d
        out[m] = math.sqrt(r2)
    return out
