"""How the gradient's norm grows with the horizon: 50, 200 and 700 steps of the hanging cloth in the wind.

Scene: ``common.hanging_cloth`` (1 m sheet, RESxRES cells, gray-interlock x2, two soft handles, 5 m/s wind, dt 0.02 s,
default SolverOptions), in float32 and float64. Loss: the final mean height of the cloth. Gradients of the loss with
respect to the initial velocities (2-norm over every particle's three components), the density, and the 6x4
stretching table (2-norm). Horizons up to --tape-max steps are recorded on one ``wp.Tape``; longer ones go through
``wc.checkpointed_backward`` (O(sqrt T) stored states).

    |dL/dv0|, |dL/drho|, |dL/dS|   the norms at each horizon
    growth                         norm / norm at the previous horizon
    rate /s                        ln(growth) / (time between the horizons): the exponential growth rate
    f32 vs f64                     |g32 - g64| / |g64|: whether float32's gradient is still the same gradient

Usage: python benchmarks/gradient_growth.py [--quick] [--out PATH] [--res 16] [--horizons 50,200,700]
       [--tape-max 200]
"""

from __future__ import annotations

import math
import time

import common
import numpy as np
import warp as wp
from common import wc

TAPE_MAX = 200
"""Longest horizon recorded on a single tape (default of --tape-max); longer ones are checkpointed."""


@wp.kernel
def mean_height_f32(x: wp.array(dtype=wp.vec3), loss: wp.array(dtype=wp.float32)):
    wp.atomic_add(loss, 0, x[wp.tid()][2] / float(x.shape[0]))


@wp.kernel
def mean_height_f64(x: wp.array(dtype=wp.vec3d), loss: wp.array(dtype=wp.float64)):
    wp.atomic_add(loss, 0, x[wp.tid()][2] / wp.float64(x.shape[0]))


def gradients(res: int, dtype, steps: int, tape_max: int = TAPE_MAX) -> dict:
    """Loss and gradients of one horizon, from a fresh model and simulator."""
    model = common.hanging_cloth(res, requires_grad=True, dtype=dtype)
    sim = wc.Simulator(model, common.DT)
    state = model.state()
    kernel = mean_height_f32 if dtype == wp.float32 else mean_height_f64
    t0 = time.perf_counter()
    if steps <= tape_max:
        tape = wp.Tape()
        with tape:
            final = wc.rollout(sim, state, steps=steps)[-1]
            out = wp.zeros(1, dtype=dtype, requires_grad=True)
            wp.launch(kernel, model.particle_count, inputs=[final.particle_x], outputs=[out])
        tape.backward(out)
        loss, method = float(out.numpy()[0]), "tape"
    else:
        def step_loss(i, s, out):
            if i == steps:
                wp.launch(kernel, model.particle_count, inputs=[s.particle_x], outputs=[out])

        loss, _ = wc.checkpointed_backward(sim, state, None, steps=steps, loss=step_loss)
        method = "checkpointed"
    seconds = time.perf_counter() - t0
    g_v = state.particle_v.grad.numpy().astype(np.float64)
    g_rho = model.material_density.grad.numpy().astype(np.float64)
    g_s = model.material_stretching.grad.numpy().astype(np.float64)
    return {
        "dtype": "float32" if dtype == wp.float32 else "float64",
        "steps": steps,
        "t_s": steps * common.DT,
        "method": method,
        "seconds": seconds,
        "loss": loss,
        "grad_v0_norm": float(np.linalg.norm(g_v)),
        "grad_density_norm": float(np.linalg.norm(g_rho)),
        "grad_stretching_norm": float(np.linalg.norm(g_s)),
        "finite": bool(np.all(np.isfinite(g_v)) and np.all(np.isfinite(g_rho)) and np.all(np.isfinite(g_s))),
        "_g": {"v0": g_v, "density": g_rho, "stretching": g_s},
    }


def main():
    args = common.parse_args(__doc__, res=16, horizons="50,200,700", tape_max=TAPE_MAX,
                             quick={"res": 4, "horizons": "4,16", "tape_max": 8})
    horizons = sorted(int(h) for h in args.horizons.split(",") if h)
    info = common.machine_info()
    common.print_machine(info)
    print(f"scene: hanging {args.res}x{args.res} sheet, wind {common.WIND}, gray-interlock x{common.THICKEN:g}, "
          f"dt {common.DT}; loss = final mean height; horizons {horizons} (tape up to {args.tape_max} steps, "
          "checkpointed beyond)")

    records = []
    for dtype in (wp.float32, wp.float64):
        gradients(args.res, dtype, 2)  # load the kernels and their adjoints (untimed)
        previous = None
        for steps in horizons:
            rec = gradients(args.res, dtype, steps, args.tape_max)
            for key in ("v0", "density", "stretching"):
                norm = rec[f"grad_{key}_norm"]
                growth = rate = None
                if previous is not None:
                    before = previous[f"grad_{key}_norm"]
                    growth = norm / before if before > 0.0 else math.inf
                    rate = math.log(growth) / (rec["t_s"] - previous["t_s"]) if 0.0 < growth < math.inf else None
                rec[f"growth_{key}"], rec[f"rate_{key}_per_s"] = growth, rate
            records.append(rec)
            previous = rec
            print(f"  {rec['dtype']} {steps} steps ({rec['method']}, {rec['seconds']:.1f} s): "
                  f"|dL/dv0| {rec['grad_v0_norm']:.4g}, |dL/drho| {rec['grad_density_norm']:.4g}, "
                  f"|dL/dS| {rec['grad_stretching_norm']:.4g}", flush=True)

    # float32 against float64, horizon by horizon
    by_key = {(r["dtype"], r["steps"]): r for r in records}
    for steps in horizons:
        r32, r64 = by_key[("float32", steps)], by_key[("float64", steps)]
        for key in ("v0", "density", "stretching"):
            g32, g64 = r32["_g"][key], r64["_g"][key]
            diff = float(np.linalg.norm(g32 - g64) / max(np.linalg.norm(g64), 1e-300))
            r32[f"f32_vs_f64_{key}"] = r64[f"f32_vs_f64_{key}"] = diff

    rows = []
    for r in records:
        rows.append([r["dtype"], r["steps"], r["t_s"], r["method"], r["seconds"], r["loss"],
                     r["grad_v0_norm"], r["growth_v0"], r["rate_v0_per_s"],
                     r["grad_density_norm"], r["growth_density"], r["rate_density_per_s"],
                     r["grad_stretching_norm"], r["growth_stretching"], r["rate_stretching_per_s"],
                     r["f32_vs_f64_v0"], r["finite"]])
    common.print_table(
        ["dtype", "steps", "t s", "method", "wall s", "loss m", "|dL/dv0|", "growth", "rate /s", "|dL/drho|",
         "growth", "rate /s", "|dL/dS|", "growth", "rate /s", "f32 vs f64 (v0)", "finite"],
        rows, ["", "d", ".0f", "", ".1f", ".4f", ".4g", ".3g", ".3f", ".4g", ".3g", ".3f", ".4g", ".3g", ".3f",
               ".2e", ""],
        title="gradient norms by horizon (growth: over the previous horizon; rate: ln(growth) per simulated second)")
    for r in records:
        del r["_g"]
        r["res"] = args.res
    common.write_result(args, {"res": args.res, "dt": common.DT, "tape_max": args.tape_max, "records": records})


if __name__ == "__main__":
    main()
