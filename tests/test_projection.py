"""The collision QP over impact zones (warpcloth/collision/reference/): KKT conditions, an independent oracle,
the QR and dense KKT adjoints against each other and against central finite differences, and the errors."""

import functools
import itertools

import numpy as np
import pytest
from scipy.optimize import nnls

from warpcloth.collision.reference import ProjectionError, backward, mass_gradient, project
from warpcloth.collision.reference.dual import ZoneSolver

DELTA = 5.0e-4


# ---------------------------------------------------------------------------------------------------------------
# Random problems


def _unit(v):
    return v / np.linalg.norm(v)


def _tilted(rng, tilt):
    return _unit(np.array([0.0, 0.0, 1.0]) + tilt * rng.normal(size=3))


class _Builder:
    """Particles, obstacle vertices and contacts; obstacle vertex i is referred to as -(i + 1) until build()."""

    def __init__(self, rng):
        self.rng = rng
        self.x, self.mass, self.fixed, self.obs = [], [], [], []
        self.nodes, self.weights, self.normals = [], [], []

    def particle(self, pos, fixed=False):
        self.x.append(np.asarray(pos, dtype=float))
        self.mass.append(self.rng.uniform(0.5, 2.0) * 1e-3)
        self.fixed.append(fixed)
        return len(self.x) - 1

    def obstacle(self, pos):
        self.obs.append(np.asarray(pos, dtype=float))
        return -len(self.obs)

    def pos(self, node):
        return self.x[node] if node >= 0 else self.obs[-node - 1]

    def contact(self, nodes, weights, normal):
        self.nodes.append(list(nodes))
        self.weights.append(list(weights))
        self.normals.append(np.asarray(normal, dtype=float))

    def gap(self, slack):
        """Signed distance along the normal: slack ones stay clear of δ, the others violate it."""
        if self.rng.uniform() < slack:
            return self.rng.uniform(2.0, 3.0) * DELTA
        return self.rng.uniform(-1.0, 0.6) * DELTA

    def build(self, rotate=True):
        n = len(self.x)
        x = np.array(self.x)
        obs = np.array(self.obs).reshape(-1, 3)
        nodes = np.array([[k if k >= 0 else n - k - 1 for k in row] for row in self.nodes], dtype=np.int64)
        normals = np.array(self.normals).reshape(-1, 3)
        if rotate:  # the QP is rotation-equivariant; leave no axis-aligned structure
            q, _ = np.linalg.qr(self.rng.normal(size=(3, 3)))
            x, obs, normals = x @ q.T, obs @ q.T, normals @ q.T
        return dict(x_hat=x, mass=np.array(self.mass), fixed=np.array(self.fixed, dtype=bool), obstacle_x=obs,
                    nodes=nodes.reshape(-1, 4), weights=np.array(self.weights).reshape(-1, 4), normals=normals,
                    thickness=DELTA)


def random_problem(seed, *, groups=3, slack=0.3, fixed=True, ee=True, ceiling=True, duplicates=False,
                   split=False, zero_weight=True, loose=2):
    """Groups of free particles on an obstacle floor, more particles resting on them (vertex-face and edge-edge
    contacts, some against pinned particles), faces pushed down by obstacle vertices; feasible by construction."""
    rng = np.random.default_rng(seed)
    b = _Builder(rng)
    corners = [b.obstacle(p) for p in ([-0.1, -0.1, 0], [0.1, -0.1, 0], [0.1, 0.1, 0], [-0.1, 0.1, 0])]
    tris = [(corners[0], corners[1], corners[2]), (corners[0], corners[2], corners[3])]

    def floor_contact(p):
        xy = b.x[p][:2]
        for tri in tris:
            P = np.array([b.pos(v)[:2] for v in tri])
            lam = np.linalg.solve(np.vstack([P.T, np.ones(3)]), np.array([xy[0], xy[1], 1.0]))
            if np.all(lam >= -1e-12):
                b.contact([p, *tri], [1.0, *(-lam)], [0.0, 0.0, 1.0])
                return
        raise AssertionError("particle off the floor")

    for g in range(groups):
        centre = np.array([-0.06 + 0.04 * g, 0.01 * g, 0.0])
        base = []
        for _ in range(rng.integers(3, 5)):
            p = b.particle(centre + [*rng.uniform(-0.004, 0.004, 2), b.gap(slack)])
            floor_contact(p)
            base.append(p)
        if fixed and g % 2 == 0:
            base.append(b.particle(centre + [*rng.uniform(-0.004, 0.004, 2), 3.0 * DELTA], fixed=True))
        for _ in range(rng.integers(1, 3)):  # vertex on a face of base particles
            q = rng.choice(base, 3, replace=False)
            bary = rng.dirichlet(np.ones(3) * 3)
            n = _tilted(rng, 0.15)
            p = b.particle(sum(bb * b.x[qq] for bb, qq in zip(bary, q)) + b.gap(slack) * n)
            b.contact([p, *q], [1.0, *(-bary)], n)
        if ee:  # an edge resting across an edge of base particles
            q0, q1 = rng.choice(base, 2, replace=False)
            s, u = rng.uniform(0.2, 0.8, 2)
            n = _tilted(rng, 0.15)
            target = (1 - u) * b.x[q0] + u * b.x[q1] + b.gap(slack) * n
            e = _unit(np.cross(n, rng.normal(size=3))) * rng.uniform(0.003, 0.006)
            p0, p1 = b.particle(target - s * e), b.particle(target + (1 - s) * e)
            b.contact([p0, p1, q0, q1], [1 - s, s, -(1 - u), -u], n)
        if zero_weight:  # a vertex-edge contact listing one node twice, once with zero weight
            q0, q1 = rng.choice(base, 2, replace=False)
            u = rng.uniform(0.2, 0.8)
            n = _tilted(rng, 0.15)
            p = b.particle((1 - u) * b.x[q0] + u * b.x[q1] + b.gap(slack) * n)
            b.contact([p, q0, q1, q1], [1.0, -(1 - u), -u, 0.0], n)
        if ceiling:  # an obstacle vertex above a free face, pushing it down
            f = [b.particle(centre + [*rng.uniform(-0.004, 0.004, 2), 0.01 + rng.uniform(0, 1e-3)])
                 for _ in range(3)]
            bary = rng.dirichlet(np.ones(3) * 3)
            n = _tilted(rng, 0.15)
            o = b.obstacle(sum(bb * b.x[ff] for bb, ff in zip(bary, f)) + b.gap(slack) * n)
            b.contact([o, *f], [1.0, *(-bary)], n)
    if duplicates:
        for j in rng.choice(len(b.nodes), 2, replace=False):  # the same contact twice
            b.contact(b.nodes[j], b.weights[j], b.normals[j])
    if split:
        # a floor contact of a particle at another point of the same plane, listing a node twice: the same row of
        # G as the first (dependent), with a different obstacle combination
        j = next(j for j, row in enumerate(b.nodes) if row[0] >= 0 and all(k < 0 for k in row[1:]))
        row, w = b.nodes[j], b.weights[j]
        b.contact([row[0], row[1], row[2], row[2]], [w[0], w[1] + 0.5 * w[3], w[2], 0.5 * w[3]], b.normals[j])
    for _ in range(loose):  # particles in no contact
        b.particle(rng.uniform(-0.05, 0.05, 3) + [0, 0, 0.05])
    return b.build()


def layered_problem(seed, res=6, slack=0.2):
    """Two cloth layers on a floor: each lower particle on the floor, each upper particle on a lower face."""
    rng = np.random.default_rng(seed)
    b = _Builder(rng)
    h = 0.004
    size = 0.1
    o = [b.obstacle(p) for p in ([-size, -size, 0], [size, -size, 0], [size, size, 0], [-size, size, 0])]
    lower = np.empty((res, res), dtype=int)
    for i, j in itertools.product(range(res), range(res)):
        xy = np.array([i, j]) * h + rng.uniform(-0.1, 0.1, 2) * h
        lower[i, j] = b.particle([*xy, b.gap(slack)])
        tri = (o[0], o[1], o[2]) if xy[0] >= xy[1] else (o[0], o[2], o[3])
        P = np.array([b.pos(v)[:2] for v in tri])
        lam = np.linalg.solve(np.vstack([P.T, np.ones(3)]), np.array([xy[0], xy[1], 1.0]))
        b.contact([lower[i, j], *tri], [1.0, *(-lam)], [0.0, 0.0, 1.0])
    for i, j in itertools.product(range(res - 1), range(res - 1)):
        q = [lower[i, j], lower[i + 1, j], lower[i + 1, j + 1]] if rng.uniform() < 0.5 else \
            [lower[i, j], lower[i + 1, j + 1], lower[i, j + 1]]
        bary = rng.dirichlet(np.ones(3) * 4)
        n = _tilted(rng, 0.05)
        p = b.particle(sum(bb * b.x[qq] for bb, qq in zip(bary, q)) + b.gap(slack) * n)
        b.contact([p, *q], [1.0, *(-bary)], n)
    return b.build()


# ---------------------------------------------------------------------------------------------------------------
# Oracles and helpers


def constraint_values(prob, z):
    """c_j(z) for every contact, with constant nodes at x_hat (pinned) or obstacle_x."""
    pos = np.concatenate([np.where(prob["fixed"][:, None], prob["x_hat"], z), prob["obstacle_x"]])
    return prob["thickness"] - np.einsum("ja,jad,jd->j", prob["weights"], pos[prob["nodes"]], prob["normals"])


def dense_constraints(prob):
    """G (m, 3n) and h (m,) of the whole problem (pinned particles as constants)."""
    n = prob["x_hat"].shape[0]
    m = prob["nodes"].shape[0]
    G = np.zeros((m, 3 * n))
    h = np.full(m, prob["thickness"])
    const = np.concatenate([prob["x_hat"], prob["obstacle_x"]])
    for j in range(m):
        for a in range(4):
            k, w, nj = prob["nodes"][j, a], prob["weights"][j, a], prob["normals"][j]
            if k < n and not prob["fixed"][k]:
                G[j, 3 * k:3 * k + 3] -= w * nj
            else:
                h[j] -= w * nj @ const[k]
    return G, h


def oracle_ldp(prob):
    """z* by least distance programming through scipy's NNLS (an independent Lawson–Hanson code) on the whole
    problem with the raw masses: the zones are decoupled, so their mass normalisation does not matter."""
    G, h = dense_constraints(prob)
    x = prob["x_hat"].ravel()
    free = np.repeat(~prob["fixed"], 3)
    sw = np.sqrt(np.repeat(prob["mass"] / np.mean(prob["mass"]), 3))
    E = -(G[:, free] / sw[free])  # E u ≥ f with u = W^{1/2}(z − x̂)/δ, in units of δ for a well-scaled NNLS
    f = (G @ x + h) / DELTA
    M = np.vstack([E.T, f[None, :]])
    e = np.zeros(M.shape[0])
    e[-1] = 1.0
    y, _ = nnls(M, e, maxiter=50 * M.shape[1])
    r = M @ y - e
    u = -r[:-1] / r[-1]
    z = x.copy()
    z[free] += u * DELTA / sw[free]
    return z.reshape(-1, 3)


def oracle_enumerate(prob):
    """z* by trying every active set (tiny problems only): the feasible stationary point of least cost."""
    G, h = dense_constraints(prob)
    x = prob["x_hat"].ravel()
    free = np.repeat(~prob["fixed"], 3)
    Gf = G[:, free]
    Winv = 1.0 / np.repeat(prob["mass"], 3)[free]
    rows = np.flatnonzero(np.any(Gf != 0.0, axis=1))
    best, best_cost = None, np.inf
    for r in range(len(rows) + 1):
        for S in itertools.combinations(rows, r):
            S = list(S)
            z = x[free].copy()
            if S:
                A = Gf[S]
                lam = np.linalg.lstsq((A * Winv) @ A.T, Gf[S] @ x[free] + (G[S] @ x - Gf[S] @ x[free]) + h[S],
                                      rcond=None)[0]
                z = x[free] - Winv * (A.T @ lam)
            full = x.copy()
            full[free] = z
            if np.max(G @ full + h) > 1e-12:
                continue
            cost = np.sum((z - x[free]) ** 2 / Winv)
            if cost < best_cost - 1e-18:
                best, best_cost = full, cost
    return best.reshape(-1, 3)


def check_kkt(prob, res, tol):
    z, lam = res.z, res.lam
    c = constraint_values(prob, z)
    assert np.all(lam >= 0.0)
    assert np.max(c) <= tol
    assert np.all(np.abs(c[lam > 0]) <= tol)
    G, _ = dense_constraints(prob)
    free = np.repeat(~prob["fixed"], 3)
    W = np.repeat(prob["mass"], 3)
    # stationarity per zone with the zone-normalised masses
    stat = np.zeros(3 * len(prob["mass"]))
    for zone in res.zones:
        idx = (3 * zone.nodes[:, None] + np.arange(3)).ravel()
        scale = np.mean(1.0 / prob["mass"][zone.nodes])
        stat[idx] = W[idx] * scale * (z.ravel()[idx] - prob["x_hat"].ravel()[idx]) + \
            (G[zone.contacts][:, idx].T @ lam[zone.contacts])
    assert np.max(np.abs(stat[free])) <= 1e-14
    # particles in no zone and pinned particles do not move
    moved = np.zeros(len(prob["mass"]), dtype=bool)
    for zone in res.zones:
        moved[zone.nodes] = True
    np.testing.assert_array_equal(z[~moved], prob["x_hat"][~moved])


def strictly_complementary(prob, res, margin=2e-6):
    """Every contact with a free node is clearly active (λ > 1e-3 max λ) or clearly slack (c < −margin), so small
    perturbations keep the active set."""
    c = constraint_values(prob, res.z)
    clean = (res.lam > 1e-3 * np.max(res.lam, initial=0.0)) | (c < -margin)
    return bool(np.all(clean | ~_has_free_node(prob))) and len(res.zones) > 0


def _has_free_node(prob):
    n = prob["x_hat"].shape[0]
    k = prob["nodes"]
    free = np.zeros(k.shape, dtype=bool)
    inside = k < n
    free[inside] = ~prob["fixed"][k[inside]]
    return free.any(axis=1)


def solve(prob, **kw):
    return project(prob["x_hat"], prob["mass"], prob["fixed"], prob["obstacle_x"], prob["nodes"], prob["weights"],
                   prob["normals"], prob["thickness"], **kw)


def clean_problems(count, start=0, **kw):
    """The first ``count`` seeds whose solution is strictly complementary (stable active set under FD)."""
    out, seed = [], start
    while len(out) < count:
        prob = random_problem(seed, **kw)
        if strictly_complementary(prob, solve(prob)):
            out.append(prob)
        seed += 1
    return out


# ---------------------------------------------------------------------------------------------------------------
# Forward


@pytest.mark.parametrize("seed", range(6))
def test_kkt_and_ldp_oracle(seed):
    prob = random_problem(seed, duplicates=seed % 2 == 1, split=seed % 3 == 1)
    res = solve(prob, precompute_qr=True)
    check_kkt(prob, res, 1e-10)
    np.testing.assert_allclose(res.z, oracle_ldp(prob), rtol=0, atol=1e-8)
    assert len(res.zones) >= 3
    for rec in res.stats:
        assert rec["kkt_residual"] <= 1e-10
        assert rec["nvar"] == 3 * rec["nodes"] and rec["kkt_size"] == rec["nvar"] + rec["ncon"]
        assert rec["independent"] <= rec["active"] <= rec["ncon"]


def test_enumeration_oracle_tiny():
    prob = random_problem(11, groups=1, ee=False, ceiling=False, zero_weight=True, loose=1)
    res = solve(prob)
    check_kkt(prob, res, 1e-10)
    np.testing.assert_allclose(res.z, oracle_enumerate(prob), rtol=0, atol=1e-8)


@pytest.mark.parametrize("seed", range(2))
def test_layered_zone(seed):
    """One zone of ~60 particles and ~60 contacts (the Gauss–Seidel warm start runs)."""
    prob = layered_problem(seed)
    res = solve(prob)
    assert max(rec["ncon"] for rec in res.stats) >= 50
    assert max(rec["sweeps"] for rec in res.stats) > 0
    check_kkt(prob, res, 1e-10)
    np.testing.assert_allclose(res.z, oracle_ldp(prob), rtol=0, atol=1e-8)
    tight = solve(prob, tol=1e-13)
    check_kkt(prob, tight, 1e-13)


def test_dependent_constraints_share():
    """Exact duplicates: the same z as without the copy, multipliers summing to the single one."""
    prob = random_problem(3, duplicates=False)
    res = solve(prob)
    j = int(np.argmax(res.lam))
    dup = dict(prob)
    dup["nodes"] = np.vstack([prob["nodes"], prob["nodes"][j:j + 1], prob["nodes"][j:j + 1]])
    dup["weights"] = np.vstack([prob["weights"], prob["weights"][j:j + 1], prob["weights"][j:j + 1]])
    dup["normals"] = np.vstack([prob["normals"], prob["normals"][j:j + 1], prob["normals"][j:j + 1]])
    res2 = solve(dup, precompute_qr=True)
    check_kkt(dup, res2, 1e-10)
    np.testing.assert_allclose(res2.z, res.z, rtol=0, atol=1e-12)
    m = len(prob["nodes"])
    np.testing.assert_allclose(res2.lam[j] + res2.lam[m] + res2.lam[m + 1], res.lam[j], rtol=1e-8)
    zone = next(zone for zone in res2.zones if j in zone.contacts)
    assert zone.stats["independent"] == zone.stats["active"] - 2


def test_all_constant_contacts():
    prob = random_problem(4)
    n = len(prob["mass"])
    ok = dict(prob)
    # an obstacle vertex well above an obstacle triangle: satisfied, ignored
    ok["obstacle_x"] = np.vstack([prob["obstacle_x"], prob["obstacle_x"][:3].mean(0) + 0.01 * _plane_normal(prob)])
    V = len(ok["obstacle_x"])
    row = np.array([[n + V - 1, n, n + 1, n + 2]])
    ok["nodes"] = np.vstack([prob["nodes"], row])
    ok["weights"] = np.vstack([prob["weights"], [[1.0, -1 / 3, -1 / 3, -1 / 3]]])
    ok["normals"] = np.vstack([prob["normals"], _plane_normal(prob)[None]])
    res = solve(ok)
    assert res.lam[-1] == 0.0
    np.testing.assert_allclose(res.z, solve(prob).z, rtol=0, atol=1e-15)
    bad = dict(ok)
    bad["normals"] = ok["normals"].copy()
    bad["normals"][-1] *= -1.0
    with pytest.raises(ProjectionError, match=rf"contact {len(ok['nodes']) - 1} \(nodes \[{n + V - 1}, {n}"):
        solve(bad)


def _plane_normal(prob):
    o = prob["obstacle_x"]
    return _unit(np.cross(o[1] - o[0], o[2] - o[0]))


def test_infeasible_zone():
    """A particle between the floor and an obstacle vertex closer than 2δ above it."""
    prob = random_problem(5, groups=1, ee=False, ceiling=False, zero_weight=False, loose=0, fixed=False)
    n = len(prob["mass"])
    res = solve(prob)
    zone = res.zones[-1]
    p = int(zone.nodes[0])
    up = _plane_normal(prob)
    obs = np.vstack([prob["obstacle_x"], prob["x_hat"][p] + 1.5 * DELTA * up])
    bad = dict(prob, obstacle_x=obs)
    bad["nodes"] = np.vstack([prob["nodes"], [[n + len(obs) - 1, p, p, p]]])
    bad["weights"] = np.vstack([prob["weights"], [[1.0, -1.0, 0.0, 0.0]]])
    bad["normals"] = np.vstack([prob["normals"], up[None]])
    # the particle's floor contact puts it at ≥ δ above the floor, the new one at ≥ δ below the vertex
    floor = next(j for j in range(len(prob["nodes"])) if prob["nodes"][j, 0] == p)
    bad["x_hat"] = prob["x_hat"].copy()
    height = -constraint_values(prob, prob["x_hat"])[floor] + DELTA
    obs[-1] = prob["x_hat"][p] + (1.5 * DELTA - height) * up
    zi = next(zone.index for zone in res.zones if p in zone.nodes)
    with pytest.raises(ProjectionError, match=rf"impact zone {zi} \(\d+ free particles, \d+ contacts\) is infeasible") \
            as err:
        solve(bad)
    assert p in bad["nodes"][err.value.contact]  # a contact of the failing zone (a caller names its world)
    # separated by 2.5δ it is feasible
    obs[-1] = prob["x_hat"][p] + (2.5 * DELTA - height) * up
    check_kkt(bad, solve(bad), 1e-10)


def test_no_convergence():
    prob = random_problem(2)
    res = solve(prob)
    zone = max(res.zones, key=lambda zone: zone.stats["iterations"])
    assert zone.stats["iterations"] >= 2
    with pytest.raises(ProjectionError, match=rf"impact zone {zone.index} \({zone.stats['nodes']} free particles, "
                                              rf"{zone.stats['ncon']} contacts\) did not converge in 1 ") as err:
        solve(prob, max_iterations=1)
    assert err.value.contact in zone.contacts


def test_contact_without_free_weight():
    """A violated contact whose free particle has zero weight cannot be resolved (a zone of its own)."""
    prob = random_problem(6, groups=1)
    n = len(prob["mass"])
    p = n - 1  # a loose particle
    bad = dict(prob)
    bad["nodes"] = np.vstack([prob["nodes"], [[p, n, n + 1, n + 2]]])
    bad["weights"] = np.vstack([prob["weights"], [[0.0, -0.2, -0.3, -0.5]]])
    bad["normals"] = np.vstack([prob["normals"], -_plane_normal(prob)[None]])  # obstacle plane "above" itself
    zi = len(solve(prob).zones)  # the loose particle has the largest index: the last zone
    with pytest.raises(ProjectionError, match=rf"impact zone {zi} \(1 free particles, 1 contacts\) is infeasible") \
            as err:
        solve(bad)
    assert err.value.contact == len(bad["nodes"]) - 1


def test_dual_solvers_random_dense():
    """The primal–dual active set and the monotone Lawson–Hanson method on random duals, with dependent columns
    and no M-matrix structure: both satisfy the KKT conditions and give the same primal displacement."""
    fallbacks = 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        nv, k = rng.integers(3, 20), rng.integers(2, 40)
        A = rng.normal(size=(nv, k))
        if seed % 3 == 0:
            A[:, -1] = A[:, 0]
        H = A.T @ A
        b = A.T @ rng.normal(size=nv) * 1e-3 - rng.uniform(0, 1e-3, k) * (rng.uniform(size=k) < 0.5)
        sols = []
        s = ZoneSolver(H, b, 1e-10, 1000)
        lam, best = s.pdas(np.zeros(k), 20)
        if lam is None:
            fallbacks += 1
            lam = s.lawson_hanson(best)
        sols.append(lam)
        sols.append(ZoneSolver(H, b, 1e-10, 1000).lawson_hanson(np.zeros(k)))
        for lam in sols:
            c = b - H @ lam
            assert np.all(lam >= 0) and np.max(c) <= 1e-10 and np.max(np.abs(c[lam > 0]), initial=0) <= 1e-10
        np.testing.assert_allclose(A @ sols[0], A @ sols[1], rtol=0, atol=1e-9)
    assert fallbacks > 0  # the fallback path ran


def test_bad_inputs():
    prob = random_problem(0)
    cases = {
        "x_hat": prob["x_hat"][:, :2],
        "mass": -prob["mass"],
        "fixed": prob["fixed"][:-1],
        "obstacle_x": np.full((2, 3), np.nan),
        "weights": np.where(np.arange(4) == 2, np.nan, prob["weights"]),
        "normals": prob["normals"][:-1],
        "thickness": 0.0,
    }
    for name, value in cases.items():
        with pytest.raises(ValueError, match=name):
            solve(dict(prob, **{name: value}))
    nodes = prob["nodes"].copy()
    nodes[1, 2] = len(prob["mass"]) + len(prob["obstacle_x"])
    with pytest.raises(ValueError, match=r"nodes\[1, 2\]"):
        solve(dict(prob, nodes=nodes))
    with pytest.raises(ValueError, match="nodes"):
        solve(dict(prob, nodes=prob["nodes"].astype(float)))
    res = solve(prob)
    with pytest.raises(ValueError, match="grad_z"):
        backward(res, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="mode"):
        backward(res, np.zeros_like(res.z), mode="lu")


def test_no_contacts():
    prob = random_problem(0)
    res = project(prob["x_hat"], prob["mass"], None, None, np.zeros((0, 4), dtype=np.int64), np.zeros((0, 4)),
                  np.zeros((0, 3)), DELTA)
    np.testing.assert_array_equal(res.z, prob["x_hat"])
    g = np.random.default_rng(0).normal(size=res.z.shape)
    gx, gw, gn, gob, _ = backward(res, g)
    np.testing.assert_array_equal(gx, g)
    assert gw.shape == (0, 4) and gn.shape == (0, 3) and gob.shape == (0, 3)


# ---------------------------------------------------------------------------------------------------------------
# Adjoint


@pytest.mark.parametrize("one_block", [0, 64])
def test_qr_equals_kkt_independent(one_block, monkeypatch):
    # one_block 0: every zone split into groups of active contacts sharing no particle (the path of big zones)
    monkeypatch.setattr("warpcloth.collision.reference.adjoint.ONE_BLOCK", one_block)
    blocks = 0
    for prob in clean_problems(5):
        res = solve(prob, precompute_qr=True)
        assert all(rec["independent"] == rec["active"] for rec in res.stats)
        blocks = max([blocks] + [len(res.factorisations[zone.index].blocks) for zone in res.zones if not zone.single])
        g = np.random.default_rng(1).normal(size=res.z.shape)
        qr = backward(res, g, mode="qr")
        kkt = backward(res, g, mode="kkt")
        for a, b in zip(qr, kkt):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.max(np.abs(b)))
        assert [rec["qr_size"] for rec in res.backward_stats] == [rec["active"] for rec in res.stats]
    assert (blocks > 1) == (one_block == 0)  # a zone whose active contacts fall into groups sharing no particle


def test_qr_kkt_dependent():
    """Dependent active contacts: z* is still differentiable in x̂ (the other gradients are one-sided)."""
    for seed in range(2):
        prob = random_problem(seed, duplicates=True, split=True)
        res = solve(prob, precompute_qr=True)
        assert sum(rec["active"] - rec["independent"] for rec in res.stats) >= 1
        g = np.random.default_rng(2).normal(size=res.z.shape)
        qr = backward(res, g, mode="qr")
        kkt = backward(res, g, mode="kkt")
        for a in (*qr, *kkt):
            assert np.all(np.isfinite(a))
        np.testing.assert_allclose(qr[0], kkt[0], rtol=1e-9, atol=1e-9 * np.max(np.abs(kkt[0])))


def _finite_differences(prob, R, group, eps):
    """Central differences of L = Σ R·z* for every entry of one input group."""
    base = prob[group]
    out = np.zeros_like(base)
    for idx in np.ndindex(base.shape):
        vals = []
        for sgn in (1.0, -1.0):
            arr = base.copy()
            arr[idx] += sgn * eps
            vals.append(np.sum(R * solve(dict(prob, **{group: arr})).z))
        out[idx] = (vals[0] - vals[1]) / (2 * eps)
    return out


@pytest.mark.parametrize("mode", ["qr", "kkt"])
def test_finite_differences(mode):
    prob = clean_problems(1, start=20, groups=2)[0]
    prob["thickness"] = np.full(prob["nodes"].shape[0], prob["thickness"])  # one target gap per contact
    res = solve(prob)
    R = np.random.default_rng(3).normal(size=res.z.shape)
    grads = dict(zip(("x_hat", "weights", "normals", "obstacle_x", "thickness"), backward(res, R, mode=mode)))
    assert np.any(prob["fixed"]) and np.any(grads["obstacle_x"] != 0) and np.any(grads["thickness"] != 0)
    for group, g in grads.items():
        fd = _finite_differences(prob, R, group, 1e-7)
        np.testing.assert_allclose(g, fd, rtol=0, atol=1e-6 * max(1.0, np.max(np.abs(fd))), err_msg=group)


@pytest.mark.parametrize("problem", ["random", "layered"])
def test_mass_gradient_matches_finite_differences(problem):
    """The masses in W (two fabrics in contact: which side gives way), from either adjoint's dL/dx̂."""
    prob = clean_problems(1, start=20, groups=2)[0] if problem == "random" else layered_problem(7, res=4)
    res = solve(prob)
    assert strictly_complementary(prob, res)
    R = np.random.default_rng(6).normal(size=res.z.shape)
    fd = _finite_differences(prob, R, "mass", 1e-7)
    assert np.abs(fd).max() > 1e-3  # the masses matter here
    for mode in ("qr", "kkt"):
        gm = mass_gradient(res, backward(res, R, mode=mode)[0])
        np.testing.assert_allclose(gm, fd, rtol=0, atol=1e-6 * np.abs(fd).max(), err_msg=mode)


def test_finite_differences_layered():
    """A bigger zone, both adjoints, the input groups that affect every contact: x_hat and obstacle_x."""
    prob = layered_problem(7, res=4)
    res = solve(prob)
    assert strictly_complementary(prob, res)
    R = np.random.default_rng(4).normal(size=res.z.shape)
    fdx = _finite_differences(prob, R, "x_hat", 1e-7)
    fdo = _finite_differences(prob, R, "obstacle_x", 1e-7)
    for mode in ("qr", "kkt"):
        gx, _, _, gob, _ = backward(res, R, mode=mode)
        np.testing.assert_allclose(gx, fdx, rtol=0, atol=1e-6)
        np.testing.assert_allclose(gob, fdo, rtol=0, atol=1e-6)


def test_finite_differences_dependent():
    """With duplicated contacts z*(x̂, obstacle_x) stays smooth; both adjoints match it."""
    probs = [p for p in (random_problem(s, duplicates=True, groups=2) for s in range(30, 60))
             if strictly_complementary(p, solve(p))]
    prob = probs[0]
    res = solve(prob, precompute_qr=True)
    assert any(rec["independent"] < rec["active"] for rec in res.stats)
    R = np.random.default_rng(5).normal(size=res.z.shape)
    fdx = _finite_differences(prob, R, "x_hat", 1e-7)
    fdo = _finite_differences(prob, R, "obstacle_x", 1e-7)
    # perturbing both copies of a duplicated contact together keeps them duplicates: smooth, and the sum of the two
    # copies' gradients must match (this needs the dropped copy's multiplier folded into the kept one)
    rows = np.hstack([prob["nodes"], prob["weights"], prob["normals"]])
    pairs = [(i, j) for i in range(len(rows)) for j in range(i + 1, len(rows)) if np.array_equal(rows[i], rows[j])]
    pairs = [(i, j) for i, j in pairs if res.lam[i] > 0]
    assert pairs
    fd_pairs = []
    for i, j in pairs:
        for group in ("weights", "normals"):
            for col in range(prob[group].shape[1]):
                vals = []
                for sgn in (1.0, -1.0):
                    arr = prob[group].copy()
                    arr[[i, j], col] += sgn * 1e-7
                    vals.append(np.sum(R * solve(dict(prob, **{group: arr})).z))
                fd_pairs.append((group, i, j, col, (vals[0] - vals[1]) / 2e-7))
    for mode in ("qr", "kkt"):
        gx, gw, gn, gob, _ = backward(res, R, mode=mode)
        np.testing.assert_allclose(gx, fdx, rtol=0, atol=1e-6)
        np.testing.assert_allclose(gob, fdo, rtol=0, atol=1e-6)
        grads = {"weights": gw, "normals": gn}
        for group, i, j, col, fd in fd_pairs:
            np.testing.assert_allclose(grads[group][i, col] + grads[group][j, col], fd, rtol=0,
                                       atol=1e-6 * max(1.0, abs(fd)), err_msg=f"{mode} {group} {i} {j} {col}")


def test_lazy_qr():
    prob = clean_problems(1, start=40)[0]
    eager = solve(prob, precompute_qr=True)
    lazy = solve(prob)
    multi = [rec["ncon"] > 1 for rec in lazy.stats]
    assert any(multi)
    # single-contact zones are differentiated in closed form, their sizes are known at once
    assert all((rec["independent"] is None) == big for rec, big in zip(lazy.stats, multi))
    g = np.random.default_rng(6).normal(size=eager.z.shape)
    for a, b in zip(backward(eager, g), backward(lazy, g)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    assert [rec["qr_in_backward"] for rec in lazy.backward_stats] == multi
    assert not any(rec["qr_in_backward"] for rec in eager.backward_stats)
    assert [rec["qr_size"] for rec in lazy.zones_stats()] == [rec["independent"] for rec in eager.stats]


def test_gram_cholesky_is_qr_r_without_q_and_drops_dependent_columns():
    from warpcloth.collision.reference.linalg import gram_cholesky

    rng = np.random.default_rng(11)
    A = rng.normal(size=(12, 5))
    A = np.column_stack([A[:, :3], A[:, 1], A[:, 3], A[:, 0] - 2.0 * A[:, 2], A[:, 4]])  # 3: copy, 5: combination
    keep, drop, L = gram_cholesky(A.T @ A)
    assert keep.tolist() == [0, 1, 2, 4, 6] and drop.tolist() == [3, 5]
    R = np.linalg.qr(A[:, keep])[1]
    np.testing.assert_allclose(L.T, np.sign(np.diag(R))[:, None] * R, rtol=1e-10, atol=1e-12)
    keep, drop, L = gram_cholesky(A[:, keep].T @ A[:, keep])  # full rank: LAPACK's factorisation, nothing dropped
    assert drop.size == 0 and keep.size == 5


# ---------------------------------------------------------------------------------------------------------------
# The device solver (kernels/projection.py): the same problem over all contacts at once, no zones


def _device_solve(prob, device, node_world=None, world_count=1, **kw):
    """Solve ``prob`` with the device projection (node_world: each node's world, cloth particles then obstacle
    vertices); returns the solver and its kept solution."""
    import warp as wp

    from warpcloth.collision.projection import DeviceProjection

    n, V = prob["x_hat"].shape[0], prob["obstacle_x"].shape[0]
    inv_mass = np.zeros(n + V)
    inv_mass[:n] = np.where(prob["fixed"], 0.0, 1.0 / prob["mass"])
    on = functools.partial(wp.array, device=device)
    solver = DeviceProjection(device, n + V, prob["nodes"].shape[0],
                              None if node_world is None else on(node_world, dtype=wp.int32), world_count)
    solution = solver.project(
        on(np.concatenate([prob["x_hat"], prob["obstacle_x"]]), dtype=wp.vec3d),
        on(np.concatenate([~prob["fixed"], np.zeros(V, bool)]).astype(np.int32), dtype=wp.int32),
        on(inv_mass, dtype=wp.float64), on(prob["nodes"].astype(np.int32), dtype=wp.int32),
        on(prob["weights"], dtype=wp.vec4d), on(prob["normals"], dtype=wp.vec3d),
        prob["nodes"].shape[0], prob["thickness"], keep=True, **kw)
    return solver, solution


def _worlds_problem(problems):
    """The problems as the worlds of one: each one's particles, then each one's obstacle vertices, and their contacts
    dealt out in turn (each world's in its own order). Returns the problem, every node's world, and for each world
    its particles, its obstacle vertices and its contacts in the joint problem."""
    n = np.cumsum([0] + [p["x_hat"].shape[0] for p in problems])
    v = n[-1] + np.cumsum([0] + [p["obstacle_x"].shape[0] for p in problems])
    deal = sorted((i, w) for w, p in enumerate(problems) for i in range(p["nodes"].shape[0]))
    contacts = [[k for k, (_, w2) in enumerate(deal) if w2 == w] for w in range(len(problems))]
    nodes = np.array([np.where(problems[w]["nodes"][i] < problems[w]["x_hat"].shape[0],
                               problems[w]["nodes"][i] + n[w],
                               problems[w]["nodes"][i] - problems[w]["x_hat"].shape[0] + v[w]) for i, w in deal])
    joint = {name: np.concatenate([p[name] for p in problems]) for name in ("x_hat", "mass", "fixed", "obstacle_x")}
    joint.update(nodes=nodes, weights=np.array([problems[w]["weights"][i] for i, w in deal]),
                 normals=np.array([problems[w]["normals"][i] for i, w in deal]), thickness=problems[0]["thickness"])
    node_world = np.concatenate([np.repeat(np.arange(len(problems)), np.diff(n)),
                                 np.repeat(np.arange(len(problems)), np.diff(v))])
    return joint, node_world, [(np.arange(n[w], n[w + 1]), np.arange(v[w], v[w + 1]), contacts[w])
                               for w in range(len(problems))]


@pytest.mark.parametrize("problem", ["random", "layered", "dependent"])
def test_device_solver_and_adjoint_match_the_zone_solver_and_the_kkt_adjoint(problem, device):
    probs = {"random": lambda: clean_problems(3, groups=3),
             "layered": lambda: [layered_problem(7, res=6)],
             "dependent": lambda: [random_problem(s, duplicates=True, split=True) for s in range(2)]}[problem]()
    for prob in probs:
        res = solve(prob, tol=1e-13)
        solver, solution = _device_solve(prob, device, tol=1e-13)
        assert solution.converged
        n = prob["x_hat"].shape[0]
        np.testing.assert_allclose(solution.z.numpy()[:n], res.z, rtol=0, atol=1e-12)
        assert len(res.zones) > 1  # several zones, one solve
        g = np.random.default_rng(2).normal(size=res.z.shape)
        kkt = backward(res, g, mode="kkt")
        dev = solver.backward(solution, g, x_hat=prob["x_hat"], mass=prob["mass"], fixed=prob["fixed"],
                              obstacle_x=prob["obstacle_x"], nodes=prob["nodes"], weights=prob["weights"],
                              normals=prob["normals"])
        names = ("x_hat", "weights", "normals", "obstacle_x", "thickness")
        # dependent contacts share their multipliers differently (minimum norm here, folded in the QR): z* and
        # dL/dx_hat are unique, the split of the contacts' own gradients is not
        for name, a, b in list(zip(names, dev, kkt))[:1 if problem == "dependent" else 5]:
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-8 * max(np.abs(b).max(), 1e-300), err_msg=name)


@pytest.mark.parametrize("tilt", [1e-7, 1e-9, 0.0])
def test_device_adjoint_of_nearly_dependent_contacts_drops_them_as_the_qr_adjoint_does(tilt, device):
    # One particle pressed onto an obstacle triangle by two contacts whose normals are ``tilt`` rad apart: their
    # rows of H = G W^-1 G^T are dependent to within tilt^2. Both are active at the solution, but any perturbation
    # leaves one of them alone binding, and either one fixes only the particle's height: dz/dx^ keeps x and y (what
    # the QR adjoint, which drops the dependent column, gives). A plain CG on the nearly singular H_AA gave a d_lam
    # of 1/tilt^2 and a dL/dx^ without its x component; the shifted solve (kernels/projection.py DEPENDENT_SHIFT)
    # damps the dependent direction, by a factor that fades from 1 to 0 around tilt^2 = 1e-10 where the QR's rank
    # test switches at once (at tilt 1e-7 the x component is 1.5e-4 short).
    normals = np.array([[0.0, 0.0, 1.0], [np.sin(tilt), 0.0, np.cos(tilt)]])
    prob = dict(x_hat=np.array([[0.0, 0.0, -1e-3]]), mass=np.array([0.01]), fixed=np.zeros(1, bool),
                obstacle_x=np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]]),
                nodes=np.array([[0, 1, 2, 3]] * 2), weights=np.array([[1.0, -0.25, -0.25, -0.5]] * 2),
                normals=normals, thickness=1e-3)
    res = solve(prob, tol=1e-13)
    solver, solution = _device_solve(prob, device, tol=1e-13)
    assert solution.converged
    g = np.array([[0.3, -0.7, 1.1]])
    qr = backward(res, g, mode="qr")[0]
    np.testing.assert_allclose(qr, [[0.3, -0.7, 0.0]], atol=1e-6)
    dev = solver.backward(solution, g, x_hat=prob["x_hat"], mass=prob["mass"], fixed=prob["fixed"],
                          obstacle_x=prob["obstacle_x"], nodes=prob["nodes"], weights=prob["weights"],
                          normals=prob["normals"])[0]
    np.testing.assert_allclose(dev, qr, atol=1e-4)


def test_device_solver_reports_contacts_no_positions_satisfy(device):
    # a particle pressed between two obstacle planes 0.5 delta apart: infeasible
    prob = dict(x_hat=np.zeros((1, 3)), mass=np.ones(1), fixed=np.zeros(1, bool),
                obstacle_x=np.array([[0, 0, -0.25 * DELTA], [0, 0, 0.25 * DELTA]], dtype=float),
                nodes=np.array([[0, 1, 1, 1], [0, 2, 2, 2]]), weights=np.array([[1.0, -1.0, 0, 0], [1.0, -1.0, 0, 0]]),
                normals=np.array([[0, 0, 1.0], [0, 0, -1.0]]), thickness=DELTA)
    _, solution = _device_solve(prob, device, max_iters=500)
    assert not solution.converged and solution.unbounded


def test_device_solver_solves_each_world_as_that_world_alone_bit_for_bit(device):
    # Three problems (two with contacts that share particles and obstacle vertices) as the worlds of one call, their
    # contacts interleaved: the contacts are grouped by world, each world's node sums gathered in its contacts'
    # order (kernels/projection.py node_sums), so each world's positions, multipliers and adjoint are those of the
    # problem solved alone, to the bit, on every device.
    problems = [layered_problem(3, res=4), clean_problems(1, groups=3)[0], layered_problem(5, res=3)]
    joint, node_world, parts = _worlds_problem(problems)
    assert len(set(node_world[joint["nodes"][:8, 0]])) == 3  # interleaved
    solver, solution = _device_solve(joint, device, node_world=node_world, world_count=3, tol=1e-12)
    assert solution.converged
    rng = np.random.default_rng(4)
    g = rng.normal(size=(joint["x_hat"].shape[0] + joint["obstacle_x"].shape[0], 3))
    d_z, d_lam = solver.adjoint(solution, g)
    z, lam = solution.z.numpy(), solution.lam.numpy()
    for prob, (particles, vertices, contacts) in zip(problems, parts):
        alone, alone_solution = _device_solve(prob, device, tol=1e-12)
        nodes = np.concatenate([particles, vertices])
        alone_d_z, alone_d_lam = alone.adjoint(alone_solution, g[nodes])
        np.testing.assert_array_equal(z[nodes], alone_solution.z.numpy())
        np.testing.assert_array_equal(lam[contacts], alone_solution.lam.numpy()[:len(contacts)])
        np.testing.assert_array_equal(d_z[nodes], alone_d_z)
        np.testing.assert_array_equal(d_lam[contacts], alone_d_lam)
        assert np.abs(alone_d_lam).max() > 0 and np.abs(z[particles] - joint["x_hat"][particles]).max() > 0


@pytest.mark.parametrize("block_dim", [0, 48, 2048])
def test_device_projection_refuses_a_block_that_is_not_a_power_of_two_up_to_1024(block_dim):
    from warpcloth.collision.projection import DeviceProjection

    with pytest.raises(ValueError, match=f"block_dim must be a power of two up to 1024, got {block_dim}"):
        DeviceProjection("cpu", 4, 4, block_dim=block_dim)


@pytest.mark.parametrize("problem", ["random", "layered", "dependent"])
def test_device_solver_steps_by_an_upper_bound_on_the_scaled_dual_norm(problem, device):
    # MPRGP's expansion steps converge only below 2 / ||Hs||: kernels/projection.py scaled_norm_bound must bound the
    # Jacobi-scaled dual matrix's norm from above (its step is 1.9 over it), and not loosely (4x would slow it)
    probs = {"random": lambda: clean_problems(3, groups=3), "layered": lambda: [layered_problem(7, res=6)],
             "dependent": lambda: [random_problem(s, duplicates=True, split=True) for s in range(2)]}[problem]()
    for prob in probs:
        n = prob["x_hat"].shape[0]
        G = np.zeros((prob["nodes"].shape[0], 3 * n))
        for j, (nodes, weights, normal) in enumerate(zip(prob["nodes"], prob["weights"], prob["normals"])):
            for node, weight in zip(nodes, weights):
                if node < n and not prob["fixed"][node]:
                    G[j, 3 * node:3 * node + 3] += weight * normal
        H = (G / np.repeat(prob["mass"], 3)) @ G.T
        D = np.sqrt(np.where(np.diag(H) > 0, np.diag(H), 1.0))
        norm = np.linalg.eigvalsh(H / np.outer(D, D)).max()
        _, solution = _device_solve(prob, device, tol=1e-12)
        bound = solution.info.numpy()[0, 3]
        assert norm * (1 - 1e-12) <= bound <= 4.0 * norm, (norm, bound)
