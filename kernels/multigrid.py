"""The multigrid preconditioner over an aggregation hierarchy (``Multigrid``): the sequential V-cycle on a world's
thread (cg_sequential's) and the parallel one, a launch a stage (``mg_*``) or on a world's block (cg_tiled's)."""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.block_matrix import block_matrix_kernels
from warpcloth.kernels.blocks import block_barrier
from warpcloth.kernels.types import per_precision, types

wp.set_module_options({"enable_backward": False})


@per_precision
def multigrid_kernels(scalar):
    t = types(scalar)
    vec3, mat33 = t.vec3, t.mat33
    BlockMatrix = block_matrix_kernels(scalar).BlockMatrix

    @wp.struct
    class Multigrid:
        # The aggregation hierarchies of a model's worlds (warpcloth/solver/multigrid.py WorldHierarchies) for the
        # multigrid preconditioner. Nodes of all levels are numbered in one flat range: level l is
        # [level_start[l], level_start[l + 1]), level 0 the model's particles, and world w's part of level l is
        # [world_level_lo[w, l], world_level_hi[w, l]) (world w has world_levels[w] levels). The coarse levels' rows
        # (flat node f >= level_start[1]) are row f - level_start[1] of offsets/diag_slot, with flat column ids and
        # sorted columns; their blocks are Galerkin sums P^T A P for a piecewise-constant P, so every fine block
        # just adds into one coarse slot. World w's blocks of level l are those of its rows there.
        levels: int
        level_start: wp.array(dtype=wp.int32)
        world_levels: wp.array(dtype=wp.int32)
        world_level_lo: wp.array2d(dtype=wp.int32)
        world_level_hi: wp.array2d(dtype=wp.int32)
        aggregate: wp.array(dtype=wp.int32)  # flat node -> its aggregate on the next level (-1: pinned, none)
        fine_slot: wp.array(dtype=wp.int32)  # fine block -> level-1 block (-1: a pinned row or column)
        coarse_slot: wp.array(dtype=wp.int32)  # coarse block -> next level's block (-1 on the coarsest level)
        offsets: wp.array(dtype=wp.int32)
        columns: wp.array(dtype=wp.int32)
        diag_slot: wp.array(dtype=wp.int32)
        values: wp.array(dtype=mat33)
        factor: wp.array3d(dtype=wp.float64)  # per world: its coarsest level as a dense matrix, then its Cholesky
        # the maps above inverted, for the parallel forms (no atomics): each coarse node's members on the level
        # before (restriction), and each coarse block's sources (Galerkin sums): blocks of the particles' level
        # (fine_*: level 1's) and of the level before (coarse_*: the others')
        member_start: wp.array(dtype=wp.int32)
        members: wp.array(dtype=wp.int32)
        fine_start: wp.array(dtype=wp.int32)
        fine_sources: wp.array(dtype=wp.int32)
        coarse_start: wp.array(dtype=wp.int32)
        coarse_sources: wp.array(dtype=wp.int32)
        # scratch: the coarse levels' right-hand sides and corrections (flat; the fine part is unused by the
        # sequential form), and the dense solve's vector (per world)
        b: wp.array(dtype=vec3)
        x: wp.array(dtype=vec3)
        work: wp.array2d(dtype=wp.float64)

    # -- the sequential V-cycle (cg_sequential's, on a world's one thread): block Gauss-Seidel smoothing
    @wp.func
    def smooth_down(
        offsets: wp.array(dtype=wp.int32),
        columns: wp.array(dtype=wp.int32),
        diag_slot: wp.array(dtype=wp.int32),
        values: wp.array(dtype=mat33),
        row_base: int,
        lo: int,
        hi: int,
        dinv: wp.array(dtype=mat33),
        rhs: wp.array(dtype=vec3),
        x: wp.array(dtype=vec3),
        aggregate: wp.array(dtype=wp.int32),
        coarse_rhs: wp.array(dtype=vec3),
    ):
        """One forward block Gauss-Seidel sweep from x = 0 on rows [lo, hi), restricting its residual to the next
        level on the way: with (D + L) x = rhs the residual is -U x, and row j's lower blocks, already loaded for
        its own sum, give its part -A_ij x_j = -A_ji^T x_j of every earlier row i's residual."""
        for i in range(lo, hi):
            row = i - row_base
            s = rhs[i]
            for k in range(offsets[row], diag_slot[row]):
                s -= values[k] * x[columns[k]]
            xi = dinv[i] * s
            x[i] = xi
            for k in range(offsets[row], diag_slot[row]):
                a = aggregate[columns[k]]
                if a >= 0:
                    coarse_rhs[a] = coarse_rhs[a] - wp.transpose(values[k]) * xi

    @wp.func
    def smooth_up(
        offsets: wp.array(dtype=wp.int32),
        columns: wp.array(dtype=wp.int32),
        diag_slot: wp.array(dtype=wp.int32),
        values: wp.array(dtype=mat33),
        row_base: int,
        lo: int,
        hi: int,
        dinv: wp.array(dtype=mat33),
        rhs: wp.array(dtype=vec3),
        x: wp.array(dtype=vec3),
        aggregate: wp.array(dtype=wp.int32),
        coarse_x: wp.array(dtype=vec3),
    ):
        """Add the next level's correction, then one backward block Gauss-Seidel sweep (the transpose of the
        forward one, so the V-cycle is symmetric)."""
        for i in range(lo, hi):
            a = aggregate[i]
            if a >= 0:
                x[i] = x[i] + coarse_x[a]
        for ii in range(hi - lo):
            i = hi - 1 - ii
            row = i - row_base
            s = rhs[i]
            for k in range(offsets[row], offsets[row + 1]):
                s -= values[k] * x[columns[k]]
            x[i] = x[i] + dinv[i] * s

    @wp.func
    def factor_coarsest(mg: Multigrid, w: int):
        """World w's coarsest level as a dense float64 matrix in ``mg.factor[w]``, then its Cholesky factor (lower).
        Returns False if a pivot is not positive."""
        n0 = mg.level_start[1]
        coarsest = mg.world_levels[w] - 1
        lo = mg.world_level_lo[w, coarsest]
        total = mg.world_level_hi[w, coarsest]
        m = 3 * (total - lo)
        F = mg.factor[w]
        for a in range(m):
            for b in range(m):
                F[a, b] = wp.float64(0.0)
        for f in range(lo, total):
            row = f - n0
            for k in range(mg.offsets[row], mg.offsets[row + 1]):
                c = mg.columns[k] - lo
                block = mg.values[k]
                for a in range(3):
                    for b in range(3):
                        F[3 * (f - lo) + a, 3 * c + b] = wp.float64(block[a, b])
        ok = bool(True)
        for j in range(m):
            d = F[j, j]
            for k in range(j):
                d -= F[j, k] * F[j, k]
            if d <= wp.float64(0.0):
                ok = False
                d = wp.float64(1.0)
            d = wp.sqrt(d)
            F[j, j] = d
            for i in range(j + 1, m):
                e = F[i, j]
                for k in range(j):
                    e -= F[i, k] * F[j, k]
                F[i, j] = e / d
        return ok

    @wp.func
    def solve_coarsest(mg: Multigrid, world: int, b: wp.array(dtype=vec3), x: wp.array(dtype=vec3)):
        """x = (the coarsest level's matrix)^-1 b on world ``world``'s coarsest flat nodes, by the factor of
        factor_coarsest (one thread; the level has at most MAX_COARSEST nodes)."""
        coarsest = mg.world_levels[world] - 1
        lo = mg.world_level_lo[world, coarsest]
        total = mg.world_level_hi[world, coarsest]
        m = 3 * (total - lo)
        F, w = mg.factor[world], mg.work[world]
        for i in range(m):
            s = wp.float64(b[lo + i // 3][i % 3])
            for k in range(i):
                s -= F[i, k] * w[k]
            w[i] = s / F[i, i]
        for ii in range(m):
            i = m - 1 - ii
            s = w[i]
            for k in range(i + 1, m):
                s -= F[k, i] * w[k]
            w[i] = s / F[i, i]
        for f in range(lo, total):
            j = 3 * (f - lo)
            x[f] = vec3(scalar(w[j]), scalar(w[j + 1]), scalar(w[j + 2]))

    @wp.func
    def multigrid_setup(A: BlockMatrix, mg: Multigrid, dinv: wp.array(dtype=mat33), w: int):
        """World w's coarse levels' blocks (Galerkin sums), their diagonal inverses, and the Cholesky factor of its
        coarsest level. Returns False if a pivot is not positive (A is not positive definite)."""
        n0 = mg.level_start[1]
        levels = mg.world_levels[w]
        zero = mat33()
        for level in range(1, levels):  # the world's blocks of each level: those of its rows there
            for k in range(mg.offsets[mg.world_level_lo[w, level] - n0], mg.offsets[mg.world_level_hi[w, level] - n0]):
                mg.values[k] = zero
        for k in range(A.offsets[mg.world_level_lo[w, 0]], A.offsets[mg.world_level_hi[w, 0]]):
            slot = mg.fine_slot[k]
            if slot >= 0:
                mg.values[slot] = mg.values[slot] + A.values[k]
        # level by level, so each level is complete before it is read
        for level in range(1, levels):
            for k in range(mg.offsets[mg.world_level_lo[w, level] - n0], mg.offsets[mg.world_level_hi[w, level] - n0]):
                slot = mg.coarse_slot[k]
                if slot >= 0:
                    mg.values[slot] = mg.values[slot] + mg.values[k]
        for level in range(1, levels):
            for f in range(mg.world_level_lo[w, level], mg.world_level_hi[w, level]):
                dinv[f] = wp.inverse(mg.values[mg.diag_slot[f - n0]])
        return factor_coarsest(mg, w)

    @wp.func
    def multigrid_apply(A: BlockMatrix, mg: Multigrid, dinv: wp.array(dtype=mat33), r: wp.array(dtype=vec3),
                        z: wp.array(dtype=vec3), w: int):
        """z = one symmetric V-cycle on world w's part of r (forward Gauss-Seidel down, a dense solve on the
        coarsest level, backward Gauss-Seidel up). Returns r.z over the world's rows (float64)."""
        n0 = mg.level_start[1]
        last = mg.world_levels[w] - 1
        lo, hi = mg.world_level_lo[w, 0], mg.world_level_hi[w, 0]
        zero = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        for level in range(1, last + 1):
            for f in range(mg.world_level_lo[w, level], mg.world_level_hi[w, level]):
                mg.b[f] = zero
        smooth_down(A.offsets, A.columns, A.diag_slot, A.values, 0, lo, hi, dinv, r, z, mg.aggregate, mg.b)
        for level in range(1, last):
            smooth_down(mg.offsets, mg.columns, mg.diag_slot, mg.values, n0, mg.world_level_lo[w, level],
                        mg.world_level_hi[w, level], dinv, mg.b, mg.x, mg.aggregate, mg.b)
        solve_coarsest(mg, w, mg.b, mg.x)
        for level_down in range(1, last):
            level = last - level_down
            smooth_up(mg.offsets, mg.columns, mg.diag_slot, mg.values, n0, mg.world_level_lo[w, level],
                      mg.world_level_hi[w, level], dinv, mg.b, mg.x, mg.aggregate, mg.x)
        smooth_up(A.offsets, A.columns, A.diag_slot, A.values, 0, lo, hi, dinv, r, z, mg.aggregate, mg.x)
        rz = wp.float64(0.0)
        for i in range(lo, hi):
            rz += wp.float64(wp.dot(r[i], z[i]))
        return rz
    # -- the parallel multigrid (the warp backend's "multigrid", a launch a stage; the tiled CG's, on each world's
    # thread block): the same hierarchy, a thread per node or block. Galerkin sums gather their sources (no atomics:
    # the same sums in the same order on every device), damped block-Jacobi smoothing replaces the Gauss-Seidel
    # sweeps (why: warpcloth/solver/multigrid.py, ParallelMultigrid), and the coarsest level keeps
    # its dense Cholesky solve on one thread.
    @wp.func
    def row_residual(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                     values: wp.array(dtype=mat33), row: int, b: vec3, x: wp.array(dtype=vec3)):
        """b - (A x) on one row of a level's matrix."""
        r = b
        for k in range(offsets[row], offsets[row + 1]):
            r -= values[k] * x[columns[k]]
        return r

    @wp.func
    def galerkin_block(fine: wp.array(dtype=mat33), mg: Multigrid, k: int):
        """Coarse block k: the sum of the blocks that map to it (the particles' level's ``fine`` for level 1, the
        level before's otherwise), in the order the sequential form adds them."""
        acc = mat33()
        for s in range(mg.fine_start[k], mg.fine_start[k + 1]):
            acc += fine[mg.fine_sources[s]]
        for s in range(mg.coarse_start[k], mg.coarse_start[k + 1]):
            acc += mg.values[mg.coarse_sources[s]]
        return acc

    @wp.kernel
    def mg_galerkin(fine: wp.array(dtype=mat33), mg: Multigrid, first: int):
        # one coarse block of a level (its blocks from ``first``)
        k = first + wp.tid()
        mg.values[k] = galerkin_block(fine, mg, k)

    @wp.kernel
    def mg_diag_inverse(diag_slot: wp.array(dtype=wp.int32), values: wp.array(dtype=mat33), row_base: int, lo: int,
                        dinv: wp.array(dtype=mat33)):
        # a level's diagonal block inverses (the smoother's), a thread per node
        i = lo + wp.tid()
        dinv[i] = wp.inverse(values[diag_slot[i - row_base]])

    @wp.kernel
    def mg_factor(mg: Multigrid):
        # the coarsest level's Cholesky factor (one thread); a matrix that is not positive definite poisons it
        # with a NaN, so the CG reports a non-finite residual as the sequential multigrid does
        if not factor_coarsest(mg, 0):
            mg.factor[0, 0, 0] = wp.float64(wp.nan)

    # The V-cycle's sweeps, two a level each way, fused so that a level costs two launches each way: the first sweep
    # down (from zero: omega D^-1 b) and the correction a level gets from the next (P x_coarse) are formed where a
    # sweep reads them, the same arithmetic as a launch that stored them first, so the result is bitwise that of a
    # sweep a launch.
    @wp.func
    def first_sweep(dinv: wp.array(dtype=mat33), b: wp.array(dtype=vec3), omega: scalar, j: int):
        """Node j after the first damped Jacobi sweep from zero: omega D^-1 b."""
        return omega * (dinv[j] * b[j])

    @wp.func
    def prolonged(aggregate: wp.array(dtype=wp.int32), x: wp.array(dtype=vec3), j: int):
        """Node j plus its aggregate's correction on the next level (P x_coarse; x holds both levels)."""
        xj = x[j]
        a = aggregate[j]
        if a >= 0:
            xj = xj + x[a]
        return xj

    @wp.func
    def sweep_from_zero(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                        values: wp.array(dtype=mat33), row_base: int, dinv: wp.array(dtype=mat33),
                        b: wp.array(dtype=vec3), omega: scalar, i: int):
        """Node i after two damped Jacobi sweeps from zero."""
        r = b[i]
        for k in range(offsets[i - row_base], offsets[i - row_base + 1]):
            r -= values[k] * first_sweep(dinv, b, omega, columns[k])
        return first_sweep(dinv, b, omega, i) + omega * (dinv[i] * r)

    @wp.func
    def sweep_prolonged(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                        values: wp.array(dtype=mat33), row_base: int, dinv: wp.array(dtype=mat33),
                        b: wp.array(dtype=vec3), aggregate: wp.array(dtype=wp.int32), x: wp.array(dtype=vec3),
                        omega: scalar, i: int):
        """Node i after the next level's correction and a damped Jacobi sweep."""
        r = b[i]
        for k in range(offsets[i - row_base], offsets[i - row_base + 1]):
            r -= values[k] * prolonged(aggregate, x, columns[k])
        return prolonged(aggregate, x, i) + omega * (dinv[i] * r)

    @wp.func
    def sweep(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32), values: wp.array(dtype=mat33),
              row_base: int, dinv: wp.array(dtype=mat33), b: wp.array(dtype=vec3), x: wp.array(dtype=vec3),
              omega: scalar, i: int):
        """Node i after a damped Jacobi sweep: x + omega D^-1 (b - A x)."""
        s = row_residual(offsets, columns, values, i - row_base, b[i], x)
        return x[i] + omega * (dinv[i] * s)

    @wp.func
    def restricted(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                   values: wp.array(dtype=mat33), row_base: int, mg: Multigrid, b: wp.array(dtype=vec3),
                   x: wp.array(dtype=vec3), c: int):
        """Coarse node c's right-hand side: the sum of its members' residuals b - A x (P^T r, P piecewise
        constant)."""
        acc = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        for m in range(mg.member_start[c], mg.member_start[c + 1]):
            i = mg.members[m]
            acc += row_residual(offsets, columns, values, i - row_base, b[i], x)
        return acc

    @wp.func
    def block_down(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                   values: wp.array(dtype=mat33), row_base: int, lo: int, hi: int, coarse_lo: int, coarse_hi: int,
                   dinv: wp.array(dtype=mat33), b: wp.array(dtype=vec3), mg: Multigrid, other: wp.array(dtype=vec3),
                   omega: scalar, lane: int, stride: int):
        """A level's way down on the threads of one block: its nodes [lo, hi) of mg.x after two damped Jacobi sweeps
        from zero, then the next level's right-hand side (its nodes [coarse_lo, coarse_hi) of mg.b): mg_down's and
        mg_restrict's arithmetic, the first sweep stored behind a barrier instead of formed where it is read."""
        i = lo + lane
        while i < hi:
            other[i] = first_sweep(dinv, b, omega, i)
            i += stride
        block_barrier()
        i = lo + lane
        while i < hi:
            mg.x[i] = sweep(offsets, columns, values, row_base, dinv, b, other, omega, i)
            i += stride
        block_barrier()
        c = coarse_lo + lane
        while c < coarse_hi:
            mg.b[c] = restricted(offsets, columns, values, row_base, mg, b, mg.x, c)
            c += stride
        block_barrier()

    @wp.func
    def block_up(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                 values: wp.array(dtype=mat33), row_base: int, lo: int, hi: int, dinv: wp.array(dtype=mat33),
                 b: wp.array(dtype=vec3), mg: Multigrid, other: wp.array(dtype=vec3), omega: scalar,
                 out: wp.array(dtype=vec3), lane: int, stride: int):
        """A level's way up on the threads of one block: its nodes [lo, hi) of mg.x plus the next level's correction
        (in place: a node reads only itself and its aggregate), then two damped Jacobi sweeps, the last into
        ``out`` (mg.x itself on a coarse level: that sweep reads ``other`` only)."""
        i = lo + lane
        while i < hi:
            mg.x[i] = prolonged(mg.aggregate, mg.x, i)
            i += stride
        block_barrier()
        i = lo + lane
        while i < hi:
            other[i] = sweep(offsets, columns, values, row_base, dinv, b, mg.x, omega, i)
            i += stride
        block_barrier()
        i = lo + lane
        while i < hi:
            out[i] = sweep(offsets, columns, values, row_base, dinv, b, other, omega, i)
            i += stride
        block_barrier()

    @wp.func
    def coarse_cycle(mg: Multigrid, dinv: wp.array(dtype=mat33), other: wp.array(dtype=vec3), first: int,
                     omega: scalar, w: int, lane: int, stride: int):
        """World w's V-cycle from its coarse level ``first`` (>= 1; its right-hand side in mg.b) down, the coarsest
        level's solve and back up to ``first`` (its correction in mg.x), on the threads of one block: the stages
        of ParallelMultigrid.apply's launches, the same arithmetic, with barriers between them."""
        row_base = mg.level_start[1]
        coarsest = mg.world_levels[w] - 1
        for level in range(first, coarsest):
            block_down(mg.offsets, mg.columns, mg.values, row_base, mg.world_level_lo[w, level],
                       mg.world_level_hi[w, level], mg.world_level_lo[w, level + 1], mg.world_level_hi[w, level + 1],
                       dinv, mg.b, mg, other, omega, lane, stride)
        if lane == 0:
            solve_coarsest(mg, w, mg.b, mg.x)
        block_barrier()
        for up in range(coarsest - first):
            level = coarsest - 1 - up
            block_up(mg.offsets, mg.columns, mg.values, row_base, mg.world_level_lo[w, level],
                     mg.world_level_hi[w, level], dinv, mg.b, mg, other, omega, mg.x, lane, stride)

    @wp.func
    def tiled_v_cycle(A: BlockMatrix, mg: Multigrid, dinv: wp.array(dtype=mat33), r: wp.array(dtype=vec3),
                      z: wp.array(dtype=vec3), other: wp.array(dtype=vec3), omega: scalar, w: int, lane: int,
                      stride: int):
        """z = one V-cycle of world w on r on the threads of its block: ParallelMultigrid.apply's arithmetic."""
        lo, hi = mg.world_level_lo[w, 0], mg.world_level_hi[w, 0]
        block_down(A.offsets, A.columns, A.values, 0, lo, hi, mg.world_level_lo[w, 1], mg.world_level_hi[w, 1], dinv,
                   r, mg, other, omega, lane, stride)
        coarse_cycle(mg, dinv, other, 1, omega, w, lane, stride)
        block_up(A.offsets, A.columns, A.values, 0, lo, hi, dinv, r, mg, other, omega, z, lane, stride)

    @wp.func
    def tiled_multigrid_setup(A: BlockMatrix, mg: Multigrid, dinv: wp.array(dtype=mat33), w: int, lane: int,
                              stride: int):
        """World w's coarse levels' blocks, their diagonal inverses (dinv; the particles' are the caller's) and
        its coarsest level's Cholesky factor, on the threads of its block (a pivot that is not positive poisons
        the factor with a NaN, so the CG reports a non-finite residual)."""
        n0 = mg.level_start[1]
        levels = mg.world_levels[w]
        for level in range(1, levels):  # level by level: each reads the one before
            k = mg.offsets[mg.world_level_lo[w, level] - n0] + lane
            while k < mg.offsets[mg.world_level_hi[w, level] - n0]:
                mg.values[k] = galerkin_block(A.values, mg, k)
                k += stride
            block_barrier()
        for level in range(1, levels - 1):
            f = mg.world_level_lo[w, level] + lane
            while f < mg.world_level_hi[w, level]:
                dinv[f] = wp.inverse(mg.values[mg.diag_slot[f - n0]])
                f += stride
        if lane == 0:
            if not factor_coarsest(mg, w):
                mg.factor[w, 0, 0] = wp.float64(wp.nan)
        block_barrier()

    @wp.kernel
    def mg_down(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                values: wp.array(dtype=mat33), row_base: int, lo: int, dinv: wp.array(dtype=mat33),
                b: wp.array(dtype=vec3), omega: scalar, x: wp.array(dtype=vec3)):
        # a level's two sweeps down, from zero, on its nodes [lo, lo + dim)
        i = lo + wp.tid()
        x[i] = sweep_from_zero(offsets, columns, values, row_base, dinv, b, omega, i)

    @wp.kernel
    def mg_restrict(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                    values: wp.array(dtype=mat33), row_base: int, mg: Multigrid, b: wp.array(dtype=vec3),
                    coarse_lo: int):
        # the next level's right-hand side (mg.b from coarse_lo) from a level's residual
        c = coarse_lo + wp.tid()
        mg.b[c] = restricted(offsets, columns, values, row_base, mg, b, mg.x, c)

    @wp.kernel
    def mg_up(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32), values: wp.array(dtype=mat33),
              row_base: int, lo: int, dinv: wp.array(dtype=mat33), b: wp.array(dtype=vec3),
              aggregate: wp.array(dtype=wp.int32), x: wp.array(dtype=vec3), omega: scalar,
              x_out: wp.array(dtype=vec3)):
        # a level's first sweep up, after the next level's correction
        i = lo + wp.tid()
        x_out[i] = sweep_prolonged(offsets, columns, values, row_base, dinv, b, aggregate, x, omega, i)

    @wp.kernel
    def mg_smooth(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                  values: wp.array(dtype=mat33), row_base: int, lo: int, dinv: wp.array(dtype=mat33),
                  b: wp.array(dtype=vec3), x: wp.array(dtype=vec3), omega: scalar, x_out: wp.array(dtype=vec3)):
        # a level's second sweep up
        i = lo + wp.tid()
        x_out[i] = sweep(offsets, columns, values, row_base, dinv, b, x, omega, i)

    @wp.kernel
    def mg_smooth_output(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                         values: wp.array(dtype=mat33), dinv: wp.array(dtype=mat33), b: wp.array(dtype=vec3),
                         x: wp.array(dtype=vec3), omega: scalar, y: wp.array(dtype=vec3), alpha: scalar,
                         beta: scalar, z: wp.array(dtype=vec3)):
        # the particles' second sweep up, written as z = alpha x + beta y (warp.optim.linear's matvec contract;
        # z may be b or y: a thread reads only its own node of them)
        i = wp.tid()
        zi = alpha * sweep(offsets, columns, values, 0, dinv, b, x, omega, i)
        if beta != scalar(0.0):
            zi += beta * y[i]
        z[i] = zi

    @wp.kernel
    def mg_coarse_cycle(mg: Multigrid, dinv: wp.array(dtype=mat33), other: wp.array(dtype=vec3), first: int,
                        omega: scalar):
        # the small levels' stages in one thread block (launch_tiled, one block, one world)
        _w, lane = wp.tid()
        coarse_cycle(mg, dinv, other, first, omega, 0, lane, wp.block_dim())
    return SimpleNamespace(
        Multigrid=Multigrid,
        multigrid_setup=multigrid_setup,
        multigrid_apply=multigrid_apply,
        tiled_multigrid_setup=tiled_multigrid_setup,
        tiled_v_cycle=tiled_v_cycle,
        mg_galerkin=mg_galerkin,
        mg_diag_inverse=mg_diag_inverse,
        mg_factor=mg_factor,
        mg_down=mg_down,
        mg_restrict=mg_restrict,
        mg_up=mg_up,
        mg_smooth=mg_smooth,
        mg_smooth_output=mg_smooth_output,
        mg_coarse_cycle=mg_coarse_cycle,
    )
