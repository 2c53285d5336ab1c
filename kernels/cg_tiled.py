"""The tiled CG (CUDA's backend for worlds that fit a thread block): a world's whole preconditioned CG on the
threads of one block, one launch a solve, its dot products tile reductions."""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.block_matrix import block_matrix_kernels
from warpcloth.kernels.blocks import block_barrier, block_sum
from warpcloth.kernels.multigrid import multigrid_kernels
from warpcloth.kernels.types import per_precision, types

wp.set_module_options({"enable_backward": False})


@per_precision
def tiled_cg_kernels(scalar):
    t = types(scalar)
    vec3, mat33 = t.vec3, t.mat33
    bm, mgk = block_matrix_kernels(scalar), multigrid_kernels(scalar)
    BlockMatrix, jacobi_inverse = bm.BlockMatrix, bm.jacobi_inverse
    add_pair_product, add_pair_products = bm.add_pair_product, bm.add_pair_products
    Multigrid, tiled_multigrid_setup, tiled_v_cycle = mgk.Multigrid, mgk.tiled_multigrid_setup, mgk.tiled_v_cycle

    # Under Warp's deterministic mode (wp.config.deterministic set before warpcloth is imported) no kernel may both
    # write an array directly and add to it atomically: the tiled CG then adds the pairs' products on one thread per
    # world, in pair order (a fixed order, as cg_sequential does), instead of a pair per thread.
    ordered_pairs = wp.get_module_options(__name__)["deterministic"] != wp.DeterministicMode.NOT_GUARANTEED
    @wp.func
    def add_row_products(A: BlockMatrix, p: wp.array(dtype=vec3), q: wp.array(dtype=vec3), lo: int, hi: int,
                         lane: int, stride: int):
        """q = (A p) on rows [lo, hi) from full rows (no scatter, so no two threads write one row), the rows
        ``lane, lane + stride, ...``; returns this thread's share of p . q (float64)."""
        pq = wp.float64(0.0)
        i = lo + lane
        while i < hi:
            acc = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
            for k in range(A.offsets[i], A.offsets[i + 1]):
                acc += A.values[k] * p[A.columns[k]]
            q[i] = acc
            pq += wp.float64(wp.dot(p[i], acc))
            i += stride
        return pq

    @wp.func
    def add_world_pair_products(A: BlockMatrix, p: wp.array(dtype=vec3), q: wp.array(dtype=vec3), sign: scalar,
                                world: int, lane: int, stride: int):
        """q += sign (the cross blocks of ``world``'s pairs) p, a pair per thread (atomic adds); returns this
        thread's share of p . (that product)."""
        pq = wp.float64(0.0)
        k = A.pair_world_start[world] + lane
        while k < A.pair_world_start[world + 1]:
            pq += add_pair_product(A, k, p, q, sign)
            k += stride
        return pq

    def tiled_cg(with_multigrid: bool):
        # named for its preconditioner: a CPU graph finds a kernel by name (kernels/implicit.py, element_kernel_pair)
        @wp.kernel(name="cg_tiled_multigrid" if with_multigrid else "cg_tiled")
        def cg_tiled(
            A: BlockMatrix,
            b: wp.array(dtype=vec3),
            rtol: wp.float64,
            atol: wp.float64,
            max_iters: int,
            preconditioner: int,
            mg: Multigrid,
            omega: scalar,
            warm_start: int,
            guess: wp.array(dtype=vec3),
            # scratch:
            r: wp.array(dtype=vec3),
            z: wp.array(dtype=vec3),
            p: wp.array(dtype=vec3),
            q: wp.array(dtype=vec3),
            other: wp.array(dtype=vec3),
            precond: wp.array(dtype=mat33),
            world_start: wp.array(dtype=wp.int32),
            # out: per world [iterations, relative (recursive) residual, converged (0/1)]
            x: wp.array(dtype=vec3),
            info: wp.array2d(dtype=wp.float64),
        ):
            # The whole preconditioned CG of one world in one thread block (launch_tiled, one block per world): its
            # threads share the rows, and the dot products are tile reductions, which double as the barriers between
            # the phases of an iteration. One launch a solve and no host round trip: the parallel form of
            # cg_sequential, for CUDA. Each world stops when it converges, as with cg_sequential, and the reductions
            # run in a fixed order, so a world's result does not depend on the other worlds. ``preconditioner``: 0
            # Jacobi, 1 block Jacobi; with_multigrid: the multigrid instead (``mg``: the parallel V-cycle, damped
            # block-Jacobi sweeps with ``omega``, on the block's threads; ``precond`` then holds every level's diagonal
            # inverses, ``other`` is the V-cycle's scratch). A kernel of its own, so that the block-Jacobi form's
            # registers do not grow by the V-cycle's.
            w, lane = wp.tid()
            stride = wp.block_dim()
            lo = world_start[w]
            hi = world_start[w + 1]
            zero = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
            pairs = A.pair_count > 0
            use_block = wp.where(preconditioner == 0, 0, 1)
            bb = wp.float64(0.0)
            i = lo + lane
            while i < hi:
                precond[i] = jacobi_inverse(A.values[A.diag_slot[i]], use_block)
                if warm_start != 0:
                    x[i] = guess[i]
                else:
                    x[i] = zero
                bb += wp.float64(wp.dot(b[i], b[i]))
                i += stride
            bb = block_sum(bb)
            if wp.static(with_multigrid):
                tiled_multigrid_setup(A, mg, precond, w, lane, stride)
            if warm_start != 0:
                add_row_products(A, x, r, lo, hi, lane, stride)  # r = A x0 for now
                if pairs:
                    block_barrier()
                    if wp.static(ordered_pairs):
                        if lane == 0:
                            add_pair_products(A, x, r, scalar(1.0), w)
                    else:
                        add_world_pair_products(A, x, r, scalar(1.0), w, lane, stride)
                block_barrier()
            rr = wp.float64(0.0)
            rz = wp.float64(0.0)
            i = lo + lane
            while i < hi:
                ri = b[i]
                if warm_start != 0:
                    ri = ri - r[i]
                r[i] = ri
                rr += wp.float64(wp.dot(ri, ri))
                if not wp.static(with_multigrid):
                    zi = precond[i] * ri
                    p[i] = zi
                    rz += wp.float64(wp.dot(ri, zi))
                i += stride
            if wp.static(with_multigrid):
                block_barrier()  # every r written before the V-cycle reads it
                tiled_v_cycle(A, mg, precond, r, z, other, omega, w, lane, stride)
                i = lo + lane
                while i < hi:
                    p[i] = z[i]
                    rz += wp.float64(wp.dot(r[i], z[i]))
                    i += stride
            rr = block_sum(rr)
            rz = block_sum(rz)
            threshold = wp.max(rtol * wp.sqrt(bb), atol)
            rnorm = wp.sqrt(rr)
            it = int(0)
            while it < max_iters and rnorm > threshold:  # the same on every thread: reduced values only
                pq = add_row_products(A, p, q, lo, hi, lane, stride)
                if pairs:
                    block_barrier()
                    if wp.static(ordered_pairs):
                        if lane == 0:
                            pq += add_pair_products(A, p, q, scalar(1.0), w)
                    else:
                        pq += add_world_pair_products(A, p, q, scalar(1.0), w, lane, stride)
                pq = block_sum(pq)
                alpha = scalar(rz / pq)
                rr = wp.float64(0.0)
                rz_new = wp.float64(0.0)
                i = lo + lane
                while i < hi:
                    xi = x[i] + alpha * p[i]
                    ri = r[i] - alpha * q[i]
                    x[i] = xi
                    r[i] = ri
                    rr += wp.float64(wp.dot(ri, ri))
                    if not wp.static(with_multigrid):
                        zi = precond[i] * ri
                        z[i] = zi
                        rz_new += wp.float64(wp.dot(ri, zi))
                    i += stride
                if wp.static(with_multigrid):
                    block_barrier()
                    tiled_v_cycle(A, mg, precond, r, z, other, omega, w, lane, stride)
                    i = lo + lane
                    while i < hi:
                        rz_new += wp.float64(wp.dot(r[i], z[i]))
                        i += stride
                rr = block_sum(rr)
                rz_new = block_sum(rz_new)
                beta = scalar(rz_new / rz)
                rz = rz_new
                i = lo + lane
                while i < hi:
                    p[i] = z[i] + beta * p[i]
                    i += stride
                block_barrier()  # every p written before the next product reads it
                rnorm = wp.sqrt(rr)
                it += 1
            if lane == 0:
                info[w, 0] = wp.float64(it)
                info[w, 1] = rnorm / wp.max(wp.sqrt(bb), wp.float64(1.0e-300))
                info[w, 2] = wp.where(rnorm <= threshold, wp.float64(1.0), wp.float64(0.0))

        return cg_tiled

    cg_tiled = tiled_cg(False)
    cg_tiled_multigrid = tiled_cg(True)
    return SimpleNamespace(cg_tiled=cg_tiled, cg_tiled_multigrid=cg_tiled_multigrid)
