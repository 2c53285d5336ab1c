"""The 3x3-block matrix every CG backend solves with (``BlockMatrix``), the functions on it the CG kernels share
(the proximity pairs' products, the Jacobi inverse), and the scatter of a solve's adjoint onto its blocks."""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import per_precision, types

wp.set_module_options({"enable_backward": False})


@per_precision
def block_matrix_kernels(scalar):
    t = types(scalar)
    vec3, vec4, mat33 = t.vec3, t.vec4, t.mat33

    @wp.struct
    class BlockMatrix:
        # A symmetric 3x3-block matrix: blocks on the model's fixed pattern (row i's are values[offsets[i]:
        # offsets[i + 1]] in columns columns[...], its diagonal block at diag_slot[i]) plus, matrix-free, the cross
        # blocks w_a w_b K (a != b) of pair_count proximity pairs (their own blocks w_a^2 K are in the pattern's
        # diagonal; warpcloth/solver/proximity.py).
        offsets: wp.array(dtype=wp.int32)
        columns: wp.array(dtype=wp.int32)
        diag_slot: wp.array(dtype=wp.int32)
        values: wp.array(dtype=mat33)
        pair_count: int
        pair_world_start: wp.array(dtype=wp.int32)  # world w's pairs are [start[w], start[w + 1])
        pair_nodes: wp.array2d(dtype=wp.int32)
        pair_w: wp.array(dtype=vec4)
        pair_k: wp.array(dtype=mat33)
    @wp.func
    def pair_cross(A: BlockMatrix, k: int, p: wp.array(dtype=vec3), a: int, Ks: vec3):
        """Pair k's cross blocks times p on its node a: w_a (K s - K w_a p_a), with Ks = K s; and
        w_a p_a . K w_a p_a (float64), what p . (that product) takes off p_a's share of s . K s."""
        w = A.pair_w[k][a]
        node = A.pair_nodes[k, a]
        own = A.pair_k[k] * (w * p[node])
        return w * (Ks - own), wp.float64(w * wp.dot(p[node], own))

    @wp.func
    def pair_start(A: BlockMatrix, k: int, p: wp.array(dtype=vec3)):
        """K s with s = sum_a w_a p_a (pair k's weighted positions), and s . K s (float64)."""
        w = A.pair_w[k]
        s = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        for a in range(4):
            if w[a] != scalar(0.0):
                s += w[a] * p[A.pair_nodes[k, a]]
        Ks = A.pair_k[k] * s
        return Ks, wp.float64(wp.dot(s, Ks))

    @wp.func
    def add_pair_product(A: BlockMatrix, k: int, p: wp.array(dtype=vec3), q: wp.array(dtype=vec3), sign: scalar):
        """q += sign * (pair k's cross blocks) p, by atomic adds (threads share nodes); returns p . (that product),
        in float64."""
        Ks, pq = pair_start(A, k, p)
        for a in range(4):
            if A.pair_w[k][a] != scalar(0.0):
                cross, own = pair_cross(A, k, p, a, Ks)
                wp.atomic_add(q, A.pair_nodes[k, a], sign * cross)
                pq -= own
        return pq

    @wp.func
    def add_pair_products(A: BlockMatrix, p: wp.array(dtype=vec3), q: wp.array(dtype=vec3), sign: scalar,
                          world: int):
        """q += sign * (the cross blocks of ``world``'s pairs) p on one thread, in pair order (plain writes: no
        other thread touches the world's nodes); returns p . (that product), in float64."""
        pq = wp.float64(0.0)
        for k in range(A.pair_world_start[world], A.pair_world_start[world + 1]):
            Ks, pk = pair_start(A, k, p)
            for a in range(4):
                if A.pair_w[k][a] != scalar(0.0):
                    node = A.pair_nodes[k, a]
                    cross, own = pair_cross(A, k, p, a, Ks)
                    q[node] = q[node] + sign * cross
                    pk -= own
            pq += pk
        return pq

    @wp.func
    def jacobi_inverse(block: mat33, use_block: int):
        if use_block != 0:
            return wp.inverse(block)
        zero = scalar(0.0)
        return mat33(
            scalar(1.0) / block[0, 0], zero, zero,
            zero, scalar(1.0) / block[1, 1], zero,
            zero, zero, scalar(1.0) / block[2, 2],
        )

    @wp.kernel
    def solve_adjoint_scatter(
        A: BlockMatrix,
        lam: wp.array(dtype=vec3),
        solution: wp.array(dtype=vec3),
        # out:
        values_grad: wp.array(dtype=mat33),
        b_grad: wp.array(dtype=vec3),
    ):
        # dL/db = lam and dL/dA_ij = -lam_i dv_j^T on stored blocks (SPEC §4.1)
        i = wp.tid()
        b_grad[i] = b_grad[i] + lam[i]
        for k in range(A.offsets[i], A.offsets[i + 1]):
            values_grad[k] = values_grad[k] - wp.outer(lam[i], solution[A.columns[k]])
    return SimpleNamespace(
        BlockMatrix=BlockMatrix,
        pair_cross=pair_cross,
        pair_start=pair_start,
        add_pair_product=add_pair_product,
        add_pair_products=add_pair_products,
        jacobi_inverse=jacobi_inverse,
        solve_adjoint_scatter=solve_adjoint_scatter,
    )
