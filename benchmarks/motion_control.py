"""The seed's Table 3: throw a cloth over a wall into a basket, open-loop and with an MLP controller; and the memory
of back-propagating the 700 steps with a full tape against checkpointing.

Scene (SPEC.md §5(c)): 0.7 m gray-interlock cloth (8x8 cells) flat at z = 2 over x in [-3.7, -3], the seed's basket
and wall, dt 0.01, 700 steps, collisions on. Control: 4 corner pushes per second for the first 3 s (36 numbers);
loss 1/2 |com_T - (0, 0, -0.7)|^2; error % = |com_T - target| / |com_0 - target| x 100. ``simulations`` = forward +
backward simulations until the best result.

Memory: each mode runs one forward + backward in a fresh process; the figure is the peak resident set size during
it minus the resident size before it (Warp's CPU arrays live in the process heap).

Usage: python benchmarks/motion_control.py [--quick] [--out PATH] [--open-loop-iters 50] [--mlp-iters 100]
       [--memory 1] [--steps 700]      (--quick: 10 steps, 2 open-loop simulations, 1 MLP iteration)
"""

from __future__ import annotations

import os

# The collision projection's dense algebra runs in NumPy on the host; a multi-threaded BLAS spin-waits against other
# jobs on a shared 2-core machine, so this benchmark uses one BLAS thread unless the environment says otherwise (set
# before NumPy loads; recorded in the JSON's meta.env).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import common  # noqa: E402
import numpy as np  # noqa: E402
from common import wc  # noqa: E402

from warpcloth.tasks import throw as C  # noqa: E402
from warpcloth.tasks.scenes import basket_scene  # noqa: E402


def _rss_mb() -> float:
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * resource.getpagesize() / 2**20


def memory_child(mode: str, steps: int = C.STEPS) -> None:
    """One forward + backward of the whole throw; prints JSON with the peak memory above the starting point."""
    model = basket_scene()
    C.ThrowTask(model, steps=2).loss_and_grad(np.zeros(C.N_PARAMS))  # loads every kernel module, tiny peak
    task = C.ThrowTask(model, steps=steps, segment_steps=steps if mode == "full" else None)  # one segment: a tape
    before = _rss_mb()
    params = np.random.default_rng(0).normal(scale=5.0, size=C.N_PARAMS)
    loss, grad, _ = task.loss_and_grad(params)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"mode": mode, "peak_mb_above_start": peak - before, "grad_norm": float(np.linalg.norm(grad)),
                      "loss": loss}))


def measure_memory(steps: int = C.STEPS) -> list[dict]:
    out = []
    for mode in ("full", "checkpointed"):
        res = subprocess.run([sys.executable, __file__, "--memory-child", mode, str(steps)], capture_output=True,
                             text=True, check=True)
        out.append(json.loads(res.stdout.strip().splitlines()[-1]))
    return out


def main():
    if len(sys.argv) == 4 and sys.argv[1] == "--memory-child":
        memory_child(sys.argv[2], int(sys.argv[3]))
        return
    args = common.parse_args(__doc__, open_loop_iters=50, mlp_iters=100, memory=1, steps=C.STEPS,
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
    if args.memory:
        mem = measure_memory(args.steps)
        records["memory"] = mem
        print(f"\nmemory of one forward + backward of {args.steps} steps (peak RSS above the start)")
        common.print_table(["mode", "peak MB", "|grad|"],
                           [[m["mode"], f"{m['peak_mb_above_start']:.1f}", f"{m['grad_norm']:.6g}"] for m in mem])
    common.write_result(args, records)


if __name__ == "__main__":
    main()
