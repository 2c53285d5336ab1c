"""Backward Euler against BDF2 (SolverOptions.integrator): order of convergence and energy over time.

Scenes (float64, no wind, no collisions, tight solves: cg_tol 1e-12):
    free fall   a 0.5 m 2x2 sheet falling for T = 0.4 s; error against the exact x(T) = x0 - g T^2 / 2
    swinging    a 0.5 m 6x6 sheet of an isotropic material (density 0.2 kg/m^2, stretch 200 N/m, shear 50 N/m,
                bending 1e-4) hanging in the XZ plane from soft handles at its two top corners (300 N/m), every
                particle starting at 1 m/s along x: it swings in its own plane. Error at T = 0.4 s against BDF2 at
                REF_FACTOR times the finest step's count.

    err_m       RMS vertex distance from the exact solution or the reference [m]
    order       least-squares slope of log(err) against log(dt) over the sweep (2 for a second-order method)

Energy: the swinging sheet over ENERGY_T seconds at dt 1/100 and 1/400 (``Simulator.energy``: kinetic, stretching,
bending, gravitational and handle energy); nothing in the scene dissipates, so any loss is the integrator's
numerical damping. Reported: the total energy's change relative to its initial value, at the end and at its lowest.

Output: a table, JSON, and a log-log plot of error against dt with the energy curves (PNG beside the JSON).

Usage: python benchmarks/integrators.py [--quick] [--out PATH]
"""

from __future__ import annotations

import time
from pathlib import Path

import common
import numpy as np
import warp as wp
from common import wc

T = 0.4
STEPS = (20, 40, 80, 160, 320, 640)
QUICK_STEPS = (10, 20)
REF_FACTOR = 16
ENERGY_T = 2.0
ENERGY_DTS = (1.0 / 100, 1.0 / 400)
INTEGRATORS = ("euler", "bdf2")
G = 9.8


def options(integrator: str) -> wc.SolverOptions:
    return wc.SolverOptions(integrator=integrator, cg_tol=1.0e-12, cg_max_iters=5000)


def free_fall_model() -> wc.Model:
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_cloth_grid((2, 2), (0.5, 0.5), material=wc.preset("gray-interlock"))
    return b.finalize("cpu", dtype=wp.float64)


def swinging_model() -> tuple[wc.Model, wc.State]:
    material = wc.Material.isotropic(density=0.2, stretch_stiffness=200.0, shear_stiffness=50.0,
                                     bend_stiffness=1.0e-4)
    res, size = 6, 0.5
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # grid y -> world z: a wall
    b.add_cloth_grid((res, res), (size, size), material=material, rot=rot, pos=(0.0, 0.0, -size))
    for corner in (res * (res + 1), res * (res + 1) + res):  # the two top corners
        b.add_handle(corner, stiffness=300.0)
    model = b.finalize("cpu", dtype=wp.float64)
    state = model.state()
    state.particle_v.assign(np.tile([1.0, 0.0, 0.0], (model.particle_count, 1)))
    return model, state


def final_positions(scene: str, integrator: str, steps: int, horizon: float = T) -> tuple[np.ndarray, float]:
    model, state = (free_fall_model(), None) if scene == "free fall" else swinging_model()
    state = state or model.state()
    sim = wc.Simulator(model, horizon / steps, options=options(integrator))
    t0 = time.perf_counter()
    x = wc.rollout(sim, state, steps=steps)[-1].particle_x.numpy()
    return x, time.perf_counter() - t0


def order_study(scene: str, steps_list) -> list[dict]:
    if scene == "free fall":
        x0 = free_fall_model().particle_x0.numpy()
        exact = x0 - np.array([0.0, 0.0, 0.5 * G * T * T])
    else:
        exact, _ = final_positions(scene, "bdf2", REF_FACTOR * max(steps_list))
    records = []
    for integrator in INTEGRATORS:
        errs = []
        for steps in steps_list:
            x, seconds = final_positions(scene, integrator, steps)
            err = float(np.sqrt(np.mean(np.sum((x - exact) ** 2, axis=1))))
            errs.append(err)
            records.append({"scene": scene, "integrator": integrator, "steps": steps, "dt": T / steps, "err_m": err,
                            "seconds": seconds})
        slope = float(np.polyfit(np.log([T / s for s in steps_list]), np.log(errs), 1)[0])
        for r in records[-len(steps_list):]:
            r["order"] = slope
    return records


def energy_study(dts, horizon: float) -> list[dict]:
    records = []
    for integrator in INTEGRATORS:
        for dt in dts:
            model, state = swinging_model()
            sim = wc.Simulator(model, dt, options=options(integrator))
            steps = int(round(horizon / dt))
            totals = [sim.energy(state)["total"]]
            for _ in range(steps):
                nxt = model.empty_state()
                sim.step(state, nxt)
                state = nxt
                totals.append(sim.energy(state)["total"])
            e = np.array(totals)
            kinetic0 = 0.5 * float(np.sum(model.particle_mass())) * 1.0  # the start's kinetic energy: 1 m/s
            records.append({"integrator": integrator, "dt": dt, "steps": steps, "energy": e.tolist(),
                            "end_change": float((e[-1] - e[0]) / kinetic0),
                            "lowest_change": float((e.min() - e[0]) / kinetic0)})
    return records


def plot(orders: list[dict], energies: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    for ax, scene in zip(axes[:2], ("free fall", "swinging")):
        for k, integrator in enumerate(INTEGRATORS):
            rs = [r for r in orders if r["scene"] == scene and r["integrator"] == integrator]
            if rs:
                ax.loglog([r["dt"] for r in rs], [r["err_m"] for r in rs], "o-", color=f"C{k}",
                          label=f"{integrator} (slope {rs[0]['order']:.2f})")
        rs = [r for r in orders if r["scene"] == scene]
        if rs:
            dts = np.array(sorted({r["dt"] for r in rs}))
            top = max(r["err_m"] for r in rs)
            for p, style in ((1, ":"), (2, "--")):
                ax.loglog(dts, top * (dts / dts.max()) ** p, "k" + style, lw=0.8, label=f"order {p}")
        ax.set_xlabel("dt [s]")
        ax.set_ylabel("RMS error at T [m]")
        ax.set_title(f"{scene}, T = {T} s")
        ax.legend(fontsize=8)
    ax = axes[2]
    for r in energies:
        t = np.arange(len(r["energy"])) * r["dt"]
        k = INTEGRATORS.index(r["integrator"])
        e = np.array(r["energy"])
        ax.plot(t, e - e[0], color=f"C{k}", ls="-" if r["dt"] == max(ENERGY_DTS) else "--",
                label=f"{r['integrator']} dt 1/{round(1 / r['dt'])}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("total energy - initial [J]")
    ax.set_title("swinging sheet: energy (nothing dissipates)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")


def main():
    args = common.parse_args(__doc__)
    steps_list = QUICK_STEPS if args.quick else STEPS
    energy_t = 0.1 if args.quick else ENERGY_T
    orders = order_study("free fall", steps_list) + order_study("swinging", steps_list)
    rows = [[r["scene"], r["integrator"], f"1/{round(1 / r['dt'])}", f"{r['err_m']:.3e}", f"{r['order']:.2f}",
             f"{r['seconds']:.2f}"] for r in orders]
    common.print_table(["scene", "integrator", "dt", "err m", "order", "wall s"], rows,
                       title=f"order of convergence at T = {T} s (float64, cg_tol 1e-12)")
    energies = energy_study(ENERGY_DTS, energy_t)
    print()
    common.print_table(["integrator", "dt", "energy change at the end", "lowest"],
                       [[r["integrator"], f"1/{round(1 / r['dt'])}", f"{100 * r['end_change']:+.2f} %",
                         f"{100 * r['lowest_change']:+.2f} %"] for r in energies],
                       title=f"swinging sheet over {energy_t:g} s: total energy change in % of the initial kinetic "
                             "energy")
    path = common.write_result(args, {"T": T, "orders": orders, "energies": energies, "energy_T": energy_t})
    plot(orders, energies, path.with_suffix(".png"))


if __name__ == "__main__":
    main()
