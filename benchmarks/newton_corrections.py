"""How much of BDF2's error is its linearisation? BDF2 with Newton corrections, emulated with the public API.

The library's step (SolverOptions(integrator="bdf2")) solves one linear system per step: ARCSim's linearisation of
the backward-Euler step of 2/3 dt from the blend, with ARCSim's stiffness (its stretching Hessian keeps only the
positive-definite part, so it is not the exact Jacobian). Here each step instead goes on with ``corrections`` Newton
iterations on the nonlinear BDF2 system R(v) = M (v - v~) - h f(x~ + h v, v) = 0 (h = 2/3 dt), each one assembling
the system at the iterate with ``Simulator.assemble`` and solving it directly (SciPy, exact): J dv = -R(v_k) with
-R(v_k) = b(x_k, v_k) + h^2 H(x_k) v_k - M (v_k - v~), where b and J = M + h (h + beta) H + ... are the assembled
right-hand side and matrix at (x_k, v_k). Zero corrections is the library's step (checked against it on the scene
without wind). The wind is evaluated at each iterate (the library takes it at the extrapolation 2 x_n - x_{n-1}).

Scenes (16x16, float64, each error against the same method at dt 1/REF_STEPS_PER_S; --quick: 8x8, fewer steps):
    hanging   benchmarks/tradeoff.py's hanging sheet (gray-interlock, soft handles, 5 m/s wind), T = 0.4 s
    pinned    benchmarks/peers.py's sheet (isotropic, two pinned corners, no wind), T = 0.5 s

    err_pct   RMS vertex distance at T from the reference, in % of the 1 m side
    solves    linear solves (and assemblies) per step: the cost, against 1 for the library's step

Usage: python benchmarks/newton_corrections.py [--quick] [--out PATH]
"""

from __future__ import annotations

import time

import common
import numpy as np
import peers
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import warp as wp
from common import wc

RES, QUICK_RES = 16, 8
STEPS_PER_S, QUICK_STEPS_PER_S = (50, 100, 200, 400), (50, 100)
REF_STEPS_PER_S, QUICK_REF_STEPS_PER_S = 2000, 200
CORRECTIONS, QUICK_CORRECTIONS = (0, 1, 3), (0, 1)
HORIZON = {"hanging": 0.4, "pinned": 0.5}


def pinned_sheet(res: int) -> wc.Model:
    positions, triangles = peers.grid(res)
    mesh = wc.TriangleMesh(positions=positions, triangles=triangles, tri_uv=positions[triangles][:, :, :2].copy())
    material = wc.Material.isotropic(density=peers.DENSITY, stretch_stiffness=2 * peers.MU + peers.LAMBDA,
                                     shear_stiffness=2 * peers.MU, poisson_coupling=peers.LAMBDA,
                                     bend_stiffness=peers.BEND_KE)
    b = wc.ModelBuilder(gravity=peers.GRAVITY)
    b.add_cloth_mesh(mesh, material=material)
    for p in peers.pinned(res):
        b.add_pin(p)
    return b.finalize("cpu", dtype=wp.float64)


def model_of(scene: str, res: int) -> wc.Model:
    return common.hanging_cloth(res, dtype=wp.float64) if scene == "hanging" else pinned_sheet(res)


class Bdf2Newton:
    """BDF2 steps with ``corrections`` Newton iterations after the library's linearised solve."""

    def __init__(self, model: wc.Model, corrections: int):
        self.model, self.corrections = model, corrections
        self.offsets, self.columns = model.bsr_offsets.numpy(), model.bsr_columns.numpy()
        self.mass = np.repeat(model.particle_mass(), 3)
        self.fixed = np.repeat(model.particle_pin.numpy() >= 0, 3)  # pinned: their dv is prescribed, no correction
        self.sims = {}

    def assemble(self, h: float, x: np.ndarray, v: np.ndarray):
        sim = self.sims.get(h) or self.sims.setdefault(h, wc.Simulator(self.model, h,
                                                                       options=wc.SolverOptions(cg_tol=1e-10)))
        vec3 = self.model.types.vec3
        values, rhs, _ = sim.assemble(wc.State(wp.array(x.reshape(-1, 3), dtype=vec3),
                                               wp.array(v.reshape(-1, 3), dtype=vec3)))
        n3 = 3 * self.model.particle_count
        A = sp.bsr_matrix((values.numpy(), self.columns, self.offsets), shape=(n3, n3)).tocsc()
        return A, rhs.numpy().reshape(-1).astype(np.float64)

    def run(self, steps_per_s: int, horizon: float) -> np.ndarray:
        dt, m = 1.0 / steps_per_s, self.mass
        alpha, beta = float(self.model.damping_mass.numpy()[0]), float(self.model.damping_stiffness.numpy()[0])
        s0 = self.model.state()
        x = s0.particle_x.numpy().reshape(-1).astype(np.float64)
        v = s0.particle_v.numpy().reshape(-1).astype(np.float64)
        x_last = v_last = None
        for _ in range(round(horizon * steps_per_s)):
            if x_last is None:  # the first step has no history: backward Euler, as the library does
                xb, vb, h = x, v, dt
            else:
                xb, vb, h = (4 * x - x_last) / 3, (4 * v - v_last) / 3, 2 * dt / 3
            A, b = self.assemble(h, xb, vb)
            vk = vb + sla.spsolve(A, b)
            for _ in range(self.corrections):
                A, b = self.assemble(h, xb + h * vk, vk)
                # H v from J = (1 + h alpha) M + h (h + beta) H
                stiffness_v = (A @ vk - (1 + h * alpha) * m * vk) / (h * (h + beta))
                r = b + h * h * stiffness_v - m * (vk - vb)
                r[self.fixed] = 0.0
                vk = vk + sla.spsolve(A, r)
            x_last, v_last = x, v
            x, v = xb + h * vk, vk
        return x.reshape(-1, 3)


def library_bdf2(model: wc.Model, steps_per_s: int, horizon: float) -> np.ndarray:
    sim = wc.Simulator(model, 1.0 / steps_per_s, options=wc.SolverOptions(integrator="bdf2", cg_tol=1e-12,
                                                                          cg_atol=1e-30))
    return wc.rollout(sim, model.state(), steps=round(horizon * steps_per_s))[-1].particle_x.numpy()


def main():
    args = common.parse_args(__doc__)
    steps_list = QUICK_STEPS_PER_S if args.quick else STEPS_PER_S
    ref_steps = QUICK_REF_STEPS_PER_S if args.quick else REF_STEPS_PER_S
    res = QUICK_RES if args.quick else RES
    rows = []
    # the emulation with no correction is the library's step (the scene without wind, where they coincide)
    model = model_of("pinned", res)
    check = float(np.abs(Bdf2Newton(model, 0).run(steps_list[0], 0.1) - library_bdf2(model, steps_list[0], 0.1)).max())
    print(f"emulated BDF2 without corrections against the library's step, pinned sheet, 0.1 s: max |dx| {check:.2e} m")
    for scene, horizon in HORIZON.items():
        model = model_of(scene, res)
        for corrections in QUICK_CORRECTIONS if args.quick else CORRECTIONS:
            method = Bdf2Newton(model, corrections)
            ref = method.run(ref_steps, horizon)
            for k in steps_list:
                t0 = time.perf_counter()
                x = method.run(k, horizon)
                err = 100.0 * float(np.sqrt(np.mean(np.sum((x - ref) ** 2, axis=1))))
                rows.append({"scene": scene, "corrections": corrections, "solves": corrections + 1, "dt": 1.0 / k,
                             "err_pct": err, "wall_s": time.perf_counter() - t0})
                print(f"{scene:8s} corrections {corrections}  dt 1/{k:<4d} err {err:7.3f} %", flush=True)
    print()
    for scene in HORIZON:
        table = [[r["corrections"], r["solves"]] + [f"{s['err_pct']:.2f}" for s in rows
                                                     if s["scene"] == scene and s["corrections"] == r["corrections"]]
                 for r in rows if r["scene"] == scene and r["dt"] == 1.0 / steps_list[0]]
        common.print_table(["corrections", "solves/step"] + [f"1/{k} err %" for k in steps_list], table,
                           title=f"{scene}: BDF2 error at T = {HORIZON[scene]} s against its own 1/{ref_steps} "
                                 "reference, by Newton corrections per step")
        print()
    common.write_result(args, {"res": res, "horizon": HORIZON, "reference_steps_per_s": ref_steps,
                               "library_check_max_dx_m": check, "rows": rows})


if __name__ == "__main__":
    main()
