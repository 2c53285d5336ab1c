"""Rebuild or refit the collision BVHs at each detection (``CollisionOptions.bvh``): wall time and results.

Since contacts and proximity pairs are sorted by key after every query (warpcloth/collision/detection.py RowSort),
the order in which a BVH's traversal meets primitives no longer reaches the results, so a refitted BVH (the topology
of the Simulator's first detection, its boxes moved) gives the same rollout as one rebuilt from the current boxes;
this benchmark checks that (the largest difference of any position over the rollout, expected 0) and times both.

Cases, each uncaptured (``wc.rollout``), the two options interleaved, medians of ``--reps`` runs:
  drape        the drape-sphere scene (a 1 m gray-interlock square dropped on a 0.3 m sphere, repulsion and friction,
               dt 0.01) at its 24x24 grid, 100 steps, and at 64x64, 50 steps
  drape+self   the 24x24 drape with self-collision (the cloth folds over the sphere onto itself)
  pile+self    a 0.6 m 24x24 sheet dropped upright onto the ground, self-collision and friction, dt 0.005, 300 steps:
               it buckles and piles onto itself, far from the flat shape the refitted BVHs were built on
  throw        the seed's basket throw (8x8, 700 steps) at the open loop's pushes, which land it in the basket
               (benchmarks/results/motion_control.json), forward only

Usage: python benchmarks/bvh_update.py [--quick] [--out PATH] [--reps 3]
"""

from __future__ import annotations

import dataclasses
import json

import common
import numpy as np
import warp as wp

import warpcloth as wc

OPTIONS = ("rebuild", "refit")


def drape_model(res: int, self_collision: bool) -> tuple[wc.Model, float]:
    scene = wc.load_scene("drape-sphere")
    b = wc.ModelBuilder()
    b.add_cloth_grid((res, res), (1.0, 1.0), material=wc.preset("gray-interlock", thicken=2), pos=(-0.5, -0.5, 0.4))
    b.add_obstacle_sphere(0.3, subdivisions=3)
    b.set_collision(self_collision=self_collision, obstacle_friction=0.3)
    return b.finalize("cpu"), scene.dt


def pile_model(res: int) -> wc.Model:
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    upright = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # the grid's XY onto world XZ
    b.add_cloth_grid((res, res), (0.6, 0.6), material=wc.preset("gray-interlock", thicken=2), pos=(-0.3, 0.0, 0.02),
                     rot=upright)
    b.add_obstacle_plane((3.0, 3.0))
    b.set_collision(self_collision=True, friction=0.3, obstacle_friction=0.3)
    return b.finalize("cpu")


def landing_pushes(n_params: int) -> np.ndarray:
    """The open loop's best pushes from zero (benchmarks/results/motion_control.json), which land the throw in the
    basket; zeros where that file has none."""
    path = common.RESULTS_DIR / "motion_control.json"
    if path.exists():
        runs = json.loads(path.read_text())["open_loop"]["runs"]
        if runs and "params" in runs[0]:
            return np.asarray(runs[0]["params"], dtype=np.float64)
    return np.zeros(n_params)


def throw(steps: int | None, reps: int) -> dict:
    """The throw's forward pass (ThrowTask.trajectory) with either option."""
    from warpcloth.scene import load_scene
    from warpcloth.tasks.throw import ThrowTask

    options = load_scene("basket-throw").solver_options
    tasks = {bvh: ThrowTask(**({"steps": steps} if steps else {}), options=dataclasses.replace(
        options, collision=dataclasses.replace(options.collision, bvh=bvh))) for bvh in OPTIONS}
    params = landing_pushes(tasks["rebuild"].n_params)
    runs, frames = {bvh: [] for bvh in OPTIONS}, {}
    for bvh in OPTIONS:
        tasks[bvh].trajectory(params)  # compiles, builds the BVHs
    for _ in range(reps):
        for bvh in OPTIONS:
            seconds, frames[bvh] = common.timed(tasks[bvh].trajectory, params)
            runs[bvh].append(seconds)
    task = tasks["rebuild"]
    diff = max(float(np.max(np.abs(a - b))) for a, b in zip(frames["rebuild"], frames["refit"]))
    return summary(task.model.particle_count, task.steps, diff, task.sim, runs)


def compare(model: wc.Model, dt: float, steps: int, reps: int) -> dict:
    """A rollout from the model's start with either option."""
    options = wc.SolverOptions()
    sims = {bvh: wc.Simulator(model, dt, options=dataclasses.replace(
        options, collision=dataclasses.replace(options.collision, bvh=bvh))) for bvh in OPTIONS}
    runs = {bvh: [] for bvh in OPTIONS}
    trajectories = {}
    for bvh in OPTIONS:  # compiles, builds the BVHs
        wc.rollout(sims[bvh], model.state(), steps=1)
    for _ in range(reps):
        for bvh in OPTIONS:
            seconds, trajectory = common.timed(lambda s=sims[bvh]: wc.rollout(s, model.state(), steps=steps))
            runs[bvh].append(seconds)
            trajectories[bvh] = trajectory
    diff = max(float(np.max(np.abs(a.particle_x.numpy() - b.particle_x.numpy())))
               for a, b in zip(trajectories["rebuild"], trajectories["refit"]))
    return summary(model.particle_count, steps, diff, sims["rebuild"], runs)


def summary(particles: int, steps: int, diff: float, sim: wc.Simulator, runs: dict) -> dict:
    out = {"particles": particles, "steps": steps, "max_diff_m": diff,
           "contacts_last_step": sim.collision.last.contacts,
           "pairs_last_step": sim.proximity.last_count if sim.proximity else 0}
    for bvh in OPTIONS:
        out[f"{bvh}_ms_per_step"] = 1e3 * common.median(runs[bvh]) / steps
        out[f"{bvh}_runs_s"] = runs[bvh]
    out["speedup"] = out["rebuild_ms_per_step"] / out["refit_ms_per_step"]
    return out


def main():
    args = common.parse_args(__doc__, reps=3, quick={"reps": 1})
    common.print_machine(common.machine_info())
    quick = args.quick
    cases = {}
    for res, steps in ((8, 10),) if quick else ((24, 100), (64, 50)):
        model, dt = drape_model(res, False)
        cases[f"drape {res}x{res}"] = compare(model, dt, steps, args.reps)
    model, dt = drape_model(8 if quick else 24, True)
    cases[f"drape+self {8 if quick else 24}x{8 if quick else 24}"] = compare(model, dt, 10 if quick else 100,
                                                                             args.reps)
    res = 8 if quick else 24
    cases[f"pile+self {res}x{res}"] = compare(pile_model(res), 0.005, 20 if quick else 300, args.reps)
    cases["throw"] = throw(60 if quick else None, args.reps)
    common.print_table(["case", "particles", "steps", "rebuild ms/step", "refit ms/step", "speedup", "max diff m",
                        "contacts", "pairs"],
                       [[name, c["particles"], c["steps"], c["rebuild_ms_per_step"], c["refit_ms_per_step"],
                         c["speedup"], c["max_diff_m"], c["contacts_last_step"], c["pairs_last_step"]]
                        for name, c in cases.items()],
                       specs=["", "d", "d", ".2f", ".2f", ".2f", ".1e", "d", "d"],
                       title=f"BVHs rebuilt or refitted at each detection, medians of {args.reps} runs, uncaptured")
    common.write_result(args, {"cases": cases})


if __name__ == "__main__":
    wp.init()
    main()
