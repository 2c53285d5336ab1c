"""Step time of the hanging cloth with and without graph capture, on the CPU or CUDA (issue #37).

Scene: the seed's hanging cloth in the wind (benchmarks/common.py hanging_cloth: 1 m sheet, soft handles on the
top corners, 5 m/s wind, gray-interlock thicken 2), dt 0.02, float32, default SolverOptions (on the CPU the
sequential one-launch CG with the multigrid preconditioner, or block SSOR for several worlds; on CUDA the warp
backend with block Jacobi and device-side convergence), after a spin-up of SPINUP steps. Worlds: copies of the
sheet in one model (``ModelBuilder.replicate``).

    step_ms              wc.rollout per step, checking the failure record every step (sync_every=1, the default)
    step_ms_sync0        the same with SolverOptions(sync_every=0): the record read once, at the rollout's end
    captured_ms          wc.CapturedRollout.run per step (one graph for the rollout)
    world_steps_per_s    worlds x steps per second of the captured rollout
    cg_iters             mean forward CG iterations per step (the most of any world)
    launches_per_step    kernel launches of an uncaptured step (warp.optim's included)
    allocs_per_step      Warp array allocations of an untaped step between two preallocated States (CPU only)
    fwd_bwd_s            a taped rollout and its backward pass, uncaptured and captured (single world only)
    throw                the seed's basket throw, one forward + backward evaluation (ThrowTask.evaluate) at zero
                         pushes (the cloth falls past everything: no contact, no repulsion pair) and at the open
                         loop's best pushes of benchmarks/results/motion_control.json (it lands in the basket:
                         contacts and pairs): a task's first evaluation (uncaptured: fwd_bwd_s, with its Warp
                         launches and arrays made per step), its second (capturing_s: on the CPU it records one
                         speculative graph a step, wc.CapturedRollout) and later ones (replayed_s, with the steps
                         that met contact and ran uncaptured: rerun_steps)
    drape                the drape-sphere scene (24x24 cloth dropped onto a sphere, 100 steps, proximity pairs from
                         its 14th step): the rollout uncaptured and replayed per step (drape_ms, captured_ms), the
                         steps replayed with proximity pairs (pair_steps) and with contacts (contact_steps) in their
                         graphs, and those that ran uncaptured (rerun_steps); the host's reads of whether the
                         replayed steps kept to their plans (flag_reads: one a step, SolverOptions.sync_every 1),
                         and the replay reading them once (captured_read_once_ms, read_once_flag_reads: sync_every
                         0); the same with a loss on the final height, forward + backward (fwd_bwd_s,
                         fwd_bwd_captured_s)
    max_diff             largest difference between the captured and the uncaptured final positions [m] (and
                         wind gradients): 0 on the CPU, where both run the same kernels in the same order; on CUDA
                         the assembly's atomic additions make any two runs differ in the last bits

Each time is the median of --reps repetitions. ``--preconditioners auto,block_jacobi,multigrid`` times each grid
with each (``SolverOptions.preconditioner``: on CUDA the multigrid runs with the tiled backend, each world's V-cycle
on its thread block, where a world fits one, and with the warp backend for one larger world), on the same device in
one run; ``--backends auto,tiled`` likewise with each ``SolverOptions.cg_backend`` (the tiled multigrid at
64x64, which "auto" runs with the warp backend).

Usage: python benchmarks/graph_step.py [--quick] [--device cuda:0] [--sizes 16,64] [--worlds 1,64] [--steps 50]
       [--preconditioners auto] [--backends auto]
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import warnings

import common
import numpy as np
import warp as wp
from common import wc

from warpcloth.tasks import scenes

SPINUP = 10


@wp.kernel
def _height(x: wp.array(dtype=wp.vec3), loss: wp.array(dtype=float)):
    wp.atomic_add(loss, 0, x[wp.tid()][2])


def _loss(trajectory):
    loss = wp.zeros(1, dtype=float, requires_grad=True)
    wp.launch(_height, trajectory[-1].particle_x.shape[0], inputs=[trajectory[-1].particle_x], outputs=[loss])
    return loss


def model_of(res: int, worlds: int, device: str, requires_grad: bool = False) -> wc.Model:
    """The hanging sheet, or ``worlds`` copies of it in one model."""
    builder = scenes.hanging_cloth_builder(wc.preset("gray-interlock", thicken=common.THICKEN), res=res)
    if worlds > 1:
        many = wc.ModelBuilder(gravity=tuple(common.GRAVITY))
        many.replicate(builder, worlds)
        builder = many
    return builder.finalize(device, requires_grad=requires_grad)


def spun_up(sim: wc.Simulator, steps: int) -> wc.State:
    """A flapping cloth's positions and velocities, as a State with no first guess (a cold first solve)."""
    return common.cold(common.advance(sim, sim.model.state(), steps))


def case(res: int, worlds: int, device: str, steps: int, reps: int, preconditioner: str = "auto",
         backend: str = "auto") -> dict:
    model = model_of(res, worlds, device)
    out = {"res": res, "worlds": worlds, "particles": model.particle_count, "steps": steps}
    options = wc.SolverOptions(preconditioner=preconditioner, cg_backend=backend)
    sim = wc.Simulator(model, common.DT, options=options)
    out["backend"], out["preconditioner"] = sim.linear_solver.backend, sim.linear_solver.preconditioner
    start = spun_up(sim, SPINUP)

    def rollout():
        return wc.rollout(sim, start, steps=steps)

    before = sim.stats["cg_iterations"]
    reference = rollout()[-1].particle_x.numpy().copy()
    out["cg_iters"] = (sim.stats["cg_iterations"] - before) / steps
    out["step_ms"] = 1e3 * common.median_time(rollout, reps=reps) / steps
    with common.launch_profile() as launches:
        rollout()
    out["launches_per_step"] = sum(calls for calls, _ in launches.values()) / steps

    sim0 = wc.Simulator(model, common.DT, options=dataclasses.replace(options, sync_every=0))
    out["step_ms_sync0"] = 1e3 * common.median_time(lambda: wc.rollout(sim0, start, steps=steps), reps=reps) / steps

    captured = wc.CapturedRollout(sim, start, steps=steps)
    out["captured_ms"] = 1e3 * common.median_time(captured.run, reps=reps) / steps
    out["world_steps_per_s"] = worlds * 1e3 / out["captured_ms"]
    out["max_diff"] = float(np.abs(captured.run()[-1].particle_x.numpy() - reference).max())

    if wp.get_device(device).is_cpu:  # untaped steps between two preallocated States
        a, b = wc.State(wp.clone(start.particle_x), wp.clone(start.particle_v), start.time), model.empty_state()
        sim.step(a, b)
        sim.step(b, a)
        with common.alloc_profile() as allocs:
            for _ in range(5):
                sim.step(a, b)
                sim.step(b, a)
        out["allocs_per_step"] = None if allocs["count"] is None else allocs["count"] / 10
    return out


def gradient_case(res: int, device: str, steps: int, reps: int) -> dict:
    model = model_of(res, 1, device, requires_grad=True)
    sim = wc.Simulator(model, common.DT)
    start = spun_up(sim, SPINUP)

    def uncaptured():
        tape = wp.Tape()
        with wp.ScopedDevice(device), tape:
            loss = _loss(wc.rollout(sim, start, steps=steps))
        tape.backward(loss)
        grad = model.wind_velocity.grad.numpy().copy()
        tape.zero()
        return grad

    grad = uncaptured()
    out = {"res": res, "steps": steps,
           "fwd_bwd_s": common.median_time(uncaptured, reps=reps)}
    captured = wc.CapturedRollout(sim, start, steps=steps, loss=_loss)
    out["fwd_bwd_captured_s"] = common.median_time(captured.run, reps=reps)
    captured.run()
    out["max_diff"] = float(np.abs(model.wind_velocity.grad.numpy() - grad).max())
    return out


def landing_pushes() -> np.ndarray | None:
    """The open loop's best pushes from zero (benchmarks/results/motion_control.json), which land the cloth in the
    basket; None where that file has none."""
    path = common.RESULTS_DIR / "motion_control.json"
    if not path.exists():
        return None
    runs = json.loads(path.read_text())["open_loop"]["runs"]
    return np.asarray(runs[0]["params"], dtype=np.float64) if runs and "params" in runs[0] else None


def throw_case(device: str, reps: int, steps: int | None, params: np.ndarray) -> dict:
    """The throw's forward + backward at ``params`` (ThrowTask.evaluate): a task's first evaluation (uncaptured), its
    second (it captures the graphs, on the CPU), and later ones (replays); launches and arrays a step."""
    from warpcloth.tasks.throw import ThrowTask

    def task():
        return ThrowTask(**({"steps": steps} if steps else {}))

    with wp.ScopedDevice(device):  # the task's model is made on the default device
        task().evaluate(params)  # compiles
        first, capturing = [], []
        for _ in range(reps):
            replayed = task()
            first.append(common.timed(lambda t=replayed: t.evaluate(params))[0])
            capturing.append(common.timed(lambda t=replayed: t.evaluate(params))[0])
        error = replayed.error_pct(replayed.evaluate(params).positions)
        replay_s = common.median_time(lambda: replayed.evaluate(params), reps=reps)
        with common.launch_profile() as launches, common.alloc_profile() as allocs:
            task().evaluate(params)
        with common.launch_profile() as replay_launches:
            replayed.evaluate(params)
    per_step = 1.0 / replayed.steps
    return {"steps": replayed.steps, "particles": replayed.model.particle_count, "error_pct": error,
            "fwd_bwd_s": float(np.median(first)), "capturing_s": float(np.median(capturing)),
            "replayed_s": replay_s, "rerun_steps": len(replayed.rerun_steps),
            "launches_per_step": per_step * sum(calls for calls, _ in launches.values()),
            "replay_launches_per_step": per_step * sum(calls for calls, _ in replay_launches.values()),
            "allocs_per_step": None if allocs["count"] is None else per_step * allocs["count"]}


def drape_case(device: str, reps: int, steps: int | None) -> dict:
    """The drape-sphere scene, uncaptured and replayed one graph a step, forward and forward + backward."""
    from warpcloth.scene import load_scene

    scene = load_scene("drape-sphere")
    steps = steps or scene.steps
    model = scene.finalize(device=device, requires_grad=True)
    sim = wc.Simulator(model, scene.dt, options=scene.solver_options)
    out = {"steps": steps, "particles": model.particle_count}
    with wp.ScopedDevice(device):
        state = model.state()
        expected = wc.rollout(sim, state, steps=steps)[-1].particle_x.numpy()
        out["drape_ms"] = 1e3 / steps * common.median_time(lambda: wc.rollout(sim, state, steps=steps), reps=reps)
        captured = wc.CapturedRollout(sim, state, steps=steps)
        out["captured_ms"] = 1e3 / steps * common.median_time(captured.run, reps=reps)
        out["max_diff"] = float(np.max(np.abs(captured.trajectory[-1].particle_x.numpy() - expected)))
        out["rerun_steps"] = len(captured.rerun_steps)
        replayed = [k for k in range(steps) if k not in captured.rerun_steps]
        out["pair_steps"] = sum(captured.pair_budgets[k] > 0 for k in replayed)
        out["contact_steps"] = sum(bool(captured.contact_plans[k]) for k in replayed)
        out["flag_reads"] = captured.flag_reads
        # the same replay reading the plans' flags once, after the forward pass (SolverOptions.sync_every = 0)
        once = wc.Simulator(model, scene.dt, options=dataclasses.replace(scene.solver_options, sync_every=0))
        captured = wc.CapturedRollout(once, state, steps=steps)
        out["captured_read_once_ms"] = 1e3 / steps * common.median_time(captured.run, reps=reps)
        out["read_once_flag_reads"] = captured.flag_reads
        out["read_once_max_diff"] = float(np.max(np.abs(captured.trajectory[-1].particle_x.numpy() - expected)))
        taped = model.state(requires_grad=True)

        def uncaptured():
            tape = wp.Tape()
            with tape:
                loss = _loss(wc.rollout(sim, taped, steps=steps))
            tape.backward(loss)
            tape.zero()

        out["fwd_bwd_s"] = common.median_time(uncaptured, reps=reps)
        replayed = wc.CapturedRollout(sim, taped, steps=steps, loss=_loss)
        out["fwd_bwd_captured_s"] = common.median_time(replayed.run, reps=reps)
    return out


def main():
    args = common.parse_args(__doc__, quick={"sizes": "8", "worlds": "1,4", "steps": 5, "reps": 2},
                             device="cpu", sizes="16,64", worlds="1,64", steps=50, reps=3, preconditioners="auto",
                             backends="auto")
    sizes = [int(s) for s in args.sizes.split(",")]
    world_counts = [int(w) for w in args.worlds.split(",")]
    common.print_machine(common.machine_info(args.device))
    warnings.simplefilter("ignore", RuntimeWarning)  # tolerance warnings of the 1024-world float32 solves
    rows = []
    for res in sizes:
        for worlds in world_counts:
            if worlds > 1 and res > 16:
                continue  # many worlds: the 16x16 sheet only
            for backend, preconditioner in itertools.product(args.backends.split(","),
                                                             args.preconditioners.split(",")):
                r = case(res, worlds, args.device, args.steps, args.reps, preconditioner, backend)
                rows.append(r)
                print(f"  {res}x{res} x{worlds} {r['backend']} {r['preconditioner']}: {r['step_ms']:.3f} ms/step, "
                      f"captured "
                      f"{r['captured_ms']:.3f}", flush=True)
    common.print_table(
        ["grid", "worlds", "backend", "precond", "CG it", "launches", "allocs", "step ms", "sync0 ms", "captured ms",
         "world-steps/s", "max diff"],
        [[f"{r['res']}x{r['res']}", r["worlds"], r["backend"], r["preconditioner"], r["cg_iters"],
          r["launches_per_step"], r.get("allocs_per_step"), r["step_ms"], r["step_ms_sync0"], r["captured_ms"],
          r["world_steps_per_s"], r["max_diff"]] for r in rows],
        ["", "", "", "", ".1f", ".1f", ".1f", ".3f", ".3f", ".3f", ",.0f", ".1e"],
        title=f"per step on {args.device} ({args.steps} steps a rollout, median of {args.reps})")
    gradients = [gradient_case(res, args.device, args.steps, args.reps) for res in sizes[:1]]
    common.print_table(
        ["grid", "steps", "fwd+bwd s", "captured s", "max diff"],
        [[f"{g['res']}x{g['res']}", g["steps"], g["fwd_bwd_s"], g["fwd_bwd_captured_s"], g["max_diff"]]
         for g in gradients], ["", "", ".4f", ".4f", ".1e"], title="a taped rollout and its backward pass")
    zero = np.zeros((3, 4, 3))
    landing = None if args.quick else landing_pushes()
    throws = {"zero pushes": throw_case(args.device, args.reps, 20 if args.quick else None, zero)}
    if landing is not None:
        throws["the open loop's pushes"] = throw_case(args.device, args.reps, None, landing)
    for label, throw in throws.items():
        print(f"\nthe throw at {label} ({throw['steps']} steps, {throw['particles']} particles, error "
              f"{throw['error_pct']:.1f} %): forward + backward {throw['fwd_bwd_s']:.3f} s uncaptured "
              f"({throw['launches_per_step']:.1f} launches and {common.fmt(throw['allocs_per_step'], '.1f')} arrays "
              f"a step), {throw['capturing_s']:.3f} s capturing, {throw['replayed_s']:.3f} s replayed "
              f"({throw['rerun_steps']} steps in contact run uncaptured, "
              f"{throw['replay_launches_per_step']:.1f} launches a step)")
    drape = drape_case(args.device, args.reps, 10 if args.quick else None)
    print(f"\ndrape-sphere ({drape['steps']} steps, {drape['particles']} particles): {drape['drape_ms']:.2f} ms a step "
          f"uncaptured, {drape['captured_ms']:.2f} replayed ({drape['pair_steps']} steps replayed with proximity "
          f"pairs, {drape['contact_steps']} with contacts, {drape['rerun_steps']} run uncaptured; max diff "
          f"{drape['max_diff']:.1e}; {drape['flag_reads']} reads of the plans' flags, or "
          f"{drape['captured_read_once_ms']:.2f} ms with {drape['read_once_flag_reads']} (sync_every 0)); forward + "
          f"backward {drape['fwd_bwd_s']:.3f} s, replayed {drape['fwd_bwd_captured_s']:.3f} s")
    common.write_result(args, {"cases": rows, "gradients": gradients, "throw": throws["zero pushes"],
                               "throw_landing": throws.get("the open loop's pushes"), "drape": drape},
                        device=args.device)


if __name__ == "__main__":
    main()
