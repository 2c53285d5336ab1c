"""Collision response as a quadratic program over impact zones, and its adjoint (SPEC.md §3 and §4.2).

Pure NumPy (float64) on the host; one call of :func:`project` per collision round, one call of :func:`backward` per
backward pass through that round.

Formulation (SPEC §3; Liang, Lin and Koltun 2019, §3)
------------------------------------------------------
Contact j couples four nodes a = 0..3 through frozen weights w_ja and a frozen unit normal n_j::

    c_j(z) = δ − Σ_a w_ja n_j·p(node_ja) ≤ 0,

where p is the unknown position z for a free cloth particle and a constant otherwise (x̂ for a hard-pinned
particle, ``obstacle_x`` for an obstacle vertex). A node may appear twice in one contact; its weights add up.
Free particles linked by contacts form impact zones (connected components). Each zone solves::

    min_z ½ (z − x̂)ᵀ W (z − x̂)   s.t.   G z + h ≤ 0,

with W = diag(m̃_i) (each coordinate of particle i), m̃_i = m_i · mean_k(1/m_k) over the zone's particles,
G_j,i = −w_ji n_jᵀ and h_j = δ − Σ_{constant nodes} w_ja n_j·x_a. Particles in no zone keep z = x̂. A contact with no
free node cannot move: if it is violated by more than ``tol`` the call raises :class:`ProjectionError`.

Solver
------
The zone is solved in its dual. Writing z(λ) = x̂ − W⁻¹Gᵀλ (stationarity holds exactly by construction), the
multipliers minimise ½λᵀHλ − bᵀλ over λ ≥ 0, with H = G W⁻¹ Gᵀ (dense, assembled from the contacts that share a
particle) and b = G x̂ + h = c(x̂); the constraint values are c(λ) = b − Hλ.

0. Zones of a single contact (the common cloth–obstacle case) are solved all at once in closed form,
   λ = max(0, b/H).
1. Warm start (zones with 8 or more contacts): projected Gauss–Seidel on the dual (Hildreth's method), vectorised
   over colour classes of contacts that share no particle, at most ``warm_sweeps`` sweeps.
2. Primal–dual active set (semismooth Newton on min(λ, −c) = 0): with P the working set, solve H_PP λ_P = b_P
   (Cholesky with a 1e-12-relative diagonal shift plus iterative refinement, so dependent but consistent
   constraints, e.g. duplicates, share their multiplier), then drop j ∈ P with λ_j < 0 and add j ∉ P with
   c_j > tol/2, until the set no longer changes. Usually 1–7 solves from the warm start.
3. If that cycles or takes more than 20 solves, a monotone Lawson–Hanson style active-set method (step back to the
   boundary λ ≥ 0 and drop, add the violated contacts — all at once while the dual objective decreases, else only
   the most violated) finishes from the best non-negative iterate.

Termination: the solution is accepted when λ ≥ 0, max_j c_j(z) ≤ tol and |c_j(z)| ≤ tol for every j with λ_j > 0
(so |λ_j c_j| ≤ tol·λ_j), all measured on z itself. A working set whose λ_P ≥ 0 cannot satisfy its own equations to
``tol`` is inconsistent: the zone is infeasible (e.g. a particle squeezed between two constant planes closer than
2δ) and a :class:`ProjectionError` names the zone, its sizes and the residual; so does running out of
``max_iterations`` (active-set solves per zone).

Adjoint (SPEC §4.2; the paper's §3)
-----------------------------------
On the active set A = {j : |c_j(z*)| ≤ active_tol} ∪ {j : λ_j > 0} the KKT conditions W(z − x̂) + G_Aᵀλ = 0,
G_A z + h_A = 0 define z*(x̂, G, h). With ḡ = ∂L/∂z, solve K [d_z; d_λ] = [ḡ; 0], K = [[W, G_Aᵀ], [G_A, 0]]; then,
as dL = ḡᵀdz = d_zᵀ(W dx̂ − dG_Aᵀλ) + d_λᵀ(−dG_A z − dh_A)::

    ∂L/∂x̂ = W d_z,   ∂L/∂G_A = −λ d_zᵀ − d_λ zᵀ,   ∂L/∂h_A = −d_λ,

which on the contacts reads, with p and d the position and d_z of each node (d = 0 for a constant node):
∂L/∂w_ja = (d_λj p_a + λ_j d_a)·n_j, ∂L/∂n_j = Σ_a w_ja (d_λj p_a + λ_j d_a), and for a constant node
∂L/∂x_a += d_λj w_ja n_j (obstacle vertices and pinned particles get this gradient here, unlike the seed).

* ``mode="qr"`` (the paper's method): Ã = W^{-1/2} G_Aᵀ (rows of particles touched by active contacts only;
  block diagonal over groups of active contacts linked by shared particles, each group factorised on its own),
  Householder QR Ã = QR; columns with |R_kk| < 1e-10·max|R_kk| are dependent on earlier ones and are dropped, the
  kept ones refactored, and the dropped multipliers folded into the kept ones (λ_keep += Cλ_drop with
  Ã_drop = Ã_keep C) so that G_Aᵀλ is unchanged. Then q = Qᵀ W^{-1/2} ḡ, d_λ = R⁻¹q (blocked triangular solve),
  d_z = W^{-1/2}(W^{-1/2}ḡ − Qq). By default the QR is computed lazily by the first :func:`backward` and its time
  is included in that call's ``backward_s`` (an honest comparison with the KKT mode); ``precompute_qr=True``
  computes it in :func:`project` instead, as the seed does (its time is then ``qr_s`` of the forward stats).
  Single-contact zones use the closed form of the same formulas (R = ‖Ã‖) in both modes.
* ``mode="kkt"`` (the seed's baseline and the oracle of the QR mode): the dense symmetric system of size
  nvar + ncon over all zone contacts, K = [[W, GᵀS], [SG, I − S]] with S the active indicator, by
  ``np.linalg.solve`` (``np.linalg.lstsq`` when the active rows are dependent or the solve fails).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

__all__ = ["ProjectionError", "ProjectionResult", "Zone", "backward", "project"]


class ProjectionError(RuntimeError):
    """A zone is infeasible or its solve did not converge, or a contact with only constant nodes is violated."""

    def __init__(self, message: str, *, zone: int | None = None, contact: int | None = None,
                 residual: float | None = None):
        super().__init__(message)
        self.zone = zone
        self.contact = contact
        self.residual = residual


_BLOCK = 128
"""Block size of the blocked triangular solves."""
_DEPENDENT_RTOL = 1.0e-10
"""|R_kk| < this · max|R_kk| marks a dependent active constraint in the QR adjoint."""
_SHIFT = 1.0e-12
"""Relative diagonal shift of the Cholesky factorisations of H_PP."""
_WARM_MIN = 8
"""Zones with at least this many contacts get the Gauss–Seidel warm start."""
_PDAS_LIMIT = 20
"""Most primal–dual active-set solves before the monotone method takes over."""


# ---------------------------------------------------------------------------------------------------------------
# Dense linear algebra helpers (NumPy has no triangular solve)


def _tri_solve(T: np.ndarray, B: np.ndarray, *, lower: bool) -> np.ndarray:
    """Solve T X = B for a triangular T by blocked substitution (O(k²) work per right-hand side)."""
    k = T.shape[0]
    if k == 0:
        return np.array(B, dtype=np.float64, copy=True)
    if k <= _BLOCK:
        return np.linalg.solve(T, B)
    X = np.array(B, dtype=np.float64, copy=True)
    if lower:
        for i0 in range(0, k, _BLOCK):
            i1 = min(i0 + _BLOCK, k)
            if i0:
                X[i0:i1] -= T[i0:i1, :i0] @ X[:i0]
            X[i0:i1] = np.linalg.solve(T[i0:i1, i0:i1], X[i0:i1])
    else:
        for i1 in range(k, 0, -_BLOCK):
            i0 = max(i1 - _BLOCK, 0)
            if i1 < k:
                X[i0:i1] -= T[i0:i1, i1:] @ X[i1:]
            X[i0:i1] = np.linalg.solve(T[i0:i1, i0:i1], X[i0:i1])
    return X


def _spd_solve(M: np.ndarray, rhs: np.ndarray, *, atol: float, refinements: int = 6) -> np.ndarray:
    """Solve M x = rhs for a symmetric positive semidefinite M.

    Cholesky of M + εI (ε = 1e-12·max diag, raised while the factorisation fails) with iterative refinement against
    M itself: consistent singular systems converge to a solution (near the minimum-norm one), inconsistent ones
    leave a residual the caller detects.
    """
    k = M.shape[0]
    if k == 0:
        return np.zeros(0)
    scale = float(np.max(np.diag(M))) if k else 1.0
    scale = scale if scale > 0.0 else 1.0
    eps = _SHIFT * scale
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
        return _tri_solve(U, _tri_solve(L, r, lower=True), lower=False)

    x = solve(rhs)
    for _ in range(refinements):
        res = rhs - M @ x
        if np.max(np.abs(res)) <= atol:
            break
        x = x + solve(res)
    return x


# ---------------------------------------------------------------------------------------------------------------
# Results


@dataclass
class _QRBlock:
    """QR factorisation of one connected group of active constraints (see the module docstring)."""

    rows: np.ndarray
    """Local particle indices whose coordinates are the rows of Ã (the particles these constraints touch)."""
    cols: np.ndarray
    """Local contact indices of these active constraints (the columns of Ã, sorted)."""
    keep: np.ndarray
    """Positions in ``cols`` of the independent columns kept in the factorisation, in factorisation order."""
    drop: np.ndarray
    """Positions in ``cols`` of the dependent columns dropped."""
    Q: np.ndarray
    R: np.ndarray
    lam: np.ndarray
    """Multipliers of the kept columns with the dropped ones folded in."""


@dataclass
class _QR:
    """The adjoint's factorisation of a zone: Ã is block diagonal over groups of active constraints that share no
    particle, so each group is factorised on its own (same Q and R up to a permutation, far less work)."""

    blocks: list[_QRBlock]
    seconds: float

    @property
    def independent(self) -> int:
        return sum(int(b.keep.size) for b in self.blocks)

    @property
    def dependent(self) -> int:
        return sum(int(b.drop.size) for b in self.blocks)


@dataclass
class Zone:
    """One impact zone: its particles and contacts, the solution, and what the adjoint needs."""

    index: int
    nodes: np.ndarray
    """Global indices of the zone's free particles (sorted)."""
    contacts: np.ndarray
    """Global indices of the zone's contacts (sorted)."""
    mass: np.ndarray
    """Normalised masses m̃ of ``nodes``."""
    slot_con: np.ndarray
    """Merged (contact, particle) couplings: local contact index ..."""
    slot_node: np.ndarray
    """... local particle index ..."""
    slot_dir: np.ndarray
    """... and (Σ of the weights of that particle in that contact)·n_j, shape (S, 3); G's block is −slot_dir."""
    h: np.ndarray
    """Constant part h of each contact's constraint."""
    lam: np.ndarray
    """Multipliers of ``contacts``."""
    c: np.ndarray
    """Constraint values c_j(z*) of ``contacts``."""
    active: np.ndarray
    """Local indices of the active set used by the adjoint."""
    single: bool = False
    """A zone of one contact, solved (and differentiated) in closed form together with all such zones."""
    qr: _QR | None = None
    stats: dict = field(default_factory=dict)


@dataclass
class ProjectionResult:
    """What :func:`project` returns: positions, multipliers, zones and the inputs the adjoint needs."""

    z: np.ndarray
    """Projected positions (n, 3); x̂ for particles in no zone and for pinned particles."""
    lam: np.ndarray
    """Multiplier of every contact (m,); 0 for contacts in no zone."""
    zones: list[Zone]
    x_hat: np.ndarray
    obstacle_x: np.ndarray
    fixed: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    normals: np.ndarray
    thickness: float
    tol: float
    active_tol: float
    singles: dict = field(default_factory=dict)
    """Batched data of the single-contact zones (closed-form solve and adjoint)."""
    backward_stats: list[dict] = field(default_factory=list)
    """Per-zone records of the last :func:`backward` call."""

    @property
    def stats(self) -> list[dict]:
        """Per-zone forward records (see :func:`project`)."""
        return [zone.stats for zone in self.zones]

    def zones_stats(self) -> list[dict]:
        """Per-zone forward records merged with those of the last backward pass, if any."""
        out = [dict(zone.stats) for zone in self.zones]
        for rec, back in zip(out, self.backward_stats):
            rec.update(back)
        return out

    def backward(self, grad_z: np.ndarray, *, mode: str = "qr"):
        """Same as :func:`backward` (result, grad_z, mode=mode)."""
        return backward(self, grad_z, mode=mode)


# ---------------------------------------------------------------------------------------------------------------
# Input checks


def _float_array(name: str, value, shape: tuple) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be a float array of shape {shape}: {err}") from None
    if arr.size == 0 and len(shape) == 2 and shape[0] is None:
        arr = arr.reshape(0, shape[1])
    if arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape)):
        raise ValueError(f"{name} must have shape {tuple('?' if s is None else s for s in shape)}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ValueError(f"{name} has a non-finite entry at {tuple(int(i) for i in bad)}")
    return arr


def _check_inputs(x_hat, mass, fixed, obstacle_x, nodes, weights, normals, thickness):
    x_hat = _float_array("x_hat", x_hat, (None, 3))
    n = x_hat.shape[0]
    mass = _float_array("mass", mass, (n,))
    if fixed is None:
        fixed = np.zeros(n, dtype=bool)
    fixed = np.asarray(fixed)
    if fixed.shape != (n,):
        raise ValueError(f"fixed must have shape ({n},), got {fixed.shape}")
    if fixed.dtype != bool:
        if not (np.issubdtype(fixed.dtype, np.integer) and np.all((fixed == 0) | (fixed == 1))):
            raise ValueError(f"fixed must be a boolean array, got dtype {fixed.dtype}")
        fixed = fixed.astype(bool)
    bad = np.flatnonzero(~fixed & ~(mass > 0.0))
    if bad.size:
        raise ValueError(f"mass must be > 0 for every free particle; particle {int(bad[0])} has {mass[bad[0]]}")
    obstacle_x = _float_array("obstacle_x", np.zeros((0, 3)) if obstacle_x is None else obstacle_x, (None, 3))
    V = obstacle_x.shape[0]
    nodes_arr = np.asarray(nodes)
    if nodes_arr.size == 0:
        nodes_arr = nodes_arr.reshape(0, 4)
    if nodes_arr.ndim != 2 or nodes_arr.shape[1] != 4:
        raise ValueError(f"nodes must have shape (m, 4), got {nodes_arr.shape}")
    if nodes_arr.size and not np.issubdtype(nodes_arr.dtype, np.integer):
        raise ValueError(f"nodes must be an integer array, got dtype {nodes_arr.dtype}")
    nodes_arr = nodes_arr.astype(np.int64)
    m = nodes_arr.shape[0]
    out = (nodes_arr < 0) | (nodes_arr >= n + V)
    if out.any():
        j, a = np.argwhere(out)[0]
        raise ValueError(f"nodes[{j}, {a}] = {nodes_arr[j, a]} is outside [0, {n + V}) "
                         f"({n} particles + {V} obstacle vertices)")
    weights = _float_array("weights", weights, (m, 4))
    normals = _float_array("normals", normals, (m, 3))
    try:
        thickness = float(thickness)
    except (TypeError, ValueError):
        raise ValueError(f"thickness must be a number, got {thickness!r}") from None
    if not math.isfinite(thickness) or thickness <= 0.0:
        raise ValueError(f"thickness must be finite and > 0, got {thickness}")
    return x_hat, mass, fixed, obstacle_x, nodes_arr, weights, normals, thickness


# ---------------------------------------------------------------------------------------------------------------
# Zones


def _components(n: int, edges_u: np.ndarray, edges_v: np.ndarray) -> np.ndarray:
    """Label of every particle: the smallest index in its connected component (hooking + pointer jumping)."""
    parent = np.arange(n, dtype=np.int64)
    if edges_u.size == 0:
        return parent
    while True:
        pu, pv = parent[edges_u], parent[edges_v]
        if np.array_equal(pu, pv):
            return parent
        lo = np.minimum(pu, pv)
        np.minimum.at(parent, pu, lo)
        np.minimum.at(parent, pv, lo)
        while True:
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand


def _gram(k: int, slot_con, slot_node, slot_dir, invm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """H = G W⁻¹ Gᵀ (k, k) from the merged slots, and the (contact, contact) pairs that share a particle."""
    S = slot_con.size
    order = np.argsort(slot_node, kind="stable")
    sn = slot_node[order]
    start = np.searchsorted(sn, sn, side="left")
    cnt = np.searchsorted(sn, sn, side="right") - start
    left = np.repeat(np.arange(S), cnt)
    offs = np.arange(left.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    right = start[left] + offs
    li, ri = order[left], order[right]
    vals = np.einsum("ij,ij->i", slot_dir[li], slot_dir[ri]) * invm[slot_node[li]]
    ci, cj = slot_con[li], slot_con[ri]
    H = np.bincount(ci * k + cj, weights=vals, minlength=k * k).reshape(k, k)
    return H, ci, cj


def _colour_classes(k: int, ci: np.ndarray, cj: np.ndarray) -> list[np.ndarray]:
    """Greedy colouring of the contacts; contacts of one colour share no particle."""
    off = ci != cj
    ci, cj = ci[off], cj[off]
    order = np.argsort(ci, kind="stable")
    ci, cj = ci[order], cj[order]
    bounds = np.searchsorted(ci, np.arange(k + 1))
    nbr = cj.tolist()
    b = bounds.tolist()
    colour = [-1] * k
    for j in range(k):
        used = {colour[x] for x in nbr[b[j]:b[j + 1]]}
        c = 0
        while c in used:
            c += 1
        colour[j] = c
    colour = np.asarray(colour)
    return [np.flatnonzero(colour == c) for c in range(int(colour.max()) + 1)] if k else []


def _dual_value(H, b, lam) -> float:
    return float(0.5 * lam @ (H @ lam) - b @ lam)


class _ZoneSolver:
    """Dual active-set solve of one zone (see the module docstring)."""

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
        self.iterations += 1
        if self.iterations > self.max_iterations:
            raise _NotConverged()
        lam = np.zeros(self.k)
        idx = np.flatnonzero(P)
        if idx.size:
            lam[idx] = _spd_solve(self.H[np.ix_(idx, idx)], self.b[idx], atol=self.atol)
        if np.all(lam >= 0.0):
            self.last = lam
        return lam

    def residual(self, lam, P) -> float:
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
        best, best_val = lam0, _dual_value(H, b, lam0)
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
                val = _dual_value(H, b, lam)
                if val < best_val:
                    best, best_val = lam, val
                if not add.any():
                    if np.max(np.abs(c[P]), initial=0.0) <= self.tol:
                        return lam, lam
                    return None, best  # inconsistent working set: let the monotone method decide
            P = (P & ~drop) | add
        return None, best

    def lawson_hanson(self, lam0: np.ndarray) -> np.ndarray:
        """Monotone active-set method from lam0 ≥ 0; raises _Infeasible when a consistent set cannot be found."""
        H, b = self.H, self.b
        lam = np.maximum(lam0, 0.0)
        P = lam > 0.0
        if P.any():
            lam, P = self._inner(lam, P)
        val = _dual_value(H, b, lam)
        single = False
        while True:
            c = b - H @ lam
            viol = ~P & (c > self.add_tol)
            if not viol.any():
                if np.max(np.abs(c[P]), initial=0.0) <= self.tol:
                    return lam
                raise _Infeasible(self.residual(lam, P))
            if single:
                P[np.flatnonzero(viol)[np.argmax(c[viol])]] = True
            else:
                P |= viol
            lam, P = self._inner(lam, P)
            new_val = _dual_value(H, b, lam)
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


class _NotConverged(Exception):
    pass


class _Infeasible(Exception):
    def __init__(self, residual):
        super().__init__(residual)
        self.residual = residual


def _warm_start(b, s_con, s_node, s_dir, invm, colours, sweeps: int) -> tuple[np.ndarray, int]:
    """Projected Gauss–Seidel on the dual (Hildreth), vectorised over colour classes (contacts sharing no particle).

    Works on the sparse couplings: the displacement y = z − x̂ = −W⁻¹Gᵀλ is kept per particle, so a sweep costs
    O(couplings), not O(k²). Returns (λ ≥ 0, sweeps done).
    """
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
    for done in range(1, sweeps + 1):
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


# ---------------------------------------------------------------------------------------------------------------
# Forward


def project(x_hat, mass, fixed, obstacle_x, nodes, weights, normals, thickness, *, tol: float = 1.0e-10,
            max_iterations: int = 500, active_tol: float = 1.0e-9, warm_sweeps: int = 30,
            precompute_qr: bool = False, lam_init=None) -> ProjectionResult:
    """Project x̂ onto the non-penetrating set of the contacts, zone by zone (see the module docstring).

    Args:
        x_hat: (n, 3) positions after the implicit step.
        mass: (n,) lumped masses (> 0 for every free particle).
        fixed: (n,) bool, particles held constant (hard pins); None for none.
        obstacle_x: (V, 3) obstacle vertex positions (constants); None or (0, 3) for none.
        nodes: (m, 4) integer node ids: k < n is particle k, k ≥ n is obstacle vertex k − n.
        weights: (m, 4) contact weights w_ja.
        normals: (m, 3) contact normals n_j (unit).
        thickness: δ > 0 [m].
        tol: KKT tolerance [m] on constraint violation and on |c_j| of contacts with λ_j > 0.
        max_iterations: most active-set solves per zone.
        active_tol: |c_j(z*)| ≤ active_tol [m] makes contact j active in the adjoint (as does λ_j > 0).
        warm_sweeps: most Gauss–Seidel sweeps of the warm start.
        precompute_qr: factorise the adjoint's QR here (True) or in the first :func:`backward` (False).
        lam_init: (m,) multipliers to start the active-set method from (e.g. the previous collision round's, with
            zeros for the new contacts); a zone with a positive entry skips the Gauss–Seidel warm start.

    Returns:
        A :class:`ProjectionResult`; ``result.stats`` has one record per zone with ``nodes`` (free particles),
        ``nvar``, ``ncon``, ``active``, ``independent`` (QR size; None until factorised), ``kkt_size``,
        ``qr_size``, ``kkt_residual`` [m], ``stationarity``, ``complementarity``, ``iterations`` (active-set
        solves), ``sweeps`` (warm-start sweeps), ``solve_s``, ``qr_s`` and ``forward_s``.

    Raises:
        ValueError: a malformed argument (named).
        ProjectionError: a violated contact with no free node, an infeasible zone, or no convergence.
    """
    x_hat, mass, fixed, obstacle_x, nodes, weights, normals, thickness = _check_inputs(
        x_hat, mass, fixed, obstacle_x, nodes, weights, normals, thickness)
    for name, val in (("tol", tol), ("active_tol", active_tol)):
        try:
            ok = math.isfinite(float(val)) and float(val) > 0.0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"{name} must be finite and > 0, got {val!r}")
    tol, active_tol = float(tol), float(active_tol)
    for name, val, low in (("max_iterations", max_iterations, 1), ("warm_sweeps", warm_sweeps, 0)):
        if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {val!r}")
    n, m = x_hat.shape[0], nodes.shape[0]
    if lam_init is not None:
        lam_init = _float_array("lam_init", lam_init, (m,))
    positions = np.concatenate([x_hat, obstacle_x])  # constants (and x̂ for free particles)
    free_ext = np.concatenate([~fixed, np.zeros(obstacle_x.shape[0], dtype=bool)])

    free = free_ext[nodes]  # (m, 4)
    proj = np.einsum("jad,jd->ja", positions[nodes], normals)  # n_j · p_a
    h_all = thickness - np.sum(np.where(free, 0.0, weights * proj), axis=1)
    has_free = free.any(axis=1)
    const = np.flatnonzero(~has_free)
    if const.size:
        bad = const[h_all[const] > tol]
        if bad.size:
            j = int(bad[np.argmax(h_all[bad])])
            raise ProjectionError(
                f"contact {j} (nodes {nodes[j].tolist()}) has no free node and is violated by {h_all[j]:.3e} m "
                f"> tol {tol:.1e} ({bad.size} such contact(s)); pinned particles or obstacles overlap",
                contact=j, residual=float(h_all[j]))

    # Merged (contact, free particle) slots: a particle listed twice in one contact gets its weights summed.
    sj, sa = np.nonzero(free)
    sn = nodes[sj, sa]
    key, inv = np.unique(sj * n + sn, return_inverse=True)
    slot_j, slot_n = key // n, key % n
    slot_w = np.bincount(inv.ravel(), weights=weights[sj, sa], minlength=key.size)

    # Impact zones: components of the free particles linked by contacts.
    first = np.full(m, -1, dtype=np.int64)
    order_j = np.argsort(slot_j, kind="stable")
    uj, pos = np.unique(slot_j[order_j], return_index=True)
    first[uj] = slot_n[order_j][pos]
    label = _components(n, first[slot_j], slot_n)
    in_zone = np.zeros(n, dtype=bool)
    in_zone[slot_n] = True
    roots = np.unique(label[in_zone])
    zone_of_node = np.full(n, -1, dtype=np.int64)
    zone_of_node[in_zone] = np.searchsorted(roots, label[in_zone])
    zone_of_contact = np.full(m, -1, dtype=np.int64)
    zone_of_contact[uj] = zone_of_node[first[uj]]

    nzones = roots.size
    k_of_zone = np.bincount(zone_of_contact[zone_of_contact >= 0], minlength=nzones)
    z = x_hat.copy()
    lam_all = np.zeros(m)
    zones: list[Zone | None] = [None] * nzones
    slot_zone = zone_of_contact[slot_j]
    singles = _solve_singles(np.flatnonzero(k_of_zone[slot_zone] == 1), slot_j, slot_n, slot_w, zone_of_contact,
                             x_hat, mass, normals, h_all, tol, active_tol, z, lam_all, zones)
    multi = np.flatnonzero(k_of_zone > 1)
    node_groups = _group(zone_of_node, nzones)
    con_groups = _group(zone_of_contact, nzones)
    slot_groups = _group(slot_zone, nzones)
    local = np.zeros(n, dtype=np.int64)
    local_con = np.zeros(m, dtype=np.int64)
    for zi in multi.tolist():
        t0 = time.perf_counter()
        znodes, zcons, zslots = node_groups[zi], con_groups[zi], slot_groups[zi]
        local[znodes] = np.arange(znodes.size)
        local_con[zcons] = np.arange(zcons.size)
        zm = mass[znodes]
        mt = zm * np.mean(1.0 / zm)
        invm = 1.0 / mt
        s_con = local_con[slot_j[zslots]]
        s_node = local[slot_n[zslots]]
        s_dir = slot_w[zslots, None] * normals[slot_j[zslots]]
        h = h_all[zcons]
        k = zcons.size
        xz = x_hat[znodes]
        b = h - np.bincount(s_con, weights=np.einsum("ij,ij->i", s_dir, xz[s_node]), minlength=k)
        H, ci, cj = _gram(k, s_con, s_node, s_dir, invm)
        solver = _ZoneSolver(H, b, tol, int(max_iterations))
        sweeps = 0
        try:
            if not np.any(b > solver.add_tol):
                lam = np.zeros(k)
            else:
                lam0 = np.zeros(k)
                if lam_init is not None and np.any(lam_init[zcons] > 0.0):
                    lam0 = np.maximum(lam_init[zcons], 0.0)
                elif k >= _WARM_MIN and warm_sweeps > 0:
                    colours = _colour_classes(k, ci, cj)
                    lam0, sweeps = _warm_start(b, s_con, s_node, s_dir, invm, colours, int(warm_sweeps))
                lam, best = solver.pdas(lam0, _PDAS_LIMIT)
                if lam is None:
                    lam = solver.lawson_hanson(best)
        except _Infeasible as err:
            raise _infeasible(zi, znodes.size, k, err.residual, tol) from None
        except _NotConverged:
            res = solver.residual(solver.last, solver.last > 0.0)
            raise ProjectionError(
                f"impact zone {zi} ({znodes.size} free particles, {k} contacts) did not converge in "
                f"{max_iterations} active-set iterations; residual {res:.3e} m > tol {tol:.1e}",
                zone=zi, residual=res) from None
        lam = np.maximum(lam, 0.0)
        disp = np.stack([np.bincount(s_node, weights=lam[s_con] * s_dir[:, d], minlength=znodes.size)
                         for d in range(3)], axis=1)
        zz = xz + invm[:, None] * disp
        c = h - np.bincount(s_con, weights=np.einsum("ij,ij->i", s_dir, zz[s_node]), minlength=k)
        pos_l = lam > 0.0
        residual = _check_solution(zi, znodes.size, c, pos_l, tol)
        stat = mt[:, None] * (zz - xz) - disp  # W(z − x̂) + Gᵀλ
        z[znodes] = zz
        lam_all[zcons] = lam
        active = np.flatnonzero((np.abs(c) <= active_tol) | pos_l)
        solve_s = time.perf_counter() - t0
        zone = Zone(index=zi, nodes=znodes, contacts=zcons, mass=mt, slot_con=s_con, slot_node=s_node,
                    slot_dir=s_dir, h=h, lam=lam, c=c, active=active)
        zone.stats = {
            "nodes": int(znodes.size), "nvar": 3 * int(znodes.size), "ncon": int(k), "active": int(active.size),
            "independent": None, "kkt_size": 3 * int(znodes.size) + int(k), "qr_size": None,
            "kkt_residual": residual, "stationarity": float(np.max(np.abs(stat), initial=0.0)),
            "complementarity": float(np.max(np.abs(lam * c), initial=0.0)), "iterations": solver.iterations,
            "sweeps": sweeps, "solve_s": solve_s, "qr_s": 0.0, "forward_s": solve_s,
        }
        if precompute_qr:
            _factorise(zone)
            zone.stats["forward_s"] += zone.qr.seconds
        zones[zi] = zone
    return ProjectionResult(z=z, lam=lam_all, zones=zones, x_hat=x_hat, obstacle_x=obstacle_x, fixed=fixed,
                            nodes=nodes, weights=weights, normals=normals, thickness=thickness, tol=float(tol),
                            active_tol=float(active_tol), singles=singles)


def _infeasible(zi, nodes, k, residual, tol) -> ProjectionError:
    return ProjectionError(
        f"impact zone {zi} ({nodes} free particles, {k} contacts) is infeasible: the best working set leaves a "
        f"constraint residual of {residual:.3e} m > tol {tol:.1e} (cloth squeezed between constant nodes closer "
        "than 2δ?)", zone=zi, residual=residual)


def _check_solution(zi, nodes, c, positive, tol) -> float:
    """KKT residual [m] of a zone's solution (violation, and |c_j| where λ_j > 0); raises beyond tol."""
    residual = max(float(np.max(c, initial=0.0)), float(np.max(np.abs(c[positive]), initial=0.0)))
    if residual > tol:
        raise ProjectionError(
            f"impact zone {zi} ({nodes} free particles, {c.size} contacts): the solution misses the KKT "
            f"tolerance, residual {residual:.3e} m > tol {tol:.1e}", zone=zi, residual=residual)
    return residual


def _solve_singles(ss, slot_j, slot_n, slot_w, zone_of_contact, x_hat, mass, normals, h_all, tol, active_tol,
                   z, lam_all, zones) -> dict:
    """All zones with a single contact at once, in closed form: λ = max(0, b/H), z = x̂ + λ W⁻¹ dir.

    ``ss`` are their merged slots (sorted by contact). Fills z, lam_all and zones; returns the arrays the
    backward pass needs (its closed form is the QR formula with the 1×1 R = ‖Ã‖, in both modes).
    """
    t0 = time.perf_counter()
    sj, sn = slot_j[ss], slot_n[ss]
    J, pos = np.unique(sj, return_inverse=True)
    nJ = J.size
    sdir = slot_w[ss, None] * normals[sj]
    cnt = np.bincount(pos, minlength=nJ)
    meaninv = np.bincount(pos, weights=1.0 / mass[sn], minlength=nJ) / np.maximum(cnt, 1)
    mt = mass[sn] * meaninv[pos]
    Hj = np.bincount(pos, weights=np.einsum("ij,ij->i", sdir, sdir) / mt, minlength=nJ)
    hj = h_all[J]
    bj = hj - np.bincount(pos, weights=np.einsum("ij,ij->i", sdir, x_hat[sn]), minlength=nJ)
    bad = np.flatnonzero((bj > tol) & ~(Hj > 0.0))
    if bad.size:
        i = int(bad[0])
        raise _infeasible(int(zone_of_contact[J[i]]), int(cnt[i]), 1, float(bj[i]), tol)
    lam = np.where((bj > 0.5 * tol) & (Hj > 0.0), bj / np.where(Hj > 0.0, Hj, 1.0), 0.0)
    zz = x_hat[sn] + (lam[pos] / mt)[:, None] * sdir
    z[sn] = zz
    lam_all[J] = lam
    c = hj - np.bincount(pos, weights=np.einsum("ij,ij->i", sdir, zz), minlength=nJ)
    positive = lam > 0.0
    viol = np.maximum(c, 0.0)
    viol[positive] = np.abs(c[positive])
    if nJ and np.max(viol) > tol:
        i = int(np.argmax(viol))
        _check_solution(int(zone_of_contact[J[i]]), int(cnt[i]), c[i:i + 1], positive[i:i + 1], tol)
    stat = np.abs(mt[:, None] * (zz - x_hat[sn]) - lam[pos, None] * sdir)
    stat = np.bincount(pos, weights=np.max(stat, axis=1), minlength=nJ)
    act = (np.abs(c) <= active_tol) | positive
    indep = act & (Hj > 0.0)
    bounds = np.concatenate([[0], np.cumsum(cnt)])
    share = (time.perf_counter() - t0) / max(nJ, 1)
    zero = np.zeros(1, dtype=np.int64)
    empty = np.zeros(0, dtype=np.int64)
    for i in range(nJ):
        a, b = bounds[i], bounds[i + 1]
        zi = int(zone_of_contact[J[i]])
        zone = Zone(index=zi, nodes=sn[a:b], contacts=J[i:i + 1], mass=mt[a:b], slot_con=np.zeros(b - a, np.int64),
                    slot_node=np.arange(b - a), slot_dir=sdir[a:b], h=hj[i:i + 1], lam=lam[i:i + 1],
                    c=c[i:i + 1], active=zero if act[i] else empty, single=True)
        nn = int(b - a)
        zone.stats = {
            "nodes": nn, "nvar": 3 * nn, "ncon": 1, "active": int(act[i]), "independent": int(indep[i]),
            "kkt_size": 3 * nn + 1, "qr_size": int(indep[i]), "kkt_residual": float(viol[i]),
            "stationarity": float(stat[i]), "complementarity": float(abs(lam[i] * c[i])),
            "iterations": int(lam[i] > 0.0), "sweeps": 0, "solve_s": share, "qr_s": 0.0, "forward_s": share,
        }
        zones[zi] = zone
    return {"contacts": J, "pos": pos, "nodes": sn, "dir": sdir, "mass": mt, "H": Hj, "lam": lam,
            "independent": indep, "zones": zone_of_contact[J]}


def _group(ids: np.ndarray, count: int) -> list[np.ndarray]:
    """Indices i with ids[i] == g for g in range(count), each sorted (ids < 0 are left out)."""
    order = np.argsort(ids, kind="stable")
    bounds = np.searchsorted(ids[order], np.arange(count + 1))
    return [order[bounds[g]:bounds[g + 1]] for g in range(count)]


# ---------------------------------------------------------------------------------------------------------------
# Adjoint


def _atilde(zone: Zone, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ã = W^{-1/2} G_Aᵀ restricted to the columns ``cols`` (local contacts) and to the particles they touch."""
    sel = np.isin(zone.slot_con, cols)
    rows = np.unique(zone.slot_node[sel])
    rpos = np.searchsorted(rows, zone.slot_node[sel])
    cpos = np.searchsorted(cols, zone.slot_con[sel])  # cols is sorted
    A = np.zeros((3 * rows.size, cols.size))
    vals = -zone.slot_dir[sel] / np.sqrt(zone.mass[zone.slot_node[sel]])[:, None]
    for d in range(3):
        A[3 * rpos + d, cpos] = vals[:, d]
    return A, rows


def _householder(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reduced Householder QR of the columns of A that are independent of the columns before them.

    A column with |R_kk| < 1e-10·max|R_kk| is dependent on earlier ones: it is dropped and the rest refactorised.
    (A dropped column that turns out not to lie in the span of the kept ones, which the unpivoted QR can cause
    after a dependent column, is put back at the end.) Returns (keep, drop, Q, R), keep in factorisation order.
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
            good[:r] = diag >= _DEPENDENT_RTOL * float(np.max(diag))
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


def _factorise(zone: Zone) -> _QR:
    """Householder QR of Ã on the active set, per group of active constraints linked by shared particles, with the
    dependent columns dropped and their multipliers folded into the kept ones."""
    t0 = time.perf_counter()
    act = zone.active
    blocks = []
    if act.size:
        sel = np.isin(zone.slot_con, act)
        sc, snode = zone.slot_con[sel], zone.slot_node[sel]
        first = np.full(zone.lam.size, -1, dtype=np.int64)
        first[sc[::-1]] = snode[::-1]  # one particle of each active contact
        label = _components(zone.mass.size, first[sc], snode)
        group = label[first[act]]
        for g in np.unique(group):
            cols = act[group == g]
            A, rows = _atilde(zone, cols)
            keep, drop, Q, R = _householder(A)
            lam = zone.lam[cols]
            lam_keep = lam[keep].copy()
            if drop.size and keep.size:
                C = _tri_solve(R, Q.T @ A[:, drop], lower=False)  # Ã_drop = Ã_keep C
                lam_keep += C @ lam[drop]
            blocks.append(_QRBlock(rows=rows, cols=cols, keep=keep, drop=drop, Q=Q, R=R, lam=lam_keep))
    zone.qr = _QR(blocks=blocks, seconds=time.perf_counter() - t0)
    zone.stats["independent"] = zone.qr.independent
    zone.stats["qr_size"] = zone.qr.independent
    zone.stats["qr_s"] = zone.qr.seconds
    return zone.qr


def _zone_adjoint_qr(zone: Zone, g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d_z (nz, 3), d_λ (k,), λ used with ∂L/∂G (k,)) of one zone by the QR formula."""
    qr = zone.qr if zone.qr is not None else _factorise(zone)
    sq = np.sqrt(zone.mass)
    gp = g / sq[:, None]  # W^{-1/2} ḡ
    u = gp.copy()
    k = zone.lam.size
    d_lam = np.zeros(k)
    lam = np.zeros(k)
    for blk in qr.blocks:
        if blk.keep.size == 0:
            continue
        grow = gp[blk.rows].ravel()
        q = blk.Q.T @ grow
        u[blk.rows] = (grow - blk.Q @ q).reshape(-1, 3)
        d_lam[blk.cols[blk.keep]] = _tri_solve(blk.R, q, lower=False)
        lam[blk.cols[blk.keep]] = blk.lam
    return u / sq[:, None], d_lam, lam


def _zone_adjoint_kkt(zone: Zone, g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Same as _zone_adjoint_qr by the dense (nvar + ncon) KKT system over all zone contacts."""
    nz, k = zone.mass.size, zone.lam.size
    nvar = 3 * nz
    G = np.zeros((k, nvar))
    for d in range(3):
        G[zone.slot_con, 3 * zone.slot_node + d] = -zone.slot_dir[:, d]
    s = np.zeros(k)
    s[zone.active] = 1.0
    K = np.zeros((nvar + k, nvar + k))
    K[np.arange(nvar), np.arange(nvar)] = np.repeat(zone.mass, 3)
    K[:nvar, nvar:] = G.T * s[None, :]
    K[nvar:, :nvar] = G * s[:, None]
    K[np.arange(nvar, nvar + k), np.arange(nvar, nvar + k)] = 1.0 - s
    rhs = np.concatenate([g.ravel(), np.zeros(k)])
    qr = zone.qr if zone.qr is not None else _factorise(zone)  # its rank test picks solve or lstsq
    dependent = qr.dependent > 0
    sol = None
    if not dependent:
        try:
            sol = np.linalg.solve(K, rhs)
            if not np.all(np.isfinite(sol)):
                sol = None
        except np.linalg.LinAlgError:
            sol = None
    if sol is None:
        sol = np.linalg.lstsq(K, rhs, rcond=None)[0]
    return sol[:nvar].reshape(nz, 3), sol[nvar:] * s, zone.lam.copy()


def backward(result: ProjectionResult, grad_z, *, mode: str = "qr"):
    """Gradients of a loss L(z*) given ∂L/∂z (n, 3); see the module docstring (SPEC §4.2).

    Returns:
        (∂L/∂x̂ (n, 3), ∂L/∂weights (m, 4), ∂L/∂normals (m, 3), ∂L/∂obstacle_x (V, 3)). ∂L/∂x̂ passes ∂L/∂z
        through for particles in no zone, and for pinned particles adds their contributions as constant nodes.
        ``result.backward_stats`` gets one record per zone: ``mode``, ``backward_s`` (the zone's solve, the QR when
        it was not precomputed (``qr_in_backward``), and its share of pushing the result onto the contacts),
        ``kkt_size``, ``qr_size``. Single-contact zones use the closed form (1×1 R) in both modes, all at once;
        each gets an equal share of that time.
    """
    if mode not in ("qr", "kkt"):
        raise ValueError(f"mode must be 'qr' or 'kkt', got {mode!r}")
    n = result.x_hat.shape[0]
    grad_z = _float_array("grad_z", grad_z, (n, 3))
    V = result.obstacle_x.shape[0]
    m = result.nodes.shape[0]
    grad_x = grad_z.copy()
    d_ext = np.zeros((n + V, 3))  # d_z of the free zone particles, 0 elsewhere
    d_lam = np.zeros(m)
    lam = np.zeros(m)  # the multipliers the adjoint uses (dependent ones folded into the kept ones in QR mode)
    seconds = np.zeros(len(result.zones))
    lazy = np.zeros(len(result.zones), dtype=bool)

    t0 = time.perf_counter()
    sg = result.singles
    if sg and sg["contacts"].size:
        pos, sn, sdir, mt = sg["pos"], sg["nodes"], sg["dir"], sg["mass"]
        t = np.bincount(pos, weights=np.einsum("ij,ij->i", sdir, grad_z[sn]) / mt, minlength=sg["H"].size)
        dl = np.where(sg["independent"], -t / np.where(sg["independent"], sg["H"], 1.0), 0.0)
        gx = grad_z[sn] + dl[pos, None] * sdir  # W d_z = ḡ − G_Aᵀ d_λ
        grad_x[sn] = gx
        d_ext[sn] = gx / mt[:, None]
        d_lam[sg["contacts"]] = dl
        lam[sg["contacts"]] = np.where(sg["independent"], sg["lam"], 0.0)
        seconds[sg["zones"]] = (time.perf_counter() - t0) / sg["contacts"].size
    for zone in result.zones:
        if zone.single:
            continue
        t0 = time.perf_counter()
        lazy[zone.index] = zone.qr is None
        g = grad_z[zone.nodes]
        if mode == "qr":
            d_z, dl, lz = _zone_adjoint_qr(zone, g)
        else:
            d_z, dl, lz = _zone_adjoint_kkt(zone, g)
        grad_x[zone.nodes] = zone.mass[:, None] * d_z
        d_ext[zone.nodes] = d_z
        d_lam[zone.contacts] = dl
        lam[zone.contacts] = lz
        seconds[zone.index] = time.perf_counter() - t0

    # Push onto the contacts: ∂L/∂w_ja = (d_λj p_a + λ_j d_a)·n_j, ∂L/∂n_j = Σ_a w_ja (d_λj p_a + λ_j d_a),
    # and ∂L/∂x_a += d_λj w_ja n_j for the constant nodes (d_a = 0 there).
    t0 = time.perf_counter()
    cons = np.flatnonzero((d_lam != 0.0) | (lam != 0.0))
    nd = result.nodes[cons]
    w = result.weights[cons]
    nrm = result.normals[cons]
    free_ext = np.concatenate([~result.fixed, np.zeros(V, dtype=bool)])
    fr = free_ext[nd]
    positions = np.concatenate([result.z, result.obstacle_x])
    v = d_lam[cons, None, None] * positions[nd] + lam[cons, None, None] * d_ext[nd]  # (k, 4, 3)
    grad_w = np.zeros((m, 4))
    grad_n = np.zeros((m, 3))
    grad_w[cons] = np.einsum("kad,kd->ka", v, nrm)
    grad_n[cons] = np.einsum("ka,kad->kd", w, v)
    grad_ext = np.zeros((n + V, 3))
    cj, ca = np.nonzero(~fr)
    if cj.size:
        contrib = (d_lam[cons[cj]] * w[cj, ca])[:, None] * nrm[cj]
        for d in range(3):
            grad_ext[:, d] += np.bincount(nd[cj, ca], weights=contrib[:, d], minlength=n + V)
    push = time.perf_counter() - t0
    ncon = np.array([zone.stats["ncon"] for zone in result.zones], dtype=float)
    if ncon.size:
        seconds += push * ncon / ncon.sum()
    result.backward_stats = [
        {"mode": mode, "backward_s": float(seconds[zone.index]), "qr_in_backward": bool(lazy[zone.index]),
         "kkt_size": zone.stats["kkt_size"], "qr_size": zone.stats["qr_size"]} for zone in result.zones]
    grad_x += grad_ext[:n]  # only pinned particles (constant cloth nodes) receive anything here
    return grad_x, grad_w, grad_n, grad_ext[n:].copy()
