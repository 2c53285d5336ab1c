"""The reference projection QP (float64 NumPy; method: docs/concepts/contact.md). Contact j couples nodes a = 0..3 by
frozen weights w_ja and unit normal n_j: c_j(z) = δ_j − Σ_a w_ja n_j·p_a ≤ 0, p_a a free particle's unknown z, else a
constant. Each impact zone (free particles linked by contacts) solves min_z ½ (z − x̂)ᵀ W (z − x̂) s.t. G z + h ≤ 0,
W = diag(m_i mean_k(1/m_k)), in its dual (:mod:`warpcloth.collision.reference.dual`; one contact: closed form)."""

from __future__ import annotations

import time

import numpy as np

from warpcloth.collision.reference import adjoint
from warpcloth.collision.reference.checks import check_inputs, check_options, float_array
from warpcloth.collision.reference.dual import ZoneInfeasible, ZoneNotConverged, ZoneSolver, warm_start
from warpcloth.collision.reference.zones import ProjectionResult, Zone, colour_classes, gram, group, impact_zones

__all__ = ["ProjectionError", "ProjectionResult", "project"]


class ProjectionError(RuntimeError):
    """An infeasible or unconverged ``zone`` (None: a violated constant-only contact); ``contact``, ``residual`` [m]."""

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
    """Project x̂ onto the non-penetrating set of the contacts, zone by zone.

    Args:
        x_hat: (n, 3) positions after the implicit step [m].
        mass: (n,) lumped masses (> 0 for every free particle).
        fixed: (n,) bool, particles held constant (hard pins); None for none.
        obstacle_x: (V, 3) obstacle vertex positions (constants); None or (0, 3) for none.
        nodes, weights, normals: (m, 4) int node ids (k ≥ n: obstacle vertex k − n), (m, 4) w_ja, (m, 3) unit n_j.
        thickness: δ > 0 [m], or each contact's target gap (m,) [m] (any finite values).
        tol: KKT tolerance [m] on constraint violation and on |c_j| of contacts with λ_j > 0.
        active_tol: |c_j(z*)| ≤ active_tol [m] makes contact j active in the adjoint (as does λ_j > 0).
        max_iterations, warm_sweeps: most active-set solves per zone, most Gauss–Seidel sweeps of the warm start.
        precompute_qr: factorise the adjoint's QR here, not in the first ``adjoint.backward``.
        lam_init: (m,) multipliers to start from (a zone with a positive entry skips the warm start).

    Returns:
        A :class:`ProjectionResult`; ``result.stats``: per zone ``nodes``, ``nvar``, ``ncon``, ``active``,
        ``independent`` (None until factorised), ``kkt_size``, ``qr_size``, ``kkt_residual`` [m], ``stationarity``,
        ``complementarity``, ``iterations``, ``sweeps``, ``solve_s``, ``qr_s``, ``forward_s``.

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
    """Solve every one-contact zone (slots ``ss``): λ = max(0, b/H), z = x̂ + λ W⁻¹ dir; returns the adjoint's data."""
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
