"""Time per implicit step, forward and backward, of a hanging cloth in the wind, for grids 16^2 .. 128^2.

Scene: 1 m square, vertical (facing the +x wind), soft handles (k 1e3) on the two top corners, gravity, wind 5 m/s,
gray-interlock thicken 2, dt 0.02, no collisions, float32, the library's default SolverOptions (printed; on the CPU
the "auto" backend is the one-launch sequential CG). Timed rollouts start after an untimed spin-up of SPINUP steps
(the first steps from the flat sheet need fewer CG iterations than the flapping cloth).

    forward_ms          rollout without tape (requires_grad=False model), per step
    taped_forward_ms    rollout recorded on a wp.Tape (requires_grad=True model), per step
    backward_ms         tape.backward of that rollout (loss = sum of final positions), per step
    forward_backward_ms taped_forward_ms + backward_ms
    cg_iters            mean forward CG iterations per step (adjoint_cg_iters: the adjoint solves;
                        cg_iters_cold: forward with warm_start=False)

Every timed rollout starts from the same spun-up positions and velocities with a cold first solve (a State without
``particle_dv``), so repetitions are alike. Profiles (--profile-res) time every kernel launch and count array
allocations per step.

Usage: python benchmarks/step_time.py [--quick] [--out PATH] [--sizes 16,32,64,128] [--profile-res 16,64]
       [--before PATH --before-label TEXT] [--preconditioner NAME]
       (--quick: an 8x8 grid, 5 steps, results/quick/step_time.json)
--before: the JSON of an earlier run (this script's, or a list of its records) to compare with, e.g. the same
benchmark at an older commit or with another --preconditioner (SolverOptions.preconditioner, default "auto") run
back to back with this one; the comparison is printed and stored under "before".
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import common
import numpy as np
import warp as wp
from common import wc

# res -> (steps per timed rollout, repetitions); the 128^2 case is kept short
CASES = {16: (50, 5), 32: (20, 3), 64: (10, 3), 128: (3, 2)}
QUICK_CASE = (5, 2)
SPINUP = 10
QUICK_SPINUP = 2
TARGET_STEP_MS_64 = 15.0
TARGET_FWD_BWD_MS_16 = 3.0


def forward_rollouts(sim, s0, steps, reps):
    times, iters = [], []
    for _ in range(reps):
        before = sim.stats["cg_iterations"]
        t, _ = common.timed(wc.rollout, sim, s0, steps=steps)
        times.append(t / steps)
        iters.append((sim.stats["cg_iterations"] - before) / steps)
    return times, iters


def record(tape, sim, s0, control, steps):
    with tape:
        return wc.rollout(sim, s0, control, steps=steps)


def loss_seed(traj):
    """d(loss)/d(x_final) for loss = sum of the final positions."""
    return {traj[-1].particle_x: wp.ones_like(traj[-1].particle_x, requires_grad=False)}


def taped_rollout(sim, s0, control, steps):
    """(forward s, backward s, forward iters, adjoint iters) of one taped rollout and its backward pass."""
    before = sim.stats  # a snapshot: read again after
    tape = wp.Tape()
    t_fwd, traj = common.timed(record, tape, sim, s0, control, steps)
    t_bwd, _ = common.timed(tape.backward, grads=loss_seed(traj))
    tape.zero()
    tape.reset()
    after = sim.stats
    return (t_fwd, t_bwd, after["cg_iterations"] - before["cg_iterations"],
            after["adjoint_cg_iterations"] - before["adjoint_cg_iterations"])


def profile(res, steps, sim, s0, simg, s0g, control):
    """Per-kernel wall time per step of one forward, one taped forward and its backward; allocations per step."""
    phases = ("forward", "taped", "backward")
    out = {}
    with common.launch_profile() as la, common.alloc_profile() as al:
        t, _ = common.timed(wc.rollout, sim, s0, steps=steps)
    out["forward"] = (t, dict(la), None, dict(al))
    tape = wp.Tape()
    with common.launch_profile() as la, common.alloc_profile() as al:
        t, traj = common.timed(record, tape, simg, s0g, control, steps)
    out["taped"] = (t, dict(la), None, dict(al))
    seed = loss_seed(traj)
    with common.launch_profile() as la, common.alloc_profile() as al:
        t, _ = common.timed(tape.backward, grads=seed)
    out["backward"] = (t, dict(la), None, dict(al))
    tape.zero()
    tape.reset()

    def per_step(p, table, key, idx=1):
        entry = out[p][table].get(key)
        return None if entry is None else entry[idx] / steps * (1e3 if idx == 1 else 1)

    keys = sorted({k for p in phases for k in out[p][1]}, key=lambda k: (k.endswith("[adj]"), k))
    rows = []
    for k in keys:
        calls = next(c for c in (per_step(p, 1, k, 0) for p in phases) if c)
        rows.append([k, calls, *(per_step(p, 1, k) for p in phases)])
    rows.append(["host time outside launches", None,
                 *((out[p][0] - sum(s for _, s in out[p][1].values())) / steps * 1e3 for p in phases)])
    rows.append(["TOTAL", None, *(out[p][0] / steps * 1e3 for p in phases)])
    if all(out[p][3]["count"] is not None for p in phases):
        rows.append(["array allocations / step", None, *(out[p][3]["count"] / steps for p in phases)])
        rows.append(["allocated KiB / step", None, *(out[p][3]["bytes"] / steps / 1024 for p in phases)])
    common.print_table(["kernel / phase", "launches/step", "forward ms", "taped fwd ms", "backward ms"], rows,
                       ["", ".1f", ".3f", ".3f", ".3f"],
                       title=f"profile {res}x{res}, per step over {steps} steps (wall time around each launch; "
                             "cg_sequential under 'backward' is the adjoint solve)")
    return {p: {"total_ms": out[p][0] / steps * 1e3,
                "launch_ms": {k: s / steps * 1e3 for k, (c, s) in out[p][1].items()},
                "allocations_per_step": None if out[p][3]["count"] is None else out[p][3]["count"] / steps,
                "allocated_bytes_per_step": None if out[p][3]["bytes"] is None else out[p][3]["bytes"] / steps}
            for p in phases}


COMPARED = ("forward_ms", "taped_forward_ms", "backward_ms", "forward_backward_ms", "cg_iters", "adjoint_cg_iters")


def compare(path: str, label: str, records: list[dict]) -> dict:
    """Print this run against an earlier one (grid by grid) and return what the JSON keeps of it."""
    data = json.loads(Path(path).read_text())
    old = {r["res"]: r for r in (data["records"] if isinstance(data, dict) else data)}
    rows = []
    for r in records:
        o = old.get(r["res"])
        if o is None:
            continue
        rows.append([f"{r['res']}x{r['res']}"] + [v for k in COMPARED[:4] for v in
                                                   (o[k], r[k], 100.0 * (r[k] / o[k] - 1.0))]
                    + [f"{o['cg_iters']:.1f} / {r['cg_iters']:.1f}"])
    header = ["grid"] + [h for k in ("forward", "taped fwd", "backward", "fwd+bwd")
                         for h in (f"{k} ms {label}", f"{k} ms now", "change %")] + ["CG it"]
    common.print_table(header, rows, ["", *([".2f", ".2f", "+.1f"] * 4), ""],
                       title=f"{label} ({path}) against this run, ms per step (medians)")
    return {"label": label, "path": str(path),
            "records": [{k: o.get(k) for k in ("res", *COMPARED)} for o in old.values()]}


def main():
    args = common.parse_args(__doc__, sizes=",".join(map(str, CASES)), profile_res="16,64", before="",
                             before_label="before", preconditioner="auto",
                             quick={"sizes": "8", "profile_res": "8"})
    info = common.machine_info()
    common.print_machine(info)
    sizes = [int(r) for r in args.sizes.split(",") if r]
    prof_res = {int(r) for r in args.profile_res.split(",") if r}
    spinup = QUICK_SPINUP if args.quick else SPINUP
    options = wc.SolverOptions(preconditioner=args.preconditioner)
    print(f"scene: hanging 1 m sheet, wind (5,0,0), gray-interlock x2, dt {common.DT}, float32; timed after {spinup} "
          f"spin-up steps\noptions: {options}")

    records = []
    for res in sizes:
        steps, reps = QUICK_CASE if args.quick else CASES.get(res, (10, 3))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            m = common.hanging_cloth(res, requires_grad=False)
            sim = wc.Simulator(m, common.DT, options=options)
            s0 = common.cold(common.advance(sim, m.state(), spinup))  # also compiles
            fwd, iters = forward_rollouts(sim, s0, steps, reps)
            cold_sim = wc.Simulator(m, common.DT, options=dataclasses.replace(options, warm_start=False))
            _, cold_iters = forward_rollouts(cold_sim, s0, steps, 1)

            mg = common.hanging_cloth(res, requires_grad=True)
            simg = wc.Simulator(mg, common.DT, options=options)
            s0g = common.cold(s0, requires_grad=True)
            control = mg.control()
            taped_rollout(simg, s0g, control, 1)  # warm-up (adjoint kernels)
            runs = [taped_rollout(simg, s0g, control, steps) for _ in range(reps)]
            tf, tb = [r[0] / steps for r in runs], [r[1] / steps for r in runs]
        unconverged = [str(w.message) for w in caught if "did not converge" in str(w.message)]
        rec = {
            "res": res,
            "particles": m.particle_count,
            "triangles": m.tri_count,
            "bsr_blocks": m.bsr_nnz,
            "steps": steps,
            "reps": reps,
            "forward_ms": common.median(fwd) * 1e3,
            "taped_forward_ms": common.median(tf) * 1e3,
            "backward_ms": common.median(tb) * 1e3,
            "forward_backward_ms": common.median([a + b for a, b in zip(tf, tb)]) * 1e3,
            "cg_iters": float(np.mean(iters)),
            "cg_iters_cold": float(np.mean(cold_iters)),
            "taped_cg_iters": float(np.mean([r[2] for r in runs])) / steps,
            "adjoint_cg_iters": float(np.mean([r[3] for r in runs])) / steps,
            "unconverged_solves": len(unconverged),
            "unconverged_example": unconverged[0] if unconverged else None,
            "profile": None,
        }
        records.append(rec)
        print(f"  {res}x{res}: forward {rec['forward_ms']:.2f} ms/step, backward {rec['backward_ms']:.2f} ms/step, "
              f"{rec['cg_iters']:.0f} CG it/step" + (f"; {len(unconverged)} solves missed cg_tol, e.g. "
                                                      f"{unconverged[0]}" if unconverged else ""), flush=True)
        if res in prof_res:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rec["profile"] = profile(res, steps, sim, s0, simg, s0g, control)

    rows = []
    for r in records:
        target = ""
        if r["res"] == 64:
            target = f"step <= {TARGET_STEP_MS_64:g} ms: {'PASS' if r['forward_ms'] <= TARGET_STEP_MS_64 else 'FAIL'}"
        if r["res"] == 16:
            ok = r["forward_backward_ms"] <= TARGET_FWD_BWD_MS_16
            target = f"fwd+bwd <= {TARGET_FWD_BWD_MS_16:g} ms: {'PASS' if ok else 'FAIL'}"
        rows.append([f"{r['res']}x{r['res']}", r["particles"], r["steps"], r["forward_ms"], r["taped_forward_ms"],
                     r["backward_ms"], r["forward_backward_ms"], r["cg_iters"], r["cg_iters_cold"],
                     r["adjoint_cg_iters"], r["forward_ms"] / max(r["cg_iters"], 1) * 1e3, target])
    common.print_table(
        ["grid", "particles", "steps", "forward ms", "taped fwd ms", "backward ms", "fwd+bwd ms", "CG it",
         "CG it cold", "adj CG it", "fwd us/CG it", "target"],
        rows, ["", "d", "d", ".2f", ".2f", ".2f", ".2f", ".1f", ".1f", ".1f", ".1f", ""],
        title="per-step wall time (medians over repetitions; CG iterations are means per step; 'cold' = "
              "warm_start=False)")
    before = compare(args.before, args.before_label, records) if args.before else None
    common.write_result(args, {"before": before, "scene": {"dt": common.DT, "spinup_steps": spinup, "dtype": "float32",
                                         "options": dataclasses.asdict(options)},
                               "targets": {"step_ms_64": TARGET_STEP_MS_64, "fwd_bwd_ms_16": TARGET_FWD_BWD_MS_16},
                               "records": records})


if __name__ == "__main__":
    main()
