"""Dense float64 linear algebra of the reference projection."""

from __future__ import annotations

import contextlib

import numpy as np
from threadpoolctl import ThreadpoolController

BLOCK = 128
"""Block size of the blocked triangular solves."""
DEPENDENT_PIVOT = 1.0e-10
"""A Cholesky pivot below this times its column's squared norm (an angle under 1e-5 rad to the columns kept before
it) marks a dependent column in :func:`gram_cholesky`."""
SHIFT = 1.0e-12
"""Relative diagonal shift of the Cholesky factorisations of :func:`spd_solve`."""
SINGLE_THREAD_UNKNOWNS = 1500
"""Problems up to this size use one BLAS thread. Why: docs/decisions.md, "One BLAS thread for small zones"."""

_controller: ThreadpoolController | None = None


def small_blas(unknowns: int):
    """A context with BLAS on one thread where ``unknowns`` <= SINGLE_THREAD_UNKNOWNS (else a no-op)."""
    global _controller
    if unknowns > SINGLE_THREAD_UNKNOWNS:
        return contextlib.nullcontext()
    if _controller is None:  # scanning the loaded libraries costs about 1 ms: once
        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")


def tri_solve(T: np.ndarray, B: np.ndarray, *, lower: bool) -> np.ndarray:
    """X with T X = B for a (k, k) lower (``lower``) or upper triangular T and B (k,) or (k, r)."""
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
    """x (k,) with M x = rhs for a (k, k) symmetric positive semidefinite M: Cholesky of M + εI (ε = SHIFT·max diag,
    raised while it fails), refined against M at most ``refinements`` times until every residual is <= ``atol``; an
    inconsistent system leaves a residual for the caller to detect."""
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
    """(keep, drop, L) of a Gram matrix M = AᵀA: the columns independent of those before them (by
    :data:`DEPENDENT_PIVOT`), the others, and the lower L with L Lᵀ = M[keep][:, keep] (Lᵀ is the R of A[:, keep])."""
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
