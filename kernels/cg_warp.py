"""Around warp.optim.linear.cg (the "warp" backend): the pairs' matrix-free term of its operator, its (block)
Jacobi preconditioner and its per-world result; its multigrid is kernels/multigrid.py's ``mg_*`` kernels."""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.block_matrix import block_matrix_kernels
from warpcloth.kernels.types import per_precision, types

wp.set_module_options({"enable_backward": False})


@per_precision
def warp_cg_kernels(scalar):
    t = types(scalar)
    vec3, mat33 = t.vec3, t.mat33
    bm = block_matrix_kernels(scalar)
    BlockMatrix, add_pair_product, jacobi_inverse = bm.BlockMatrix, bm.add_pair_product, bm.jacobi_inverse

    @wp.kernel
    def diagonal_inverse(A: BlockMatrix, use_block: int, precond: wp.array(dtype=mat33)):
        # the (block) Jacobi preconditioner of the warp backend, rebuilt from each system's diagonal blocks
        i = wp.tid()
        precond[i] = jacobi_inverse(A.values[A.diag_slot[i]], use_block)

    @wp.kernel
    def apply_diagonal(precond: wp.array(dtype=mat33), x: wp.array(dtype=vec3), y: wp.array(dtype=vec3),
                       alpha: scalar, beta: scalar, z: wp.array(dtype=vec3)):
        # z = alpha M^-1 x + beta y (warp.optim.linear's matvec contract)
        i = wp.tid()
        zi = alpha * (precond[i] * x[i])
        if beta != scalar(0.0):
            zi += beta * y[i]
        z[i] = zi

    @wp.kernel
    def warp_cg_info(
        iterations: wp.array(dtype=int),
        r_norm_sq: wp.array(dtype=scalar),
        atol_sq: wp.array(dtype=scalar),
        rtol: wp.float64,
        # out: per world [iterations, relative residual, converged (0/1)], as cg_sequential writes it
        info: wp.array2d(dtype=wp.float64),
    ):
        # warp.optim.linear.cg leaves |r|^2 and its threshold max(rtol |b|, atol)^2 per world on the device; the
        # relative residual |r| / |b| is |r| rtol / threshold where the relative tolerance sets the threshold
        w = wp.tid()
        r = wp.sqrt(wp.float64(r_norm_sq[w]))
        threshold = wp.sqrt(wp.float64(atol_sq[w]))
        info[w, 0] = wp.float64(iterations[0])
        info[w, 1] = r * rtol / wp.max(threshold, wp.float64(1.0e-300))
        info[w, 2] = wp.where(r <= threshold, wp.float64(1.0), wp.float64(0.0))

    @wp.kernel
    def pair_product(A: BlockMatrix, x: wp.array(dtype=vec3), alpha: scalar, z: wp.array(dtype=vec3)):
        # z += alpha * (pair k's cross blocks) x, one thread per pair (the warp backend's matrix-free term); a
        # captured step launches at its budget of pairs, more threads than pairs
        k = wp.tid()
        if k < A.pair_world_start[A.pair_world_start.shape[0] - 1]:
            add_pair_product(A, k, x, z, alpha)
    return SimpleNamespace(
        diagonal_inverse=diagonal_inverse,
        apply_diagonal=apply_diagonal,
        warp_cg_info=warp_cg_info,
        pair_product=pair_product,
    )
