"""Gradients through contact on the inverse problems: the throw's gradient against central differences, and a
material fit from a cloth draping on an obstacle.

1. The throw (warpcloth.tasks.throw, float64, cg_tol 1e-10): at several control points, the tape's derivative of
   the loss 1/2 |com_T - target|^2 along a random unit direction of the 36 pushes against central differences at
   steps of 1e-1 ... 1e-5 m/s^2. Points: no pushes; the issue's landing throw, (2.0, -0.3, 12.8) m/s^2 on every
   corner in the first second plus noise of sigma 0.1 (numpy.random.default_rng(0)), which landed in the basket and
   rests there; two random starts of the motion-control benchmark (pushes of sigma 5 m/s^2, seeds 1 and 2); and
   the points an open-loop optimisation reaches after its first few simulations.
2. A drape fit: a 12x12, 0.6 m cloth of tango-red-jet-set (thicken 2) dropped from 5 cm onto a 0.4 m box with
   friction 0.4, dt 0.01, 60 steps, frames every 2 (float64). Ground truth simulated by warpcloth; the density
   fitted alone (the tables known: under gravity alone density and stiffness only matter through their ratio) by
   L-BFGS on log density from 1.5x the truth, and all 40 parameters from the mean fabric, as material estimation
   does.

Usage: python benchmarks/contact_gradients.py [--quick] [--out PATH] [--fit-iters 20] [--points 4]
       [--before PATH --before-label TEXT]

--before: the JSON of this script's run on an earlier commit (the same points: they do not depend on the code but
for the optimisation's), stored under "before" for the README's comparison.
"""

from __future__ import annotations

import json
import math
import time

import common
import numpy as np
import warp as wp
from common import wc

from warpcloth.tasks import estimation, scenes, throw
from warpcloth.tasks.optim import lbfgs

STEPS_H = (1e-1, 1e-2, 1e-3, 1e-4, 1e-5)
MU = 0.4


def throw_points(task: throw.ThrowTask, count: int) -> list[tuple[str, np.ndarray]]:
    """(label, pushes) where the gradient is checked."""
    landing = np.zeros((throw.SECONDS_CONTROLLED, len(throw.CORNERS), 3))
    landing[0] = (2.0, -0.3, 12.8)
    landing = landing.reshape(-1) + np.random.default_rng(0).normal(0.0, 0.1, throw.N_PARAMS)
    points = [("no pushes", np.zeros(throw.N_PARAMS)), ("landing throw", landing)]
    # the motion-control benchmark's random starts (benchmarks/motion_control.py START_SIGMA), where the open loop
    # stalled while its loss took the vertex mean
    points += [(f"random start (seed {k}, sigma 5)", np.random.default_rng(k).normal(scale=5.0, size=throw.N_PARAMS))
               for k in (1, 2)]
    seen = []

    def callback(k, loss, err, params):
        seen.append((k, err, np.array(params, dtype=np.float64).reshape(-1)))

    if count > 2:
        throw.optimize_open_loop(task, iters=3 * (count - 2) + 1, callback=callback)
        for k, err, params in seen[1::3][: count - 2]:
            points.append((f"open loop, simulation {k} ({err:.2g} %)", params))
    return points if count > 1 else points[:1]


def check_throw(task: throw.ThrowTask, label: str, params: np.ndarray) -> dict:
    rng = np.random.default_rng(5)
    direction = rng.standard_normal(throw.N_PARAMS)
    direction /= np.linalg.norm(direction)
    t0 = time.perf_counter()
    e = task.evaluate(params)
    loss, grad = e.loss, e.grad
    seconds = time.perf_counter() - t0
    tape_value = float(grad @ direction)
    fds = []
    for h in STEPS_H:
        plus = task.loss_and_grad(params + h * direction)[0]
        minus = task.loss_and_grad(params - h * direction)[0]
        fds.append((plus - minus) / (2.0 * h))
    return {"point": label, "loss": loss, "error_pct": task.error_pct(e.positions),
            "grad_norm": float(np.linalg.norm(grad)), "tape": tape_value, "central_differences": fds,
            "steps_h": list(STEPS_H), "seconds_forward_backward": seconds}


def drape_model(material: wc.Material) -> wc.Model:
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    b.add_cloth_grid((12, 12), (0.6, 0.6), material=material, pos=(-0.3, -0.3, 0.25))
    b.add_obstacle_box((0.2, 0.2, 0.2))
    b.set_collision(obstacle_friction=MU)
    return b.finalize("cpu", dtype=wp.float64, requires_grad=True)


def drape_fits(iters: int, steps: int) -> dict:
    truth = wc.preset("tango-red-jet-set", thicken=2)
    model = drape_model(truth)
    targets = estimation.TrajectoryFit.simulate_targets(model, truth, steps=steps, dt=0.01)
    fit = estimation.TrajectoryFit(model, targets, steps=steps, dt=0.01,
                                   options=wc.SolverOptions(cg_tol=1e-10, cg_atol=1e-30))
    start = 1.5 * truth.density
    history = []

    def objective(theta):
        rho = start * math.exp(float(theta[0]))
        m = wc.Material(name="fit", density=rho, stretching=truth.stretching, bending=truth.bending,
                        thicken=truth.thicken)
        loss, gd, _, _ = fit.loss_and_grad(m)
        history.append((loss, rho))
        return loss, np.array([gd * rho])

    t0 = time.perf_counter()
    theta = lbfgs(objective, np.zeros(1), iters=iters)
    density_only = {"start_density_error_pct": 50.0, "evaluations": len(history),
                    "density_error_pct": 100.0 * abs(start * math.exp(theta[0]) / truth.density - 1.0),
                    "losses": [h[0] for h in history], "seconds": time.perf_counter() - t0}
    t0 = time.perf_counter()
    result = estimation.estimate_material(fit, optimizer="lbfgs", iters=iters)
    errors = estimation.parameter_errors(result.material, truth)
    full = {"evaluations": len(result.losses), "parameter_errors_pct": errors,
            "simulation_error_pct": result.simulation_error_pct,
            "initial_simulation_error_pct": result.initial_simulation_error_pct, "seconds": time.perf_counter() - t0}
    return {"fabric": truth.name, "steps": steps, "density_only": density_only, "all_parameters": full}


def main():
    args = common.parse_args(__doc__, fit_iters=20, points=4, fit_steps=60, before="", before_label="before",
                             quick={"fit_iters": 3, "points": 1, "fit_steps": 10})
    info = common.machine_info()
    common.print_machine(info)
    options = wc.SolverOptions(cg_tol=1e-10, cg_atol=1e-30, collision=wc.CollisionOptions(rounds=50))
    steps = 60 if args.quick else throw.STEPS
    task = throw.ThrowTask(scenes.basket_scene(dtype=wp.float64), options=options, steps=steps)
    rows = [check_throw(task, label, p) for label, p in throw_points(task, args.points)]
    common.print_table(["point", "error %", "|grad|", "tape", *(f"CD h={h:g}" for h in STEPS_H)],
                       [[r["point"], r["error_pct"], r["grad_norm"], r["tape"], *r["central_differences"]]
                        for r in rows], specs=["", ".1f", ".3g", ".4g", *[".4g"] * len(STEPS_H)],
                       title=f"throw ({steps} steps, float64): d loss along a random unit direction of the pushes")
    drape = drape_fits(args.fit_iters, args.fit_steps)
    d, f = drape["density_only"], drape["all_parameters"]
    print(f"\ndrape fit ({drape['fabric']}, {drape['steps']} steps): density alone from +50 %: "
          f"{d['density_error_pct']:.3g} % after {d['evaluations']} evaluations; all 40 parameters from the mean "
          f"fabric: density {f['parameter_errors_pct']['density_err_pct']:.3g} %, simulation error "
          f"{f['simulation_error_pct']:.3g} % (from {f['initial_simulation_error_pct']:.3g} %)")
    before = None
    if args.before:
        earlier = json.loads(open(args.before).read())
        before = {"label": args.before_label, "throw": earlier["throw"], "drape": earlier["drape"]}
    common.write_result(args, {"throw": rows, "drape": drape, "before": before})


if __name__ == "__main__":
    main()
