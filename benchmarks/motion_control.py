"""The seed's Table 3: throw a cloth over a wall into a basket, open-loop and with an MLP controller (the memory of
back-propagating the 700 steps is measured by benchmarks/memory.py).

Scene (SPEC.md §5(c)): 0.7 m gray-interlock cloth (8x8 cells) flat at z = 2 over x in [-3.7, -3], the seed's basket
and wall, dt 0.01, 700 steps, collisions on. Control: 4 corner pushes per second for the first 3 s (36 numbers);
loss 1/2 |com_T - (0, 0, -0.7)|^2; error % = |com_T - target| / |com_0 - target| x 100. ``simulations`` = forward +
backward simulations until the best result.

Usage: python benchmarks/motion_control.py [--quick] [--out PATH] [--open-loop-iters 50] [--mlp-iters 100]
       [--steps 700]      (--quick: 10 steps, 2 open-loop simulations, 1 MLP iteration)
"""

from __future__ import annotations

import os

# The collision projection's dense algebra runs in NumPy on the host; a multi-threaded BLAS spin-waits against other
# jobs on a shared 2-core machine, so this benchmark uses one BLAS thread unless the environment says otherwise (set
# before NumPy loads; recorded in the JSON's meta.env).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import time  # noqa: E402

import common  # noqa: E402
from common import wc  # noqa: E402

from warpcloth.tasks import throw as C  # noqa: E402


def main():
    args = common.parse_args(__doc__, open_loop_iters=50, mlp_iters=100, steps=C.STEPS,
                             quick={"open_loop_iters": 2, "mlp_iters": 1, "steps": 10})
    records = {"steps": args.steps, "dt": C.DT, "seed": C.SEED_PUBLISHED}
    task = C.ThrowTask(steps=args.steps)
    r = C.optimize_open_loop(task, iters=args.open_loop_iters, progress=True)
    records["open_loop"] = {"error_pct": r.error_pct, "simulations": r.simulations, "iters": args.open_loop_iters,
                            "seconds": r.seconds, "errors_pct": r.errors_pct, "params": r.params.tolist()}
    t_mlp = time.perf_counter()
    try:
        task = C.ThrowTask(steps=args.steps)
        r = C.train_mlp(task, iters=args.mlp_iters, progress=True)
        records["mlp"] = {"error_pct": r.error_pct, "simulations": r.simulations, "iters": args.mlp_iters,
                          "seconds": r.seconds, "errors_pct": r.errors_pct}
    except ImportError as exc:
        print(f"mlp skipped: {exc}")
    except (wc.CollisionError, wc.SimulationError) as exc:  # the training's failure is a result too
        message = f"{type(exc).__name__}: {str(exc).splitlines()[0]}"
        records["mlp_failed"] = {"iters": args.mlp_iters, "simulations": task.simulations,
                                 "seconds": time.perf_counter() - t_mlp, "error": message}
        print(f"mlp training stopped after {task.simulations} simulations: {message}")
    rows = []
    for key, seed_key in (("open_loop", "open-loop"), ("mlp", "mlp")):
        if key in records:
            rec, seed = records[key], C.SEED_PUBLISHED[seed_key]
            ok = rec["error_pct"] <= seed["target_error_pct"] and rec["simulations"] <= seed["target_simulations"]
            rows.append([key, f"{rec['error_pct']:.1f}", rec["simulations"], f"{rec['seconds'] / rec['iters']:.2f}",
                         f"{seed['error_pct']:.0f}", seed["simulations"],
                         f"<= {seed['target_error_pct']:.0f} % in <= {seed['target_simulations']}: "
                         + ("ok" if ok else "FAIL")])
    print(f"\nthrowing a cloth into a basket, {args.steps} steps of {C.DT} s, float32, {common.cpu_model()}")
    common.print_table(["controller", "error %", "simulations", "s/simulation", "seed error %", "seed sims",
                        "target"], rows)
    common.write_result(args, records)


if __name__ == "__main__":
    main()
