"""Speed against accuracy: sweep the time step, the CG tolerances and iteration cap, the mesh resolution and the
collision settings, and measure wall time and error against a converged reference of the same scene.

Scenes (1 m square of gray-interlock, thicken 2, float32 unless a row says otherwise):
    hanging   vertical sheet held by soft handles at its two top corners in a 5 m/s wind, 16x16, T = 0.4 s
    sphere    horizontal sheet dropped 0.1 m onto a 0.3 m sphere and draped over it, 16x16, T = 0.3 s

Reference: the same scene in float64 at a finer time step than any in the sweep (hanging 1/2000 s, sphere 1/800 s),
with the second-order integrator (SolverOptions(integrator="bdf2")), CG tolerance 1e-10 (resolution rows: the
finest mesh at the row's dt and with its integrator, compared on the 9x9 lattice of material points every grid
shares; thickness rows: a reference with the row's thickness).
The hanging sheet flaps: trajectories with different time steps drift apart after about half a second (dt 1/50
against 1/1000 in float64: 4 % at 0.2 s, 9 % at 0.4 s, 17 % at 0.6 s, and beyond 0.6 s no longer smaller for smaller
dt), so its horizon is 0.4 s; a longer one would measure the flapping's sensitivity, not the solver. Likewise the
frictionless sheet slides off the sphere's top in a direction that tiny differences decide (dt 1/50 against 1/800:
1.7 % at 0.2 s, 6.6 % at 0.3 s, 10 % at 0.4 s, and at 0.4 s dt 1/200 is no better than 1/100), so its horizon is
0.3 s: the fall, the impact and the start of the drape.

    err_pct       RMS distance of the vertices at T from the reference's, in % of the cloth's 1 m side
    grad_err_pct  relative error |g - g_ref| / |g_ref| in % of the gradient g = d(loss)/d(log scale) of the
                  density, the stretching table, the bending table [and the wind velocity];
                  loss = mean |x_T - x_0|^2
    solve_err_pct, solve_grad_err_pct   (solver rows) the same errors against the float64 solve at cg_tol 1e-10
                  with the row's own dt: what the solver settings alone cost, without the time step's error
    wall_s        wall time of the forward rollout per simulated second (no tape)
    grad_wall_s   wall time of the taped forward + backward per simulated second
    cg_fails      steps whose forward or adjoint solve missed its tolerance (each warns)

A setting the simulator cannot run raises; the row shows the error. The presets (warpcloth.solver.presets) are measured
the same way. Output: a table per scene, JSON, and a Pareto plot of error against wall time (PNG).

Usage: python benchmarks/tradeoff.py [--quick] [--out PATH] [--plot PNG] [--scenes hanging,sphere]
       python benchmarks/tradeoff.py --from-json PATH [--plot PNG]    (table and plot of an earlier run)
--quick: 8x8 sheets over a few steps (QUICK_SCENES), one or two settings per family: checks that every path runs,
its figures mean nothing. The plot goes beside the JSON (results/tradeoff.png; results/quick/ with --quick).
"""

from __future__ import annotations

import os

# The collision projection's dense algebra runs in NumPy on the host; a multi-threaded BLAS spin-waits against other
# jobs on a shared 2-core machine, so this benchmark uses one BLAS thread unless the environment says otherwise (set
# before NumPy loads; recorded in the JSON's meta.env).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import json  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import common  # noqa: E402
import numpy as np  # noqa: E402
import warp as wp  # noqa: E402
from common import wc  # noqa: E402

SIZE = 1.0
"""Side of the square cloth [m]: errors are reported in % of it."""
REF_TOL = 1.0e-10
LATTICE = 8
"""Resolution rows compare the (LATTICE+1)^2 material points every grid of the sweep has."""


# -- scenes ----------------------------------------------------------------------------------------------------------
def hanging(res: int, *, dtype, requires_grad: bool, thickness=None) -> wc.Model:
    return common.hanging_cloth(res, dtype=dtype, requires_grad=requires_grad)


def sphere(res: int, *, dtype, requires_grad: bool, thickness: float = 5.0e-4) -> wc.Model:
    b = wc.ModelBuilder(gravity=common.GRAVITY)
    b.add_cloth_grid((res, res), (SIZE, SIZE), material=wc.preset("gray-interlock", thicken=common.THICKEN),
                     pos=(-0.5 * SIZE, -0.5 * SIZE, 0.4))
    b.add_obstacle_sphere(0.3, 3, name="ball")
    b.set_collision(thickness=thickness)
    return b.finalize("cpu", requires_grad=requires_grad, dtype=dtype)


SCENES = {
    # name: (builder, simulated time [s], baseline dt, finest dt, coarsest dt)
    "hanging": (hanging, 0.4, 1.0 / 50, 1.0 / 2000, 1.0 / 25),
    "sphere": (sphere, 0.3, 1.0 / 100, 1.0 / 800, 1.0 / 25),
}
QUICK_SCENES = {
    "hanging": (hanging, 0.08, 1.0 / 50, 1.0 / 400, 1.0 / 25),
    "sphere": (sphere, 0.16, 1.0 / 50, 1.0 / 100, 1.0 / 25),
}
BASE_RES = {"full": 16, "quick": 8}
"""Resolution of every row but the resolution family's."""
MODE = {"base_res": BASE_RES["full"]}


@wp.kernel
def displacement_loss(x0: wp.array(dtype=Any), x1: wp.array(dtype=Any), loss: wp.array(dtype=Any)):
    i = wp.tid()
    d = x1[i] - x0[i]
    wp.atomic_add(loss, 0, wp.dot(d, d) / loss.dtype(x0.shape[0]))


# -- one run ---------------------------------------------------------------------------------------------------------
def run(scene: str, *, res: int | None = None, dt: float | None = None, dtype=wp.float32, thickness: float = 5.0e-4,
        options: wc.SolverOptions | None = None, gradient: bool = True) -> dict:
    """Forward (timed, no tape) and, with ``gradient``, taped forward + backward of one setting."""
    build, T, base_dt, _, _ = SCENES[scene]
    res = res or MODE["base_res"]
    dt = dt or base_dt
    steps = int(round(T / dt))
    options = options or wc.SolverOptions()
    out = {"scene": scene, "res": res, "dt": dt, "steps": steps, "dtype": "float64" if dtype == wp.float64
           else "float32", "thickness": thickness if scene == "sphere" else None,
           "cg_tol": options.cg_tol, "adjoint_cg_tol": options.adjoint_cg_tol or options.cg_tol,
           "cg_max_iters": options.cg_max_iters, "collision_rounds": options.collision.rounds if scene == "sphere"
           else None}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        try:
            model = build(res, dtype=dtype, requires_grad=False, thickness=thickness)
            sim = wc.Simulator(model, dt, options=options)
            wc.rollout(sim, model.state(), steps=1)  # compiles the modules outside the timing
            sim = wc.Simulator(model, dt, options=options)
            seconds, traj = common.timed(wc.rollout, sim, model.state(), steps=steps)
            out["x"] = traj[-1].particle_x.numpy().astype(np.float64)
            out["wall_s"] = seconds / T
            out["cg_iters"] = sim.stats["cg_iterations"] / steps
            if gradient:
                t_grad, out["grad"] = _gradient(build, res, dt, steps, dtype, thickness, options)
                out["grad_wall_s"] = t_grad / T
        except Exception as err:  # a setting the simulator cannot run: the row shows why
            out["error"] = f"{type(err).__name__}: {str(err).splitlines()[0][:150]}"
            if not isinstance(err, (wc.SimulationError, ValueError, RuntimeError)):
                traceback.print_exc()
    out["cg_fails"] = sum("CG solve" in str(w.message) for w in caught)
    return out


def _gradient(build, res, dt, steps, dtype, thickness, options):
    model = build(res, dtype=dtype, requires_grad=True, thickness=thickness)
    sim = wc.Simulator(model, dt, options=options)
    t0 = time.perf_counter()
    tape = wp.Tape()
    with tape:
        traj = wc.rollout(sim, model.state(), steps=steps)
        loss = wp.zeros(1, dtype=model.scalar, requires_grad=True)
        wp.launch(displacement_loss, model.particle_count, inputs=[traj[0].particle_x, traj[-1].particle_x],
                  outputs=[loss])
    tape.backward(loss)
    wp.synchronize()
    seconds = time.perf_counter() - t0
    groups = {"density": model.material_density, "stretching": model.material_stretching,
              "bending": model.material_bending, "wind": model.wind_velocity}
    # d(loss)/d(log of each group's scale): one well-conditioned number per physical parameter (single table entries
    # hit by a few strongly bent hinges have large, dt-dependent sensitivities that say little about the solver)
    grad = {k: float(np.sum(a.grad.numpy().astype(np.float64) * a.numpy())) for k, a in groups.items()
            if a is not None}
    tape.reset()
    return seconds, grad


# -- errors against the reference ------------------------------------------------------------------------------------
def lattice(x: np.ndarray, res: int) -> np.ndarray:
    """The (LATTICE+1)^2 material points shared by every grid of the sweep (vertex (i, j) = j (res + 1) + i)."""
    step = res // LATTICE
    idx = [j * (res + 1) + i for j in range(0, res + 1, step) for i in range(0, res + 1, step)]
    return x[idx]


def score(row: dict, ref: dict, *, compare_lattice: bool = False) -> dict:
    if "x" in row and "x" in ref:
        x, xr = row["x"], ref["x"]
        if compare_lattice:
            x, xr = lattice(x, row["res"]), lattice(xr, ref["res"])
        row["err_pct"] = 100.0 * float(np.sqrt(np.mean(np.sum((x - xr) ** 2, axis=1)))) / SIZE
    if "grad" in row and "grad" in ref:
        g, gr = (np.array([d[k] for k in sorted(ref["grad"])]) for d in (row["grad"], ref["grad"]))
        row["grad_err_pct"] = 100.0 * float(np.linalg.norm(g - gr) / max(np.linalg.norm(gr), 1e-300))
    return row


# -- sweeps ----------------------------------------------------------------------------------------------------------
def sweeps(scene: str, quick: bool) -> list[tuple[str, str, dict]]:
    """(family, label, run() keywords) of every setting of a scene."""
    _, T, base_dt, fine_dt, coarse_dt = SCENES[scene]
    rows = []
    dts = [1 / 25, 1 / 50, 1 / 100, 1 / 200, 1 / 500, 1 / 1000] if scene == "hanging" else \
        [1 / 25, 1 / 50, 1 / 100, 1 / 200, 1 / 400]
    if quick:
        dts = dts[:2]
    for dt in dts:
        rows.append(("dt", f"dt 1/{round(1 / dt)}", {"dt": dt, "options": wc.SolverOptions(cg_tol=1e-8)}))
    for dt in dts:  # the second-order integrator (SolverOptions.integrator) at the same steps
        rows.append(("bdf2", f"bdf2 dt 1/{round(1 / dt)}",
                     {"dt": dt, "options": wc.SolverOptions(cg_tol=1e-8, integrator="bdf2")}))
    for dt in ([1 / 50, 1 / 100, 1 / 200] if not quick else []):
        rows.append(("bdf2+cg_tol 1e-3", f"bdf2 dt 1/{round(1 / dt)} tol 1e-3",
                     {"dt": dt, "options": wc.SolverOptions(cg_tol=1e-3, integrator="bdf2")}))
    for dt in ([1 / 100, 1 / 200, 1 / 400] if not quick else []):  # small steps with a loose solve
        rows.append(("dt+cg_tol 1e-3", f"dt 1/{round(1 / dt)} tol 1e-3", {"dt": dt,
                                                                        "options": wc.SolverOptions(cg_tol=1e-3)}))
    tols = [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-8] if not quick else [1e-2]
    for tol in tols:
        rows.append(("cg_tol", f"cg_tol {tol:g}", {"options": wc.SolverOptions(cg_tol=tol)}))
    for tol in ([1e-2, 1e-4, 1e-6] if not quick else [1e-2]):
        rows.append(("adjoint_cg_tol", f"adjoint tol {tol:g}",
                     {"options": wc.SolverOptions(cg_tol=1e-8, adjoint_cg_tol=tol)}))
    for cap in ([2, 5, 10, 20, 50] if not quick else [5]):
        rows.append(("cg_max_iters", f"{cap} CG iters", {"options": wc.SolverOptions(cg_tol=1e-8, cg_max_iters=cap)}))
    rows.append(("dtype", "float64", {"dtype": wp.float64, "options": wc.SolverOptions(cg_tol=1e-8)}))
    if scene == "hanging":
        for res in ([8, 16, 32, 64, 128] if not quick else [8, 16]):
            rows.append(("res", f"{res}x{res}", {"res": res}))
    else:
        for thickness in ([1e-4, 5e-4, 2e-3, 5e-3] if not quick else [2e-3]):
            rows.append(("thickness", f"thickness {thickness:g}", {"thickness": thickness}))
        for rounds in ([1, 2, 5, 10, 20] if not quick else [20]):
            rows.append(("collision_rounds", f"{rounds} rounds",
                         {"options": wc.SolverOptions(collision=wc.CollisionOptions(rounds=rounds))}))
    for name in wc.PRESET_SOLVER_NAMES[:1] if quick else wc.PRESET_SOLVER_NAMES:
        preset = wc.solver_preset(name)
        rows.append(("preset", f"preset {name}", {"options": preset.options, "dt": preset.dt(base_dt)}))
    return rows


OWN_REFERENCE = ("res", "thickness")
"""Families scored against a reference of their own (finest mesh; same thickness), so not comparable with the rest."""
SOLVER_FAMILIES = ("cg_tol", "adjoint_cg_tol", "cg_max_iters", "dtype", "collision_rounds", "preset")
"""Rows also scored against the tight float64 solve at their own dt (solve_err_pct, solve_grad_err_pct)."""


def reference(scene: str, res: int, thickness: float = 5.0e-4, dt: float | None = None,
              integrator: str = "euler") -> dict:
    """A tight float64 run: at the scene's finest step with BDF2 (the accuracy reference), or at a row's own step
    and integrator (what the row's solver settings or mesh alone cost)."""
    _, _, _, fine_dt, _ = SCENES[scene]
    opts = wc.SolverOptions(cg_tol=REF_TOL, cg_max_iters=10_000, integrator=integrator,
                            collision=wc.CollisionOptions(rounds=100))
    return run(scene, res=res, dt=dt or fine_dt, dtype=wp.float64, thickness=thickness, options=opts)


def measure(scene: str, quick: bool, progress) -> list[dict]:
    refs: dict[tuple, dict] = {}

    def ref_for(key, **kw):
        if key not in refs:
            refs[key] = reference(scene, **kw)
            if "error" in refs[key]:
                raise SystemExit(f"{scene}: the reference run failed: {refs[key]['error']}")
        return refs[key]

    settings = sweeps(scene, quick)
    finest = max((k["res"] for f, _, k in settings if f == "res"), default=None)
    rows = []
    for family, label, kw in settings:
        row = run(scene, **kw)
        row.update(family=family, label=label)
        if family == "res":
            # resolution: against the finest mesh at the same dt (the discretisation of space alone)
            score(row, ref_for(("res", finest), res=finest, dt=row["dt"]), compare_lattice=True)  # Euler rows
        elif family == "thickness":
            score(row, ref_for(("thickness", kw["thickness"]), res=MODE["base_res"], thickness=kw["thickness"],
                               integrator="bdf2"))
        else:
            score(row, ref_for(("base",), res=MODE["base_res"], integrator="bdf2"))
        if family in SOLVER_FAMILIES:
            # the same discrete system solved tightly: what the solver settings alone cost in accuracy
            integrator = kw.get("options", wc.SolverOptions()).integrator
            same = score(dict(row), ref_for(("dt", row["dt"], integrator), res=MODE["base_res"], dt=row["dt"],
                                            integrator=integrator))
            row["solve_err_pct"], row["solve_grad_err_pct"] = same.get("err_pct"), same.get("grad_err_pct")
        rows.append(row)
        progress(row)
    return rows


# -- output ----------------------------------------------------------------------------------------------------------
HEADERS = ["setting", "dt", "err_pct", "grad_err_pct", "solve_err_pct", "solve_grad_err_pct", "wall_s",
           "grad_wall_s", "cg_iters", "cg_fails", "error"]
SPECS = ["", ".4g", ".3g", ".3g", ".2g", ".2g", ".3g", ".3g", ".1f", "d", ""]


def table_row(r: dict) -> list:
    return [r["label"], r["dt"], r.get("err_pct"), r.get("grad_err_pct"), r.get("solve_err_pct"),
            r.get("solve_grad_err_pct"), r.get("wall_s"), r.get("grad_wall_s"), r.get("cg_iters"), r.get("cg_fails"),
            r.get("error", "")[:70]]


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both time and error, by increasing time."""
    order = sorted(range(len(points)), key=lambda i: points[i])
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def plot(results: dict[str, list[dict]], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(results), figsize=(6 * len(results), 9), squeeze=False)
    for col, (scene, rows) in enumerate(results.items()):
        for r_i, (err_key, time_key, what) in enumerate((("err_pct", "wall_s", "trajectory"),
                                                         ("grad_err_pct", "grad_wall_s", "gradient"))):
            ax = axes[r_i][col]
            ok = [r for r in rows if r.get(err_key) is not None and r.get(time_key) is not None]
            for k, family in enumerate(dict.fromkeys(r["family"] for r in ok)):
                pts = [r for r in ok if r["family"] == family]
                own = family in OWN_REFERENCE
                ax.scatter([r[time_key] for r in pts], [max(r[err_key], 1e-8) for r in pts],
                           label=f"{family} (own reference)" if own else family,
                           marker="*" if family == "preset" else ("s" if own else "o"),
                           s=90 if family == "preset" else 30, edgecolors=f"C{k}",
                           facecolors="none" if own else f"C{k}")
                for r in pts:
                    if family == "preset":
                        ax.annotate(r["label"].split()[-1], (r[time_key], max(r[err_key], 1e-8)), fontsize=8)
            # resolution and thickness rows are scored against references of their own: not on the front
            same_ref = [r for r in ok if r["family"] not in OWN_REFERENCE]
            front = pareto([(r[time_key], max(r[err_key], 1e-8)) for r in same_ref])
            ax.plot([same_ref[i][time_key] for i in front], [max(same_ref[i][err_key], 1e-8) for i in front], "k--",
                    lw=0.8, label="Pareto front")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel(f"wall time per simulated second [s] ({'forward' if r_i == 0 else 'forward + backward'})")
            ax.set_ylabel(f"{what} error [%]")
            ax.set_title(f"{scene}: {what} error against time")
            ax.grid(True, which="both", lw=0.3)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main():
    args = common.parse_args(__doc__, plot="", scenes="hanging,sphere", from_json="")
    if not args.plot:
        args.plot = str(Path(args.out).with_suffix(".png"))
    if args.from_json:  # table and plot again from a previous run's JSON
        data = json.loads(Path(args.from_json).read_text())
        for scene, rows in data["scenes"].items():
            common.print_table(HEADERS, [table_row(r) for r in rows], SPECS, title=scene)
        if args.plot:
            plot(data["scenes"], args.plot)
        return
    if args.quick:
        SCENES.update(QUICK_SCENES)
        MODE["base_res"] = BASE_RES["quick"]
    info = common.machine_info()
    common.print_machine(info)
    results = {}
    for scene in args.scenes.split(","):
        print(f"\n{scene}: measuring ...", flush=True)
        rows = measure(scene, bool(args.quick), lambda r: print(f"  {r['label']:<22} err {r.get('err_pct')} "
                                                                 f"{r.get('error', '')}", flush=True))
        results[scene] = rows
        common.print_table(HEADERS, [table_row(r) for r in rows], SPECS,
                           title=f"{scene} (T = {SCENES[scene][1]} s; errors against float64, dt "
                                 f"1/{round(1 / SCENES[scene][3])}, cg_tol {REF_TOL:g})")
    if args.plot:
        plot(results, args.plot)
    strip = ("x", "grad")
    common.write_result(args, {"reference_cg_tol": REF_TOL, "base_res": MODE["base_res"],
                               "scenes_settings": {s: {"T": SCENES[s][1], "baseline_dt": SCENES[s][2],
                                                       "reference_dt": SCENES[s][3]} for s in results},
                               "scenes": {s: [{k: v for k, v in r.items() if k not in strip} for r in rows]
                                          for s, rows in results.items()}})


if __name__ == "__main__":
    main()
