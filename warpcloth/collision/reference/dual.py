"""Solvers of one impact zone's dual QP, min ½λᵀHλ − bᵀλ over λ ≥ 0 (H = G W⁻¹ Gᵀ, b = c(x̂), c = b − Hλ)."""

from __future__ import annotations

import numpy as np

from warpcloth.collision.reference.linalg import spd_solve


class ZoneNotConverged(Exception):
    """:class:`ZoneSolver` ran out of ``max_iterations`` active-set solves."""


class ZoneInfeasible(Exception):
    """No working set with λ ≥ 0 satisfies its own equations; ``residual``: the best one's [m]."""

    def __init__(self, residual):
        super().__init__(residual)
        self.residual = residual


def dual_value(H, b, lam) -> float:
    """The dual objective ½λᵀHλ − bᵀλ."""
    return float(0.5 * lam @ (H @ lam) - b @ lam)


class ZoneSolver:
    """Dual active-set solve of one zone: ``H`` (k, k) symmetric positive semidefinite, ``b`` (k,) c at λ = 0, ``tol``
    the KKT tolerance [m] on max c and on |c_j| where λ_j > 0; :meth:`solve_on` raises :class:`ZoneNotConverged`
    beyond ``max_iterations`` active-set solves."""

    def __init__(self, H, b, tol, max_iterations):
        self.H, self.b, self.tol = H, b, tol
        self.k = b.size
        self.max_iterations = max_iterations
        self.iterations = 0
        self.add_tol = 0.5 * tol
        self.atol = 1.0e-3 * tol
        self.last = np.zeros(self.k)
        """The latest non-negative iterate (for the error message when the iterations run out)."""

    def solve_on(self, P: np.ndarray) -> np.ndarray:
        """λ with H_PP λ_P = b_P on the working set P (bool, (k,)) and 0 elsewhere."""
        self.iterations += 1
        if self.iterations > self.max_iterations:
            raise ZoneNotConverged()
        lam = np.zeros(self.k)
        idx = np.flatnonzero(P)
        if idx.size:
            lam[idx] = spd_solve(self.H[np.ix_(idx, idx)], self.b[idx], atol=self.atol)
        if np.all(lam >= 0.0):
            self.last = lam
        return lam

    def residual(self, lam, P) -> float:
        """KKT residual [m] of λ with working set P: max violation and max |c_j| over P."""
        c = self.b - self.H @ lam
        r = max(float(np.max(c, initial=0.0)), float(np.max(np.abs(c[P]), initial=0.0)))
        return r

    def pdas(self, lam0: np.ndarray, limit: int) -> tuple[np.ndarray | None, np.ndarray]:
        """Primal–dual active set from lam0 ≥ 0, at most ``limit`` solves; (solution, or None when it cycles or
        runs out, best non-negative iterate)."""
        H, b = self.H, self.b
        c = b - H @ lam0
        P = (lam0 > 0.0) | (c > self.add_tol)
        seen = set()
        best, best_val = lam0, dual_value(H, b, lam0)
        for _ in range(limit):
            key = P.tobytes()
            if key in seen:
                return None, best
            seen.add(key)
            lam = self.solve_on(P)
            c = b - H @ lam
            drop = P & (lam < 0.0)
            add = ~P & (c > self.add_tol)
            if not drop.any():
                val = dual_value(H, b, lam)
                if val < best_val:
                    best, best_val = lam, val
                if not add.any():
                    if np.max(np.abs(c[P]), initial=0.0) <= self.tol:
                        return lam, lam
                    return None, best  # inconsistent working set: let the monotone method decide
            P = (P & ~drop) | add
        return None, best

    def lawson_hanson(self, lam0: np.ndarray) -> np.ndarray:
        """Monotone active-set method from lam0 ≥ 0; raises :class:`ZoneInfeasible` where no set is consistent."""
        H, b = self.H, self.b
        lam = np.maximum(lam0, 0.0)
        P = lam > 0.0
        if P.any():
            lam, P = self._inner(lam, P)
        val = dual_value(H, b, lam)
        single = False
        while True:
            c = b - H @ lam
            viol = ~P & (c > self.add_tol)
            if not viol.any():
                if np.max(np.abs(c[P]), initial=0.0) <= self.tol:
                    return lam
                raise ZoneInfeasible(self.residual(lam, P))
            if single:
                P[np.flatnonzero(viol)[np.argmax(c[viol])]] = True
            else:
                P |= viol
            lam, P = self._inner(lam, P)
            new_val = dual_value(H, b, lam)
            single = not new_val < val - 1e-15 * max(1.0, abs(val))
            val = new_val

    def _inner(self, lam, P):
        while True:
            trial = self.solve_on(P)
            neg = P & (trial <= 0.0)
            if not neg.any():
                return trial, P
            gap = lam[neg] - trial[neg]  # ≥ 0; 0 only where both are 0
            ratio = np.divide(lam[neg], gap, out=np.zeros_like(gap), where=gap > 0.0)
            alpha = float(np.min(ratio))
            lam = lam + alpha * (trial - lam)
            hit = np.flatnonzero(neg)[ratio <= alpha]
            lam[hit] = 0.0
            small = neg & (lam <= 1e-14 * max(float(np.max(lam, initial=0.0)), 1e-300))
            lam[small] = 0.0
            P = P & ~small
            P[hit] = False


def warm_start(b, s_con, s_node, s_dir, invm, colours, sweeps: int) -> tuple[np.ndarray, int]:
    """(λ ≥ 0, sweeps done) of projected Gauss–Seidel on the dual (Hildreth), vectorised over colour classes
    (contacts that share no particle), O(couplings) a sweep."""
    k = b.size
    lam = np.zeros(k)
    y = np.zeros((invm.size, 3))  # z − x̂ = Σ_j λ_j dir_j / m̃
    slot_colour = np.empty(k, dtype=np.int64)
    posmap = np.empty(k, dtype=np.int64)
    for c, cls in enumerate(colours):
        slot_colour[cls] = c
        posmap[cls] = np.arange(cls.size)
    order = np.argsort(slot_colour[s_con], kind="stable")
    bounds = np.searchsorted(slot_colour[s_con][order], np.arange(len(colours) + 1))
    classes = []
    for c, cls in enumerate(colours):
        sl = order[bounds[c]:bounds[c + 1]]
        node, d = s_node[sl], s_dir[sl]
        classes.append((cls, posmap[s_con[sl]], node, d, invm[node][:, None] * d,
                        np.bincount(posmap[s_con[sl]], weights=np.einsum("ij,ij->i", d, d) * invm[node],
                                    minlength=cls.size)))
    done = 0
    for done in range(1, sweeps + 1):  # noqa: B007 (the sweep count is returned)
        change = 0.0
        for cls, pos, node, d, dm, diag in classes:
            c = b[cls] - np.bincount(pos, weights=np.einsum("ij,ij->i", d, y[node]), minlength=cls.size)
            step = np.divide(c, diag, out=np.zeros_like(c), where=diag > 0.0)
            new = np.maximum(lam[cls] + step, 0.0)
            delta = new - lam[cls]
            lam[cls] = new
            y[node] += delta[pos][:, None] * dm
            change = max(change, float(np.max(np.abs(delta), initial=0.0)))
        if change <= 1e-3 * max(float(np.max(lam, initial=0.0)), 1e-300):
            break
    return lam, done
