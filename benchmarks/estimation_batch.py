"""An estimation's global searches with their trials one after another against as worlds of one batch
(``estimation.estimate_material(..., batch=False / True)``, issue 38).

Scene: the seed's material-estimation scene (demo_wind.obj, 50 steps, frames every 2; Table 2's), each fabric's
targets simulated by warpcloth; the fit starts from the mean fabric with the start scan. Each of the three global
searches (``smoothed``, ``multistart``, ``cmaes``, their default settings) runs with ``--iters`` evaluations, one
run after another and batched in turn, ``--reps`` times each; the batched runs simulate on
``TrajectoryFit.worlds`` (copies of the scene, a material each). Reported: the median wall time of each mode, the
speed-up, and whether the two modes gave the same search (every evaluation's loss and the material found):
bitwise on the CPU, where each world solves with its own multigrid hierarchy.

Usage: python benchmarks/estimation_batch.py [--quick] [--out PATH] [--iters 150] [--reps 2] [--device cpu]
       [--fabrics tango-red-jet-set,white-dots-on-blk] [--optimizers smoothed,multistart,cmaes] [--steps 50]
       (--quick: one fabric, 4 steps, 24 evaluations, one run each)
"""

from __future__ import annotations

import time

import common
import numpy as np
import warp as wp
from common import wc

from warpcloth.tasks import estimation as E
from warpcloth.tasks import scenes as S
from warpcloth.tasks.specs import SearchSpec

QUICK_SEARCH = SearchSpec(population=4, refine=4)
"""--quick: small populations, so that 24 evaluations make whole generations and steps."""


def fit_of(fabric: str, steps: int, device: str) -> E.TrajectoryFit:
    truth = wc.preset(fabric, thicken=S.THICKEN)
    builder = S.hanging_cloth_builder(E.initial_guess(), mesh_path=common.seed_dir() / "meshes" / "demo_wind.obj")
    model = builder.finalize(device, requires_grad=True)
    targets = E.TrajectoryFit.simulate_targets(model, truth, steps=steps)
    return E.TrajectoryFit(model, targets, steps=steps, template=builder)


def main():
    args = common.parse_args(__doc__, iters=150, reps=2, device="cpu", fabrics="tango-red-jet-set,white-dots-on-blk",
                             optimizers="smoothed,multistart,cmaes", steps=E.STEPS,
                             quick={"iters": 24, "reps": 1, "fabrics": "tango-red-jet-set", "steps": 4})
    wp.init()
    search = QUICK_SEARCH if args.quick else SearchSpec()
    records = []
    t0 = time.perf_counter()
    for fabric in args.fabrics.split(","):
        for optimizer in args.optimizers.split(","):
            runs = {False: [], True: []}
            for _ in range(args.reps):
                for batch in (False, True):  # alternated, so that a change of load hits both modes alike
                    fit = fit_of(fabric, args.steps, args.device)
                    start = time.perf_counter()
                    r = E.estimate_material(fit, optimizer=optimizer, iters=args.iters, search=search, batch=batch)
                    runs[batch].append((time.perf_counter() - start, r))
            one, batched = runs[False][0][1], runs[True][0][1]
            same = (one.losses == batched.losses or optimizer == "multistart" and sorted(one.losses) == sorted(
                batched.losses)) and all(np.array_equal(getattr(one.material, part), getattr(batched.material, part))
                                         for part in ("density", "stretching", "bending"))
            record = {"fabric": fabric, "optimizer": optimizer, "iters": args.iters,
                      "one_by_one_s": common.median([t for t, _ in runs[False]]),
                      "batched_s": common.median([t for t, _ in runs[True]]),
                      "runs_s": {"one_by_one": [t for t, _ in runs[False]], "batched": [t for t, _ in runs[True]]},
                      "same_search": bool(same), "sim_err_pct": batched.simulation_error_pct,
                      "best_loss": min(batched.losses)}
            record["speedup"] = record["one_by_one_s"] / record["batched_s"]
            records.append(record)
            print(f"{fabric} {optimizer}: one by one {record['one_by_one_s']:.1f} s, batched "
                  f"{record['batched_s']:.1f} s, same search {same}", flush=True)
    print(f"\n{args.iters} evaluations a fit, median of {args.reps} run(s) a mode, {common.cpu_model()} on "
          f"{args.device} ({time.perf_counter() - t0:.0f} s)")
    common.print_table(["fabric", "optimizer", "one by one [s]", "batched [s]", "speed-up", "same search",
                        "sim err %"],
                       [[r["fabric"], r["optimizer"], f"{r['one_by_one_s']:.1f}", f"{r['batched_s']:.1f}",
                         f"{r['speedup']:.2f}x", str(r["same_search"]), f"{r['sim_err_pct']:.2f}"] for r in records])
    common.write_result(args, {"records": records, "iters": args.iters, "reps": args.reps, "steps": args.steps},
                        device=args.device)


if __name__ == "__main__":
    main()
