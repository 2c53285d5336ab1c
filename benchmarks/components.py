"""Model only what a scene requires: the cost of each scene component, and where the time of a step goes.

Cases (the 1 m sheet of benchmarks/step_time.py, gray-interlock x2, dt 0.02, float32, default SolverOptions):

    everything off  Simulator.step on the free sheet with no wind, damping, handles, pins, forces, obstacles or
                    self-collision (the hanging cloth with every component taken out), alternating two States
    everything off (rollout)  the same through wc.rollout, which allocates a new State per step to keep the
                    trajectory (what a tape needs)
    + component     the same cloth with one component declared (wind 5 m/s; Rayleigh damping; the two top corners
                    on soft handles; a sphere 10 m away; self-collision)

Every case starts from the same state (the free-falling sheet after SPINUP steps) and uses the same CG settings, so
the iteration counts match where the physics does. Cases are interleaved (each round times every case once, which
spreads the machine's slow phases over all of them), medians over the rounds; "vs off" is the cost over
"everything off".

Phases of the "everything off" step, through the public API on the same state: ``sim.assemble`` (the system A dv = b,
in new arrays), ``sim.linear_solver.solve`` (the CG from a zero guess, as a cold step) and the whole ``sim.step``;
``assemble`` includes allocating its output arrays (a step reuses its own), so at small sizes
assemble + solve can exceed the step.

Usage: python benchmarks/components.py [--quick] [--out PATH] [--res 16,32,64] [--reps 21]
"""

from __future__ import annotations

import common
from common import wc

SPINUP = 5
STEPS = {16: 100, 32: 40, 64: 20}
QUICK_STEPS = 5
COMPONENTS = ("wind", "damping", "handles", "obstacle", "self-collision")


def build(res: int, component: str | None) -> wc.Model:
    b = wc.ModelBuilder(gravity=common.GRAVITY)
    b.add_cloth_grid((res, res), (1.0, 1.0), material=wc.preset("gray-interlock", thicken=common.THICKEN),
                     rot=common.VERTICAL_YZ, pos=(0.0, -0.5, -0.5))
    top = res * (res + 1)
    if component == "wind":
        b.set_wind(common.WIND)
    elif component == "damping":
        b.set_damping(mass=0.1, stiffness=1e-3)
    elif component == "handles":
        b.add_handle(top, stiffness=common.HANDLE_STIFFNESS)
        b.add_handle(top + res, stiffness=common.HANDLE_STIFFNESS)
    elif component == "obstacle":
        b.add_obstacle_sphere(0.3, 2, pos=(10.0, 0.0, 0.0))
    elif component == "self-collision":
        b.set_collision(self_collision=True)
    return b.finalize("cpu")


def start_state(model: wc.Model, sim: wc.Simulator) -> wc.State:
    """The sheet after SPINUP steps, as the start of a new trajectory (cold first solve)."""
    s = common.advance(sim, model.state(), SPINUP)
    return wc.State(s.particle_x, s.particle_v, s.time)


def prepare(res: int, component: str | None, steps: int, keep_trajectory: bool = False):
    """(label, run-once function, simulator) of one case, compiled and spun up."""
    model = build(res, component)
    sim = wc.Simulator(model, common.DT)
    s0 = start_state(model, sim)

    def once():
        if keep_trajectory:
            wc.rollout(sim, s0, steps=steps)
            return
        state, other = s0.clone(), model.empty_state()
        for _ in range(steps):
            sim.step(state, other)
            state, other = other, state

    once()
    label = f"+ {component}" if component else "everything off"
    if keep_trajectory:
        label += " (rollout)"
    return label, once, sim


def time_cases(res: int, steps: int, reps: int) -> list[dict]:
    """Per-step times of every case at one resolution: ``reps`` interleaved rounds, medians."""
    cases = [prepare(res, None, steps), prepare(res, None, steps, keep_trajectory=True)]
    cases += [prepare(res, c, steps) for c in COMPONENTS]
    times = {label: [] for label, _, _ in cases}
    iters0 = {label: sim.stats["cg_iterations"] for label, _, sim in cases}
    for _ in range(reps):
        for label, once, _ in cases:
            times[label].append(common.timed(once)[0])
    rows = []
    for label, _, sim in cases:
        iters = (sim.stats["cg_iterations"] - iters0[label]) / (reps * steps)
        rows.append({"res": res, "case": label, "ms_per_step": 1e3 * common.median(times[label]) / steps,
                     "cg_iters": iters, "steps": steps, "reps": reps})
    off_ms = rows[0]["ms_per_step"]
    for row in rows[1:]:
        row["vs_off_pct"] = 100.0 * (row["ms_per_step"] / off_ms - 1.0)
    return rows


def phases(res: int, reps: int) -> dict:
    """ms of sim.assemble, of linear_solver.solve (zero first guess) and of a whole cold sim.step on one state."""
    model = build(res, None)
    sim = wc.Simulator(model, common.DT)
    s0 = start_state(model, sim)
    out = model.empty_state()
    values, rhs, _ = sim.assemble(s0)
    x = model.empty_state().particle_v  # a vec3 array of the model's size for the solution
    info = sim.linear_solver.solve(values, rhs, x)  # also compiles
    t_assemble = common.median_time(lambda: sim.assemble(s0), reps=reps, warmup=1)
    t_solve = common.median_time(lambda: sim.linear_solver.solve(values, rhs, x), reps=reps, warmup=1)
    t_step = common.median_time(lambda: sim.step(s0, out), reps=reps, warmup=1)
    return {"res": res, "assemble_ms": t_assemble * 1e3, "solve_ms": t_solve * 1e3, "step_ms": t_step * 1e3,
            "rest_ms": (t_step - t_assemble - t_solve) * 1e3, "solve_iterations": info.iterations,
            "step_iterations": sim.last_solve.iterations, "backend": sim.linear_solver.backend,
            "preconditioner": sim.linear_solver.preconditioner}


def main():
    args = common.parse_args(__doc__, res="16,32,64", reps=21, quick={"res": "8", "reps": 3})
    info = common.machine_info()
    common.print_machine(info)
    sizes = [int(r) for r in args.res.split(",") if r]
    rows, phase_rows = [], []
    for res in sizes:
        steps = QUICK_STEPS if args.quick else STEPS.get(res, 20)
        rows += time_cases(res, steps, args.reps)
        phase_rows.append(phases(res, args.reps))
        print(f"  {res}x{res} done", flush=True)
    common.print_table(["res", "case", "ms_per_step", "vs off [%]", "cg_iters"],
                       [[r["res"], r["case"], r["ms_per_step"], r.get("vs_off_pct"), r["cg_iters"]] for r in rows],
                       ["d", "", ".3f", "+.1f", ".1f"], title=f"cost per step, dt {common.DT}, float32")
    common.print_table(["res", "assemble ms", "solve ms", "step ms", "rest ms", "solve it", "step it"],
                       [[p["res"], p["assemble_ms"], p["solve_ms"], p["step_ms"], p["rest_ms"],
                         p["solve_iterations"], p["step_iterations"]] for p in phase_rows],
                       ["d", ".3f", ".3f", ".3f", ".3f", "d", "d"],
                       title="phases of one cold step of the free sheet (everything off), medians")
    common.write_result(args, {"dt": common.DT, "rows": rows, "phases": phase_rows})


if __name__ == "__main__":
    main()
