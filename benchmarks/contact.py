"""Contact: a cloth draped on a sphere with repulsion and friction, wall time per step and per phase; and the
closed-form checks of friction on an incline.

Drape: the embedded drape-sphere scene (a 1 m gray-interlock square, thicken 2, dropped from 0.1 m onto a 0.3 m
sphere, dt 0.01, 100 steps, obstacle friction 0.3) at its 24x24 grid and at 64x64. Phases (Simulator.phase_seconds):
assembly (elements, handles, pins), proximity (pair detection, repulsion and friction terms), solve (CG), integrate,
collision (the impact-zone projection's detection and QP, the fail-safe).

Incline: a 0.1 m patch on a plane tilted 10 degrees (below atan 0.3) and 30 degrees with mu 0.3, 1 s at dt 0.01:
the distance slid, and the fitted acceleration against g (sin theta - mu cos theta).

Drag: a 0.1 m patch (3x3 cells) on a pinned 1 m x 0.4 m sheet (8x8), cloth-cloth mu 0.6, pushed along x by a force
per particle of m (mu g + p), p = 0.5 and 2 m/s^2, for 0.6 s: the friction it feels, (force - m a) / (mu m g),
should be 1.

Usage: python benchmarks/contact.py [--quick] [--out PATH] [--sizes 24,64] [--steps 100]
"""

from __future__ import annotations

import math
import time

import common
import numpy as np
import warp as wp

import warpcloth as wc

G = 9.8


def drape(res: int, steps: int) -> dict:
    scene = wc.load_scene("drape-sphere")
    b = wc.ModelBuilder()
    b.add_cloth_grid((res, res), (1.0, 1.0), material=wc.preset("gray-interlock", thicken=2), pos=(-0.5, -0.5, 0.4))
    b.add_obstacle_sphere(0.3, subdivisions=3)
    b.set_collision()
    model = b.finalize("cpu")
    sim = wc.Simulator(model, scene.dt)
    wc.rollout(sim, model.state(), steps=1)  # compiles and builds the BVHs
    sim = wc.Simulator(model, scene.dt)
    state = model.state()
    step_times, pairs = [], []
    t0 = time.perf_counter()
    for _ in range(steps):
        nxt = model.empty_state()
        t = time.perf_counter()
        sim.step(state, nxt)
        step_times.append(time.perf_counter() - t)
        pairs.append(sim.proximity.last_count)
        state = nxt
    wall = time.perf_counter() - t0
    x = state.particle_x.numpy()
    return {"res": res, "steps": steps, "wall_s": wall, "max_step_s": max(step_times),
            "mean_step_ms": 1e3 * wall / steps, "phase_ms_per_step": {k: 1e3 * v / steps
                                                                     for k, v in sim.phase_seconds.items()},
            "cg_iterations_per_step": sim.stats["cg_iterations"] / steps, "pairs_mean": float(np.mean(pairs)),
            "min_distance_to_centre_m": float(np.linalg.norm(x, axis=1).min())}


def incline(theta_deg: float, mu: float, steps: int) -> dict:
    th = math.radians(theta_deg)
    R = np.array([[math.cos(th), 0.0, -math.sin(th)], [0.0, 1.0, 0.0], [math.sin(th), 0.0, math.cos(th)]])
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_obstacle_plane((4.0, 4.0), rot=R)
    mesh = wc.grid_mesh(4, 4, 0.1, 0.1)
    mesh.positions = (mesh.positions + [0.45, 1.15, 0.00486]) @ R.T
    b.add_cloth_mesh(mesh, material=wc.preset("gray-interlock"))
    b.set_collision(friction=mu, obstacle_friction=mu)
    model = b.finalize("cpu", dtype=wp.float64)
    dt = 0.01
    traj = wc.rollout(wc.Simulator(model, dt), model.state(), steps=steps)
    com = np.array([s.particle_x.numpy().mean(axis=0) for s in traj])
    travel = (com - com[0]) @ (R @ np.array([-1.0, 0.0, 0.0]))
    t = np.arange(len(travel)) * dt
    fitted = 2.0 * np.polyfit(t[10:], travel[10:], 2)[0]
    expected = max(G * (math.sin(th) - mu * math.cos(th)), 0.0)
    return {"theta_deg": theta_deg, "mu": mu, "seconds": steps * dt, "travel_mm": 1e3 * float(travel[-1]),
            "acceleration": float(fitted), "expected_acceleration": expected}


def drag(steps: int, mu: float = 0.6, push: float = 2.0) -> dict:
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_cloth_grid((8, 8), (1.0, 0.4), material=wc.preset("gray-interlock"), pos=(-0.5, -0.2, 0.0))
    lower = 81
    for p in range(lower):
        b.add_pin(p)
    b.add_cloth_grid((3, 3), (0.1, 0.1), material=wc.preset("gray-interlock"), pos=(-0.3, -0.0513, 0.00486))
    b.set_collision(self_collision=True, friction=mu)
    model = b.finalize("cpu", dtype=wp.float64)
    control = model.control(particle_force=True)
    mass = model.particle_mass()
    force = np.zeros((model.particle_count, 3))
    force[lower:, 0] = mass[lower:] * (mu * G + push)
    control.particle_force.assign(force)
    dt = 0.01
    traj = wc.rollout(wc.Simulator(model, dt), model.state(), control, steps=steps)
    com = np.array([s.particle_x.numpy()[lower:].mean(axis=0) for s in traj])
    t = np.arange(len(com)) * dt
    a = 2.0 * np.polyfit(t[10:], com[10:, 0], 2)[0]
    return {"mu": mu, "seconds": steps * dt, "acceleration": float(a), "expected_acceleration": push,
            "friction_over_mu_load": float((mu * G + push - a) / (mu * G))}


def main():
    args = common.parse_args(__doc__, sizes="24,64", steps=100, quick={"sizes": "8", "steps": 5})
    info = common.machine_info()
    common.print_machine(info)
    drapes = [drape(int(r), args.steps) for r in args.sizes.split(",")]
    common.print_table(["grid", "wall s", "ms/step", "max step s", "assembly", "proximity", "solve", "integrate",
                        "collision", "CG it/step", "pairs"],
                       [[f"{d['res']}x{d['res']}", d["wall_s"], d["mean_step_ms"], d["max_step_s"],
                         *d["phase_ms_per_step"].values(), d["cg_iterations_per_step"], d["pairs_mean"]]
                        for d in drapes], specs=["", ".2f", ".1f", ".3f", ".2f", ".2f", ".2f", ".2f", ".2f", ".1f",
                                                 ".0f"],
                       title=f"drape on a sphere, {args.steps} steps of 0.01 s (phases in ms per step)")
    steps = 30 if args.quick else 100
    inclines = [incline(10.0, 0.3, steps), incline(30.0, 0.3, steps)]
    common.print_table(["theta", "mu", "slid mm", "a fitted", "a = g(sin - mu cos)"],
                       [[i["theta_deg"], i["mu"], i["travel_mm"], i["acceleration"], i["expected_acceleration"]]
                        for i in inclines], specs=[".0f", ".1f", ".3f", ".3f", ".3f"],
                       title=f"patch on an incline, {steps * 0.01:g} s")
    drags = [drag(30 if args.quick else 60, push=push) for push in (0.5, 2.0)]
    common.print_table(["mu", "a fitted", "a expected", "friction / (mu load)"],
                       [[d["mu"], d["acceleration"], d["expected_acceleration"], d["friction_over_mu_load"]]
                        for d in drags], specs=[".1f", ".3f", ".3f", ".3f"],
                       title="patch dragged over a pinned sheet")
    common.write_result(args, {"drape": drapes, "incline": inclines, "drag": drags})


if __name__ == "__main__":
    main()
