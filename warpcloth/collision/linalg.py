"""Dense linear algebra for the projection (float64 NumPy): blocked triangular solves, a semidefinite solve with
iterative refinement, and the Cholesky factor of a Gram matrix that drops dependent columns (the adjoint's R without
Q). NumPy has no triangular solve. Small problems run on one BLAS thread (:func:`small_blas`)."""

from __future__ import annotations

import contextlib

import numpy as np
from threadpoolctl import ThreadpoolController

BLOCK = 128
"""Block size of the blocked triangular solves."""
DEPENDENT_PIVOT = 1.0e-10
"""A Cholesky pivot below this times its column's diagonal entry (the squared norm left after projecting the column
onto the ones kept before it, relative to its squared norm: an angle under 1e-5 rad) marks a dependent column in
:func:`gram_cholesky`; cancellation leaves about k·1e-16 there for a column that is exactly dependent."""
SHIFT = 1.0e-12
"""Relative diagonal shift of the Cholesky factorisations of :func:`spd_solve`."""
SINGLE_THREAD_UNKNOWNS = 1500
"""Dense problems of at most this many unknowns run on one BLAS thread (:func:`small_blas`). A multi-threaded BLAS
spin-waits for its threads on every small call, which on a busy machine costs more than the work: the float64
multigrid strip of tests/test_collision.py (NumPy zones) took 45.8 s with OpenBLAS's 2 threads against 16.1 s with
one, beside the test suite on this 2-core machine (once over 600 s), the issue #37 report 127 s against 47 s."""

_controller: ThreadpoolController | None = None


def small_blas(unknowns: int):
    """A context in which BLAS runs on one thread, where ``unknowns`` is at most SINGLE_THREAD_UNKNOWNS (else it
    changes nothing)."""
    global _controller
    if unknowns > SINGLE_THREAD_UNKNOWNS:
        return contextlib.nullcontext()
    if _controller is None:  # scanning the loaded libraries costs about 1 ms: once
        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")


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


def gram_cholesky(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lower Cholesky factor of a Gram matrix M = AᵀA over the columns of A that are independent of the columns
    before them: L Lᵀ = M[keep][:, keep], so Lᵀ is the R of A[:, keep] = Q R (up to the signs of its rows).

    LAPACK's factorisation when every pivot passes :data:`DEPENDENT_PIVOT`; otherwise a right-looking one that skips
    each column whose pivot does not (the dependent columns: exact duplicates and other linear combinations).

    Returns:
        (keep, drop, L): the column indices kept (in order) and dropped, and L (len(keep), len(keep)).
    """
    k = M.shape[0]
    diag = np.diag(M).copy()
    if k:
        try:
            L = np.linalg.cholesky(M)
            if np.all(np.diag(L) ** 2 >= DEPENDENT_PIVOT * diag):
                return np.arange(k), np.zeros(0, dtype=np.int64), L
        except np.linalg.LinAlgError:
            pass
    S = np.array(M, dtype=np.float64, copy=True)  # the Schur complement, updated in place
    L = np.zeros((k, k))
    kept = np.zeros(k, dtype=bool)
    for j in range(k):
        pivot = S[j, j]
        if not pivot >= DEPENDENT_PIVOT * diag[j] or pivot <= 0.0:
            continue
        kept[j] = True
        col = S[j:, j] / np.sqrt(pivot)
        L[j:, j] = col
        S[j + 1:, j + 1:] -= np.outer(col[1:], col[1:])
    keep = np.flatnonzero(kept)
    return keep, np.flatnonzero(~kept), np.ascontiguousarray(L[np.ix_(keep, keep)])
