"""Conjugate-gradient kernels for the 3x3-block system, and the scatter of the solve's adjoint onto A.

Why a whole CG in one launch: on the CPU Warp runs each kernel on one thread and a launch costs ~20 us, while
``warp.optim.linear.cg`` spends most of its time in tile-based dot products that are slow there (measured in
``benchmarks/cg_solvers.py``). One sequential launch that loops over rows and iterations avoids both costs.
On CUDA the library solver (many threads, graph capture) is the right tool, and the host code uses it there.
Block SSOR's Gauss-Seidel sweeps are natural on one thread (~3.5x fewer iterations than block Jacobi at 64x64).
Eisenstat's trick (one product per iteration instead of three passes) was tried and measured 1.3x faster, but lost
an order of magnitude of accuracy in float32 (error vs a float64 solve 7e-5 against 3e-6 at 64x64), so it is not used.
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import per_precision, types

wp.set_module_options({"enable_backward": False})


@per_precision
def linear_kernels(scalar):
    t = types(scalar)
    vec3, vec4, mat33 = t.vec3, t.vec4, t.mat33

    @wp.struct
    class BlockMatrix:
        # A symmetric 3x3-block matrix: blocks on the model's fixed pattern (row i's are values[offsets[i]:
        # offsets[i + 1]] in columns columns[...], its diagonal block at diag_slot[i]) plus, matrix-free, the cross
        # blocks w_a w_b K (a != b) of pair_count proximity pairs (their own blocks w_a^2 K are in the pattern's
        # diagonal; warpcloth/collision/proximity.py).
        offsets: wp.array(dtype=wp.int32)
        columns: wp.array(dtype=wp.int32)
        diag_slot: wp.array(dtype=wp.int32)
        values: wp.array(dtype=mat33)
        pair_count: int
        pair_nodes: wp.array2d(dtype=wp.int32)
        pair_w: wp.array(dtype=vec4)
        pair_k: wp.array(dtype=mat33)

    @wp.func
    def add_pair_product(A: BlockMatrix, k: int, p: wp.array(dtype=vec3), q: wp.array(dtype=vec3), sign: scalar):
        """q += sign * (pair k's cross blocks) p; returns p . (that product), in float64."""
        w = A.pair_w[k]
        K = A.pair_k[k]
        s = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        for a in range(4):
            if w[a] != scalar(0.0):
                s += w[a] * p[A.pair_nodes[k, a]]
        Ks = K * s
        pq = wp.float64(wp.dot(s, Ks))
        for a in range(4):
            if w[a] != scalar(0.0):
                node = A.pair_nodes[k, a]
                own = K * (w[a] * p[node])
                wp.atomic_add(q, node, sign * (w[a] * (Ks - own)))
                pq -= wp.float64(w[a] * wp.dot(p[node], own))
        return pq

    @wp.func
    def add_pair_products(A: BlockMatrix, p: wp.array(dtype=vec3), q: wp.array(dtype=vec3), sign: scalar):
        """q += sign * (the pairs' cross blocks) p; returns p . (that product), in float64."""
        pq = wp.float64(0.0)
        for k in range(A.pair_count):
            pq += add_pair_product(A, k, p, q, sign)
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

    @wp.func
    def ssor_apply(
        A: BlockMatrix,
        dinv: wp.array(dtype=mat33),
        omega: scalar,
        r: wp.array(dtype=vec3),
        lower: wp.array(dtype=vec3),
        z: wp.array(dtype=vec3),
    ):
        """z = M^-1 r for block SSOR, M = w/(2-w) (D/w + L) D^-1 (D/w + U), reading only the upper blocks.

        Forward sweep w_i = omega D_i^-1 (r_i - sum_{j<i} A_ij w_j), the lower sums gathered by scattering
        A_ij^T w_i to later rows; backward sweep z_i = (2 - omega) w_i - omega D_i^-1 sum_{j>i} A_ij z_j.
        Returns r.z (float64).
        """
        n = r.shape[0]
        offsets, columns, diag_slot, values = A.offsets, A.columns, A.diag_slot, A.values
        zero = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        for i in range(n):
            lower[i] = zero
        for i in range(n):
            w = omega * (dinv[i] * (r[i] - lower[i]))
            z[i] = w
            for k in range(diag_slot[i] + 1, offsets[i + 1]):
                j = columns[k]
                lower[j] = lower[j] + wp.transpose(values[k]) * w
        rz = wp.float64(0.0)
        for ii in range(n):
            i = n - 1 - ii
            upper = zero
            for k in range(diag_slot[i] + 1, offsets[i + 1]):
                upper += values[k] * z[columns[k]]
            zi = (scalar(2.0) - omega) * z[i] - omega * (dinv[i] * upper)
            z[i] = zi
            rz += wp.float64(wp.dot(r[i], zi))
        return rz

    @wp.kernel
    def cg_sequential(
        A: BlockMatrix,
        b: wp.array(dtype=vec3),
        rtol: wp.float64,
        atol: wp.float64,
        max_iters: int,
        preconditioner: int,
        omega: scalar,
        warm_start: int,
        guess: wp.array(dtype=vec3),
        # scratch:
        r: wp.array(dtype=vec3),
        z: wp.array(dtype=vec3),
        p: wp.array(dtype=vec3),
        q: wp.array(dtype=vec3),
        precond: wp.array(dtype=mat33),
        # out: [iterations, relative (recursive) residual, converged (0/1)]
        x: wp.array(dtype=vec3),
        info: wp.array(dtype=wp.float64),
    ):
        # Launched with dim 1: the whole preconditioned CG loop runs on one thread. Dot products accumulate in
        # float64 so float32 systems still reach tight relative tolerances. preconditioner: 0 Jacobi,
        # 1 block Jacobi, 2 block SSOR (its sequential sweeps suit the one-thread loop; ~3x fewer iterations).
        # With warm_start, the solve starts from ``guess`` (which may be x itself), else from zero.
        n = b.shape[0]
        offsets, columns, diag_slot, values = A.offsets, A.columns, A.diag_slot, A.values
        if warm_start != 0:
            for i in range(n):
                x[i] = guess[i]
        ssor = preconditioner == 2
        bb = wp.float64(0.0)
        rr = wp.float64(0.0)
        rz = wp.float64(0.0)
        for i in range(n):
            precond[i] = jacobi_inverse(values[diag_slot[i]], wp.where(preconditioner == 0, 0, 1))
            ri = b[i]
            if warm_start != 0:
                for k in range(offsets[i], offsets[i + 1]):
                    ri -= values[k] * x[columns[k]]
            else:
                x[i] = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
            r[i] = ri
            bb += wp.float64(wp.dot(b[i], b[i]))
        if warm_start != 0:
            add_pair_products(A, x, r, scalar(-1.0))
        for i in range(n):
            rr += wp.float64(wp.dot(r[i], r[i]))
        if ssor:
            rz = ssor_apply(A, precond, omega, r, q, z)
        else:
            for i in range(n):
                z[i] = precond[i] * r[i]
                rz += wp.float64(wp.dot(r[i], z[i]))
        for i in range(n):
            p[i] = z[i]
            q[i] = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        threshold = wp.max(rtol * wp.sqrt(bb), atol)
        rnorm = wp.sqrt(rr)
        it = int(0)
        while it < max_iters and rnorm > threshold:
            # q = A p reading only the diagonal and upper blocks (A is symmetric, A_ji = A_ij^T): half the memory
            # traffic of a full product. Row i's q is complete once row i is done, so p.q accumulates on the way.
            pq = wp.float64(0.0)
            for i in range(n):
                pi = p[i]
                s = diag_slot[i]
                acc = q[i] + values[s] * pi
                for k in range(s + 1, offsets[i + 1]):
                    j = columns[k]
                    a = values[k]
                    acc += a * p[j]
                    q[j] = q[j] + wp.transpose(a) * pi
                q[i] = acc
                pq += wp.float64(wp.dot(pi, acc))
            pq += add_pair_products(A, p, q, scalar(1.0))
            alpha = scalar(rz / pq)
            rr = wp.float64(0.0)
            rz_new = wp.float64(0.0)
            for i in range(n):
                x[i] = x[i] + alpha * p[i]
                r[i] = r[i] - alpha * q[i]
                rr += wp.float64(wp.dot(r[i], r[i]))
                if not ssor:
                    z[i] = precond[i] * r[i]
                    rz_new += wp.float64(wp.dot(r[i], z[i]))
            if ssor:
                rz_new = ssor_apply(A, precond, omega, r, q, z)
            beta = scalar(rz_new / rz)
            rz = rz_new
            for i in range(n):
                p[i] = z[i] + beta * p[i]
                q[i] = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
            rnorm = wp.sqrt(rr)
            it += 1
        info[0] = wp.float64(it)
        info[1] = rnorm / wp.max(wp.sqrt(bb), wp.float64(1.0e-300))
        info[2] = wp.where(rnorm <= threshold, wp.float64(1.0), wp.float64(0.0))

    @wp.kernel
    def pair_product(A: BlockMatrix, x: wp.array(dtype=vec3), alpha: scalar, z: wp.array(dtype=vec3)):
        # z += alpha * (pair k's cross blocks) x, one thread per pair (the warp backend's matrix-free term)
        add_pair_product(A, wp.tid(), x, z, alpha)

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
        cg_sequential=cg_sequential,
        pair_product=pair_product,
        solve_adjoint_scatter=solve_adjoint_scatter,
    )

