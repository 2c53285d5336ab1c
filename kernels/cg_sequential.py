"""The sequential CG (the CPU's backend): a world's whole preconditioned CG on one thread, one launch a solve.
Why: docs/decisions.md, 'A whole CG in one launch on the CPU'."""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.block_matrix import block_matrix_kernels
from warpcloth.kernels.multigrid import multigrid_kernels
from warpcloth.kernels.types import per_precision, types

wp.set_module_options({"enable_backward": False})


@per_precision
def sequential_cg_kernels(scalar):
    t = types(scalar)
    vec3, mat33 = t.vec3, t.mat33
    bm, mgk = block_matrix_kernels(scalar), multigrid_kernels(scalar)
    BlockMatrix, add_pair_products, jacobi_inverse = bm.BlockMatrix, bm.add_pair_products, bm.jacobi_inverse
    Multigrid, multigrid_setup, multigrid_apply = mgk.Multigrid, mgk.multigrid_setup, mgk.multigrid_apply

    @wp.func
    def ssor_apply(
        A: BlockMatrix,
        dinv: wp.array(dtype=mat33),
        omega: scalar,
        r: wp.array(dtype=vec3),
        lower: wp.array(dtype=vec3),
        z: wp.array(dtype=vec3),
        lo: int,
        hi: int,
    ):
        """z = M^-1 r for block SSOR, M = w/(2-w) (D/w + L) D^-1 (D/w + U), reading only the upper blocks.

        Forward sweep w_i = omega D_i^-1 (r_i - sum_{j<i} A_ij w_j), the lower sums gathered by scattering
        A_ij^T w_i to later rows; backward sweep z_i = (2 - omega) w_i - omega D_i^-1 sum_{j>i} A_ij z_j.
        Rows [lo, hi) only (one world's). Returns r.z (float64)."""
        offsets, columns, diag_slot, values = A.offsets, A.columns, A.diag_slot, A.values
        zero = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        for i in range(lo, hi):
            lower[i] = zero
        for i in range(lo, hi):
            w = omega * (dinv[i] * (r[i] - lower[i]))
            z[i] = w
            for k in range(diag_slot[i] + 1, offsets[i + 1]):
                j = columns[k]
                lower[j] = lower[j] + wp.transpose(values[k]) * w
        rz = wp.float64(0.0)
        for ii in range(lo, hi):
            i = hi - 1 - ii + lo
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
        mg: Multigrid,
        warm_start: int,
        guess: wp.array(dtype=vec3),
        # scratch:
        r: wp.array(dtype=vec3),
        z: wp.array(dtype=vec3),
        p: wp.array(dtype=vec3),
        q: wp.array(dtype=vec3),
        precond: wp.array(dtype=mat33),
        world_start: wp.array(dtype=wp.int32),
        # out: per world [iterations, relative (recursive) residual, converged (0/1)]
        x: wp.array(dtype=vec3),
        info: wp.array2d(dtype=wp.float64),
    ):
        # Launched with one thread per world: each runs the whole preconditioned CG loop on its world's rows
        # [world_start[w], world_start[w + 1]) (worlds never share a block), so a world stops iterating when it
        # converges and its result is the one a model of that world alone gets. Dot products accumulate in
        # float64 so float32 systems still reach tight relative tolerances. preconditioner: 0 Jacobi,
        # 1 block Jacobi, 2 block SSOR (its sequential sweeps suit the one-thread loop),
        # 3 multigrid (``mg``: a symmetric V-cycle over an aggregation hierarchy).
        # With warm_start, the solve starts from ``guess`` (which may be x itself), else from zero.
        w = wp.tid()
        lo = world_start[w]
        hi = world_start[w + 1]
        offsets, columns, diag_slot, values = A.offsets, A.columns, A.diag_slot, A.values
        if warm_start != 0:
            for i in range(lo, hi):
                x[i] = guess[i]
        ssor = preconditioner == 2
        multigrid = preconditioner == 3
        bb = wp.float64(0.0)
        rr = wp.float64(0.0)
        rz = wp.float64(0.0)
        for i in range(lo, hi):
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
            add_pair_products(A, x, r, scalar(-1.0), w)
        for i in range(lo, hi):
            rr += wp.float64(wp.dot(r[i], r[i]))
        if multigrid:
            if not multigrid_setup(A, mg, precond, w):
                # a coarse pivot <= 0: A is not positive definite; report it as a non-finite residual
                info[w, 0] = wp.float64(0.0)
                info[w, 1] = wp.float64(wp.nan)
                info[w, 2] = wp.float64(0.0)
                return
            rz = multigrid_apply(A, mg, precond, r, z, w)
        elif ssor:
            rz = ssor_apply(A, precond, omega, r, q, z, lo, hi)
        else:
            for i in range(lo, hi):
                z[i] = precond[i] * r[i]
                rz += wp.float64(wp.dot(r[i], z[i]))
        for i in range(lo, hi):
            p[i] = z[i]
            q[i] = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        threshold = wp.max(rtol * wp.sqrt(bb), atol)
        rnorm = wp.sqrt(rr)
        it = int(0)
        while it < max_iters and rnorm > threshold:
            # q = A p reading only the diagonal and upper blocks (A is symmetric, A_ji = A_ij^T): half the memory
            # traffic of a full product. Row i's q is complete once row i is done, so p.q accumulates on the way.
            pq = wp.float64(0.0)
            for i in range(lo, hi):
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
            pq += add_pair_products(A, p, q, scalar(1.0), w)
            alpha = scalar(rz / pq)
            rr = wp.float64(0.0)
            rz_new = wp.float64(0.0)
            for i in range(lo, hi):
                x[i] = x[i] + alpha * p[i]
                r[i] = r[i] - alpha * q[i]
                rr += wp.float64(wp.dot(r[i], r[i]))
                if preconditioner < 2:
                    z[i] = precond[i] * r[i]
                    rz_new += wp.float64(wp.dot(r[i], z[i]))
            if multigrid:
                rz_new = multigrid_apply(A, mg, precond, r, z, w)
            elif ssor:
                rz_new = ssor_apply(A, precond, omega, r, q, z, lo, hi)
            beta = scalar(rz_new / rz)
            rz = rz_new
            for i in range(lo, hi):
                p[i] = z[i] + beta * p[i]
                q[i] = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
            rnorm = wp.sqrt(rr)
            it += 1
        info[w, 0] = wp.float64(it)
        info[w, 1] = rnorm / wp.max(wp.sqrt(bb), wp.float64(1.0e-300))
        info[w, 2] = wp.where(rnorm <= threshold, wp.float64(1.0), wp.float64(0.0))
    return SimpleNamespace(cg_sequential=cg_sequential)
