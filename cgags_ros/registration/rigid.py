"""Closed-form rigid transforms (Kabsch / Arun / Horn; steps 3 and 8), single sets and batches."""

from __future__ import annotations

import numpy as np

from . import compiled


def kabsch_batch(P: np.ndarray, Q: np.ndarray,
                 W: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """
    (Weighted) least-squares rotations and translations with ``Q ≈ R @ P + t`` per item.

    :param P, Q: (B, K, 3) corresponding point sets (K >= 3).
    :param W: optional (B, K) non-negative weights.
    :returns: R (B, 3, 3) proper rotations (det +1), t (B, 3).
    """
    if W is None:
        W = np.ones(P.shape[:2])
    W = W / W.sum(axis=1, keepdims=True)
    cp = np.einsum('bk,bki->bi', W, P)[:, None, :]
    cq = np.einsum('bk,bki->bi', W, Q)[:, None, :]
    H = np.einsum('bk,bki,bkj->bij', W, P - cp, Q - cq)
    U, _, Vt = np.linalg.svd(H)
    # Reflection fix: flip the last singular vector where det(V U^T) < 0.
    d = np.sign(np.linalg.det(np.einsum('bji,bkj->bik', Vt, U)))
    d[d == 0] = 1.0
    Vt = Vt.copy()
    Vt[:, 2, :] *= d[:, None]
    R = np.einsum('bji,bkj->bik', Vt, U)
    t = cq[:, 0, :] - np.einsum('bij,bj->bi', R, cp[:, 0, :])
    return R, t


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """
    4x4 (weighted) least-squares rigid transform mapping ``src`` (K, 3) onto ``dst``.

    The same optimum as :func:`kabsch_batch` (tested to 1e-9), by the compiled Horn fit:
    the re-fits call it several times a registration, where numpy's per-call overhead
    would dominate.
    """
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    if not w.sum() > 0.0:
        raise ValueError(f'kabsch needs points with positive total weight, got {len(src)} '
                         f'point(s) weighing {w.sum()}')
    return compiled.fit_weighted(compiled.Correspondences.of(src, dst),
                                 compiled.c_array(w, np.float64))


def residuals(T: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Euclidean residuals ``||dst_i - (R src_i + t)||`` (same units as the points)."""
    return compiled.point_residuals(compiled.c_array(T, np.float64),
                                    compiled.Correspondences.of(src, dst))
