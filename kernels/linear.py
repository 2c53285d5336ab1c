"""Conjugate-gradient kernels for the 3x3-block system, and the scatter of the solve's adjoint onto A.

Why a whole CG in one launch: on the CPU Warp runs each kernel on one thread and a launch costs ~20 us, while
``warp.optim.linear.cg`` spends most of its time in tile-based dot products that are slow there (measured in
``benchmarks/cg_solvers.py``). One sequential launch that loops over rows and iterations avoids both costs.
On CUDA the same idea takes a thread block per world (cg_tiled: one launch a solve, tile reductions), and for
worlds too large for one block the library solver (every operation across the GPU, convergence tested on the device
inside a graph) with the diagonal or the parallel multigrid preconditioner kernels below (mg_*).
Block SSOR's Gauss-Seidel sweeps are natural on one thread (~3.5x fewer iterations than block Jacobi at 64x64).
Eisenstat's trick (one product per iteration instead of three passes) was tried and measured 1.3x faster, but lost
an order of magnitude of accuracy in float32 (error vs a float64 solve 7e-5 against 3e-6 at 64x64), so it is not used.
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.blocks import block_barrier, block_sum
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
        pair_world_start: wp.array(dtype=wp.int32)  # world w's pairs are [start[w], start[w + 1])
        pair_nodes: wp.array2d(dtype=wp.int32)
        pair_w: wp.array(dtype=vec4)
        pair_k: wp.array(dtype=mat33)

    # Under Warp's deterministic mode (wp.config.deterministic set before warpcloth is imported) no kernel may both
    # write an array directly and add to it atomically: the CG kernels then add the pairs' products on one thread
    # per world, in pair order (a fixed order; the tiled backend gives up its parallel pair loop for it).
    ordered_pairs = wp.get_module_options(__name__)["deterministic"] != wp.DeterministicMode.NOT_GUARANTEED

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
        Rows [lo, hi) only (one world's). Returns r.z (float64).
        """
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
        # 1 block Jacobi, 2 block SSOR (its sequential sweeps suit the one-thread loop; ~3x fewer iterations),
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
        # named for its preconditioner: a CPU graph finds a kernel by name (element_kernel_pair says why)
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

    # -- the parallel multigrid (the warp backend's "multigrid", a launch a stage; the tiled CG's, on each world's
    # thread block): the same hierarchy, a thread per node or block. Galerkin sums gather their sources (no atomics:
    # the same sums in the same order on every device), damped block-Jacobi smoothing replaces the Gauss-Seidel
    # sweeps (warpcloth/solver/multigrid.py ParallelMultigrid has the measurements), and the coarsest level keeps
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
        from zero, then the next level's right-hand side (its nodes [coarse_lo, coarse_hi) of mg.b). A barrier is
        cheaper here than forming the first sweep where it is read (sweep_from_zero: a launch's fusion), and the
        arithmetic is the same."""
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
        """z = one V-cycle of world w on r, on the threads of its block (the tiled CG's multigrid): the stages of
        ParallelMultigrid.apply, the same arithmetic."""
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
        Multigrid=Multigrid,
        cg_sequential=cg_sequential,
        cg_tiled=cg_tiled,
        cg_tiled_multigrid=cg_tiled_multigrid,
        diagonal_inverse=diagonal_inverse,
        mg_galerkin=mg_galerkin,
        mg_diag_inverse=mg_diag_inverse,
        mg_factor=mg_factor,
        mg_down=mg_down,
        mg_restrict=mg_restrict,
        mg_up=mg_up,
        mg_smooth=mg_smooth,
        mg_smooth_output=mg_smooth_output,
        mg_coarse_cycle=mg_coarse_cycle,
        apply_diagonal=apply_diagonal,
        warp_cg_info=warp_cg_info,
        pair_product=pair_product,
        solve_adjoint_scatter=solve_adjoint_scatter,
    )

