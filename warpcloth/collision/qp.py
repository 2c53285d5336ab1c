"""The projection QP: collision response over impact zones (SPEC.md §3), solved zone by zone.

Pure NumPy (float64) on the host; one call of :func:`project` per collision round. The adjoint is in
:mod:`warpcloth.collision.adjoint`, the zones in :mod:`warpcloth.collision.zones`, the dual solvers in
:mod:`warpcloth.collision.dual`.

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
"""

from __future__ import annotations

import time

import numpy as np

from warpcloth.collision import adjoint
from warpcloth.collision.checks import check_inputs, check_options, float_array
from warpcloth.collision.dual import ZoneInfeasible, ZoneNotConverged, ZoneSolver, warm_start
from warpcloth.collision.zones import ProjectionResult, Zone, colour_classes, gram, group, impact_zones

__all__ = ["ProjectionError", "ProjectionResult", "project"]


class ProjectionError(RuntimeError):
    """A zone is infeasible or its solve did not converge, or a contact with only constant nodes is violated.

    ``contact``: the violated contact, or one of the failing zone's (so a caller can name its world); ``zone``: the
    failing impact zone, where a zone failed."""

    def __init__(self, message: str, *, zone: int | None = None, contact: int | None = None,
                 residual: float | None = None):
        super().__init__(message)
        self.zone = zone
        self.contact = contact
        self.residual = residual


_WARM_MIN = 8
"""Zones with at least this many contacts get the Gauss–Seidel warm start."""
_PDAS_LIMIT = 20
"""Most primal–dual active-set solves before the monotone method takes over."""


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
        thickness: δ > 0 [m], or the target gap of each contact (m,) (any finite values: the collision stage's
            are δ, or less for a pair that started closer than δ).
        tol: KKT tolerance [m] on constraint violation and on |c_j| of contacts with λ_j > 0.
        max_iterations: most active-set solves per zone.
        active_tol: |c_j(z*)| ≤ active_tol [m] makes contact j active in the adjoint (as does λ_j > 0).
        warm_sweeps: most Gauss–Seidel sweeps of the warm start.
        precompute_qr: factorise the adjoint's QR here (True) or in the first
            :func:`~warpcloth.collision.adjoint.backward` (False).
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
    x_hat, mass, fixed, obstacle_x, nodes, weights, normals, thickness = check_inputs(
        x_hat, mass, fixed, obstacle_x, nodes, weights, normals, thickness)
    tol, active_tol = check_options(tol, active_tol, max_iterations, warm_sweeps)
    n, m = x_hat.shape[0], nodes.shape[0]
    if lam_init is not None:
        lam_init = float_array("lam_init", lam_init, (m,))
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

    part = impact_zones(nodes, free, weights, n)
    slot_j, slot_n, slot_w = part.slot_contact, part.slot_node, part.slot_weight
    zone_of_node, zone_of_contact, nzones = part.zone_of_node, part.zone_of_contact, part.count
    k_of_zone = np.bincount(zone_of_contact[zone_of_contact >= 0], minlength=nzones)
    z = x_hat.copy()
    lam_all = np.zeros(m)
    zones: list[Zone | None] = [None] * nzones
    slot_zone = zone_of_contact[slot_j]
    singles = _solve_singles(np.flatnonzero(k_of_zone[slot_zone] == 1), slot_j, slot_n, slot_w, zone_of_contact,
                             x_hat, mass, normals, h_all, tol, active_tol, z, lam_all, zones)
    multi = np.flatnonzero(k_of_zone > 1)
    node_groups = group(zone_of_node, nzones)
    con_groups = group(zone_of_contact, nzones)
    slot_groups = group(slot_zone, nzones)
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
        H, ci, cj = gram(k, s_con, s_node, s_dir, invm)
        solver = ZoneSolver(H, b, tol, int(max_iterations))
        sweeps = 0
        try:
            if not np.any(b > solver.add_tol):
                lam = np.zeros(k)
            else:
                lam0 = np.zeros(k)
                if lam_init is not None and np.any(lam_init[zcons] > 0.0):
                    lam0 = np.maximum(lam_init[zcons], 0.0)
                elif k >= _WARM_MIN and warm_sweeps > 0:
                    colours = colour_classes(k, ci, cj)
                    lam0, sweeps = warm_start(b, s_con, s_node, s_dir, invm, colours, int(warm_sweeps))
                lam, best = solver.pdas(lam0, _PDAS_LIMIT)
                if lam is None:
                    lam = solver.lawson_hanson(best)
        except ZoneInfeasible as err:
            raise _infeasible(zi, znodes.size, k, err.residual, tol, int(zcons[0])) from None
        except ZoneNotConverged:
            res = solver.residual(solver.last, solver.last > 0.0)
            raise ProjectionError(
                f"impact zone {zi} ({znodes.size} free particles, {k} contacts) did not converge in "
                f"{max_iterations} active-set iterations; residual {res:.3e} m > tol {tol:.1e}",
                zone=zi, contact=int(zcons[0]), residual=res) from None
        lam = np.maximum(lam, 0.0)
        disp = np.stack([np.bincount(s_node, weights=lam[s_con] * s_dir[:, d], minlength=znodes.size)
                         for d in range(3)], axis=1)
        zz = xz + invm[:, None] * disp
        c = h - np.bincount(s_con, weights=np.einsum("ij,ij->i", s_dir, zz[s_node]), minlength=k)
        pos_l = lam > 0.0
        residual = _check_solution(zi, znodes.size, c, pos_l, tol, int(zcons[0]))
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
        zones[zi] = zone
    result = ProjectionResult(z=z, lam=lam_all, zones=zones, x_hat=x_hat, mass=mass, obstacle_x=obstacle_x,
                              fixed=fixed, nodes=nodes, weights=weights, normals=normals, thickness=thickness,
                              tol=float(tol), active_tol=float(active_tol), singles=singles)
    if precompute_qr:
        for zone in zones:
            if not zone.single:
                zone.stats["forward_s"] += adjoint.factorisation(result, zone).seconds
    return result


def _infeasible(zi, nodes, k, residual, tol, contact) -> ProjectionError:
    return ProjectionError(
        f"impact zone {zi} ({nodes} free particles, {k} contacts) is infeasible: the best working set leaves a "
        f"constraint residual of {residual:.3e} m > tol {tol:.1e} (cloth squeezed between constant nodes closer "
        "than 2δ?)", zone=zi, contact=contact, residual=residual)


def _check_solution(zi, nodes, c, positive, tol, contact) -> float:
    """KKT residual [m] of a zone's solution (violation, and |c_j| where λ_j > 0); raises beyond tol."""
    residual = max(float(np.max(c, initial=0.0)), float(np.max(np.abs(c[positive]), initial=0.0)))
    if residual > tol:
        raise ProjectionError(
            f"impact zone {zi} ({nodes} free particles, {c.size} contacts): the solution misses the KKT "
            f"tolerance, residual {residual:.3e} m > tol {tol:.1e}", zone=zi, contact=contact, residual=residual)
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
        raise _infeasible(int(zone_of_contact[J[i]]), int(cnt[i]), 1, float(bj[i]), tol, int(J[i]))
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
        _check_solution(int(zone_of_contact[J[i]]), int(cnt[i]), c[i:i + 1], positive[i:i + 1], tol, int(J[i]))
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
