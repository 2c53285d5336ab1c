"""The seed's Table 3: throw a cloth over a wall into a basket, open-loop and with an MLP controller; and the memory
of back-propagating the 700 steps with a full tape against checkpointing.

Scene (SPEC.md §5(c)): 0.7 m gray-interlock cloth (8x8 cells) flat at z = 2 over x in [-3.7, -3], the seed's basket
and wall, dt 0.01, 700 steps, collisions on. Control: 4 corner pushes per second for the first 3 s (36 numbers);
loss 1/2 |com_T - (0, 0, -0.7)|^2; error % = |com_T - target| / |com_0 - target| x 100. ``simulations`` = forward +
backward simulations until the best result.

Memory: each mode runs one forward + backward in a fresh process; the figure is the peak resident set size during
it minus the resident size before it (Warp's CPU arrays live in the process heap).

Usage: python benchmarks/motion_control.py [--open-loop-iters 50] [--mlp-iters 100] [--memory 1] [--json PATH]
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np

import common
from warpcloth.tasks import throw as C


def _rss_mb() -> float:
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * resource.getpagesize() / 2**20


def memory_child(mode: str) -> None:
    """One forward + backward of the whole throw; prints JSON with the peak memory above the starting point."""
    model = C.basket_scene()
    C.ThrowTask(model, steps=2).loss_and_grad(np.zeros(C.N_PARAMS))  # loads every kernel module, tiny peak
    task = C.ThrowTask(model, segment_steps=C.STEPS if mode == "full" else None)  # one segment = a full tape
    before = _rss_mb()
    params = np.random.default_rng(0).normal(scale=5.0, size=C.N_PARAMS)
    loss, grad, _ = task.loss_and_grad(params)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"mode": mode, "peak_mb_above_start": peak - before, "grad_norm": float(np.linalg.norm(grad)),
                      "loss": loss}))


def measure_memory() -> list[dict]:
    out = []
    for mode in ("full", "checkpointed"):
        res = subprocess.run([sys.executable, __file__, "--memory-child", mode], capture_output=True, text=True,
                             check=True)
        out.append(json.loads(res.stdout.strip().splitlines()[-1]))
    return out


def main():
    if len(sys.argv) == 3 and sys.argv[1] == "--memory-child":
        memory_child(sys.argv[2])
        return
    args = common.parse_args(__doc__.splitlines()[0], open_loop_iters=50, mlp_iters=100, memory=1)
    records = {}
    task = C.ThrowTask()
    r = C.optimize_open_loop(task, iters=args.open_loop_iters, progress=True)
    records["open_loop"] = {"error_pct": r.error_pct, "simulations": r.simulations, "iters": args.open_loop_iters,
                            "seconds": r.seconds, "errors_pct": r.errors_pct, "params": r.params.tolist()}
    try:
        task = C.ThrowTask()
        r = C.train_mlp(task, iters=args.mlp_iters, progress=True)
        records["mlp"] = {"error_pct": r.error_pct, "simulations": r.simulations, "iters": args.mlp_iters,
                          "seconds": r.seconds, "errors_pct": r.errors_pct}
    except ImportError as exc:
        print(f"mlp skipped: {exc}")
    rows = []
    for key, seed_key in (("open_loop", "open-loop"), ("mlp", "mlp")):
        if key in records:
            rec, seed = records[key], C.SEED_PUBLISHED[seed_key]
            ok = rec["error_pct"] <= seed["target_error_pct"] and rec["simulations"] <= seed["target_simulations"]
            rows.append([key, f"{rec['error_pct']:.1f}", rec["simulations"], f"{rec['seconds'] / rec['iters']:.2f}",
                         f"{seed['error_pct']:.0f}", seed["simulations"],
                         f"<= {seed['target_error_pct']:.0f} % in <= {seed['target_simulations']}: "
                         + ("ok" if ok else "FAIL")])
    print(f"\nthrowing a cloth into a basket, {C.STEPS} steps of {C.DT} s, float32, {common.cpu_model()}")
    common.print_table(["controller", "error %", "simulations", "s/simulation", "seed error %", "seed sims",
                        "target"], rows)
    if args.memory:
        mem = measure_memory()
        records["memory"] = mem
        print(f"\nmemory of one forward + backward of {C.STEPS} steps (peak RSS above the start)")
        common.print_table(["mode", "peak MB", "|grad|"],
                           [[m["mode"], f"{m['peak_mb_above_start']:.1f}", f"{m['grad_norm']:.6g}"] for m in mem])
    common.write_json(args.json, records)


if __name__ == "__main__":
    main()
