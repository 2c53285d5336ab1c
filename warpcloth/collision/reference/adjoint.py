"""The adjoint of :func:`~warpcloth.collision.reference.qp.project`.

On the active set A = {j : |c_j(z*)| ≤ active_tol} ∪ {j : λ_j > 0}, with ḡ = ∂L/∂z, K [d_z; d_λ] = [ḡ; 0] for
K = [[W, G_Aᵀ], [G_A, 0]]; then ∂L/∂x̂ = W d_z, ∂L/∂G_A = −λ d_zᵀ − d_λ zᵀ, ∂L/∂h_A = −d_λ. ``mode="qr"`` factorises
Ã = W^{-1/2} G_Aᵀ per group of active contacts sharing particles by the Cholesky factor R of ÃᵀÃ, dropping dependent
columns; ``mode="kkt"``, its oracle, solves K = [[W, GᵀS], [SG, I − S]] over all zone contacts, S the active
indicator. Why no Q: docs/decisions.md, "QR adjoint without Q"."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from warpcloth.collision.reference.checks import float_array
from warpcloth.collision.reference.linalg import gram_cholesky, tri_solve
from warpcloth.collision.reference.zones import ProjectionResult, Zone, components, gram

ONE_BLOCK = 64
"""Zones with at most this many active constraints are factorised whole, not split into groups (cheaper there)."""


@dataclass
class QRBlock:
    """One group's Ã, sparse, and Cholesky factor L of ÃᵀÃ over its independent columns. ``rows``, ``cols``: local
    particles and (sorted) active contacts; ``keep``, ``drop``: positions in ``cols`` of the independent and dependent
    columns; ``entry_*``: Ã's nonzero 3-vectors (−slot_dir/√m̃); ``lam``: the kept multipliers, the dropped folded in."""

    rows: np.ndarray
    cols: np.ndarray
    keep: np.ndarray
    drop: np.ndarray
    entry_row: np.ndarray
    entry_col: np.ndarray
    entry_vec: np.ndarray
    L: np.ndarray
    lam: np.ndarray

    def at_vectors(self, v: np.ndarray) -> np.ndarray:
        """Ãᵀ v for v (len(rows), 3): one value per column."""
        dots = np.einsum("ed,ed->e", self.entry_vec, v[self.entry_row])
        return np.bincount(self.entry_col, weights=dots, minlength=self.cols.size)

    def times(self, d: np.ndarray) -> np.ndarray:
        """Ã d for d (len(cols),): (len(rows), 3)."""
        contrib = self.entry_vec * d[self.entry_col, None]
        return np.stack([np.bincount(self.entry_row, weights=contrib[:, c], minlength=self.rows.size)
                         for c in range(3)], axis=1)

    def solve_kept(self, rhs: np.ndarray) -> np.ndarray:
        """(Ã_keepᵀ Ã_keep)⁻¹ rhs = R⁻¹R⁻ᵀ rhs."""
        return tri_solve(self.L.T, tri_solve(self.L, rhs, lower=True), lower=False)


@dataclass
class ZoneQR:
    """A zone's factorisation: one block per group of active constraints that share particles."""

    blocks: list[QRBlock]
    seconds: float

    @property
    def independent(self) -> int:
        """Number of independent active constraints (columns kept)."""
        return sum(int(b.keep.size) for b in self.blocks)

    @property
    def dependent(self) -> int:
        """Number of dependent active constraints (columns dropped)."""
        return sum(int(b.drop.size) for b in self.blocks)


def factorisation(result: ProjectionResult, zone: Zone) -> ZoneQR:
    """:func:`factorise` on first use, kept in ``result.factorisations``; its figures go to ``zone.stats``."""
    qr = result.factorisations.get(zone.index)
    if qr is None:
        qr = result.factorisations[zone.index] = factorise(zone)
        zone.stats.update(independent=qr.independent, qr_size=qr.independent, qr_s=qr.seconds)
    return qr


def factorise(zone: Zone) -> ZoneQR:
    """The zone's :class:`ZoneQR`, dependent columns dropped: λ_keep += Cλ_drop, C = (Ã_keepᵀÃ_keep)⁻¹Ã_keepᵀÃ_drop."""
    t0 = time.perf_counter()
    act = zone.active
    blocks = []
    if act.size:
        sel = np.isin(zone.slot_con, act)
        sc, snode, sdir = zone.slot_con[sel], zone.slot_node[sel], zone.slot_dir[sel]
        if act.size <= ONE_BLOCK:  # splitting costs more than it saves
            group, slot_group = np.zeros(act.size, dtype=np.int64), np.zeros(sc.size, dtype=np.int64)
        else:
            first = np.full(zone.lam.size, -1, dtype=np.int64)
            first[sc[::-1]] = snode[::-1]  # one particle of each active contact
            label = components(zone.mass.size, first[sc], snode)
            group = label[first[act]]
            slot_group = label[snode]
        invm = 1.0 / zone.mass
        for g in np.unique(group):
            cols = act[group == g]  # sorted: act is
            mine = slot_group == g
            node, con, vec = snode[mine], np.searchsorted(cols, sc[mine]), sdir[mine]
            rows = np.unique(node)
            M = gram(cols.size, con, node, vec, invm)[0]
            keep, drop, L = gram_cholesky(M)
            lam = zone.lam[cols]
            blk = QRBlock(rows=rows, cols=cols, keep=keep, drop=drop, entry_row=np.searchsorted(rows, node),
                          entry_col=con, entry_vec=-vec / np.sqrt(zone.mass[node])[:, None], L=L,
                          lam=lam[keep].copy())
            if drop.size and keep.size:
                blk.lam += blk.solve_kept(M[np.ix_(keep, drop)] @ lam[drop])
            blocks.append(blk)
    return ZoneQR(blocks=blocks, seconds=time.perf_counter() - t0)


def _zone_adjoint_qr(zone: Zone, qr: ZoneQR, g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d_z (nz, 3), d_λ (k,), λ used with ∂L/∂G (k,)) of one zone by the QR formula."""
    sq = np.sqrt(zone.mass)
    gp = g / sq[:, None]  # W^{-1/2} ḡ
    u = gp.copy()
    k = zone.lam.size
    d_lam = np.zeros(k)
    lam = np.zeros(k)
    for blk in qr.blocks:
        if blk.keep.size == 0:
            continue
        # q = Qᵀ W^{-1/2}ḡ and d_λ = R⁻¹q = (Ã_keepᵀÃ_keep)⁻¹ Ã_keepᵀ W^{-1/2}ḡ; u = W^{-1/2}ḡ − Q q = ... − Ã_keep d_λ
        dl = blk.solve_kept(blk.at_vectors(gp[blk.rows])[blk.keep])
        full = np.zeros(blk.cols.size)
        full[blk.keep] = dl
        u[blk.rows] -= blk.times(full)
        d_lam[blk.cols[blk.keep]] = dl
        lam[blk.cols[blk.keep]] = blk.lam
    return u / sq[:, None], d_lam, lam


def _zone_adjoint_kkt(zone: Zone, qr: ZoneQR, g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    # the factorisation's rank test picks solve or lstsq
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
    """Gradients of a loss L(z*) given ∂L/∂z (n, 3), by ``mode`` ``"qr"`` or ``"kkt"``.

    Returns:
        (∂L/∂x̂ (n, 3), ∂L/∂weights (m, 4), ∂L/∂normals (m, 3), ∂L/∂obstacle_x (V, 3), ∂L/∂thickness (m,) = −d_λ);
        ∂L/∂x̂ is ∂L/∂z for particles in no zone, pinned ones' counted as constant nodes'. One record per zone
        (``mode``, ``backward_s``, ``kkt_size``, ``qr_size``) goes to ``result.backward_stats``.

    Raises:
        ValueError: an unknown ``mode`` or a malformed ``grad_z``.
    """
    if mode not in ("qr", "kkt"):
        raise ValueError(f"mode must be 'qr' or 'kkt', got {mode!r}")
    n = result.x_hat.shape[0]
    grad_z = float_array("grad_z", grad_z, (n, 3))
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
        lazy[zone.index] = zone.index not in result.factorisations
        qr = factorisation(result, zone)
        g = grad_z[zone.nodes]
        if mode == "qr":
            d_z, dl, lz = _zone_adjoint_qr(zone, qr, g)
        else:
            d_z, dl, lz = _zone_adjoint_kkt(zone, qr, g)
        grad_x[zone.nodes] = zone.mass[:, None] * d_z
        d_ext[zone.nodes] = d_z
        d_lam[zone.contacts] = dl
        lam[zone.contacts] = lz
        seconds[zone.index] = time.perf_counter() - t0

    t0 = time.perf_counter()
    grad_w, grad_n, grad_ext = push_onto_contacts(result.nodes, result.weights, result.normals, result.fixed,
                                                  result.z, result.obstacle_x, d_ext, d_lam, lam)
    push = time.perf_counter() - t0
    ncon = np.array([zone.stats["ncon"] for zone in result.zones], dtype=float)
    if ncon.size:
        seconds += push * ncon / ncon.sum()
    result.backward_stats = [
        {"mode": mode, "backward_s": float(seconds[zone.index]), "qr_in_backward": bool(lazy[zone.index]),
         "kkt_size": zone.stats["kkt_size"], "qr_size": zone.stats["qr_size"]} for zone in result.zones]
    grad_x += grad_ext[:n]  # only pinned particles (constant cloth nodes) receive anything here
    return grad_x, grad_w, grad_n, grad_ext[n:].copy(), -d_lam


def mass_gradient(result: ProjectionResult, grad_x: np.ndarray) -> np.ndarray:
    """∂L/∂m_i = −(∂L/∂x̂)_i·(z_i − x̂_i)/m_i (n,) from :func:`backward`'s ∂L/∂x̂; 0 where pinned or in no zone."""
    n = result.x_hat.shape[0]
    grad_x = float_array("grad_x", grad_x, (n, 3))
    return mass_gradient_of(grad_x, result.z, result.x_hat, result.mass, result.fixed)


def mass_gradient_of(grad_x: np.ndarray, z: np.ndarray, x_hat: np.ndarray, mass: np.ndarray,
                     fixed: np.ndarray) -> np.ndarray:
    """:func:`mass_gradient` from its parts (any solver's z and ∂L/∂x̂)."""
    shift = z - x_hat
    return np.where(fixed, 0.0, -np.einsum("id,id->i", grad_x, shift) / np.where(fixed, 1.0, mass))


def push_onto_contacts(nodes, weights, normals, fixed, z, obstacle_x, d_ext, d_lam, lam):
    """(∂L/∂weights (m, 4), ∂L/∂normals (m, 3), ∂L/∂x of the constant nodes (n + V, 3)) from every contact's λ and
    d_λ and every node's d_z (``d_ext``, 0 for constant nodes): ∂L/∂w_ja = (d_λj p_a + λ_j d_a)·n_j,
    ∂L/∂n_j = Σ_a w_ja (d_λj p_a + λ_j d_a), and ∂L/∂x_a += d_λj w_ja n_j for a constant node."""
    n, V, m = z.shape[0], obstacle_x.shape[0], nodes.shape[0]
    cons = np.flatnonzero((d_lam != 0.0) | (lam != 0.0))
    nd = nodes[cons]
    w = weights[cons]
    nrm = normals[cons]
    free_ext = np.concatenate([~fixed, np.zeros(V, dtype=bool)])
    fr = free_ext[nd]
    positions = np.concatenate([z, obstacle_x])
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
    return grad_w, grad_n, grad_ext
