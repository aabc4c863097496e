"""
Compiled functions (numba) of the FPFH descriptors the correspondences are matched on.

FPFH (Rusu et al., ICRA 2009) is the feature the paper matches to get its putative
correspondences (docs/method.md, "Input"). These functions compute Open3D's definition of it
(``pipelines/registration/Feature.cpp``: pair features, 11 bins per angle, SPFH weights
100 / neighbours, FPFH = own SPFH + neighbours' SPFH weighted by 1 / squared distance, each
block scaled to 100) with two shortcuts that change no value:

- one neighbour search serves both passes (Open3D searches twice), on a voxel grid of
  cells a fraction of the radius wide, whose neighbouring cells are ranges of one sorted
  key array (:func:`.neighbours.radius_neighbours`);
- every SPFH is computed once, before the FPFH pass reads it (as Open3D does);
- a point's pair features are computed without branches, in a loop that vectorizes; only
  the rare pairs whose bins need acos or atan2 to decide go pair by pair (:func:`spfh_pass`).

Neighbours are the ``max_nn`` nearest within the radius, the point itself included, as in
Open3D's hybrid search; ties at the ``max_nn``-th distance go to the lower row.
Both passes are ``nogil`` over a range of points (the caller splits them over threads).
"""

from __future__ import annotations

from numba import njit
import numpy as np

from .types import NEIGHBOUR_LISTS
from ...compiled_types import F64_2D, INT


@njit(cache=True, nogil=True, inline='always')
def _acos_greater(x, y):
    """
    Return ``acos(x) > acos(y)`` as Open3D computes it, with acos only where it decides.

    acos falls with slope <= -1 and rounds by at most 2.2e-16 on [0, 1], so x and y more
    than 1e-15 apart compare as ``x < y``; closer ones (e.g. both ~0 on a plane, where acos
    rounds both to pi/2 and the comparison is False) are compared as Open3D does.
    """
    if abs(x - y) > 1e-15:
        return x < y
    return np.arccos(x) > np.arccos(y)


@njit(cache=True, nogil=True, inline='always')
def _bin(x):
    return min(max(np.int64(np.floor(x)), 0), 10)


# atan(a) ~ a P(a^2) on [0, 1], max error 1.3e-9 rad (least-squares Chebyshev fit).
_ATAN = (0.9999999997078668, -0.3333332567963894, 0.19999667044842653, -0.142800186851488,
         0.11060466260535327, -0.08822430218659709, 0.06772960541082935,
         -0.04519964450357349, 0.023025541806010855, -0.007569204358060716,
         0.0011682793695642916)
_EDGE = 1e-6  # bin units: 450x the approximation's error


@njit(cache=True, nogil=True, inline='always')
def _angle_poly(y, x):
    """
    Return ``(k, clear)``: the floor of the pair angle's bin value from the polynomial atan.

    ``clear`` says whether it decides the bin: it lies more than ``_EDGE`` from a bin edge
    and neither argument is zero or NaN. No branches (selects only), so a loop over pairs
    vectorizes.
    """
    ax, ay = abs(x), abs(y)
    lo, hi = min(ax, ay), max(ax, ay)
    a = lo / (hi if hi > 0.0 else 1.0)
    s = a * a
    s2 = s * s
    s4 = s2 * s2
    # Estrin's scheme: a shallower dependency chain than Horner's
    low = (_ATAN[0] + _ATAN[1] * s) + s2 * (_ATAN[2] + _ATAN[3] * s)
    mid = (_ATAN[4] + _ATAN[5] * s) + s2 * (_ATAN[6] + _ATAN[7] * s)
    high = (_ATAN[8] + _ATAN[9] * s) + s2 * _ATAN[10]
    t = a * (low + s4 * (mid + s4 * high))
    t = 0.5 * np.pi - t if ay > ax else t
    t = np.pi - t if x < 0.0 else t
    t = -t if y < 0.0 else t
    v = 11.0 * (t + np.pi) / (2.0 * np.pi)
    k = np.floor(v)
    clear = (hi > 0.0) & (x == x) & (y == y) & (v - k > _EDGE) & (k + 1.0 - v > _EDGE)
    return k, clear


@njit(cache=True, nogil=True, inline='always')
def _angle_bin(y, x):
    """
    Return ``_bin(11 (atan2(y, x) + pi) / 2 pi)``, Open3D's bin of the pair's angle.

    The angle from a polynomial good to 1.3e-9 rad decides the bin unless it lies within
    ``_EDGE`` of a bin edge; there (and for zero or NaN arguments) libm's atan2 decides as
    in Open3D: the same bins, without atan2's cost for all but ~1e-5 of the pairs.
    """
    k, clear = _angle_poly(y, x)
    if clear:
        return min(max(np.int64(k), 0), 10)
    return _bin(11.0 * (np.arctan2(y, x) + np.pi) / (2.0 * np.pi))


@njit(cache=True, nogil=True, inline='always')
def _darboux(dx, dy, dz, a0, a1, a2, b0, b1, b2):
    """
    Return ``(|v|, f1, y, x)`` of a pair in the Darboux frame at its source point.

    a: the source's normal, d: the line to the other point, b: that point's normal;
    v = d x a, w = a x v / |v|, f1 = v / |v| . b, y = w . b, x = a . b (Open3D's
    ``ComputePairFeatures``). With |v| = 0 the other three are meaningless, not an error.
    """
    v0 = dy * a2 - dz * a1
    v1 = dz * a0 - dx * a2
    v2 = dx * a1 - dy * a0
    vn = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    scale = vn if vn > 0.0 else 1.0
    v0 /= scale
    v1 /= scale
    v2 /= scale
    w0 = a1 * v2 - a2 * v1
    w1 = a2 * v0 - a0 * v2
    w2 = a0 * v1 - a1 * v0
    return (vn, v0 * b0 + v1 * b1 + v2 * b2, w0 * b0 + w1 * b1 + w2 * b2,
            a0 * b0 + a1 * b1 + a2 * b2)


@njit(cache=True, nogil=True, inline='always')
def _pair_bins(points, normals, i, j):
    """
    Return the three bins of the pair (i, j): Open3D's ``ComputePairFeatures``, one pair.

    The Darboux frame sits at the point whose normal is more orthogonal to the connecting
    line; a degenerate pair (coincident points, or a normal along the line) counts with
    zero features, as there. :func:`spfh_pass` computes most pairs without branches and asks
    this for the rest.
    """
    bin0 = 5  # a degenerate pair's angle is 0: bin floor(11 pi / 2 pi)
    f1 = 0.0
    f2 = 0.0
    dx = points[j, 0] - points[i, 0]
    dy = points[j, 1] - points[i, 1]
    dz = points[j, 2] - points[i, 2]
    dn = np.sqrt(dx * dx + dy * dy + dz * dz)
    if dn > 0.0:
        a0, a1, a2 = normals[i, 0], normals[i, 1], normals[i, 2]
        b0, b1, b2 = normals[j, 0], normals[j, 1], normals[j, 2]
        angle1 = (a0 * dx + a1 * dy + a2 * dz) / dn
        angle2 = (b0 * dx + b1 * dy + b2 * dz) / dn
        if _acos_greater(abs(angle1), abs(angle2)):
            a0, a1, a2, b0, b1, b2 = b0, b1, b2, a0, a1, a2
            dx, dy, dz = -dx, -dy, -dz
            f2 = -angle2
        else:
            f2 = angle1
        vn, f1_, y, x = _darboux(dx, dy, dz, a0, a1, a2, b0, b1, b2)
        if vn > 0.0:
            f1 = f1_
            bin0 = _angle_bin(y, x)
        else:
            f2 = 0.0
    return bin0, _bin(11.0 * (f1 + 1.0) * 0.5), _bin(11.0 * (f2 + 1.0) * 0.5)


@njit((F64_2D, F64_2D, NEIGHBOUR_LISTS, INT, INT, F64_2D), cache=True, nogil=True,
      error_model='numpy')
def spfh_pass(points, normals, lists, first, last, out):
    """
    Set ``out``'s rows of the points at positions first .. last to their SPFH.

    Positions are in ``lists.order``, and the SPFH are the simplified point feature
    histograms. The point at position s (row order[s]) has its neighbours in row
    ``s - offset`` of ``lists.nbr``/``lists.count``, as
    :func:`.neighbours.radius_neighbours` left them.

    A point's pairs are computed in one loop without branches (selects instead, so that
    it vectorizes), with the same operations in the same order as :func:`_pair_bins`, so
    the same bins. A pair whose bins that loop cannot
    settle goes to :func:`_pair_bins`: a near-tie of the two normals' angles to the line
    (the frame's choice needs acos there), a degenerate pair, or an angle within
    ``_EDGE`` of a bin edge (atan2 decides). ``error_model='numpy'``: the degenerate
    pairs' divisions by zero give inf/NaN, which only the unused lanes see.
    """
    order, offset, nbr, count = lists
    m = nbr.shape[1]
    ex, ey, ez = np.empty(m), np.empty(m), np.empty(m)  # neighbour - point
    bx, by, bz = np.empty(m), np.empty(m), np.empty(m)  # neighbour normals
    k0, k1, k2 = np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m, np.int64)
    ok = np.empty(m, np.bool_)
    for s in range(first, last):
        i = order[s]
        c = count[s - offset]
        if c <= 1:
            continue
        inc = 100.0 / (c - 1)
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        a0, a1, a2 = normals[i, 0], normals[i, 1], normals[i, 2]
        for k in range(c):
            j = nbr[s - offset, k]
            ex[k] = points[j, 0] - px
            ey[k] = points[j, 1] - py
            ez[k] = points[j, 2] - pz
            bx[k] = normals[j, 0]
            by[k] = normals[j, 1]
            bz[k] = normals[j, 2]
        for k in range(c):
            dx, dy, dz = ex[k], ey[k], ez[k]
            n0, n1, n2 = bx[k], by[k], bz[k]
            dn = np.sqrt(dx * dx + dy * dy + dz * dz)
            angle1 = (a0 * dx + a1 * dy + a2 * dz) / dn
            angle2 = (n0 * dx + n1 * dy + n2 * dz) / dn
            x = abs(angle1)
            y = abs(angle2)
            swap = x < y
            sure = abs(x - y) > 1e-15
            s0 = n0 if swap else a0
            s1 = n1 if swap else a1
            s2 = n2 if swap else a2
            t0 = a0 if swap else n0
            t1 = a1 if swap else n1
            t2 = a2 if swap else n2
            qx = -dx if swap else dx
            qy = -dy if swap else dy
            qz = -dz if swap else dz
            f2 = -angle2 if swap else angle1
            vn, f1, yy, xx = _darboux(qx, qy, qz, s0, s1, s2, t0, t1, t2)
            kf, clear = _angle_poly(yy, xx)
            ok[k] = sure & (dn > 0.0) & (vn > 0.0) & clear
            # bins as _pair_bins takes them; NaN (a degenerate pair's, unused) kept out of
            # the integer conversion
            u1 = 11.0 * (f1 + 1.0) * 0.5
            u2 = 11.0 * (f2 + 1.0) * 0.5
            k0[k] = _bin(kf) if clear else 0
            k1[k] = _bin(u1) if u1 == u1 else 0
            k2[k] = _bin(u2) if u2 == u2 else 0
        for k in range(c):
            j = nbr[s - offset, k]
            if j == i:
                continue
            if ok[k]:
                c0, c1, c2 = k0[k], k1[k], k2[k]
            else:
                c0, c1, c2 = _pair_bins(points, normals, i, j)
            out[i, c0] += inc
            out[i, 11 + c1] += inc
            out[i, 22 + c2] += inc


@njit((F64_2D, F64_2D, NEIGHBOUR_LISTS, INT, INT, F64_2D), cache=True, nogil=True)
def fpfh_pass(points, spf, lists, first, last, out):
    """
    Set ``out``'s rows of the points at positions first .. last to their FPFH.

    From the SPFH rows ``spf``; positions and neighbours as in :func:`spfh_pass`.

    Own SPFH plus the neighbours' weighted by 1 / squared distance, each 11-bin block of
    the neighbours' part scaled to sum to 100 (Open3D's ``ComputeFPFHFeature``).
    """
    order, offset, nbr, count = lists
    acc = np.empty(33)  # the row being summed: a local array, so the sum vectorizes
    for s in range(first, last):
        i = order[s]
        c = count[s - offset]
        if c <= 1:
            continue
        acc[:] = out[i]
        for k in range(c):
            j = nbr[s - offset, k]
            ex = points[j, 0] - points[i, 0]
            ey = points[j, 1] - points[i, 1]
            ez = points[j, 2] - points[i, 2]
            e = ex * ex + ey * ey + ez * ez  # as in the neighbour search: the same bits
            if e == 0.0:
                continue
            w = 1.0 / e
            row = spf[j]
            for t in range(33):
                acc[t] += row[t] * w
        for block in range(3):
            total = 0.0
            for t in range(11 * block, 11 * block + 11):
                total += acc[t]
            scale = 100.0 / total if total != 0.0 else 0.0
            for t in range(11 * block, 11 * block + 11):
                out[i, t] = acc[t] * scale + spf[i, t]
