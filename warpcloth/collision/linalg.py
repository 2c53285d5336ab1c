"""Dense linear algebra for the projection (float64 NumPy): blocked triangular solves, a semidefinite solve with
iterative refinement, and a Householder QR that drops dependent columns. NumPy has no triangular solve."""

from __future__ import annotations

import numpy as np

BLOCK = 128
"""Block size of the blocked triangular solves."""
DEPENDENT_RTOL = 1.0e-10
"""|R_kk| < this · max|R_kk| marks a dependent column in :func:`householder`."""
SHIFT = 1.0e-12
"""Relative diagonal shift of the Cholesky factorisations of :func:`spd_solve`."""


def tri_solve(T: np.ndarray, B: np.ndarray, *, lower: bool) -> np.ndarray:
    """Solve T X = B for a triangular T by blocked substitution (O(k²) work per right-hand side).

    Args:
        T: (k, k) lower or upper triangular matrix.
        B: (k,) or (k, r) right-hand side(s).
        lower: whether T is lower (True) or upper (False) triangular.

    Returns:
        X with the shape of B.
    """
    k = T.shape[0]
    if k == 0:
        return np.array(B, dtype=np.float64, copy=True)
    if k <= BLOCK:
        return np.linalg.solve(T, B)
    X = np.array(B, dtype=np.float64, copy=True)
    if lower:
        for i0 in range(0, k, BLOCK):
            i1 = min(i0 + BLOCK, k)
            if i0:
                X[i0:i1] -= T[i0:i1, :i0] @ X[:i0]
            X[i0:i1] = np.linalg.solve(T[i0:i1, i0:i1], X[i0:i1])
    else:
        for i1 in range(k, 0, -BLOCK):
            i0 = max(i1 - BLOCK, 0)
            if i1 < k:
                X[i0:i1] -= T[i0:i1, i1:] @ X[i1:]
            X[i0:i1] = np.linalg.solve(T[i0:i1, i0:i1], X[i0:i1])
    return X


def spd_solve(M: np.ndarray, rhs: np.ndarray, *, atol: float, refinements: int = 6) -> np.ndarray:
    """Solve M x = rhs for a symmetric positive semidefinite M.

    Cholesky of M + εI (ε = 1e-12·max diag, raised while the factorisation fails) with iterative refinement against
    M itself: consistent singular systems converge to a solution (near the minimum-norm one), inconsistent ones
    leave a residual the caller detects.

    Args:
        M: (k, k) symmetric positive semidefinite matrix.
        rhs: (k,) right-hand side.
        atol: stop refining once every residual entry is at most this.
        refinements: most refinement steps.

    Returns:
        x, shape (k,).
    """
    k = M.shape[0]
    if k == 0:
        return np.zeros(0)
    scale = float(np.max(np.diag(M))) if k else 1.0
    scale = scale if scale > 0.0 else 1.0
    eps = SHIFT * scale
    for _ in range(8):
        shifted = M.copy()
        shifted.flat[::k + 1] += eps
        try:
            L = np.linalg.cholesky(shifted)
            break
        except np.linalg.LinAlgError:
            eps *= 100.0
    else:  # pragma: no cover - M + 1e4·max diag·I is always positive definite for a PSD M
        raise np.linalg.LinAlgError("Cholesky factorisation failed")
    U = np.ascontiguousarray(L.T)

    def solve(r):
        return tri_solve(U, tri_solve(L, r, lower=True), lower=False)

    x = solve(rhs)
    for _ in range(refinements):
        res = rhs - M @ x
        if np.max(np.abs(res)) <= atol:
            break
        x = x + solve(res)
    return x


def householder(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reduced Householder QR of the columns of A that are independent of the columns before them.

    A column with |R_kk| < 1e-10·max|R_kk| is dependent on earlier ones: it is dropped and the rest refactorised.
    (A dropped column that turns out not to lie in the span of the kept ones, which the unpivoted QR can cause
    after a dependent column, is put back at the end.)

    Args:
        A: (r, c) matrix.

    Returns:
        (keep, drop, Q, R): the column indices kept, in factorisation order, and dropped; Q (r, len(keep)) and
        R (len(keep), len(keep)) with A[:, keep] = Q R.
    """
    ncols = A.shape[1]
    keep = np.arange(ncols)
    Q, R = np.zeros((A.shape[0], 0)), np.zeros((0, 0))
    for _ in range(2 * ncols + 2):
        if keep.size == 0:
            break
        Q, R = np.linalg.qr(A[:, keep])
        r = R.shape[0]
        diag = np.abs(np.diag(R))
        good = np.zeros(keep.size, dtype=bool)
        if r:
            good[:r] = diag >= DEPENDENT_RTOL * float(np.max(diag))
        if not good.all():
            keep = keep[good]
            continue
        drop = np.setdiff1d(np.arange(ncols), keep)
        if drop.size == 0:
            break
        Ad = A[:, drop]
        res = np.linalg.norm(Ad - Q @ (Q.T @ Ad), axis=0)
        back = drop[res > 1e-6 * np.maximum(np.linalg.norm(Ad, axis=0), 1e-300)]
        if back.size == 0:
            break
        keep = np.concatenate([keep, back])
    return keep, np.setdiff1d(np.arange(ncols), keep), Q, R
