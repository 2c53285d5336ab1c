"""CG solvers on the implicit systems of the hanging-cloth scene (16^2 and 64^2 grids): time per solve and per
iteration.

The system A dv = b is taken from a real step (step SPINUP+1 of benchmarks/step_time.py's scene: ``Simulator.assemble``
of the state after SPINUP steps) and solved with ``wc.LinearSolver``, the simulator's own solver, under different
SolverOptions. Compared, all to cg_tol 1e-6 (|b - A x| <= 1e-6 |b|) from x0 = 0:
  (a) warp.optim.linear.cg with its "diag" preconditioner as the library's warp backend calls it (on the CPU
      check_every=1; SolverOptions(cg_backend="warp", preconditioner="jacobi")), the same with block Jacobi and
      with the multigrid in parallel form (the backend's default for one world, CUDA's for worlds over 1024
      particles), and raw with warp's default check_every=10; the tiled backend (CUDA's default for smaller worlds:
      one thread block a world; here a block is one thread, so only its iterations mean what they would on CUDA)
      with block Jacobi and with the multigrid's parallel V-cycle on the block's threads;
  (b) the one-launch sequential CG (cg_backend="sequential") with jacobi, block_jacobi, block_ssor (omega 1.0,
      i.e. symmetric Gauss-Seidel, and 1.5) and multigrid (the CPU default), block_ssor and multigrid also
      warm-started from the previous step's dv (``State.particle_dv``, what SolverOptions.warm_start uses);
  (c) warp.sparse.bsr_mv alone, per call.
"true res" is |b - A x| / |b| recomputed in float64 after the solve (the systems are float32: at 64^2 it floors near
3e-5 from float32 rounding in the x updates); "err vs f64" is |x - x64| / |x64| against the same system solved in
float64 to 1e-12, the accuracy that matters.

Usage: python benchmarks/cg_solvers.py [--quick] [--out PATH] [--sizes 16,64]
"""

from __future__ import annotations

import warnings

import common
import numpy as np
import warp as wp
import warp.optim.linear as wl
import warp.sparse as ws
from common import wc

SPINUP = 10
TOL = 1.0e-6

wp.set_module_options({"enable_backward": False})

vec3, mat33 = wp.types.vector(3, wp.float32), wp.types.matrix((3, 3), wp.float32)


def capture_system(res):
    """Model, (values, rhs) of one real step and the dv of the step before it (its solve's warm start)."""
    m = common.hanging_cloth(res)
    sim = wc.Simulator(m, common.DT, options=wc.SolverOptions(cg_tol=TOL, cg_backend="sequential"))
    s = common.advance(sim, m.state(), SPINUP)
    values, rhs, _ = sim.assemble(s)
    dv_prev = wp.clone(s.particle_dv)
    nxt = m.empty_state()
    sim.step(s, nxt)  # the step's own solution, for the bsr_mv timing
    return m, values, rhs, wp.clone(nxt.particle_dv), dv_prev


def solver(model, **options) -> wc.LinearSolver:
    return wc.LinearSolver(model, wc.SolverOptions(**options))


def warp_matrix(model, values):
    """A warp.sparse BSR matrix on the model's block pattern whose values are ``values``."""
    n = model.particle_count
    rows = np.repeat(np.arange(n, dtype=np.int32), np.diff(model.bsr_offsets.numpy()))
    A = ws.bsr_from_triplets(n, n, wp.array(rows, dtype=wp.int32), model.bsr_columns, values,
                             prune_numerical_zeros=False)
    if not np.array_equal(A.columns.numpy()[: model.bsr_nnz], model.bsr_columns.numpy()):
        raise RuntimeError("warp.sparse reordered the block structure")
    return A


def true_residual(model, values, rhs, x) -> float:
    """|b - A x| / |b| evaluated in float64 on the host (a float32 evaluation would floor near 1e-5 here)."""
    off, col = model.bsr_offsets.numpy(), model.bsr_columns.numpy()
    rows = np.repeat(np.arange(model.particle_count), np.diff(off))
    blocks = values.numpy().astype(np.float64)
    xs = x.numpy().astype(np.float64)
    ax = np.zeros_like(xs)
    np.add.at(ax, rows, np.einsum("kij,kj->ki", blocks, xs[col]))
    b = rhs.numpy().astype(np.float64)
    return float(np.linalg.norm(b - ax) / np.linalg.norm(b))


def reference_solution(res, values, rhs) -> np.ndarray:
    """The same (float32-rounded) system solved in float64 to 1e-12 with the library's float64 kernel."""
    m64 = common.hanging_cloth(res, dtype=wp.float64)
    t = m64.types
    x = wp.zeros(m64.particle_count, dtype=t.vec3)
    solver(m64, cg_tol=1e-12, cg_max_iters=100000).solve(wp.array(values.numpy().astype(np.float64), dtype=t.mat33),
                                                          wp.array(rhs.numpy().astype(np.float64), dtype=t.vec3), x)
    return x.numpy()


def bench_size(res, reps, quick=False):
    m, values, rhs, dv_ref, dv_prev = capture_system(res)
    n = m.particle_count
    x_f64 = reference_solution(res, values, rhs)
    x = wp.zeros(n, dtype=vec3)
    records = []

    def record(name, solve, reps_, note=""):
        info = solve()  # warm-up (compiles) and iteration count
        t = common.median_time(solve, reps=reps_, warmup=0)
        it = info[0]
        rec = {"n": n, "res": res, "solver": name, "iters": it, "ms_per_solve": t * 1e3,
               "ms_per_iter": t * 1e3 / max(it, 1), "reported_res": info[1],
               "true_res": true_residual(m, values, rhs, x),
               "err_vs_f64": float(np.linalg.norm(x.numpy() - x_f64) / np.linalg.norm(x_f64)), "note": note}
        records.append(rec)
        print(f"  {res}x{res} {name}: {it} it, {rec['ms_per_solve']:.2f} ms", flush=True)
        return rec

    # (b) library sequential CG, from x0 = 0 and warm-started from the previous step's dv (library option)
    for name, pre, omega in (("jacobi", "jacobi", 1.5), ("block_jacobi", "block_jacobi", 1.5),
                             ("block_ssor w=1.0", "block_ssor", 1.0), ("block_ssor w=1.5", "block_ssor", 1.5)):
        s = solver(m, cg_tol=TOL, preconditioner=pre, ssor_omega=omega, cg_backend="sequential")
        record(f"sequential {name}", lambda s=s: s.solve(values, rhs, x), reps)

    record("sequential block_ssor w=1.5 + warm start", lambda: s.solve(values, rhs, x, guess=dv_prev), reps,
           "x0 = previous step's dv")
    mg = solver(m, cg_tol=TOL, preconditioner="multigrid", cg_backend="sequential")
    levels = "/".join(map(str, mg.multigrid_levels))
    record("sequential multigrid", lambda: mg.solve(values, rhs, x), reps, f"levels {levels} nodes")
    record("sequential multigrid + warm start (CPU default)", lambda: mg.solve(values, rhs, x, guess=dv_prev), reps,
           "x0 = previous step's dv")

    # (a) warp.optim.linear.cg, as the library's warp backend calls it
    sw = solver(m, cg_tol=TOL, cg_backend="warp", preconditioner="jacobi")
    sb = solver(m, cg_tol=TOL, cg_backend="warp", preconditioner="block_jacobi")
    smg = solver(m, cg_tol=TOL, cg_backend="warp", preconditioner="multigrid")
    st = solver(m, cg_tol=TOL, cg_backend="tiled")
    stm = solver(m, cg_tol=TOL, cg_backend="tiled", preconditioner="multigrid")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for pre in ("jacobi", "block_jacobi", "multigrid"):  # compiles warp.sparse / warp.optim kernels
            solver(m, cg_tol=TOL, cg_backend="warp", preconditioner=pre, cg_max_iters=3).solve(values, rhs, x)
    warp_reps = 2 if quick else (3 if res <= 16 else 1)
    record("warp cg diag (library call)", lambda: sw.solve(values, rhs, x), warp_reps,
           "check_every=1, preconditioner rebuilt and b copied to host per solve")
    record("warp cg block_jacobi", lambda: sb.solve(values, rhs, x), warp_reps)
    record("warp cg multigrid (parallel form)", lambda: smg.solve(values, rhs, x), warp_reps,
           "damped block-Jacobi smoothing; CUDA's default for a world over 1024 particles")
    record("tiled block_jacobi", lambda: st.solve(values, rhs, x), reps,
           "CUDA's default for worlds up to 1024 particles; one thread a block on the CPU")
    record("tiled multigrid", lambda: stm.solve(values, rhs, x), reps,
           "the parallel V-cycle on each world's thread block; one thread a block on the CPU")
    A = warp_matrix(m, values)
    M = wl.preconditioner(A, "diag")

    def warp_raw():
        x.zero_()
        it, resid, _ = wl.cg(A, rhs, x, tol=TOL, atol=1e-12, maxiter=1000, M=M, check_every=10,
                             use_cuda_graph=False)
        return int(it), float("nan")

    record("warp cg diag (check_every=10)", warp_raw, warp_reps, "preconditioner built once")
    t_pre = common.median_time(lambda: wl.preconditioner(A, "diag"), reps=20)

    # launches per warp cg iteration (one profiled solve)
    with common.launch_profile() as launches:
        it = sw.solve(values, rhs, x).iterations
    top = sorted(launches.items(), key=lambda kv: -kv[1][1])
    n_launch = sum(c for c, _ in launches.values())
    t_launch = sum(s for _, s in launches.values())
    prof = {"iters": it, "launches_per_iter": n_launch / it, "launch_ms_per_iter": t_launch / it * 1e3,
            "top": [(k, c / it, s / it * 1e3) for k, (c, s) in top[:6]]}

    # (c) bsr_mv alone
    y = wp.zeros(n, dtype=vec3)
    p = wp.clone(dv_ref)
    t_mv = common.median_time(lambda: ws.bsr_mv(A, p, y), reps=50, warmup=3, min_time=0.2)
    empty = wp.zeros(1, dtype=wp.float32)
    t_launch0 = common.median_time(lambda: empty.zero_(), reps=50, warmup=3, min_time=0.1)

    extra = {"n": n, "res": res, "bsr_blocks": m.bsr_nnz, "bsr_mv_ms": t_mv * 1e3,
             "warp_diag_preconditioner_ms": t_pre * 1e3, "trivial_launch_us": t_launch0 * 1e6,
             "warp_cg_profile": prof}
    return records, extra


def main():
    args = common.parse_args(__doc__, sizes="16,64", quick={"sizes": "8"})
    info = common.machine_info()
    common.print_machine(info)
    all_recs, extras = [], []
    for res in (int(s) for s in args.sizes.split(",") if s):
        recs, extra = bench_size(res, reps=2 if args.quick else (9 if res <= 16 else 5), quick=args.quick)
        all_recs += recs
        extras.append(extra)

    for ex in extras:
        recs = [r for r in all_recs if r["res"] == ex["res"]]
        warp_t = next(r["ms_per_solve"] for r in recs if r["solver"].startswith("warp cg diag (library"))
        rows = [[r["solver"], r["iters"], r["ms_per_solve"], r["ms_per_iter"], r["true_res"], r["err_vs_f64"],
                 warp_t / r["ms_per_solve"]] for r in recs]
        rows.append(["warp.sparse.bsr_mv alone (per call)", None, None, ex["bsr_mv_ms"], None, None, None])
        common.print_table(["solver", "iters", "ms/solve", "ms/iter", "true res", "err vs f64", "x vs warp"], rows,
                           ["", "d", ".2f", ".4f", ".1e", ".1e", ".1f"],
                           title=f"{ex['res']}x{ex['res']} grid: {ex['n']} vertices, {ex['bsr_blocks']} 3x3 blocks, "
                                 f"tol {TOL:g}")
        pr = ex["warp_cg_profile"]
        print(f"warp cg: {pr['launches_per_iter']:.1f} launches/iteration taking {pr['launch_ms_per_iter']:.2f} ms; "
              f"top: " + "; ".join(f"{k} {c:.1f}x {ms:.3f} ms" for k, c, ms in pr["top"][:4]))
        print(f"diag preconditioner build {ex['warp_diag_preconditioner_ms']:.3f} ms; trivial launch "
              f"(array.zero_ of 1 float) {ex['trivial_launch_us']:.1f} us")

    print()
    for ex in extras:
        recs = {r["solver"]: r for r in all_recs if r["res"] == ex["res"]}
        w = recs["warp cg diag (library call)"]
        s = recs["sequential block_jacobi"]
        print(f"conclusion {ex['n']} vertices: warp cg {w['ms_per_iter']:.3f} ms/iter vs sequential "
              f"{s['ms_per_iter']:.4f} ms/iter ({w['ms_per_iter'] / s['ms_per_iter']:.0f}x), bsr_mv alone "
              f"{ex['bsr_mv_ms']:.3f} ms = {ex['bsr_mv_ms'] / s['ms_per_iter']:.1f} sequential iterations; "
              f"whole solve {w['ms_per_solve'] / s['ms_per_solve']:.0f}x faster sequential")
        b = recs["sequential block_ssor w=1.5"]
        print(f"  preconditioner: block SSOR takes {b['iters']} iterations against block Jacobi's "
              f"{s['iters']}: a {s['ms_per_solve'] / b['ms_per_solve']:.1f}x faster solve")
        g = recs["sequential multigrid"]
        print(f"  multigrid (the CPU default) takes {g['iters']} iterations against block SSOR's {b['iters']}: a "
              f"{b['ms_per_solve'] / g['ms_per_solve']:.1f}x faster solve ({g['ms_per_iter'] / b['ms_per_iter']:.1f}x "
              "the time per iteration)")
    faster = all(
        next(r for r in all_recs if r["res"] == ex["res"] and r["solver"] == "sequential block_jacobi")["ms_per_solve"]
        < next(r for r in all_recs if r["res"] == ex["res"] and r["solver"].startswith("warp cg diag (check"))[
            "ms_per_solve"] for ex in extras)
    if faster:
        print("=> on the CPU the one-launch sequential CG is the right backend: warp's cg spends most of each "
              "iteration in its tile dot products (block_dot/block_sum kernels, see above), and even one bsr_mv "
              "call costs several whole sequential iterations.")
    else:
        print("=> warp's cg beat the sequential CG on this machine: revisit cg_backend='auto'.")
    common.write_result(args, {"tol": TOL, "solves": all_recs, "sizes": extras})


if __name__ == "__main__":
    main()
