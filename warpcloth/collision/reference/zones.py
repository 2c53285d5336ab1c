"""Impact zones of the reference projection and its records: data and helpers shared by the solver and the adjoint."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Zone:
    """One impact zone: its particles, contacts and solution."""

    index: int
    nodes: np.ndarray
    """Global indices of the zone's free particles (sorted)."""
    contacts: np.ndarray
    """Global indices of the zone's contacts (sorted)."""
    mass: np.ndarray
    """Normalised masses m̃ of ``nodes``."""
    slot_con: np.ndarray
    """Merged (contact, particle) couplings (S,): local contact, ``slot_node`` and ``slot_dir`` = Σ w_ja n_j (S, 3)."""
    slot_node: np.ndarray
    slot_dir: np.ndarray
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
    stats: dict = field(default_factory=dict)
    """Diagnostics (see :func:`~warpcloth.collision.reference.qp.project`)."""


@dataclass
class ProjectionResult:
    """What :func:`~warpcloth.collision.reference.qp.project` returns: the solution and what the adjoint needs."""

    z: np.ndarray
    """Projected positions (n, 3); x̂ for particles in no zone and for pinned particles."""
    lam: np.ndarray
    """Multiplier of every contact (m,); 0 for contacts in no zone."""
    zones: list[Zone]
    x_hat: np.ndarray
    mass: np.ndarray
    obstacle_x: np.ndarray
    fixed: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    normals: np.ndarray
    thickness: np.ndarray
    """Target gap of each contact (m,) [m]."""
    tol: float
    active_tol: float
    singles: dict = field(default_factory=dict)
    """Batched data of the single-contact zones (closed-form solve and adjoint)."""
    factorisations: dict = field(default_factory=dict)
    """The adjoint's factorisation of each zone, by zone index, once computed (``adjoint.ZoneQR``)."""
    backward_stats: list[dict] = field(default_factory=list)
    """Per-zone records of the last :func:`~warpcloth.collision.reference.adjoint.backward` call."""

    @property
    def stats(self) -> list[dict]:
        """Per-zone forward records (see :func:`~warpcloth.collision.reference.qp.project`)."""
        return [zone.stats for zone in self.zones]

    def zones_stats(self) -> list[dict]:
        """Per-zone forward records merged with those of the last backward pass, if any."""
        out = [dict(zone.stats) for zone in self.zones]
        for rec, back in zip(out, self.backward_stats):
            rec.update(back)
        return out


@dataclass
class ZonePartition:
    """Couplings merged per (contact, free particle) (S,): ``slot_contact`` (sorted), ``slot_node``, ``slot_weight``
    (summed); each particle's (n,) and contact's (m,) zone (−1: none) of ``count``, numbered by smallest particle."""

    slot_contact: np.ndarray
    slot_node: np.ndarray
    slot_weight: np.ndarray
    zone_of_node: np.ndarray
    zone_of_contact: np.ndarray
    count: int


def impact_zones(nodes: np.ndarray, free: np.ndarray, weights: np.ndarray, n: int) -> ZonePartition:
    """The :class:`ZonePartition` of contacts ``nodes``, ``free``, ``weights`` (m, 4) among ``n`` particles."""
    m = nodes.shape[0]
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
    label = components(n, first[slot_j], slot_n)
    in_zone = np.zeros(n, dtype=bool)
    in_zone[slot_n] = True
    roots = np.unique(label[in_zone])
    zone_of_node = np.full(n, -1, dtype=np.int64)
    zone_of_node[in_zone] = np.searchsorted(roots, label[in_zone])
    zone_of_contact = np.full(m, -1, dtype=np.int64)
    zone_of_contact[uj] = zone_of_node[first[uj]]
    return ZonePartition(slot_contact=slot_j, slot_node=slot_n, slot_weight=slot_w, zone_of_node=zone_of_node,
                         zone_of_contact=zone_of_contact, count=int(roots.size))


def components(n: int, edges_u: np.ndarray, edges_v: np.ndarray) -> np.ndarray:
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


def group(ids: np.ndarray, count: int) -> list[np.ndarray]:
    """Indices i with ids[i] == g for g in range(count), each sorted (ids < 0 are left out)."""
    order = np.argsort(ids, kind="stable")
    bounds = np.searchsorted(ids[order], np.arange(count + 1))
    return [order[bounds[g]:bounds[g + 1]] for g in range(count)]


def gram(k: int, slot_con, slot_node, slot_dir, invm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def colour_classes(k: int, ci: np.ndarray, cj: np.ndarray) -> list[np.ndarray]:
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
