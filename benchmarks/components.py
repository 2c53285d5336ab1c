"""Model only what a scene requires: the cost of each scene component, and of the Simulator over a bare integrator.

    bare        the implicit Euler step written out here as its bare launches (stretching + bending + gravity
                assembly, the one-launch CG, the position update) on the Simulator's own buffers: no component
                dispatch, no host-side divergence check (the kernel's flag is never read), no warm-start
                bookkeeping, and two state buffers reused instead of a new State per step
    everything off  Simulator.step on the same cloth with no wind, damping, handles, pins, forces, obstacles or
                self-collision (the hanging cloth with every component taken out), alternating two States
    everything off (rollout)  the same through wc.rollout, which allocates a new State per step to keep the
                trajectory (what a tape needs)
    + component  the same cloth with one component declared (wind 5 m/s; Rayleigh damping; the two top corners on
                soft handles; a sphere 10 m away; self-collision)

Every case starts from the same state (the free-falling sheet after SPINUP steps) and uses the same CG settings, so
the iteration counts match where the physics does. Target: "everything off" within 5 % of "bare".

Usage: python benchmarks/components.py [--json PATH] [--res 16,32,64]
"""

from __future__ import annotations

import numpy as np
import warp as wp

import common
from common import wc

SPINUP = 5
STEPS = {16: 100, 32: 40, 64: 20}
REPS = 21
TARGET_OVERHEAD_PCT = 5.0


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


def bare_rollout(sim: wc.Simulator, state: wc.State, steps: int) -> None:
    """``steps`` implicit Euler steps as bare launches (the Simulator's kernels and buffers, nothing else)."""
    m, k, lin = sim.model, sim.kernels, sim.linear
    dt = m.scalar(sim.dt)
    values, rhs, dv, pin_dv = sim._buffers()
    r, z, p, q = sim._cg_scratch
    opt = sim.options
    x, v = state.particle_x, state.particle_v
    x_next, v_next = wp.empty_like(x), wp.empty_like(v)
    zero = m.scalar(0.0)
    for _ in range(steps):
        rhs.zero_()
        values.zero_()
        wp.launch(k.faces, m.tri_count, inputs=[m.tri_indices, m.tri_material, m.tri_inv_dm, m.tri_area,
                                                 m.tri_block_slot, m.particle_pin, m.material_density,
                                                 m.material_stretching, m.material_thicken, m.lut_weight, m.lut_row,
                                                 m.gravity, x, v, pin_dv, dt, zero, zero], outputs=[values, rhs])
        wp.launch(k.hinges, m.hinge_count, inputs=[m.hinge_indices, m.hinge_material, m.hinge_rest_angle,
                                                    m.hinge_rest_length, m.hinge_rest_area, m.hinge_direction,
                                                    m.hinge_block_slot, m.particle_pin, m.material_bending,
                                                    m.material_thicken, x, v, pin_dv, dt, zero],
                  outputs=[values, rhs])
        wp.launch(lin.cg_sequential, 1, inputs=[m.bsr_offsets, m.bsr_columns, values, m.particle_diag_slot, rhs,
                                                float(opt.cg_tol), float(opt.cg_atol), int(opt.cg_max_iters), 2,
                                                m.scalar(opt.ssor_omega), 1, r, z, p, q, sim._precond],
                  outputs=[dv, sim._cg_info])
        sim.stats["cg_iterations"] += int(sim._cg_info_host[0])  # the same host read as the Simulator's
        wp.launch(k.integrate, m.particle_count, inputs=[x, v, dv, dt, m.scalar(opt.max_speed)],
                  outputs=[x_next, v_next, sim._status])
        x, x_next = x_next, x
        v, v_next = v_next, v
    wp.synchronize()


def prepare(res: int, component: str | None, bare: bool = False, keep_trajectory: bool = False):
    """(label, run-once function, simulator) of one case, compiled and spun up."""
    model = build(res, component)
    sim = wc.Simulator(model, common.DT)
    s0 = common.advance(sim, model.state(), SPINUP)
    steps = STEPS[res]

    def once():
        state = common.copy_state(model, s0, requires_grad=False)
        if bare:
            sim._buffers()[2].zero_()  # the same cold start for the CG's guess as the Simulator's first step
            bare_rollout(sim, state, steps)
        elif keep_trajectory:
            sim._previous_dv = None
            wc.rollout(sim, state, steps=steps)
        else:
            sim._previous_dv = None
            other = model.empty_state()
            for _ in range(steps):
                sim.step(state, other)
                state, other = other, state

    once()
    label = "bare" if bare else (f"+ {component}" if component else "everything off")
    if keep_trajectory:
        label += " (rollout)"
    return label, once, sim


def time_cases(res: int) -> list[dict]:
    """Per-step times of every case at one resolution: REPS rounds, each timing every case once in turn (the
    interleaving spreads the machine's slow phases over all cases), then the median per case."""
    cases = [prepare(res, None, bare=True), prepare(res, None), prepare(res, None, keep_trajectory=True)]
    cases += [prepare(res, c) for c in ("wind", "damping", "handles", "obstacle", "self-collision")]
    times = {label: [] for label, _, _ in cases}
    iters0 = {label: sim.stats["cg_iterations"] for label, _, sim in cases}
    for _ in range(REPS):
        for label, once, _ in cases:
            times[label].append(common.timed(once)[0])
    rows = []
    for label, _, sim in cases:
        iters = (sim.stats["cg_iterations"] - iters0[label]) / (REPS * STEPS[res])
        rows.append({"res": res, "case": label, "ms_per_step": 1e3 * common.median(times[label]) / STEPS[res],
                     "cg_iters": iters})
    bare_ms = rows[0]["ms_per_step"]
    for row in rows[1:]:
        row["overhead_pct"] = 100.0 * (row["ms_per_step"] / bare_ms - 1.0)
    return rows


def main():
    args = common.parse_args(__doc__.splitlines()[0], res="16,32,64")
    info = common.machine_info()
    common.print_machine(info)
    rows = [row for res in (int(r) for r in args.res.split(",")) for row in time_cases(res)]
    common.print_table(["res", "case", "ms_per_step", "vs bare [%]", "cg_iters"],
                       [[r["res"], r["case"], r["ms_per_step"], r.get("overhead_pct"), r["cg_iters"]] for r in rows],
                       ["d", "", ".3f", "+.1f", ".1f"], title=f"cost per step, dt {common.DT}, float32")
    worst = max(r["overhead_pct"] for r in rows if r["case"] == "everything off")  # the Simulator's own overhead
    print(f"\neverything off vs bare: worst {worst:+.1f} % (target <= {TARGET_OVERHEAD_PCT:g} %): "
          f"{'met' if worst <= TARGET_OVERHEAD_PCT else 'NOT met'}")
    common.write_json(args.json, {"machine": info, "dt": common.DT, "rows": rows,
                                  "target_overhead_pct": TARGET_OVERHEAD_PCT, "worst_overhead_pct": worst})


if __name__ == "__main__":
    main()
