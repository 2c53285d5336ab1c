"""Conjugate-gradient kernels for the 3x3-block system, and the scatter of the solve's adjoint onto A.

Why a whole CG in one launch: on the CPU Warp runs each kernel on one thread and a launch costs ~20 us, while
``warp.optim.linear.cg`` spends most of its time in tile-based dot products that are slow there (measured in
``benchmarks/cg_solvers.py``). One sequential launch that loops over rows and iterations avoids both costs.
On CUDA the library solver (many threads, graph capture) is the right tool, and the host code uses it there.
Two sequential kernels: ``cg_sequential`` (Jacobi or block Jacobi) and ``cg_ssor_eisenstat`` (block SSOR, whose
Gauss-Seidel sweeps are natural on one thread: ~3-4x fewer iterations at 64x64).
"""

import functools
from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import types

wp.set_module_options({"enable_backward": False})


@functools.cache
def linear_kernels(scalar):
    t = types(scalar)
    vec3, mat33 = t.vec3, t.mat33

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
    def cg_sequential(
        offsets: wp.array(dtype=wp.int32),
        columns: wp.array(dtype=wp.int32),
        values: wp.array(dtype=mat33),
        diag_slot: wp.array(dtype=wp.int32),
        b: wp.array(dtype=vec3),
        rtol: wp.float64,
        atol: wp.float64,
        max_iters: int,
        block_jacobi: int,
        warm_start: int,
        # scratch:
        r: wp.array(dtype=vec3),
        z: wp.array(dtype=vec3),
        p: wp.array(dtype=vec3),
        q: wp.array(dtype=vec3),
        precond: wp.array(dtype=mat33),
        # out: [iterations, relative residual, converged (0/1)]
        x: wp.array(dtype=vec3),
        info: wp.array(dtype=wp.float64),
    ):
        # Launched with dim 1: the whole (block) Jacobi-preconditioned CG loop runs on one thread. Dot products
        # accumulate in float64 so float32 systems still reach tight relative tolerances. With warm_start, x holds
        # the initial guess on entry.
        n = b.shape[0]
        bb = wp.float64(0.0)
        rr = wp.float64(0.0)
        rz = wp.float64(0.0)
        for i in range(n):
            precond[i] = jacobi_inverse(values[diag_slot[i]], block_jacobi)
            ri = b[i]
            if warm_start != 0:
                for k in range(offsets[i], offsets[i + 1]):
                    ri -= values[k] * x[columns[k]]
            else:
                x[i] = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
            r[i] = ri
            bb += wp.float64(wp.dot(b[i], b[i]))
            rr += wp.float64(wp.dot(ri, ri))
        for i in range(n):
            z[i] = precond[i] * r[i]
            rz += wp.float64(wp.dot(r[i], z[i]))
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
            alpha = scalar(rz / pq)
            rr = wp.float64(0.0)
            rz_new = wp.float64(0.0)
            for i in range(n):
                x[i] = x[i] + alpha * p[i]
                r[i] = r[i] - alpha * q[i]
                rr += wp.float64(wp.dot(r[i], r[i]))
                z[i] = precond[i] * r[i]
                rz_new += wp.float64(wp.dot(r[i], z[i]))
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

    @wp.func
    def cholesky3(a: mat33):
        """Lower-triangular L with a = L L^T (a symmetric positive definite)."""
        zero = scalar(0.0)
        l00 = wp.sqrt(a[0, 0])
        l10 = a[1, 0] / l00
        l20 = a[2, 0] / l00
        l11 = wp.sqrt(a[1, 1] - l10 * l10)
        l21 = (a[2, 1] - l20 * l10) / l11
        l22 = wp.sqrt(a[2, 2] - l20 * l20 - l21 * l21)
        return mat33(l00, zero, zero, l10, l11, zero, l20, l21, l22)

    @wp.func
    def upper_backward_solve(
        offsets: wp.array(dtype=wp.int32),
        columns: wp.array(dtype=wp.int32),
        values: wp.array(dtype=mat33),
        diag_slot: wp.array(dtype=wp.int32),
        rinv: wp.array(dtype=mat33),
        p: wp.array(dtype=vec3),
        t: wp.array(dtype=vec3),
        t_scaled: wp.array(dtype=vec3),
    ):
        # t = (I + U~)^-1 p with U~_ij = Rinv_i A_ij Rinv_j^T (j > i); t_scaled = Rinv^T t
        n = p.shape[0]
        for ii in range(n):
            i = n - 1 - ii
            s = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
            for k in range(diag_slot[i] + 1, offsets[i + 1]):
                s += values[k] * t_scaled[columns[k]]
            ti = p[i] - rinv[i] * s
            t[i] = ti
            t_scaled[i] = wp.transpose(rinv[i]) * ti

    @wp.func
    def true_residual(
        offsets: wp.array(dtype=wp.int32),
        columns: wp.array(dtype=wp.int32),
        values: wp.array(dtype=mat33),
        diag_slot: wp.array(dtype=wp.int32),
        b: wp.array(dtype=vec3),
        x: wp.array(dtype=vec3),
        acc: wp.array(dtype=vec3),
        r: wp.array(dtype=vec3),
    ):
        # r = b - A x from the diagonal and upper blocks (lower ones scattered as transposes); returns |r|^2
        n = b.shape[0]
        zero = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        for i in range(n):
            acc[i] = zero
        rr = wp.float64(0.0)
        for i in range(n):
            xi = x[i]
            ri = b[i] - acc[i] - values[diag_slot[i]] * xi
            for k in range(diag_slot[i] + 1, offsets[i + 1]):
                j = columns[k]
                ri -= values[k] * x[j]
                acc[j] = acc[j] + wp.transpose(values[k]) * xi
            r[i] = ri
            rr += wp.float64(wp.dot(ri, ri))
        return rr

    @wp.kernel
    def cg_ssor_eisenstat(
        offsets: wp.array(dtype=wp.int32),
        columns: wp.array(dtype=wp.int32),
        values: wp.array(dtype=mat33),
        diag_slot: wp.array(dtype=wp.int32),
        b: wp.array(dtype=vec3),
        rtol: wp.float64,
        atol: wp.float64,
        max_iters: int,
        omega: scalar,
        warm_start: int,
        # scratch:
        y: wp.array(dtype=vec3),
        r: wp.array(dtype=vec3),
        p: wp.array(dtype=vec3),
        q: wp.array(dtype=vec3),
        t: wp.array(dtype=vec3),
        t_scaled: wp.array(dtype=vec3),
        acc: wp.array(dtype=vec3),
        x_best: wp.array(dtype=vec3),
        chol: wp.array(dtype=mat33),
        rinv: wp.array(dtype=mat33),
        # out: [iterations, relative residual, converged (0/1)]
        x: wp.array(dtype=vec3),
        info: wp.array(dtype=wp.float64),
    ):
        # Block SSOR-preconditioned CG with Eisenstat's trick (Eisenstat 1981), one thread. Scale by the Cholesky
        # factors of D/omega (S = blockdiag(R^-1)): A~ = S A S^T = L~ + omega I + L~^T, and SSOR on A~ is
        # (I + L~)(I + L~^T). CG runs on B = (I + L~)^-1 A~ (I + L~^T)^-1, whose product needs only one backward and
        # one forward sweep: B p = t + (I + L~)^-1 (p + (omega - 2) t), t = (I + L~^T)^-1 p. The block Jacobi CG
        # needs one product per iteration, plain SSOR three passes; this needs two. x = S^T (I + L~^T)^-1 y.
        # The stopping test is on the true residual |b - A x| <= max(rtol |b|, atol).
        n = b.shape[0]
        zero = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        inv_omega = scalar(1.0) / omega
        bb = wp.float64(0.0)
        for i in range(n):
            c = cholesky3(values[diag_slot[i]] * inv_omega)
            chol[i] = c
            rinv[i] = wp.inverse(c)
            bb += wp.float64(wp.dot(b[i], b[i]))
            acc[i] = zero
        # r = c_hat = (I + L~)^-1 S b (forward sweep; lower blocks are transposes of stored upper ones)
        cc = wp.float64(0.0)
        for i in range(n):
            ri = rinv[i] * (b[i] - acc[i])
            r[i] = ri
            cc += wp.float64(wp.dot(ri, ri))
            rs = wp.transpose(rinv[i]) * ri
            for k in range(diag_slot[i] + 1, offsets[i + 1]):
                acc[columns[k]] = acc[columns[k]] + wp.transpose(values[k]) * rs
        if warm_start != 0:
            # y0 = (I + L~^T) S^-T x0 = R^T x0 + Rinv (sum_{j>i} A_ij x0_j); then r = c_hat - B y0
            for i in range(n):
                s = zero
                for k in range(diag_slot[i] + 1, offsets[i + 1]):
                    s += values[k] * x[columns[k]]
                y[i] = wp.transpose(chol[i]) * x[i] + rinv[i] * s
            upper_backward_solve(offsets, columns, values, diag_slot, rinv, y, t, t_scaled)
            for i in range(n):
                acc[i] = zero
            for i in range(n):
                u = (y[i] + (omega - scalar(2.0)) * t[i]) - rinv[i] * acc[i]
                r[i] = r[i] - (t[i] + u)
                us = wp.transpose(rinv[i]) * u
                for k in range(diag_slot[i] + 1, offsets[i + 1]):
                    acc[columns[k]] = acc[columns[k]] + wp.transpose(values[k]) * us
        else:
            for i in range(n):
                y[i] = zero
        rr = wp.float64(0.0)
        for i in range(n):
            p[i] = r[i]
            rr += wp.float64(wp.dot(r[i], r[i]))
        cc = wp.max(cc, wp.float64(1.0e-300))  # |c_hat|^2: the transformed |b|, scale of the estimate
        threshold = wp.max(rtol * wp.sqrt(bb), atol)
        # The recursive transformed residual drifts from the true one (float32 above all): when it says the
        # tolerance may hold, form x and the true b - A x; stop if it holds, else replace the recursive residual by
        # the transformed true one (residual replacement) and demand a smaller estimate next time.
        # A check that finds no progress since the previous one means the precision floor is reached (float32 at
        # large sizes): stop there and report the true residual, which the host compares with the tolerance.
        estimate_factor = wp.float64(1.0)
        true_norm = wp.sqrt(bb)
        last_norm = wp.float64(1.0e300)
        it = int(0)
        done = int(0)
        exhausted = int(0)
        while done == 0:
            if wp.sqrt(rr / cc) <= rtol * estimate_factor or it >= max_iters or exhausted != 0:
                upper_backward_solve(offsets, columns, values, diag_slot, rinv, y, t, x)
                true_norm = wp.sqrt(true_residual(offsets, columns, values, diag_slot, b, x, acc, q))
                stalled = true_norm > wp.float64(0.9) * last_norm
                if stalled and true_norm > last_norm:
                    # worse than at the previous check (float32 noise took over): return that iterate
                    for i in range(n):
                        x[i] = x_best[i]
                    true_norm = last_norm
                if true_norm <= threshold or it >= max_iters or exhausted != 0 or stalled:
                    done = 1
                else:
                    last_norm = true_norm
                    for i in range(n):
                        x_best[i] = x[i]
                    estimate_factor = estimate_factor * wp.float64(0.5)
                    for i in range(n):
                        acc[i] = zero
                    rr = wp.float64(0.0)
                    for i in range(n):
                        ri = rinv[i] * (q[i] - acc[i])
                        r[i] = ri
                        rr += wp.float64(wp.dot(ri, ri))
                        rs = wp.transpose(rinv[i]) * ri
                        for k in range(diag_slot[i] + 1, offsets[i + 1]):
                            acc[columns[k]] = acc[columns[k]] + wp.transpose(values[k]) * rs
            if done == 0:
                upper_backward_solve(offsets, columns, values, diag_slot, rinv, p, t, t_scaled)
                for i in range(n):
                    acc[i] = zero
                pq = wp.float64(0.0)
                for i in range(n):
                    u = (p[i] + (omega - scalar(2.0)) * t[i]) - rinv[i] * acc[i]
                    qi = t[i] + u
                    q[i] = qi
                    pq += wp.float64(wp.dot(p[i], qi))
                    us = wp.transpose(rinv[i]) * u
                    for k in range(diag_slot[i] + 1, offsets[i + 1]):
                        acc[columns[k]] = acc[columns[k]] + wp.transpose(values[k]) * us
                if pq > wp.float64(0.0) and rr > wp.float64(0.0):
                    alpha = scalar(rr / pq)
                    rr_new = wp.float64(0.0)
                    for i in range(n):
                        y[i] = y[i] + alpha * p[i]
                        r[i] = r[i] - alpha * q[i]
                        rr_new += wp.float64(wp.dot(r[i], r[i]))
                    beta = scalar(rr_new / rr)
                    rr = rr_new
                    for i in range(n):
                        p[i] = r[i] + beta * p[i]
                    it += 1
                else:
                    # exhausted (zero or non-finite residual, non-positive curvature): finish with the true residual
                    exhausted = int(1)
        info[0] = wp.float64(it)
        info[1] = true_norm / wp.max(wp.sqrt(bb), wp.float64(1.0e-300))
        info[2] = wp.where(true_norm <= threshold, wp.float64(1.0), wp.float64(0.0))

    @wp.kernel
    def residual_norms(
        offsets: wp.array(dtype=wp.int32),
        columns: wp.array(dtype=wp.int32),
        values: wp.array(dtype=mat33),
        b: wp.array(dtype=vec3),
        x: wp.array(dtype=vec3),
        # out: [|b - A x|^2, |b|^2]
        sums: wp.array(dtype=wp.float64),
    ):
        i = wp.tid()
        acc = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        for k in range(offsets[i], offsets[i + 1]):
            acc += values[k] * x[columns[k]]
        r = b[i] - acc
        wp.atomic_add(sums, 0, wp.float64(wp.dot(r, r)))
        wp.atomic_add(sums, 1, wp.float64(wp.dot(b[i], b[i])))

    @wp.kernel
    def solve_adjoint_scatter(
        offsets: wp.array(dtype=wp.int32),
        columns: wp.array(dtype=wp.int32),
        lam: wp.array(dtype=vec3),
        solution: wp.array(dtype=vec3),
        # out:
        values_grad: wp.array(dtype=mat33),
        b_grad: wp.array(dtype=vec3),
    ):
        # dL/db = lam and dL/dA_ij = -lam_i dv_j^T on stored blocks (SPEC §4.1)
        i = wp.tid()
        b_grad[i] = b_grad[i] + lam[i]
        for k in range(offsets[i], offsets[i + 1]):
            values_grad[k] = values_grad[k] - wp.outer(lam[i], solution[columns[k]])

    @wp.kernel
    def copy_guess(src: wp.array(dtype=vec3), dst: wp.array(dtype=vec3)):
        # a plain copy that no tape records: a warm start's initial guess carries no gradient
        i = wp.tid()
        dst[i] = src[i]

    @wp.kernel
    def check_state(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        max_speed: scalar,
        # out: [first bad particle + 1 (0 if none)]
        status: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        xi = x[i]
        vi = v[i]
        finite = wp.isfinite(xi) and wp.isfinite(vi)
        if not finite or wp.length(vi) > max_speed:
            wp.atomic_max(status, 0, i + 1)

    return SimpleNamespace(
        cg_sequential=cg_sequential,
        cg_ssor_eisenstat=cg_ssor_eisenstat,
        residual_norms=residual_norms,
        solve_adjoint_scatter=solve_adjoint_scatter,
        check_state=check_state,
        copy_guess=copy_guess,
    )


# Instantiate both precisions at import so the module's hash (and its kernel cache entry) never changes.
for _scalar in (wp.float32, wp.float64):
    linear_kernels(_scalar)
