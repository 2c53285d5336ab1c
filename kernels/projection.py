"""The collision projection and its adjoint on the device, over all contacts at once (no impact zones needed).

The problem is warpcloth/collision/reference/qp.py's: contact j couples nodes a = 0..3 (cloth particles, then obstacle
vertices) with weights w_ja along a unit normal n_j; with g_j the row that gathers sum_a w_ja n_j . z_a over the
free particles and h_j = delta - sum_{constant a} w_ja n_j . p_a, the constraint is c_j(z) = g_j z - h_j >= 0 and

    min_z 1/2 (z - x^)^T W (z - x^)  s.t.  c(z) >= 0,   z = x^ + W^-1 G^T lam,  lam >= 0,  lam_j c_j = 0.

Solver (one thread block per world on its own contacts, dot products and maxima by block reductions,
kernels/blocks.py; on the CPU a block is one thread, solving a world bit for bit as a model of it alone does): the
dual, min 1/2 lam^T H lam - b^T lam over lam >= 0 (H = G W^-1 G^T applied matrix-free, b = h - G x^), by MPRGP
(Dostal's modified proportioning with reduced gradient projections: CG steps on the free multipliers, projected
gradient expansions at the bound, proportioning steps that release multipliers) on the Jacobi-scaled x = D lam
(D = sqrt(diag H)). Why MPRGP: docs/decisions.md, 'MPRGP for the collision QP'. The dual's gradient H lam - b is
c(z), so the stopping test is the projection's KKT test: max violation and max |c_j| over lam_j > 0 within ``tol``.

Adjoint (the same formulas as warpcloth/collision/reference/adjoint.py): on the active set A, CG on
H_AA d_lam = G_A W^-1 g (g = dL/dz), then d_z = W^-1 (g - G_A^T d_lam). A consistent singular H_AA (dependent
contacts) is fine for CG from zero: d_z is unique, d_lam is the minimum-norm split among the dependent contacts.
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.blocks import block_barrier, block_max, block_min, block_sum
from warpcloth.kernels.types import per_precision, types

CONVERGED = 0
NOT_CONVERGED = 1
UNBOUNDED = 2
"""The dual decreases without bound along a direction: no positions satisfy the contacts."""
DEPENDENT_SHIFT = 1.0e-10
"""The adjoint solves (H_AA + DEPENDENT_SHIFT diag(H_AA)) d_lam = rhs: a contact that is dependent on others to
within this (its squared distance from their span, relative to its own squared norm: the NumPy adjoint's
DEPENDENT_PIVOT, warpcloth/collision/reference/linalg.py) is damped out of d_lam as the QR adjoint drops it."""
REFINEMENTS = 2
"""Passes of iterative refinement after the shifted adjoint solve (``adjoint``)."""
DIVERGED = 1.0e4
"""A KKT residual this many times the first one means the multipliers are running away (UNBOUNDED)."""
FALSE_CONVERGENCE = wp.constant(wp.float64(100.0))
"""A solve that passed its KKT test but leaves a contact violated by more than this many times the tolerance (its
step-by-step gradient drifted) is NOT_CONVERGED."""


@wp.func
def merged_weight(nodes: wp.array2d(dtype=wp.int32), w: wp.array(dtype=wp.vec4d), free: wp.array(dtype=wp.int32),
                  j: int, a: int):
    """Contact j's weight on its a-th node with repeated nodes merged into their first slot; 0 for a repeat and
    for a node that is not free."""
    node = nodes[j, a]
    if free[node] == 0:
        return wp.float64(0.0)
    for b in range(a):
        if nodes[j, b] == node:
            return wp.float64(0.0)
    s = w[j][a]
    for b in range(a + 1, 4):
        if nodes[j, b] == node:
            s += w[j][b]
    return s


@wp.struct
class Rows:
    # the contacts as the solver reads them: sorted by world (each world's in the order they were found), so that
    # world w owns the slots start[w] .. start[w + 1] and its solve is the one a model of that world alone runs
    count: int
    nodes: wp.array2d(dtype=wp.int32)  # sorted
    fw: wp.array(dtype=wp.vec4d)  # merged weights of free nodes, 0 elsewhere (sorted)
    normal: wp.array(dtype=wp.vec3d)  # sorted
    h: wp.array(dtype=wp.float64)  # sorted
    diag: wp.array(dtype=wp.float64)  # H_jj (sorted)
    inv_mass: wp.array(dtype=wp.float64)  # per node; 0 for constant nodes
    order: wp.array(dtype=wp.int32)  # sorted slot -> the contact's index in the caller's lists
    start: wp.array(dtype=wp.int32)  # (worlds + 1): world w's slots
    # the rows' node entries (sorted slot k's node a) grouped by node, each node's in row order, world w's at
    # 4 start[w] .. 4 start[w + 1] (prepare_rows, incidence_runs): what lets a node's sum over its contacts be
    # gathered in one order by one thread (node_sums) instead of scattered by atomic adds in any order
    entry_row: wp.array(dtype=wp.int32)  # (4 count): the entry's row k
    entry_weight: wp.array(dtype=wp.float64)  # (4 count): its merged weight over its node's mass, fw[k][a] / m
    run_end: wp.array(dtype=wp.int32)  # (4 count): at a free node's first entry, one past its last; 0 elsewhere
    run_node: wp.array(dtype=wp.int32)  # (4 count): at a free node's first entry, the node


@wp.kernel(enable_backward=False)
def world_keys(nodes: wp.array2d(dtype=wp.int32), node_world: wp.array(dtype=wp.int32), count: int, first_new: int,
               world_count: int, keys: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int32),
               held: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int32), solve_world: wp.array(dtype=wp.int32)):
    # one thread a contact (at least one): its world as its sort key, its index as its value, and whether its world
    # has a contact at or after first_new (the others keep their last solution; solve_world zeroed before). Several
    # worlds: wp.utils.radix_sort_pairs then sorts the contacts by world (stably: each world's in the order found)
    # and geometry.py world_starts finds each world's first slot. One world: the order as found, nothing to sort.
    j = wp.tid()
    if j == 0:
        held[0] = count
        if world_count == 1:
            start[0] = 0
            start[1] = count
    if j < count:
        w = node_world[nodes[j, 0]]
        keys[j] = wp.int64(w)
        order[j] = j
        if j >= first_new:
            solve_world[w] = 1


@wp.kernel(enable_backward=False)
def gather(values: wp.array(dtype=wp.float64), order: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.float64)):
    k = wp.tid()
    out[k] = values[order[k]]


@wp.kernel(enable_backward=False)
def scatter(values: wp.array(dtype=wp.float64), order: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.float64)):
    k = wp.tid()
    out[order[k]] = values[k]


@wp.kernel(enable_backward=False)
def incidence_runs(keys: wp.array(dtype=wp.int64), entries: wp.array(dtype=wp.int32), count: int, node_count: int,
                   sorted_nodes: wp.array2d(dtype=wp.int32), fw: wp.array(dtype=wp.vec4d),
                   inv_mass: wp.array(dtype=wp.float64), entry_row: wp.array(dtype=wp.int32),
                   entry_weight: wp.array(dtype=wp.float64), run_end: wp.array(dtype=wp.int32),
                   run_node: wp.array(dtype=wp.int32)):
    # the entries sorted by key: each one's row and weight, and at each free node's first entry the node and one
    # past its last entry (0 for the entries without weight)
    e = wp.tid()
    k = entries[e] // 4
    a = entries[e] % 4
    node = sorted_nodes[k, a]
    entry_row[e] = k
    entry_weight[e] = fw[k][a] * inv_mass[node]
    end = int(0)
    if (e == 0 or keys[e] != keys[e - 1]) and keys[e] % wp.int64(node_count + 1) != wp.int64(node_count):
        end = e + 1
        while end < count and keys[end] == keys[e]:
            end += 1
    run_end[e] = end
    run_node[e] = node


@wp.kernel(enable_backward=False)
def prepare_rows(nodes: wp.array2d(dtype=wp.int32), w: wp.array(dtype=wp.vec4d), normal: wp.array(dtype=wp.vec3d),
                 positions: wp.array(dtype=wp.vec3d), free: wp.array(dtype=wp.int32),
                 inv_mass: wp.array(dtype=wp.float64), target: wp.array(dtype=wp.float64),
                 order: wp.array(dtype=wp.int32), node_world: wp.array(dtype=wp.int32), node_count: int,
                 sorted_nodes: wp.array2d(dtype=wp.int32), sorted_normal: wp.array(dtype=wp.vec3d),
                 fw: wp.array(dtype=wp.vec4d), h: wp.array(dtype=wp.float64), diag: wp.array(dtype=wp.float64),
                 entry_keys: wp.array(dtype=wp.int64), entries: wp.array(dtype=wp.int32)):
    # sorted slot k holds contact j = order[k]; target: each contact's gap (the thickness, or less for a pair that
    # started closer). Its node entries 4 k + a get their keys (world, node) for a stable sort that groups the
    # entries by node, world by world, each node's in entry order (incidence_runs); entries without weight (constant
    # nodes, repeats) take the key (world, node_count), after the world's nodes: node sums skip them, so a node that
    # many contacts share (an obstacle's vertex) costs nothing
    k = wp.tid()
    j = order[k]
    n = normal[j]
    hj = target[j]
    d = wp.float64(0.0)
    f = wp.vec4d()
    for a in range(4):
        node = nodes[j, a]
        sorted_nodes[k, a] = node
        if free[node] == 0:
            hj -= w[j][a] * wp.dot(n, positions[node])
        m = merged_weight(nodes, w, free, j, a)
        f[a] = m
        d += m * m * inv_mass[node]
        slot = wp.int64(node_count)
        if m != wp.float64(0.0):
            slot = wp.int64(node)
        entry_keys[4 * k + a] = wp.int64(node_world[node]) * wp.int64(node_count + 1) + slot
        entries[4 * k + a] = 4 * k + a
    sorted_normal[k] = n
    fw[k] = f
    h[k] = hj
    diag[k] = d


@wp.func
def row_dot(r: Rows, v: wp.array(dtype=wp.vec3d), j: int):
    # g_j v: contact j's row of G applied to per-node vectors v
    s = wp.float64(0.0)
    for a in range(4):
        if r.fw[j][a] != wp.float64(0.0):
            s += r.fw[j][a] * wp.dot(r.normal[j], v[r.nodes[j, a]])
    return s


@wp.func
def constraint(r: Rows, z: wp.array(dtype=wp.vec3d), j: int):
    return row_dot(r, z, j) - r.h[j]


@wp.func
def node_sums(r: Rows, lo: int, hi: int, lane: int, stride: int, mask: wp.array(dtype=wp.int32),
              amount: wp.array(dtype=wp.float64), sign: wp.float64, skip_zero: int, base: wp.array(dtype=wp.vec3d),
              use_base: int, out: wp.array(dtype=wp.vec3d)):
    # out = base + W^-1 sum_j g_j^T (sign amount_j) at every node of the contacts lo..hi, over the contacts with
    # mask != 0 (and amount != 0 where skip_zero): each node's sum gathered by one thread, over its contacts in their
    # order (no atomics, so the same sums on every device and every run)
    e = 4 * lo + lane
    while e < 4 * hi:
        end = r.run_end[e]
        if end > e:
            node = r.run_node[e]
            acc = wp.vec3d()
            if use_base != 0:
                acc = base[node]
            for f in range(e, end):  # the entries with weight on this node
                j = r.entry_row[f]
                if mask[j] != 0 and (skip_zero == 0 or amount[j] != wp.float64(0.0)):
                    acc = acc + (r.entry_weight[f] * (sign * amount[j])) * r.normal[j]
            out[node] = acc
        e += stride


@wp.func
def dual_product(r: Rows, lo: int, hi: int, lane: int, stride: int, mask: wp.array(dtype=wp.int32),
                 v: wp.array(dtype=wp.float64), scratch: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.float64)):
    # out = H_MM v on the contacts with mask != 0 (0 elsewhere); scratch: per node
    block_barrier()  # v written, and the last product's reads of scratch done
    node_sums(r, lo, hi, lane, stride, mask, v, wp.float64(1.0), 0, scratch, 0, scratch)
    block_barrier()
    j = lo + lane
    while j < hi:  # row_dot inlined: this loop is the solver's hot path, and a Rows argument is copied
        o = wp.float64(0.0)
        if mask[j] != 0:
            for a in range(4):
                if r.fw[j][a] != wp.float64(0.0):
                    o += r.fw[j][a] * wp.dot(r.normal[j], scratch[r.nodes[j, a]])
        out[j] = o
        j += stride


@wp.func
def shifted_product(r: Rows, lo: int, hi: int, lane: int, stride: int, mask: wp.array(dtype=wp.int32),
                    v: wp.array(dtype=wp.float64), scratch: wp.array(dtype=wp.vec3d), shift: wp.float64,
                    out: wp.array(dtype=wp.float64)):
    # out = (H_MM + shift diag(H)_MM) v
    dual_product(r, lo, hi, lane, stride, mask, v, scratch, out)
    j = lo + lane
    while j < hi:
        if mask[j] != 0:
            out[j] = out[j] + shift * r.diag[j] * v[j]
        j += stride


@wp.func
def masked_cg(r: Rows, lo: int, hi: int, lane: int, stride: int, mask: wp.array(dtype=wp.int32),
              rhs: wp.array(dtype=wp.float64), x: wp.array(dtype=wp.float64), res: wp.array(dtype=wp.float64),
              p: wp.array(dtype=wp.float64), q: wp.array(dtype=wp.float64), scratch: wp.array(dtype=wp.vec3d),
              rtol: wp.float64, reference_sq: wp.float64, max_iters: int, shift: wp.float64):
    """CG on (H_MM + shift diag(H)_MM) x = rhs_M from x (masked entries only; Jacobi preconditioned) until its
    residual is below rtol times a norm whose square is ``reference_sq`` (the adjoint's first right-hand side's, for
    the refinements that follow it too). Returns the iterations."""
    shifted_product(r, lo, hi, lane, stride, mask, x, scratch, shift, q)
    rz = wp.float64(0.0)
    j = lo + lane
    while j < hi:
        rj = wp.float64(0.0)
        if mask[j] != 0:
            rj = rhs[j] - q[j]
        res[j] = rj
        p[j] = rj / wp.max(r.diag[j], wp.float64(1.0e-300))
        rz += rj * p[j]
        j += stride
    rz = block_sum(rz)
    limit = rtol * rtol * reference_sq
    it = int(0)
    while it < max_iters:
        rr = wp.float64(0.0)
        j = lo + lane
        while j < hi:
            rr += res[j] * res[j]
            j += stride
        rr = block_sum(rr)
        if rr <= limit or rz <= wp.float64(0.0):
            break
        shifted_product(r, lo, hi, lane, stride, mask, p, scratch, shift, q)
        pq = wp.float64(0.0)
        j = lo + lane
        while j < hi:
            pq += p[j] * q[j]
            j += stride
        pq = block_sum(pq)
        if pq <= wp.float64(0.0):
            break
        alpha = rz / pq
        rz_new = wp.float64(0.0)
        j = lo + lane
        while j < hi:
            x[j] = x[j] + alpha * p[j]
            res[j] = res[j] - alpha * q[j]
            rz_new += res[j] * res[j] / wp.max(r.diag[j], wp.float64(1.0e-300))
            j += stride
        rz_new = block_sum(rz_new)
        beta = rz_new / rz
        rz = rz_new
        j = lo + lane
        while j < hi:
            p[j] = res[j] / wp.max(r.diag[j], wp.float64(1.0e-300)) + beta * p[j]
            j += stride
        it += 1
    return it


@wp.func
def scale(r: Rows, j: int):
    # D_j = sqrt(H_jj); 1 for a contact with no free node (its row of H is 0, its multiplier stays 0)
    return wp.where(r.diag[j] > wp.float64(0.0), wp.sqrt(r.diag[j]), wp.float64(1.0))


@wp.func
def scaled_product(r: Rows, lo: int, hi: int, lane: int, stride: int, ones: wp.array(dtype=wp.int32),
                   v: wp.array(dtype=wp.float64), tmp: wp.array(dtype=wp.float64), scratch: wp.array(dtype=wp.vec3d),
                   out: wp.array(dtype=wp.float64)):
    # out = D^-1 H D^-1 v (D = sqrt(diag H)): the Jacobi-scaled dual matrix
    j = lo + lane
    while j < hi:
        tmp[j] = v[j] / scale(r, j)
        j += stride
    dual_product(r, lo, hi, lane, stride, ones, tmp, scratch, out)
    j = lo + lane
    while j < hi:
        out[j] = out[j] / scale(r, j)
        j += stride


@wp.func
def dual_gradient(r: Rows, lo: int, hi: int, lane: int, stride: int, ones: wp.array(dtype=wp.int32),
                  x_hat: wp.array(dtype=wp.vec3d), x: wp.array(dtype=wp.float64), tmp: wp.array(dtype=wp.float64),
                  scratch: wp.array(dtype=wp.vec3d), g: wp.array(dtype=wp.float64), p: wp.array(dtype=wp.float64)):
    # g = Hs x - bs (bs_j = (h_j - g_j x^) / D_j), the scaled dual's gradient, and p its free part
    scaled_product(r, lo, hi, lane, stride, ones, x, tmp, scratch, g)
    j = lo + lane
    while j < hi:
        g[j] = g[j] - (r.h[j] - row_dot(r, x_hat, j)) / scale(r, j)
        p[j] = wp.where(x[j] > wp.float64(0.0), g[j], wp.float64(0.0))
        j += stride


@wp.func
def scaled_norm_bound(r: Rows, lo: int, hi: int, lane: int, stride: int, l1: wp.array(dtype=wp.float64)):
    """An upper bound on ||Hs||, the spectral norm of the Jacobi-scaled dual matrix of contacts lo..hi, returned to
    every thread of the block (``l1``: per-contact scratch).

    Hs = D^-1 G W^-1 G^T D^-1 has the eigenvalues of M = sum_j u_j u_j^T, u_j = W^-1/2 g_j^T / D_j, whose part at
    node a has length |u_ja| = |fw_ja| sqrt(1/m_a) / D_j. By Cauchy-Schwarz with weights |u_ja|,
    (u_j . x)^2 <= |u_j|_1 sum_a |u_ja| |x_a|^2, so x^T M x <= max_a (sum over the contacts j at node a of
    |u_ja| |u_j|_1) |x|^2: one gather over the nodes' runs."""
    j = lo + lane
    while j < hi:
        s = wp.float64(0.0)
        for a in range(4):
            if r.fw[j][a] != wp.float64(0.0):
                s += wp.abs(r.fw[j][a]) * wp.sqrt(r.inv_mass[r.nodes[j, a]])
        l1[j] = s / scale(r, j)
        j += stride
    block_barrier()
    bound = wp.float64(0.0)
    e = 4 * lo + lane
    while e < 4 * hi:
        end = r.run_end[e]
        root = wp.sqrt(r.inv_mass[r.run_node[e]])
        if end > e and root > wp.float64(0.0):  # a node of zero inverse mass: no contact moves it
            s = wp.float64(0.0)
            for f in range(e, end):  # entry_weight = fw inv_mass: |fw| sqrt(inv_mass) = |entry_weight| / sqrt(...)
                k = r.entry_row[f]
                s += wp.abs(r.entry_weight[f]) / (root * scale(r, k)) * l1[k]
            bound = wp.max(bound, s)
        e += stride
    return block_max(bound)


@wp.kernel(enable_backward=False)
def solve(r: Rows, x_hat: wp.array(dtype=wp.vec3d), tol: wp.float64, max_iters: int, stall: int,
          ones: wp.array(dtype=wp.int32), solve_world: wp.array(dtype=wp.int32),
          lam: wp.array(dtype=wp.float64), z: wp.array(dtype=wp.vec3d), x: wp.array(dtype=wp.float64),
          g: wp.array(dtype=wp.float64), p: wp.array(dtype=wp.float64), hp: wp.array(dtype=wp.float64),
          tmp: wp.array(dtype=wp.float64), scratch: wp.array(dtype=wp.vec3d), info: wp.array2d(dtype=wp.float64),
          failed: wp.array(dtype=wp.int32)):
    # One thread block per world, on its own slots (its own QP: worlds share no node). MPRGP on the Jacobi-scaled
    # dual min 1/2 x^T Hs x - bs^T x, x >= 0 (x = D lam, Hs = D^-1 H D^-1, bs = D^-1 (h - G x^)); its gradient
    # g = Hs x - bs is D^-1 c(z), so the stopping test max(|c_j| over x_j > 0, -c_j over x_j = 0) <= tol is the
    # projection's KKT test. Stops as NOT_CONVERGED when its residual has not halved in ``stall`` iterations
    # (contacts that contradict each other stall it). On entry lam (sorted) holds the warm start and z every node's
    # last positions; a world with solve_world 0 keeps them (it found nothing new), the others restart their
    # contacts' nodes from x^. failed[0] = 1 where a world ends other than CONVERGED (or with a non-finite KKT
    # residual): the host reads that flag alone, and the worlds' info only then. Every branch below tests reduced
    # values only, so the block's threads take it together.
    world, lane = wp.tid()
    stride = wp.block_dim()
    lo = r.start[world]
    hi = r.start[world + 1]
    if lane == 0:
        for c in range(5):
            info[world, c] = wp.float64(0.0)
    if solve_world[world] == 0 or hi == lo:
        return
    # the step of the expansions: 1.9 / ||Hs|| (projected gradient steps converge up to 2 / ||Hs||), with ||Hs|| by
    # the bound of scaled_norm_bound (why a bound: docs/decisions.md, 'MPRGP step from a norm bound')
    norm = scaled_norm_bound(r, lo, hi, lane, stride, tmp)
    step = wp.float64(1.9) / wp.max(norm, wp.float64(1.0e-300))
    # start: x = D lam (projected)
    j = lo + lane
    while j < hi:
        x[j] = wp.where(r.diag[j] > wp.float64(0.0), wp.max(lam[j] * scale(r, j), wp.float64(0.0)), wp.float64(0.0))
        j += stride
    dual_gradient(r, lo, hi, lane, stride, ones, x_hat, x, tmp, scratch, g, p)
    status = int(NOT_CONVERGED)
    it = int(0)
    worst = wp.float64(0.0)
    first = wp.float64(-1.0)
    best = wp.float64(1.0e300)
    best_it = int(0)
    while it < max_iters:
        # free (phi), chopped (beta) and reduced free gradients
        worst = wp.float64(0.0)
        bb = wp.float64(0.0)
        ff = wp.float64(0.0)
        j = lo + lane
        while j < hi:
            if x[j] > wp.float64(0.0):
                worst = wp.max(worst, wp.abs(g[j]) * scale(r, j))
                ff += wp.min(x[j] / step, g[j]) * g[j]
            else:
                beta = wp.min(g[j], wp.float64(0.0))
                worst = wp.max(worst, -beta * scale(r, j))
                if r.diag[j] > wp.float64(0.0):
                    bb += beta * beta
            j += stride
        worst = block_max(worst)
        bb = block_sum(bb)
        ff = block_sum(ff)
        if worst <= tol:
            status = CONVERGED
            break
        if first < wp.float64(0.0):
            first = worst
        elif not (worst <= wp.float64(DIVERGED) * (first + tol)):  # NaN included
            status = UNBOUNDED  # the multipliers run away: the dual has no minimum
            break
        if worst < wp.float64(0.5) * best:
            best = worst
            best_it = it
        elif it - best_it > stall:
            break
        it += 1
        if bb <= ff:
            scaled_product(r, lo, hi, lane, stride, ones, p, tmp, scratch, hp)
            php = wp.float64(0.0)
            gp = wp.float64(0.0)
            feasible = wp.float64(1.0e300)
            j = lo + lane
            while j < hi:
                php += p[j] * hp[j]
                gp += g[j] * p[j]
                if p[j] > wp.float64(0.0):
                    feasible = wp.min(feasible, x[j] / p[j])
                j += stride
            php = block_sum(php)
            gp = block_sum(gp)
            feasible = block_min(feasible)
            a_cg = wp.where(php > wp.float64(0.0), gp / php, wp.float64(0.0))
            if a_cg <= feasible:  # conjugate gradient step
                fhp = wp.float64(0.0)
                j = lo + lane
                while j < hi:
                    x[j] = x[j] - a_cg * p[j]
                    g[j] = g[j] - a_cg * hp[j]
                    if x[j] > wp.float64(0.0):
                        fhp += g[j] * hp[j]
                    j += stride
                gamma = block_sum(fhp) / php
                j = lo + lane
                while j < hi:
                    p[j] = wp.where(x[j] > wp.float64(0.0), g[j], wp.float64(0.0)) - gamma * p[j]
                    j += stride
            else:  # expansion: to the boundary, then a projected gradient step on the free set
                j = lo + lane
                while j < hi:
                    x[j] = wp.max(x[j] - feasible * p[j], wp.float64(0.0))
                    g[j] = g[j] - feasible * hp[j]
                    if x[j] > wp.float64(0.0):
                        x[j] = wp.max(x[j] - step * g[j], wp.float64(0.0))
                    j += stride
                dual_gradient(r, lo, hi, lane, stride, ones, x_hat, x, tmp, scratch, g, p)
        else:  # proportioning: release the contacts whose multipliers should grow
            j = lo + lane
            while j < hi:
                chopped = wp.min(g[j], wp.float64(0.0))
                p[j] = wp.where(x[j] > wp.float64(0.0) or r.diag[j] <= wp.float64(0.0), wp.float64(0.0), chopped)
                j += stride
            scaled_product(r, lo, hi, lane, stride, ones, p, tmp, scratch, hp)
            dhd = wp.float64(0.0)
            gd = wp.float64(0.0)
            j = lo + lane
            while j < hi:
                dhd += p[j] * hp[j]
                gd += g[j] * p[j]
                j += stride
            dhd = block_sum(dhd)
            gd = block_sum(gd)
            if dhd <= wp.float64(0.0):  # H d = 0 while g.d < 0: the dual is unbounded below
                status = UNBOUNDED
                break
            a_p = gd / dhd
            j = lo + lane
            while j < hi:
                x[j] = x[j] - a_p * p[j]
                g[j] = g[j] - a_p * hp[j]
                p[j] = wp.where(x[j] > wp.float64(0.0), g[j], wp.float64(0.0))
                j += stride
    # lam = D^-1 x and z = x^ + W^-1 G^T lam at the contacts' nodes
    j = lo + lane
    while j < hi:
        lam[j] = x[j] / scale(r, j)
        j += stride
    block_barrier()
    node_sums(r, lo, hi, lane, stride, ones, lam, wp.float64(1.0), 1, x_hat, 1, z)
    block_barrier()
    violated = wp.float64(0.0)
    broken = wp.float64(0.0)  # wp.max drops a NaN, so the tests above and below cannot see one: count them
    j = lo + lane
    while j < hi:
        gap = constraint(r, z, j)
        if not (wp.isfinite(gap) and wp.isfinite(lam[j])):
            broken += wp.float64(1.0)
        violated = wp.max(violated, -gap)
        j += stride
    violated = block_max(violated)
    finite = block_sum(broken) == wp.float64(0.0)
    if status == CONVERGED and not (finite and violated <= FALSE_CONVERGENCE * tol):
        # the test above reads the gradient updated step by step, which drifts from c(z) where the multipliers grow
        # huge (contacts nearly contradicting each other): a contact violated by 4e-5 m passed it
        status = NOT_CONVERGED
    if lane == 0:
        info[world, 0] = wp.float64(status)
        info[world, 1] = wp.float64(it)
        info[world, 2] = worst
        if status != CONVERGED or not wp.isfinite(worst):
            failed[0] = 1
        info[world, 3] = norm
        info[world, 4] = violated


@wp.kernel(enable_backward=False)
def adjoint(r: Rows, active: wp.array(dtype=wp.int32), rtol: wp.float64,
            d_lam: wp.array(dtype=wp.float64), d_z: wp.array(dtype=wp.vec3d), rhs: wp.array(dtype=wp.float64),
            res: wp.array(dtype=wp.float64), p: wp.array(dtype=wp.float64), q: wp.array(dtype=wp.float64),
            correction: wp.array(dtype=wp.float64), remainder: wp.array(dtype=wp.float64),
            scratch: wp.array(dtype=wp.vec3d), info: wp.array2d(dtype=wp.float64)):
    # One thread block per world, on its own slots. d_z (per node, in/out): W^-1 grad_z on entry for free nodes, 0
    # elsewhere; on return W^-1 (g - G_A^T d_lam)
    world, lane = wp.tid()
    stride = wp.block_dim()
    lo = r.start[world]
    hi = r.start[world + 1]
    max_iters = 10 * (hi - lo) + 100
    shift = wp.float64(DEPENDENT_SHIFT)
    bb = wp.float64(0.0)
    j = lo + lane
    while j < hi:
        rhs[j] = wp.where(active[j] != 0, row_dot(r, d_z, j), wp.float64(0.0))
        d_lam[j] = wp.float64(0.0)
        bb += rhs[j] * rhs[j]
        j += stride
    bb = block_sum(bb)
    iters = masked_cg(r, lo, hi, lane, stride, active, rhs, d_lam, res, p, q, scratch, rtol, bb, max_iters, shift)
    # iterative refinement against the unshifted H_AA: it takes the shift's error off independent contacts (a
    # factor shift * cond(H_AA) a pass) and leaves dependent ones damped. Each pass solves to the first solve's
    # accuracy, rtol of the first right-hand side, not of its own, far smaller, one (docs/decisions.md, 'Adjoint
    # refinement tolerance')
    for _refine in range(REFINEMENTS):
        dual_product(r, lo, hi, lane, stride, active, d_lam, scratch, q)
        j = lo + lane
        while j < hi:
            remainder[j] = rhs[j] - q[j]
            correction[j] = wp.float64(0.0)
            j += stride
        iters += masked_cg(r, lo, hi, lane, stride, active, remainder, correction, res, p, q, scratch, rtol, bb,
                           max_iters, shift)
        j = lo + lane
        while j < hi:
            d_lam[j] = d_lam[j] + correction[j]
            j += stride
    rr = wp.float64(0.0)
    j = lo + lane
    while j < hi:
        rr += res[j] * res[j]
        j += stride
    rr = block_sum(rr)  # also the barrier after d_lam's last update
    node_sums(r, lo, hi, lane, stride, active, d_lam, wp.float64(-1.0), 0, d_z, 1, d_z)
    if lane == 0:
        info[world, 0] = wp.float64(iters)
        info[world, 1] = wp.sqrt(rr / wp.max(bb, wp.float64(1.0e-300)))  # the last solve's residual, relative


@wp.kernel(enable_backward=False)
def active_set(r: Rows, z: wp.array(dtype=wp.vec3d), lam: wp.array(dtype=wp.float64), active_tol: wp.float64,
               active: wp.array(dtype=wp.int32)):
    # the adjoint's active set: lam_j > 0 or |c_j| <= active_tol (a contact with no free node is never active)
    j = wp.tid()
    on = lam[j] > wp.float64(0.0) or wp.abs(constraint(r, z, j)) <= active_tol
    active[j] = wp.where(on and r.diag[j] > wp.float64(0.0), 1, 0)


FOUND, DEGENERATE, FAILED, STRAINED = 0, 1, 2, 3
"""The slots of the collision detector's round flags (warpcloth/collision/detection.py ContactDetector.flags)."""


@wp.kernel(enable_backward=False)
def expect_found(flags: wp.array(dtype=wp.int32), expected: int, check_strain: int, mismatch: wp.array(dtype=wp.int32)):
    # a planned (captured) step's detection must find the contacts its plan expects, and its last one, where the
    # step had contacts, must see no projection that stretched the cloth past the limit (collision/stage.py)
    if flags[FOUND] != expected or (check_strain != 0 and flags[STRAINED] != 0):
        mismatch[0] = 1


@wp.kernel(enable_backward=False)
def expect_solved(flags: wp.array(dtype=wp.int32), found: int, mismatch: wp.array(dtype=wp.int32)):
    # a planned step's projection must meet no degenerate contact among the round's found and no failed solve
    if flags[DEGENERATE] - 1 < found or flags[FAILED] != 0:
        mismatch[0] = 1


@wp.kernel(enable_backward=False)
def worst_residual(info: wp.array2d(dtype=wp.float64), worst: wp.array(dtype=wp.float64)):
    # the largest relative residual of the adjoint CG of any world (a non-finite one counts as infinite), kept over
    # the adjoints of a captured backward pass, which cannot read each one back
    for w in range(info.shape[0]):
        r = info[w, 1]
        if not wp.isfinite(r):
            r = wp.float64(wp.inf)
        worst[0] = wp.max(worst[0], r)


@per_precision
def device_round_kernels(scalar):
    """Kernels that move the collision stage's data between the model's precision and the projection's float64,
    and push the adjoint back onto the contacts, the particles and the materials, all on the device."""
    t = types(scalar)
    vec3, vec4 = t.vec3, t.vec4

    @wp.kernel(enable_backward=False)
    def positions64(x_hat: wp.array(dtype=vec3), obstacle: wp.array(dtype=vec3), cloth_count: int,
                    out: wp.array(dtype=wp.vec3d)):
        i = wp.tid()
        if i < cloth_count:
            out[i] = wp.vec3d(x_hat[i])
        else:
            out[i] = wp.vec3d(obstacle[i - cloth_count])

    @wp.kernel(enable_backward=False)
    def inverse_mass(mass: wp.array(dtype=scalar), pin: wp.array(dtype=wp.int32), cloth_count: int,
                     free: wp.array(dtype=wp.int32), inv_mass: wp.array(dtype=wp.float64)):
        i = wp.tid()
        movable = i < cloth_count and pin[wp.min(i, cloth_count - 1)] < 0
        free[i] = wp.where(movable, 1, 0)
        inv_mass[i] = wp.where(movable, wp.float64(1.0) / wp.float64(mass[wp.min(i, cloth_count - 1)]),
                               wp.float64(0.0))

    @wp.kernel(enable_backward=False)
    def append_geometry(normal: wp.array(dtype=vec3), weight: wp.array(dtype=vec4), target: wp.array(dtype=scalar),
                        offset: int, normals: wp.array(dtype=wp.vec3d), weights: wp.array(dtype=wp.vec4d),
                        targets: wp.array(dtype=wp.float64), bad: wp.array(dtype=wp.int32)):
        # a round's contacts into the step's float64 lists; bad[0] = 1 + the first degenerate one, if any
        j = wp.tid()
        n = wp.vec3d(normal[j])
        w = wp.vec4d(weight[j])
        normals[offset + j] = n
        weights[offset + j] = w
        targets[offset + j] = wp.float64(target[j])
        if not (wp.isfinite(n) and wp.isfinite(w)):
            wp.atomic_min(bad, 0, j + 1)

    @wp.kernel(enable_backward=False)
    def cloth_positions(z: wp.array(dtype=wp.vec3d), out: wp.array(dtype=vec3)):
        i = wp.tid()
        out[i] = vec3(z[i])

    @wp.kernel(enable_backward=False)
    def scaled_gradient(grad: wp.array(dtype=vec3), inv_mass: wp.array(dtype=wp.float64), cloth_count: int,
                        d_z: wp.array(dtype=wp.vec3d)):
        # d_z = W^-1 dL/dz for free particles, 0 for every other node
        i = wp.tid()
        d = wp.vec3d()
        if i < cloth_count:
            d = inv_mass[i] * wp.vec3d(grad[i])
        d_z[i] = d

    @wp.kernel(enable_backward=False)
    def push_contacts(nodes: wp.array2d(dtype=wp.int32), weights: wp.array(dtype=wp.vec4d),
                      normals: wp.array(dtype=wp.vec3d), free: wp.array(dtype=wp.int32),
                      z: wp.array(dtype=wp.vec3d), d_z: wp.array(dtype=wp.vec3d), lam: wp.array(dtype=wp.float64),
                      d_lam: wp.array(dtype=wp.float64),
                      grad_w: wp.array(dtype=wp.vec4d), grad_n: wp.array(dtype=wp.vec3d),
                      grad_const: wp.array(dtype=wp.vec3d), grad_target: wp.array(dtype=wp.float64)):
        # warpcloth/collision/reference/adjoint.py push_onto_contacts, with the kernels' d_lam (its negative there):
        # dL/dw_ja = (-d_lam_j p_a + lam_j d_a) . n_j, dL/dn_j = sum_a w_ja (...), constant nodes -d_lam_j w_ja n_j,
        # and the target gap's dL/dh_j = d_lam_j
        j = wp.tid()
        grad_target[j] = d_lam[j]
        n = normals[j]
        gw = wp.vec4d()
        gn = wp.vec3d()
        for a in range(4):
            node = nodes[j, a]
            v = -d_lam[j] * z[node] + lam[j] * d_z[node]
            gw[a] = wp.dot(v, n)
            gn += weights[j][a] * v
            if free[node] == 0:
                wp.atomic_add(grad_const, node, (-d_lam[j] * weights[j][a]) * n)
        grad_w[j] = gw
        grad_n[j] = gn

    @wp.kernel(enable_backward=False)
    def position_gradients(grad_z: wp.array(dtype=vec3), d_z: wp.array(dtype=wp.vec3d),
                           d_z_in: wp.array(dtype=wp.vec3d), inv_mass: wp.array(dtype=wp.float64),
                           grad_const: wp.array(dtype=wp.vec3d), z: wp.array(dtype=wp.vec3d),
                           x_hat: wp.array(dtype=wp.vec3d), cloth_count: int,
                           x_hat_grad: wp.array(dtype=vec3), obstacle_grad: wp.array(dtype=vec3),
                           mass_grad: wp.array(dtype=scalar)):
        # dL/dx^ (free: W d_z; pinned: dL/dz plus the push), dL/dobstacle, dL/dm_i = -dL/dx^_i . (z_i - x^_i) / m_i.
        # A free particle whose d_z the adjoint left as it was (d_z_in: in no active contact) passes dL/dz on exactly,
        # as in a step, or a world, without contacts (W W^-1 g is g only up to rounding)
        i = wp.tid()
        if i < cloth_count:
            g = wp.vec3d(grad_z[i]) + grad_const[i]
            m = wp.float64(0.0)
            if inv_mass[i] > wp.float64(0.0):
                if wp.length_sq(d_z[i] - d_z_in[i]) > wp.float64(0.0):
                    g = d_z[i] / inv_mass[i]
                m = -wp.dot(g, z[i] - x_hat[i]) * inv_mass[i]
            x_hat_grad[i] = x_hat_grad[i] + vec3(g)
            mass_grad[i] = mass_grad[i] + scalar(m)
        else:
            o = i - cloth_count
            obstacle_grad[o] = obstacle_grad[o] + vec3(grad_const[i])

    @wp.kernel(enable_backward=False)
    def geometry_gradients(grad_n: wp.array(dtype=wp.vec3d), grad_w: wp.array(dtype=wp.vec4d),
                           grad_target: wp.array(dtype=wp.float64), offset: int,
                           normal_grad: wp.array(dtype=vec3), weight_grad: wp.array(dtype=vec4),
                           target_grad: wp.array(dtype=scalar)):
        j = wp.tid()
        normal_grad[j] = normal_grad[j] + vec3(grad_n[offset + j])
        weight_grad[j] = weight_grad[j] + vec4(grad_w[offset + j])
        target_grad[j] = target_grad[j] + scalar(grad_target[offset + j])

    @wp.kernel(enable_backward=False)
    def largest_strain(x_hat: wp.array(dtype=vec3), z: wp.array(dtype=vec3), ends: wp.array2d(dtype=wp.int32),
                       rest: wp.array(dtype=wp.float64), limit: wp.float64, over: wp.array(dtype=wp.int32)):
        # the projection-strain guard's test (warpcloth/collision/stage.py): over[0] = 1 where an edge's strain is
        # above the limit (the host names the edge only then)
        e = wp.tid()
        a = ends[e, 0]
        b = ends[e, 1]
        grown = wp.float64(wp.length(z[a] - z[b])) - wp.float64(wp.length(x_hat[a] - x_hat[b]))
        if grown / rest[e] > limit:
            over[0] = 1

    return SimpleNamespace(largest_strain=largest_strain, positions64=positions64, inverse_mass=inverse_mass,
                           append_geometry=append_geometry, cloth_positions=cloth_positions,
                           scaled_gradient=scaled_gradient, push_contacts=push_contacts,
                           position_gradients=position_gradients,
                           geometry_gradients=geometry_gradients)
