"""Proximity repulsion and friction inside the implicit step (ARCSim's, SPEC.md §1.4), differentiated.

Detection (not differentiated) finds, at the start of a step, vertex-face and edge-edge pairs closer than twice the
repulsion thickness delta: for each vertex the closest triangle; for each edge every edge whose closest points lie
inside both, the stiffness fading to 0 near either end. Primitives of neighbouring elements pair only where the
cloth folds onto itself (a vertex over a triangle's interior, edges crossing at more than 30 degrees). Each pair k
has nodes (up to 4: cloth particles, then obstacle vertices) and weights w with sum_i w_i x_i = the gap vector
(VF: w = (1, -b0, -b1, -b2); EE: w = (1 - s, s, -(1 - u), -u)), unit normal n along it, distance
d = n . sum_i w_i x_i.

With c = d - delta, the pair's energy is E(c) = k max(-c, 0)^3 / (6 delta) (k = repulsion stiffness [N/m^3] times
the smaller rest area of the pair's two primitives [m^2], as ARCSim: a vertex's is a third of its triangles', an edge's
a third of its one or two triangles'; against an obstacle, the cloth primitive's): normal force
f_n = k max(-c, 0)^2 / (2 delta) along w_i n, stiffness h = k max(-c, 0) / delta.

One linearised backward-Euler step (Baraff and Witkin) adds, for free nodes i, j of a pair,
    A_ij += w_i w_j K,  b_i += w_i R,   K = dt^2 h n n^T,   R = dt (f_n - h dt (n . u)) n
(u = sum_i w_i V_i: V the start velocity of free nodes, the known end velocity of pinned and obstacle nodes), the
Newton linearisation of the normal force. The own blocks w_i^2 K go on the block diagonal, the cross blocks are
applied matrix-free. The normal impulse is j_n = dt max(f_n - h dt (n . u_end), 0), u_end at the solution.

Friction is Coulomb's law applied to the solved velocities as impulses (after Bridson, Fedkiw and Anderson 2002),
bounded by mu times the normal impulse: it sticks exactly where the bound allows (the relative tangential velocity
goes to 0) and otherwise takes mu times the normal impulse off the slip, never reversing it.
- Against obstacles, per particle (one pass, exact): its pairs' loads add up, L = sum_k |w_k| dt f_n,k (the normal
  forces at the step's start, as ARCSim), their normal forces give the tangent plane (n along
  sum_k w_k f_n,k n_k), and the obstacle's velocity there is the load-weighted mean of its contact points'. The
  particle's slip s against it is removed if |s| <= mu L / m, else shortened by mu L / m.
- Between cloth pieces, per pair (both sides move): FRICTION_SWEEPS projected Jacobi sweeps, each adding to the
  pair's impulse P the one that stops its slip (effective mass 1 / sum_i w_i^2 c_i / m_i, each particle's mass
  split among the c_i pairs it is in) and clipping P to the disk |P| <= mu j_n; node i receives -w_i P / m_i.
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.geometry import KEY_END, box_rounding, segment_parameters, triangle_barycentric, world_root
from warpcloth.kernels.types import per_precision, types

COINCIDENT = 1.0e-9
"""A pair whose points are closer than this times the thickness has no direction from its gap; its normal comes
from its primitives (crossing_normal): a cloth laid exactly on an obstacle, or BDF2's blend crossing one."""
VERTEX_FACE = 0
EDGE_EDGE = 1
EDGE_FADE = 0.1
"""Fraction of an edge at each end over which an edge-edge pair's stiffness fades to 0 (kernels edge_fade)."""
FRICTION_SWEEPS = 16
"""Projected Jacobi sweeps of the cloth-cloth friction impulses a step (module docstring)."""
NEIGHBOUR_EDGE_SINE2 = 0.25
"""Edges of neighbouring elements make a pair only when they cross at more than asin(sqrt(this)) = 30 degrees."""


@wp.func
def in_row(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32), row: int, col: int):
    """Whether block (row, col) is in the block pattern: the two cloth nodes share an element."""
    for k in range(offsets[row], offsets[row + 1]):
        if columns[k] == col:
            return True
    return False


@per_precision
def proximity_kernels(scalar):
    t = types(scalar)
    vec3, vec4, mat33 = t.vec3, t.vec4, t.mat33

    @wp.func
    def neighbours(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32), cloth_count: int,
                   a: int, b: int):
        # cloth nodes that share an element are the mesh's own neighbours, not a fold touching itself
        return a < cloth_count and b < cloth_count and in_row(offsets, columns, a, b)

    @wp.func
    def edge_fade(s: scalar):
        # An edge-edge pair's weight along each edge: 1 in the middle, falling linearly to 0 within EDGE_FADE of
        # either end, where the vertex-face pairs of the end vertex take over: the pair appears and vanishes with
        # zero force, so the forces stay continuous as closest points slide along the edges.
        return wp.clamp(wp.min(s, scalar(1.0) - s) / scalar(EDGE_FADE), scalar(0.0), scalar(1.0))

    @wp.kernel(enable_backward=False)
    def primitive_boxes(x: wp.array(dtype=vec3), indices: wp.array2d(dtype=wp.int32), radius: float,
                        # out:
                        lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
        # a target's box grown by the search radius: a query box, grown by rounding alone, meets it wherever the
        # two primitives may be closer than the radius (growing both would search twice as far)
        i = wp.tid()
        lo = wp.vec3(x[indices[i, 0]])
        hi = lo
        for c in range(1, indices.shape[1]):
            p = wp.vec3(x[indices[i, c]])
            lo = wp.min(lo, p)
            hi = wp.max(hi, p)
        g = radius + box_rounding(lo, hi)
        pad = wp.vec3(g, g, g)
        lowers[i] = lo - pad
        uppers[i] = hi + pad

    @wp.struct
    class PairSearch:
        # What the pair queries share: the block pattern (cloth neighbours), the search radius, and the output
        # buffer (a counter that may pass its capacity: the host reports the overflow).
        offsets: wp.array(dtype=wp.int32)
        columns: wp.array(dtype=wp.int32)
        cloth_count: int
        radius: scalar
        count: wp.array(dtype=wp.int32)
        pair_nodes: wp.array2d(dtype=wp.int32)
        pair_kind: wp.array(dtype=wp.int32)
        pair_area: wp.array(dtype=scalar)
        node_world: wp.array(dtype=wp.int32)  # the world of every node; BVHs grouped by world where grouped != 0
        grouped: int
        # each pair's sort key (world, query row, target primitive) and its slot, by which the pairs are sorted
        # (warpcloth/solver/proximity.py detect): query rows numbered across the queries (row_count in all),
        # targets below target_count
        keys: wp.array(dtype=wp.int64)
        slot_of: wp.array(dtype=wp.int32)
        row_count: wp.int64
        target_count: wp.int64

    @wp.func
    def emit(search: PairSearch, nodes: wp.vec4i, kind: int, area: scalar, row: int, target: int):
        k = wp.atomic_add(search.count, 0, 1)
        if k < search.pair_kind.shape[0]:
            for c in range(4):
                search.pair_nodes[k, c] = nodes[c]
            search.pair_kind[k] = kind
            search.pair_area[k] = area
            world = wp.int64(search.node_world[nodes[0]])
            search.keys[k] = (world * search.row_count + wp.int64(row)) * search.target_count + wp.int64(target)
            search.slot_of[k] = k

    @wp.func
    def near(search: PairSearch, a: int, b: int):
        return neighbours(search.offsets, search.columns, search.cloth_count, a, b)

    @wp.kernel(enable_backward=False)
    def vertex_face_pairs(
        bvh: wp.uint64,
        x: wp.array(dtype=vec3),
        queries: wp.array(dtype=wp.int32),
        triangles: wp.array2d(dtype=wp.int32),
        node_area: wp.array(dtype=scalar),
        triangle_area: wp.array(dtype=scalar),
        search: PairSearch,
        first_row: int,
    ):
        # the closest triangle within radius of each query vertex
        i = wp.tid()
        q = queries[i]
        p = x[q]
        root = world_root(bvh, search.grouped, search.node_world[q])
        if root == -2:
            return
        g = box_rounding(wp.vec3(p), wp.vec3(p))  # the targets' boxes hold the radius (primitive_boxes)
        pad = wp.vec3(g, g, g)
        query = wp.bvh_query_aabb(bvh, wp.vec3(p) - pad, wp.vec3(p) + pad, root)
        j = int(0)
        best = search.radius
        best_j = int(-1)
        while wp.bvh_query_next(query, j):
            a = triangles[j, 0]
            b = triangles[j, 1]
            c = triangles[j, 2]
            if q == a or q == b or q == c:
                continue
            u, v, w = triangle_barycentric(p, x[a], x[b], x[c])
            d = wp.length(p - (u * x[a] + v * x[b] + w * x[c]))
            if not (d < best or (d == best and j < best_j)):  # a tie: the lower index, whatever the BVH's order
                continue
            # a mesh neighbour of the triangle counts only where the cloth folds over it (ARCSim excludes only the
            # triangles around q): its closest point must be interior, so a flat or gently curved cloth has none.
            # (Tested after the distance: the neighbour lookups cost more, and most targets are too far anyway.)
            if near(search, q, a) or near(search, q, b) or near(search, q, c):
                if wp.min(wp.min(u, v), w) <= scalar(0.0):
                    continue
            best = d
            best_j = j
        if best_j >= 0:
            emit(search, wp.vec4i(q, triangles[best_j, 0], triangles[best_j, 1], triangles[best_j, 2]), VERTEX_FACE,
                 wp.min(node_area[q], triangle_area[best_j]), first_row + i, best_j)

    @wp.kernel(enable_backward=False)
    def edge_edge_pairs(
        bvh: wp.uint64,
        x: wp.array(dtype=vec3),
        edges: wp.array2d(dtype=wp.int32),
        targets: wp.array2d(dtype=wp.int32),
        edge_area: wp.array(dtype=scalar),
        target_area: wp.array(dtype=scalar),
        same_set: int,
        search: PairSearch,
        first_row: int,
    ):
        # every target edge within radius whose closest points are inside both edges (within one set: each pair
        # once). Not only the closest: flat sheets tie, and a tie broken either way would move the force.
        i = wp.tid()
        e0 = edges[i, 0]
        e1 = edges[i, 1]
        lo = wp.min(wp.vec3(x[e0]), wp.vec3(x[e1]))
        hi = wp.max(wp.vec3(x[e0]), wp.vec3(x[e1]))
        root = world_root(bvh, search.grouped, search.node_world[e0])
        if root == -2:
            return
        g = box_rounding(lo, hi)  # the targets' boxes hold the radius (primitive_boxes)
        pad = wp.vec3(g, g, g)
        query = wp.bvh_query_aabb(bvh, lo - pad, hi + pad, root)
        j = int(0)
        while wp.bvh_query_next(query, j):
            f0 = targets[j, 0]
            f1 = targets[j, 1]
            if same_set != 0 and j <= i:
                continue
            if e0 == f0 or e0 == f1 or e1 == f0 or e1 == f1:
                continue
            a = x[e1] - x[e0]
            b = x[f1] - x[f0]
            s, u = segment_parameters(x[e0], x[e1], x[f0], x[f1], scalar(1.0e-12))
            d = wp.length((x[e0] + s * a) - (x[f0] + u * b))
            if not (d < search.radius and edge_fade(s) > scalar(0.0) and edge_fade(u) > scalar(0.0)):
                continue
            if near(search, e0, f0) or near(search, e0, f1) or near(search, e1, f0) or near(search, e1, f1):
                # mesh neighbours only where a crease brings crossing edges together: the parallel edges of a
                # fine flat mesh are close too, and must not repel (tested after the distance, as above)
                cross = wp.cross(a, b)
                if wp.dot(cross, cross) < scalar(NEIGHBOUR_EDGE_SINE2) * wp.dot(a, a) * wp.dot(b, b):
                    continue
            emit(search, wp.vec4i(e0, e1, f0, f1), EDGE_EDGE, wp.min(edge_area[i], target_area[j]), first_row + i, j)

    @wp.struct
    class PairInputs:
        # What the pair terms read. Nodes: cloth particles, then obstacle vertices.
        nodes: wp.array2d(dtype=wp.int32)
        kind: wp.array(dtype=wp.int32)
        x: wp.array(dtype=vec3)
        velocity: wp.array(dtype=vec3)
        free: wp.array(dtype=wp.int32)
        area: wp.array(dtype=scalar)  # per pair
        stiffness: wp.array(dtype=scalar)
        friction: wp.array(dtype=scalar)
        cloth_count: int
        thickness: scalar
        dt: scalar
        count: wp.array(dtype=wp.int32)  # [0]: the pairs held, at most the launches' size (a captured step
        # launches its pair kernels at its budget of pairs, and the threads past the count return at once)

    @wp.func
    def pair_weights(p: PairInputs, k: int):
        """Node indices, weights (sum w_i x_i = the gap vector) and the gap vector of pair k."""
        i0 = p.nodes[k, 0]
        i1 = p.nodes[k, 1]
        i2 = p.nodes[k, 2]
        i3 = p.nodes[k, 3]
        x0 = p.x[i0]
        x1 = p.x[i1]
        x2 = p.x[i2]
        x3 = p.x[i3]
        one = scalar(1.0)
        w = vec4()
        if p.kind[k] == VERTEX_FACE:
            u, v, ww = triangle_barycentric(x0, x1, x2, x3)
            w = vec4(one, -u, -v, -ww)
        else:
            s, u = segment_parameters(x0, x1, x2, x3, scalar(1.0e-12))
            w = vec4(one - s, s, u - one, -u)
        gap = w[0] * x0 + w[1] * x1 + w[2] * x2 + w[3] * x3
        return wp.vec4i(i0, i1, i2, i3), w, gap

    @wp.func
    def crossing_normal(p: PairInputs, k: int, idx: wp.vec4i, u: vec3):
        """The normal of a pair whose two points coincide (the gap has no direction: a vertex on its face, edges
        crossing): the face's normal (vertex-face) or the edges' common normal (edge-edge), turned against the
        pair's relative velocity u, the side it came from (kept as it is when u is 0: an obstacle face's own
        orientation, outward for the built-in obstacles)."""
        x0 = p.x[idx[0]]
        x1 = p.x[idx[1]]
        x2 = p.x[idx[2]]
        x3 = p.x[idx[3]]
        g = wp.cross(x2 - x1, x3 - x1)
        if p.kind[k] == EDGE_EDGE:
            e = x1 - x0
            g = wp.cross(e, x3 - x2)
            if wp.length(g) <= scalar(1.0e-30):  # parallel edges: any normal of the first
                g = wp.cross(e, vec3(scalar(1.0), scalar(0.0), scalar(0.0)))
                if wp.length(g) <= scalar(1.0e-30):
                    g = wp.cross(e, vec3(scalar(0.0), scalar(1.0), scalar(0.0)))
        n = wp.normalize(g)
        if wp.dot(n, u) > scalar(0.0):
            n = -n
        return n

    @wp.func
    def pair_normal(p: PairInputs, k: int):
        """(nodes, weights with 0 for nodes that are not free, unit normal, f_n, h, whether an obstacle node is in
        it) of pair k (module docstring)."""
        idx, w, gap = pair_weights(p, k)
        zero = scalar(0.0)
        obstacle = False
        u = vec3()
        for a in range(4):
            node = idx[a]
            if node >= p.cloth_count:
                obstacle = True
            u += w[a] * p.velocity[node]
        d = wp.length(gap)
        n = vec3()
        if d > scalar(COINCIDENT) * p.thickness:
            n = gap / d
        else:
            n = crossing_normal(p, k, idx, u)
        c = d - p.thickness
        # the weights of free nodes (built whole: Warp does not differentiate in-place component writes)
        one = scalar(1.0)
        wf = vec4(w[0] * wp.where(p.free[idx[0]] != 0, one, zero), w[1] * wp.where(p.free[idx[1]] != 0, one, zero),
                  w[2] * wp.where(p.free[idx[2]] != 0, one, zero), w[3] * wp.where(p.free[idx[3]] != 0, one, zero))
        k_rep = p.stiffness[0] * p.area[k]
        if p.kind[k] == EDGE_EDGE:
            k_rep = k_rep * edge_fade(w[1]) * edge_fade(-w[3])
        depth = wp.max(-c, zero)
        f_n = k_rep * depth * depth / (scalar(2.0) * p.thickness)
        h = k_rep * depth / p.thickness
        return idx, w, wf, n, f_n, h, u, obstacle

    @wp.func
    def pair_terms(p: PairInputs, k: int):
        """(nodes, weights with 0 for nodes that are not free, K, R) of pair k (module docstring)."""
        idx, w, wf, n, f_n, h, u, obstacle = pair_normal(p, k)
        dt = p.dt
        K = (dt * dt * h) * wp.outer(n, n)
        R = (dt * (f_n - h * dt * wp.dot(n, u))) * n
        return idx, wf, K, R

    @wp.func
    def normal_impulse(p: PairInputs, idx: wp.vec4i, wf: vec4, n: vec3, f_n: scalar, h: scalar, u: vec3,
                       dv: wp.array(dtype=vec3)):
        """The pair's normal impulse over the step at the solved velocities, dt max(f_n - h dt n . u_end, 0)."""
        u_end = u
        for a in range(4):
            if wf[a] != scalar(0.0):
                u_end += wf[a] * dv[idx[a]]
        return p.dt * wp.max(f_n - h * p.dt * wp.dot(n, u_end), scalar(0.0))

    @wp.kernel
    def obstacle_friction_loads(
        p: PairInputs,
        # out:
        load: wp.array(dtype=scalar),
        push: wp.array(dtype=vec3),
        motion: wp.array(dtype=vec3),
    ):
        # per free cloth particle, what its cloth-obstacle pairs press on it: the normal impulse's size (load) and
        # vector (push), and the load-weighted velocity of the obstacle points it touches (motion)
        k = wp.tid()
        if k >= p.count[0]:
            return
        idx, w, wf, n, f_n, h, u, obstacle = pair_normal(p, k)
        if obstacle:
            # the normal force at the step's start (ARCSim's): the step's own normal impulse, which depends on the
            # solved velocities, made a cloth draped over a box's edge switch between sticking and sliding from one
            # step to the next, and its trajectory (and loss) rough at relative changes of 1e-4 of the density
            j_n = p.dt * f_n
            zero = scalar(0.0)
            surface = vec3()  # the obstacle point: its nodes' velocities by their share of the weights
            total = zero
            for a in range(4):
                if idx[a] >= p.cloth_count:
                    surface += w[a] * p.velocity[idx[a]]
                    total += w[a]
            surface = surface / total
            for a in range(4):
                if wf[a] != zero:
                    share = wp.abs(wf[a]) * j_n
                    wp.atomic_add(load, idx[a], share)
                    wp.atomic_add(push, idx[a], (wf[a] * j_n) * n)
                    wp.atomic_add(motion, idx[a], share * surface)

    @wp.kernel
    def obstacle_friction(
        p: PairInputs,
        dv: wp.array(dtype=vec3),
        load: wp.array(dtype=scalar),
        push: wp.array(dtype=vec3),
        motion: wp.array(dtype=vec3),
        inv_mass: wp.array(dtype=scalar),
        # out:
        change: wp.array(dtype=vec3),
    ):
        # Coulomb's law per particle against the obstacle (module docstring): stop its slip if mu load / m allows,
        # else take mu load / m off it
        i = wp.tid()
        zero = scalar(0.0)
        c = vec3()
        size = wp.length(push[i])
        if load[i] > zero and size > zero:
            n = push[i] / size
            u = p.velocity[i] + dv[i] - motion[i] / load[i]
            slip = u - wp.dot(n, u) * n
            speed = wp.length(slip)
            bound = p.friction[1] * load[i] * inv_mass[i]
            if speed <= bound:
                c = -slip  # sticks: moves with the obstacle
            else:
                c = -(bound / speed) * slip  # slides
        change[i] = c

    @wp.kernel(enable_backward=False)
    def cloth_pair_counts(p: PairInputs, per_node: wp.array(dtype=wp.int32)):
        # how many cloth-cloth pairs each free particle is in (the sweeps' mass splitting)
        k = wp.tid()
        if k < p.count[0]:
            idx, w, gap = pair_weights(p, k)
            cloth = True
            for a in range(4):
                if idx[a] >= p.cloth_count:
                    cloth = False
            if cloth:
                for a in range(4):
                    if p.free[idx[a]] != 0 and w[a] != scalar(0.0):
                        wp.atomic_add(per_node, idx[a], 1)

    @wp.kernel
    def friction_sweep(
        p: PairInputs,
        dv: wp.array(dtype=vec3),
        base: wp.array(dtype=vec3),
        change_in: wp.array(dtype=vec3),
        impulse_in: wp.array(dtype=vec3),
        inv_mass: wp.array(dtype=scalar),
        per_node: wp.array(dtype=wp.int32),
        # out:
        impulse_out: wp.array(dtype=vec3),
        change_out: wp.array(dtype=vec3),
    ):
        # One projected Jacobi sweep over the cloth-cloth pairs (module docstring): each adds the impulse that stops
        # its slip at the velocities so far (dv + base + change_in), with each particle's mass split among its
        # pairs, keeps its total within Coulomb's disk mu j_n, and scatters it onto its nodes (change_out, zeroed)
        k = wp.tid()
        if k >= p.count[0]:
            return
        idx, w, wf, n, f_n, h, u, obstacle = pair_normal(p, k)
        impulse = vec3()
        zero = scalar(0.0)
        if not obstacle:
            j_n = normal_impulse(p, idx, wf, n, f_n, h, u, dv)
            current = u
            compliance = zero  # sum_i w_i^2 c_i / m_i
            for a in range(4):
                if wf[a] != zero:
                    node = idx[a]
                    current += wf[a] * (dv[node] + base[node] + change_in[node])
                    compliance += wf[a] * wf[a] * inv_mass[node] * scalar(per_node[node])
            if compliance > zero:
                slip = current - wp.dot(n, current) * n
                impulse = impulse_in[k] + slip / compliance
                impulse = impulse - wp.dot(n, impulse) * n
                size = wp.length(impulse)
                bound = p.friction[0] * j_n
                if size > bound:  # it slides: Coulomb's bound
                    impulse = (bound / size) * impulse
                for a in range(4):
                    if wf[a] != zero:
                        wp.atomic_add(change_out, idx[a], -(wf[a] * inv_mass[idx[a]]) * impulse)
        impulse_out[k] = impulse

    @wp.kernel
    def assemble_pairs(
        p: PairInputs,
        diag_slot: wp.array(dtype=wp.int32),
        # out:
        values: wp.array(dtype=mat33),
        rhs: wp.array(dtype=vec3),
        pair_w: wp.array(dtype=vec4),
        pair_k: wp.array(dtype=mat33),
    ):
        k = wp.tid()
        if k >= p.count[0]:
            return
        idx, wf, K, R = pair_terms(p, k)
        for a in range(4):
            if wf[a] != scalar(0.0):
                wp.atomic_add(values, diag_slot[idx[a]], (wf[a] * wf[a]) * K)
                wp.atomic_add(rhs, idx[a], wf[a] * R)
        pair_w[k] = wf
        pair_k[k] = K

    @wp.kernel
    def pairs_potential(
        p: PairInputs,
        lam: wp.array(dtype=vec3),
        dv: wp.array(dtype=vec3),
        # out:
        phi: wp.array(dtype=scalar),
    ):
        # the pairs' share of the solve's adjoint, sum_i lam_i . b_i - sum_ij lam_i^T A_ij dv_j, whose gradient (lam
        # and dv held constant) Warp takes (as the element kernels' potential, kernels/implicit.py)
        k = wp.tid()
        if k >= p.count[0]:
            return
        idx, wf, K, R = pair_terms(p, k)
        L = vec3()
        D = vec3()
        for a in range(4):
            if wf[a] != scalar(0.0):
                L += wf[a] * lam[idx[a]]
                D += wf[a] * dv[idx[a]]
        wp.atomic_add(phi, 0, wp.dot(L, R) - wp.dot(L, K * D))

    @wp.kernel
    def node_state(
        cloth_x: wp.array(dtype=vec3),
        cloth_v: wp.array(dtype=vec3),
        pin_dv: wp.array(dtype=vec3),
        particle_pin: wp.array(dtype=wp.int32),
        obstacle_start: wp.array(dtype=vec3),
        obstacle_end: wp.array(dtype=vec3),
        inv_dt: scalar,
        cloth_count: int,
        # out:
        x: wp.array(dtype=vec3),
        velocity: wp.array(dtype=vec3),
    ):
        # positions at the step's start and the velocities the pairs see: free particles' start velocity, pinned
        # particles' prescribed end velocity, obstacles' velocity over the step
        i = wp.tid()
        if i < cloth_count:
            x[i] = cloth_x[i]
            vi = cloth_v[i]
            if particle_pin[i] >= 0:
                vi = vi + pin_dv[i]
            velocity[i] = vi
        else:
            o = i - cloth_count
            x[i] = obstacle_start[o]
            velocity[i] = (obstacle_end[o] - obstacle_start[o]) * inv_dt

    @wp.kernel
    def inverse_mass(mass: wp.array(dtype=scalar), free: wp.array(dtype=wp.int32), cloth_count: int,
                     inv_mass: wp.array(dtype=scalar)):
        # 1 / m for free cloth particles, 0 for pinned particles and obstacle vertices
        i = wp.tid()
        inv = scalar(0.0)
        if i < cloth_count:
            if free[i] != 0:
                inv = scalar(1.0) / mass[i]
        inv_mass[i] = inv

    @wp.kernel(enable_backward=False)
    def hold_pairs(found: wp.array(dtype=wp.int32), size: int, world_count: int,
                   # out:
                   keys: wp.array(dtype=wp.int64), slot_of: wp.array(dtype=wp.int32), held: wp.array(dtype=wp.int32),
                   spill: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int32)):
        # one thread a slot of the launches (at least one): the first min(found, size) pairs are held, the slots
        # after them sort last; whether more were found than the launches hold (a captured step's budget); one
        # world's range (several worlds: geometry.py world_starts, after the sort)
        k = wp.tid()
        count = wp.min(found[0], size)
        if k == 0:
            held[0] = count
            spill[0] = wp.where(found[0] > size, 1, 0)
            if world_count == 1:
                start[0] = 0
                start[1] = count
        if k >= count and k < size:
            keys[k] = KEY_END
            slot_of[k] = k

    @wp.kernel(enable_backward=False)
    def gather_pairs(order: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                     nodes: wp.array2d(dtype=wp.int32), kind: wp.array(dtype=wp.int32), area: wp.array(dtype=scalar),
                     # out:
                     sorted_nodes: wp.array2d(dtype=wp.int32), sorted_kind: wp.array(dtype=wp.int32),
                     sorted_area: wp.array(dtype=scalar)):
        # the held pairs in the order of their keys (order: wp.utils.radix_sort_pairs's)
        k = wp.tid()
        if k < count[0]:
            j = order[k]
            for c in range(4):
                sorted_nodes[k, c] = nodes[j, c]
            sorted_kind[k] = kind[j]
            sorted_area[k] = area[j]

    @wp.kernel
    def add_friction(dv: wp.array(dtype=vec3), obstacle: wp.array(dtype=vec3), cloth: wp.array(dtype=vec3),
                     out: wp.array(dtype=vec3)):
        i = wp.tid()
        out[i] = dv[i] + obstacle[i] + cloth[i]

    return SimpleNamespace(
        PairSearch=PairSearch, primitive_boxes=primitive_boxes, vertex_face_pairs=vertex_face_pairs,
        edge_edge_pairs=edge_edge_pairs, PairInputs=PairInputs, assemble_pairs=assemble_pairs,
        pairs_potential=pairs_potential, node_state=node_state, cloth_pair_counts=cloth_pair_counts,
        friction_sweep=friction_sweep, obstacle_friction_loads=obstacle_friction_loads,
        obstacle_friction=obstacle_friction, inverse_mass=inverse_mass,
        add_friction=add_friction, hold_pairs=hold_pairs, gather_pairs=gather_pairs,
    )
