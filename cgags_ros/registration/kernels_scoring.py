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

from .kernels_graph import lowest_bit, popcount

_ONE = np.uint64(1)


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


@njit(cache=True, nogil=True)
def fit_triples(src, dst, triples):
    """
    Return the closed-form rigid fits (step 3) of minimal subsets (rows of ``triples``).

    The least-squares rotation of the three pairs (equal weights) by Horn's unit
    quaternion: the eigenvector of the largest eigenvalue of his 4x4 matrix built from the
    cross-covariance H. It is the proper rotation Kabsch / Arun with the reflection fix
    return (:func:`~.rigid.kabsch_batch`, equal to 1e-9: test), without a LAPACK SVD per
    fit (whose workspace and copies cost several times the arithmetic).

    :returns: R (B, 3, 3), t (B, 3).
    """
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
    ascending (empty slots hold inf at the end; equal residuals in hypothesis order).
    The rows are streamed in memory order, each residual below its list's last entry
    (most are not, once the lists fill) inserted from the end: a new hypothesis goes after
    every equal residual, as its id is the largest. Sorted lists also give each list's
    median without a sort (:meth:`.PreferenceLists.quality`).
    ``res`` (E, N) float32; ids are ``first_id`` + row.
    """
    n, b = pref_res.shape
    last = pref_res[:, b - 1].copy()  # contiguous: the test every residual meets
    for e in range(res.shape[0]):
        h = first_id + e
        for m in range(n):
            r = res[e, m]
            if not r < last[m]:
                continue
            p = b - 1
            while p > 0 and pref_res[m, p - 1] > r:
                pref_res[m, p] = pref_res[m, p - 1]
                pref_ids[m, p] = pref_ids[m, p - 1]
                p -= 1
            pref_res[m, p] = r
            pref_ids[m, p] = h
            last[m] = pref_res[m, b - 1]


@njit(cache=True, nogil=True)
def preference_bits(ids, members, num_hypotheses, b):
    """
    Return the members' preference lists as bit rows (M, W) uint64 (step 5's kernel).

    The hypotheses present in the members' lists are renumbered 0..H'-1 and each list
    becomes a bit row of H' bits, so a kernel entry costs H' / 64 AND + popcounts
    (:func:`kernel_row`): the dense 0/1 matrix product it replaces multiplied mostly
    zeros. ``ids`` (N, b) int64, -1 in empty slots.
    """
    m = members.shape[0]
    slot = np.full(num_hypotheses, -1, np.int64)
    used = 0
    for a in range(m):
        for p in range(b):
            h = ids[members[a], p]
            if h >= 0 and slot[h] < 0:
                slot[h] = used
                used += 1
    w = max((used + 63) >> 6, 1)
    bits = np.zeros((m, w), np.uint64)
    for a in range(m):
        for p in range(b):
            h = ids[members[a], p]
            if h >= 0:
                s = slot[h]
                bits[a, s >> 6] |= _ONE << np.uint64(s & 63)
    return bits


@njit(cache=True, nogil=True, inline='always')
def kernel_row(bits, a, scale, out):
    """Write row a of the intersection kernel, K(a, c) = |T_a ∩ T_c| / b, to ``out``."""
    for c in range(bits.shape[0]):
        count = 0
        for k in range(bits.shape[1]):
            count += popcount(bits[a, k] & bits[c, k])
        out[c] = np.float32(count) / scale
    out[a] = 0.0


@njit(cache=True, nogil=True)
def intersection_kernel(ids, members, num_hypotheses, b):
    """
    Return the intersection kernel K (M, M) float32 of the members' preference lists.

    K(a, c) = |T_a ∩ T_c| / b, diagonal zero (step 5's kernel), every row of it; guided
    sampling computes only the rows it draws from (:func:`.kernels_sampling.draw_guided`).
    """
    bits = preference_bits(ids, members, num_hypotheses, b)
    K = np.empty((members.shape[0], members.shape[0]), np.float32)
    for a in range(members.shape[0]):
        kernel_row(bits, a, np.float32(b), K[a])
    return K


@njit(cache=True, nogil=True)
def fit_weighted(src, dst, weights):
    """
    Return the weighted least-squares rigid transform (4x4) with dst ≈ R src + t.

    Weighted centroids and cross-covariance, then Horn's quaternion as in
    :func:`fit_triples`: the re-fits of step 6 without numpy's per-call overhead.
    """
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


@njit(cache=True, nogil=True)
def point_residuals(T, src, dst):
    """Return ||dst_m - (R src_m + t)|| per row (float64), T a 4x4 rigid transform."""
    out = np.empty(src.shape[0])
    for m in range(src.shape[0]):
        r2 = 0.0
        for a in range(3):
            d = (T[a, 0] * src[m, 0] + T[a, 1] * src[m, 1] + T[a, 2] * src[m, 2] + T[a, 3]
                 - dst[m, a])
            r2 += d * d
        out[m] = math.sqrt(r2)
    return out
