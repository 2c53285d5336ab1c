"""Time per implicit step, forward and backward, of a hanging cloth in the wind, for grids 16^2 .. 128^2.

Scene: 1 m square, vertical (facing the +x wind), soft handles (k 1e3) on the two top corners, gravity, wind 5 m/s,
gray-interlock thicken 2, dt 0.02, no collisions, float32, default SolverOptions (cg_tol 1e-6, block Jacobi, the
"auto" backend = one-launch sequential CG on the CPU). Timed rollouts start after an untimed spin-up of SPINUP steps
(the first steps from the flat sheet need fewer CG iterations than the flapping cloth).

    forward_ms          rollout without tape (requires_grad=False model), per step
    taped_forward_ms    rollout recorded on a wp.Tape (requires_grad=True model), per step
    backward_ms         tape.backward of that rollout (loss = sum of final positions), per step
    forward_backward_ms taped_forward_ms + backward_ms
    cg_iters            mean forward CG iterations per step; adjoint_cg_iters the same for the adjoint solves

Usage: python benchmarks/step_time.py [--json PATH] [--profile-res 16,64]
"""

from __future__ import annotations

import numpy as np
import warp as wp

import common
from common import wc

# res -> (steps per timed rollout, repetitions); the 128^2 case is kept short
CASES = {16: (50, 5), 32: (20, 3), 64: (10, 3), 128: (3, 2)}
SPINUP = 10
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


def taped_rollout(sim, s0, control, steps):
    """(forward s, backward s, forward iters, adjoint iters, d(sum x_final)/d(density)) of one taped rollout."""
    st = sim.stats
    it0, adj0 = st["cg_iterations"], st["adjoint_cg_iterations"]
    tape = wp.Tape()

    def fwd():
        with tape:
            return wc.rollout(sim, s0, control, steps=steps)

    t_fwd, traj = common.timed(fwd)
    seed = {traj[-1].particle_x: wp.ones_like(traj[-1].particle_x, requires_grad=False)}
    t_bwd, _ = common.timed(tape.backward, grads=seed)
    g = float(sim.model.material_density.grad.numpy()[0])
    tape.zero()
    tape.reset()
    return t_fwd, t_bwd, st["cg_iterations"] - it0, st["adjoint_cg_iterations"] - adj0, g


def profile(res, steps, sim, s0, simg, s0g, control):
    """Per-kernel wall time per step of one forward, one taped forward and its backward."""
    out = {}
    with common.launch_profile() as launches, common.method_profile(sim, ["_buffers", "_cg", "_check"]) as meth:
        t, _ = common.timed(wc.rollout, sim, s0, steps=steps)
    out["forward"] = (t, dict(launches), dict(meth))
    tape = wp.Tape()
    with common.launch_profile() as launches, common.method_profile(simg, ["_buffers", "_cg", "_check"]) as meth:
        wp.synchronize()
        t, traj = common.timed(lambda: _record(tape, simg, s0g, control, steps))
    out["taped"] = (t, dict(launches), dict(meth))
    seed = {traj[-1].particle_x: wp.ones_like(traj[-1].particle_x, requires_grad=False)}
    with common.launch_profile() as launches, common.method_profile(simg, ["_cg"]) as meth:
        t, _ = common.timed(tape.backward, grads=seed)
    out["backward"] = (t, dict(launches), dict(meth))
    tape.zero()
    tape.reset()

    keys = sorted({k for _, l, _ in out.values() for k in l}, key=lambda k: (k.endswith("[adj]"), k))
    rows = []
    for k in keys:
        row = [k]
        calls = None
        for phase in ("forward", "taped", "backward"):
            c, s = out[phase][1].get(k, (0, 0.0))
            calls = calls or (c / steps if c else None)
            row.append(s / steps * 1e3 if c else None)
        rows.append([row[0], calls, *row[1:]])
    launch_sum = {p: sum(s for _, s in out[p][1].values()) for p in out}
    meth_rows = []
    for name in ("_buffers", "_check", "_cg"):
        meth_rows.append([f"Simulator.{name} (whole call)", None,
                          *(out[p][2].get(name, (0, 0.0))[1] / steps * 1e3 if name in out[p][2] else None
                            for p in ("forward", "taped", "backward"))])
    rows += meth_rows
    rows.append(["host time outside launches", None,
                 *((out[p][0] - launch_sum[p]) / steps * 1e3 for p in ("forward", "taped", "backward"))])
    rows.append(["TOTAL", None, *(out[p][0] / steps * 1e3 for p in ("forward", "taped", "backward"))])
    common.print_table(["kernel / phase", "launches/step", "forward ms", "taped fwd ms", "backward ms"], rows,
                       ["", ".1f", ".3f", ".3f", ".3f"],
                       title=f"profile {res}x{res} ({steps} steps; per step; cg_sequential in 'backward' is the "
                             "adjoint solve)")
    return {p: {"total_ms": out[p][0] / steps * 1e3,
                "launch_ms": {k: s / steps * 1e3 for k, (c, s) in out[p][1].items()}} for p in out}


def _record(tape, sim, s0, control, steps):
    with tape:
        return wc.rollout(sim, s0, control, steps=steps)


def main():
    args = common.parse_args(__doc__.splitlines()[0], profile_res="16,64")
    info = common.machine_info()
    common.print_machine(info)
    prof_res = {int(r) for r in args.profile_res.split(",") if r}
    print(f"scene: hanging 1 m sheet, wind (5,0,0), gray-interlock x2, dt {common.DT}, float32, "
          f"default SolverOptions; timed after {SPINUP} spin-up steps")

    records, profiles = [], {}
    for res, (steps, reps) in CASES.items():
        m = common.hanging_cloth(res, requires_grad=False)
        sim = wc.Simulator(m, common.DT)
        s0 = common.advance(sim, m.state(), SPINUP)  # also compiles
        wc.rollout(sim, s0, steps=1)
        fwd, iters = forward_rollouts(sim, s0, steps, reps)

        mg = common.hanging_cloth(res, requires_grad=True)
        simg = wc.Simulator(mg, common.DT)
        s0g = common.copy_state(mg, s0, requires_grad=True)
        control = mg.control()
        taped_rollout(simg, s0g, control, 1)  # warm-up (adjoint kernels)
        tf, tb, fi, ai, grads = [], [], [], [], []
        for _ in range(reps):
            a, b, c, d, g = taped_rollout(simg, s0g, control, steps)
            tf.append(a / steps)
            tb.append(b / steps)
            fi.append(c / steps)
            ai.append(d / steps)
            grads.append(g)
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
            "taped_cg_iters": float(np.mean(fi)),
            "adjoint_cg_iters": float(np.mean(ai)),
            "dsumx_ddensity": grads[-1],
            "machine": info,
        }
        records.append(rec)
        print(f"  {res}x{res}: forward {rec['forward_ms']:.2f} ms/step, backward {rec['backward_ms']:.2f} ms/step, "
              f"{rec['cg_iters']:.0f} CG it/step", flush=True)
        if res in prof_res:
            profiles[res] = profile(res, steps, sim, s0, simg, s0g, control)
        rec["profile"] = profiles.get(res)

    rows = []
    for r in records:
        target = ""
        if r["res"] == 64:
            target = f"step <= {TARGET_STEP_MS_64:g} ms: {'PASS' if r['forward_ms'] <= TARGET_STEP_MS_64 else 'FAIL'}"
        if r["res"] == 16:
            ok = r["forward_backward_ms"] <= TARGET_FWD_BWD_MS_16
            target = f"fwd+bwd <= {TARGET_FWD_BWD_MS_16:g} ms: {'PASS' if ok else 'FAIL'}"
        rows.append([f"{r['res']}x{r['res']}", r["particles"], r["steps"], r["forward_ms"], r["taped_forward_ms"],
                     r["backward_ms"], r["forward_backward_ms"], r["cg_iters"], r["adjoint_cg_iters"],
                     r["forward_ms"] / max(r["cg_iters"], 1) * 1e3, target])
    common.print_table(
        ["grid", "particles", "steps", "forward ms", "taped fwd ms", "backward ms", "fwd+bwd ms", "CG it",
         "adj CG it", "fwd us/CG it", "target"],
        rows, ["", "d", "d", ".2f", ".2f", ".2f", ".2f", ".1f", ".1f", ".1f", ""],
        title="per-step wall time (medians over repetitions; CG iterations are means per step)")
    common.write_json(args.json, records)


if __name__ == "__main__":
    main()
