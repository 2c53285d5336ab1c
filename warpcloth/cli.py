"""The ``warpcloth`` command line (also ``python -m warpcloth``): ``simulate``, ``scenes``, ``estimate`` and
``control``, each described by its ``--help``; errors are one line on stderr, the exit status :func:`main`'s."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from collections.abc import Sequence

from warpcloth.tasks.jobs import CONTROL_SCENE, ESTIMATE_SCENE  # the scenes run when none is named

__all__ = ["main"]

_IDENTIFIABILITY = ("docs/results/seed.md", "Material estimation (Table 2)")  # the page and section that explain it
_USAGE_ERROR = 2
_RUNTIME_ERROR = 1


def _parser() -> argparse.ArgumentParser:
    from warpcloth import __version__
    from warpcloth.scene import DEFAULT_SCENE

    parser = argparse.ArgumentParser(prog="warpcloth", description="Differentiable cloth simulation in NVIDIA Warp.")
    parser.add_argument("--version", action="version", version=f"warpcloth {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    sim = sub.add_parser("simulate", help="simulate a scene and write a time-sampled USD")
    sim.add_argument(
        "scene",
        nargs="?",
        default=DEFAULT_SCENE,
        help=f"embedded scene name or path to a .toml scene file (default: {DEFAULT_SCENE})",
    )
    sim.add_argument("--steps", type=int, default=None, help="number of steps (default: the scene's)")
    sim.add_argument("--dt", type=float, default=None, help="time step in seconds (default: the scene's)")
    sim.add_argument("--usd", metavar="PATH", default=None, help="output USD file (default: <scene name>.usda)")
    sim.add_argument("--preview", metavar="PATH", default=None,
                     help="also draw the cloth and its obstacles (ray cast), to see the result without a USD "
                     "viewer: an animated .gif, an .mp4 (needs ffmpeg) or a .png contact sheet of 9 frames")
    sim.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: Warp's default)")

    sub.add_parser("scenes", help="list the embedded scenes")

    from warpcloth.materials import PRESET_NAMES
    from warpcloth.tasks.specs import CONTROL_OPTIMIZERS, CONTROLLERS, ESTIMATION_OPTIMIZERS, GRIPPER_OPTIMIZERS

    est = sub.add_parser("estimate", help="estimate a fabric's material from how it moves (a scene's [estimate] task)")
    est.add_argument("scene", nargs="*", default=[],
                     help="scenes with an [estimate] table: embedded names or .toml paths, one fit each (default: "
                     f"{ESTIMATE_SCENE})")
    est.add_argument("--material", action="append", default=None, choices=PRESET_NAMES, metavar="NAME",
                     help="make the target by simulating the scene with this fabric instead of its own; repeat it "
                     f"for one fit per fabric; one of {', '.join(PRESET_NAMES)}")
    est.add_argument("--target", action="append", metavar="DIR", default=None,
                     help="instead of a scene, fit an OBJ sequence of the seed's hanging cloth (frame 0 = the start "
                     "shape with vt coordinates, one frame per 0.04 s, such as the seed's targets); repeat it for "
                     "one fit per sequence")
    est.add_argument("--optimizer", default=None, choices=ESTIMATION_OPTIMIZERS, help="default: the scene's (lbfgs)")
    est.add_argument("--batch", action="store_true",
                     help="a global search (cmaes, multistart, smoothed) simulates its trials as worlds of one batch: "
                     "the same search, slower on a CPU (docs/results/worlds-and-jobs.md), meant for a GPU")
    est.add_argument("--iters", type=int, default=None, help="forward+backward evaluations (default: the scene's)")
    est.add_argument("--free", default=None, metavar="NAMES",
                     help="comma-separated parameters to fit instead of the scene's: the material's density, "
                     "stretching, bending and scene parameters (wind, obstacle_friction, handle_stiffness, "
                     "start_placement, start_velocity, ...: warpcloth.tasks.parameters.SCENE_PARAMETERS)")
    est.add_argument("--bound", action="append", default=None, metavar="NAME=LOW,HIGH",
                     help="keep a free scene parameter inside (LOW, HIGH) (inf for none); repeat it per parameter")
    est.add_argument("--scale", action="append", default=None, metavar="NAME=SCALE",
                     help="a free scene parameter's scale (the change per unit step); repeat it per parameter")
    est.add_argument("--steps", type=int, default=None, help="steps compared (default: the scene's)")
    est.add_argument("--starts", type=int, default=1,
                     help="fits from K starts, one job each: start k the task's start with its bending times 1, 1/2, "
                     "2, 1/4, 4, ... (estimation.varied_start); the fit of least loss is named (default: 1)")
    est.add_argument("--handles", default="2,3", help="with --target: handled vertices (default: the seed's 2,3)")
    _add_workers(est)
    _add_outputs(est)

    ctl = sub.add_parser("control", help="find the pushes or gripper trajectories that move a cloth where a scene's "
                         "[control] task says")
    ctl.add_argument("scene", nargs="?", default=CONTROL_SCENE,
                     help=f"a scene with a [control] table: embedded name or .toml path (default: {CONTROL_SCENE}, "
                     "the seed's throw into a basket; fling and fold move grippers)")
    ctl.add_argument("--controller", default=None, choices=CONTROLLERS,
                     help="open-loop: the pushes themselves; mlp: a PyTorch MLP of the cloth's state, trained "
                     "through the simulator (needs the torch extra); each with the scene's optimiser where it is the "
                     "scene's controller, else its default (Gauss-Newton for a centre-of-mass target); default: the "
                     "scene's")
    ctl.add_argument("--optimizer", default=None,
                     choices=sorted({o for v in CONTROL_OPTIMIZERS.values() for o in v} | set(GRIPPER_OPTIMIZERS)),
                     help="the controller's optimiser (open loop: gauss-newton, lbfgs, or a global search over "
                     "worlds: multistart, local runs from random starts in lockstep, or cmaes or smoothed (Adam "
                     "on the Gaussian-smoothed loss), then the local default; mlp: gauss-newton or adam; a "
                     f"gripper scene: {', '.join(GRIPPER_OPTIMIZERS)}) (default: the scene's)")
    ctl.add_argument("--iters", type=int, default=None, help="simulations (default: the scene's)")
    ctl.add_argument("--warm-start", type=int, default=None, metavar="N",
                     help="the MLP: first optimise the pushes themselves with N simulations and fit the network to "
                     "them (default: the scene's, else none)")
    ctl.add_argument("--starts", type=int, default=1,
                     help="runs from K starts, one job each: the first from zero pushes (the seed's start), start k "
                     "from random pushes of seed k (the MLP: its weights' seed k) (default: 1)")
    _add_workers(ctl)
    _add_outputs(ctl)
    return parser


def _add_workers(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workers", type=int, default=1,
                        help="run the jobs on N Ray workers at once, one CPU each (default: 1, in this process; more "
                        "needs the ray extra)")
    parser.add_argument("--address", default=None,
                        help="run the jobs on the Ray cluster at this address (default: RAY_ADDRESS where set, else "
                        "this machine)")


def _add_outputs(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", metavar="PATH", default=None, help="write the result as JSON")
    parser.add_argument("--plot", metavar="PNG", default=None, help="write the loss curve")
    parser.add_argument("--usd", metavar="PATH", default=None, help="write the final trajectory")
    parser.add_argument("--preview", metavar="PATH", default=None,
                        help="draw the final trajectory (ray cast): .gif, .mp4 (needs ffmpeg) or .png")
    parser.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: Warp's default)")


def _print_solver_note(sim) -> None:
    """Say what the linear solver mapped to run on this device (a preconditioner its CG backend cannot run)."""
    solver = sim.linear_solver
    if solver.note:
        print(f"note: {solver.note} (CG backend {solver.backend}, preconditioner {solver.preconditioner})")


def _error(message: str, status: int) -> int:
    print(f"warpcloth: error: {message}", file=sys.stderr)
    return status


def _cmd_scenes() -> int:
    from warpcloth.scene import DEFAULT_SCENE, SCENE_NAMES, load_scene

    width = max(len(n) for n in SCENE_NAMES)
    scenes = [load_scene(name) for name in SCENE_NAMES]
    task_width = max(len(", ".join(s.tasks) or "-") for s in scenes)
    for s in scenes:
        mark = " (default)" if s.name == DEFAULT_SCENE else ""
        print(f"{s.name:<{width}}  {', '.join(s.tasks) or '-':<{task_width}}  {s.description}{mark}")
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from warpcloth.errors import SimulationError
    from warpcloth.obstacles import obstacle_meshes_numpy
    from warpcloth.outputs import USD_SUFFIXES, prepare_output_path
    from warpcloth.preview import check_preview_path, write_preview
    from warpcloth.progress import progress_bar
    from warpcloth.scene import load_scene
    from warpcloth.usd import write_usd

    if args.steps is not None and args.steps < 1:
        return _error(f"--steps must be >= 1, got {args.steps}", _USAGE_ERROR)
    if args.dt is not None and not (args.dt > 0.0 and args.dt < float("inf")):
        return _error(f"--dt must be a finite number > 0, got {args.dt}", _USAGE_ERROR)
    try:
        scene = load_scene(args.scene)
    except (ValueError, OSError) as exc:
        return _error(str(exc), _USAGE_ERROR)
    if args.steps is not None:
        scene.steps = args.steps
    if args.dt is not None:
        try:
            scene.set_dt(args.dt)
        except ValueError as exc:
            return _error(f"--dt: {exc}", _USAGE_ERROR)
    usd_path = args.usd if args.usd is not None else f"{scene.name}.usda"  # scene names are plain file names
    try:
        prepare_output_path(usd_path, "--usd", USD_SUFFIXES)
        if args.preview is not None:
            check_preview_path(args.preview, "--preview")
        scene.check_frame_memory()
    except ValueError as exc:
        return _error(str(exc), _USAGE_ERROR)

    try:
        model, sim = scene.build(device=args.device)
    except (ValueError, RuntimeError) as exc:  # RuntimeError: Warp's answer to an unknown --device
        return _error(str(exc), _USAGE_ERROR)
    state, nxt = model.state(), model.empty_state()
    control = model.control()
    frames, times = [state.particle_x.numpy().copy()], [state.time]  # copies: the two states swap every step
    failure = None
    start = time.perf_counter()
    with progress_bar(scene.steps, "simulate", "step") as bar:
        for _ in range(scene.steps):
            try:
                sim.step(state, nxt, control)
            except SimulationError as exc:  # keep what was simulated: the frames before the failing step are written
                failure = exc
                break
            state, nxt = nxt, state
            frames.append(state.particle_x.numpy().copy())
            times.append(state.time)
            bar.update()
    wall = time.perf_counter() - start

    # Obstacles: static ones once, moving ones at every frame's time (at the control's base placements).
    obstacles = obstacle_meshes_numpy(model, times)
    drawn = None
    try:
        write_usd(usd_path, triangles=model.tri_indices.numpy(), frames=frames, fps=1.0 / scene.dt,
                  obstacles=obstacles)
        if args.preview is not None:
            drawn = write_preview(args.preview, triangles=model.tri_indices.numpy(), frames=frames,
                                  fps=1.0 / scene.dt, obstacles=obstacles, title=scene.name)
    except (ValueError, OSError) as exc:
        return _error(str(exc), _RUNTIME_ERROR)
    if failure is not None:
        also = "" if drawn is None else f" (and {len(drawn)} of them to {os.path.abspath(args.preview)})"
        return _error(f"{failure}; wrote the {len(frames)} frames before it to {os.path.abspath(usd_path)}{also}",
                      _RUNTIME_ERROR)

    total_cg = sim.stats["cg_iterations"]
    print(f"{scene.name}: {scene.steps} steps of {scene.dt:g} s on {model.device} in {wall:.2f} s wall time")
    _print_solver_note(sim)
    print(f"CG iterations: {total_cg} total, {total_cg / scene.steps:.1f} per step")
    print(f"wrote {os.path.abspath(usd_path)} ({len(frames)} frames)")
    if drawn is not None:
        print(f"wrote {os.path.abspath(args.preview)} ({len(drawn)} frames drawn)")
    return 0


def _check_outputs(args: argparse.Namespace) -> str | None:
    """The first problem with the run's counts or output flags (warpcloth/outputs.py's rule), before any work."""
    from warpcloth.outputs import JSON_SUFFIXES, PLOT_SUFFIXES, USD_SUFFIXES, prepare_output_path

    for flag in ("iters", "steps"):
        value = getattr(args, flag, None)
        if value is not None and value < 1:
            return f"--{flag} must be >= 1, got {value}"
    from warpcloth.preview import check_preview_path

    for flag, suffixes in (("json", JSON_SUFFIXES), ("plot", PLOT_SUFFIXES), ("usd", USD_SUFFIXES)):
        path = getattr(args, flag)
        if path is not None:
            try:
                prepare_output_path(path, f"--{flag}", suffixes)
            except ValueError as exc:
                return str(exc)
    if args.preview is not None:
        try:
            check_preview_path(args.preview, "--preview")
        except ValueError as exc:
            return str(exc)
    return None


def _print_table(header: Sequence[str], rows: Sequence[Sequence]) -> None:
    cells = [[str(c) for c in header]] + [[c if isinstance(c, str) else f"{c:.3g}" for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    for k, r in enumerate(cells):
        print("  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))))
        if k == 0:
            print("  ".join("-" * w for w in widths))


def _plot_losses(path: str, curves: dict, ylabel: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for label, values in curves.items():
        ax.semilogy(range(1, len(values) + 1), values, label=label)
    ax.set_xlabel("forward + backward simulations")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _write_json(path: str, record: dict) -> None:
    import json

    with open(path, "w") as f:
        json.dump(record, f, indent=2)


def _parse_handles(text: str) -> list[int]:
    """--handles: distinct vertex indices separated by commas."""
    try:
        handles = [int(h) for h in text.split(",")]
    except ValueError:
        raise ValueError(f"--handles {text!r}: expected vertex indices separated by commas, e.g. 2,3") from None
    if len(set(handles)) != len(handles):
        raise ValueError(f"--handles {text!r} names a vertex twice")
    return handles


def _parameter_options(values: list[str] | None, flag: str, count: int) -> dict[str, list[float] | float]:
    """``NAME=X[,Y]`` options (--bound: two numbers, --scale: one) by name; ValueError naming the bad one."""
    out: dict[str, list[float] | float] = {}
    for text in values or []:
        name, _, numbers = text.partition("=")
        try:
            parsed = [float(x) for x in numbers.split(",")]
        except ValueError:
            parsed = []
        if not name or len(parsed) != count or any(x != x for x in parsed):
            raise ValueError(f"{flag} {text!r}: expected NAME={','.join(['NUMBER'] * count)}")
        if name in out:
            raise ValueError(f"{flag} {text!r}: {name} given twice")
        out[name] = parsed if count > 1 else parsed[0]
    return out


def _estimate_jobs(args: argparse.Namespace) -> list:
    """One EstimateJob per --target, else per scene and --material."""
    from warpcloth.tasks.jobs import EstimateJob

    free = None if args.free is None else tuple(n.strip() for n in args.free.split(",") if n.strip())
    if free is not None and not free:
        raise ValueError("--free names no parameter")
    bounds, scales = _parameter_options(args.bound, "--bound", 2), _parameter_options(args.scale, "--scale", 1)
    if (bounds or scales) and free is None:
        raise ValueError("--bound and --scale apply to the parameters of --free")
    common = dict(optimizer=args.optimizer, iters=args.iters, steps=args.steps, device=args.device, batch=args.batch,
                  free=free, bounds=bounds or None, scales=scales or None)
    if args.starts < 1:
        raise ValueError(f"--starts must be >= 1, got {args.starts}")
    starts = [None] if args.starts == 1 else list(range(args.starts))
    if args.target:
        if args.scene or args.material:
            raise ValueError("give scenes (and --material) or --target, not both")
        handles = tuple(_parse_handles(args.handles))
        return [EstimateJob(target=t, handles=handles, start=k, **common) for t in args.target for k in starts]
    return [EstimateJob(scene=scene, material=m, start=k, **common) for scene in args.scene or [None]
            for m in args.material or [None] for k in starts]


def _cmd_estimate(args: argparse.Namespace) -> int:
    import numpy as np

    from warpcloth.errors import SimulationError
    from warpcloth.observations import VertexFrames
    from warpcloth.preview import write_preview
    from warpcloth.tasks import estimation as E
    from warpcloth.usd import write_usd

    try:
        jobs = _estimate_jobs(args)
    except ValueError as exc:
        return _error(str(exc), _USAGE_ERROR)
    if args.starts > 1:  # refused here, before any job starts: a varied start the fit cannot use
        try:
            jobs[1].task()
        except (ValueError, OSError) as exc:
            return _error(str(exc), _USAGE_ERROR)
    if len(jobs) > 1 or args.workers > 1 or args.address:
        return _run_many(args, jobs, ["sim error [%]", "density error [%]", "simulations", "least loss"],
                         lambda r: [r["sim_err_pct"], r.get("density_err_pct", "-"), len(r["losses"]),
                                    r["best_loss"]],
                         least=lambda r: r["best_loss"])
    job = jobs[0]
    try:
        task = job.task()
    except (ValueError, OSError, RuntimeError) as exc:
        return _error(str(exc), _USAGE_ERROR)
    fit, truth = task.fit, task.truth
    optimizer, iters = job.settings(task)
    dt = fit.sim.dt
    print(f"estimating the material of {task.source}: {fit.steps} steps of {dt:g} s, optimizer {optimizer}, "
          f"{iters} simulations, fitting {', '.join(task.free)}, start: {task.start.name}")
    _print_solver_note(fit.sim)
    try:
        result = task.run(optimizer=optimizer, iters=iters, batch=job.batch, progress=True)
    except SimulationError as exc:
        return _error(str(exc), _RUNTIME_ERROR)
    except ValueError as exc:  # an optimiser that cannot fit the task (checked before any simulation)
        return _error(str(exc), _USAGE_ERROR)

    record = job.record(task, result)
    if result.scan:
        f = result.scan_factors
        print(f"start scan: {len(result.scan)} forward simulations; the fit started from density "
              f"x{f.get('density', 1.0):.3g}, warp and weft stretch x{f.get('stretch', 1.0):.3g}, then "
              f"{len(result.losses) - len(result.scan)} forward+backward")
    rows = {"runtime_s_per_step_iter": ["runtime [s/step/iter]", "-", result.seconds_per_step_iter]}
    if truth is not None:
        before = E.parameter_errors(task.start, truth)
        rows.update({key: [label, before[key], record[key]] for key, label in E.ERROR_LABELS.items()})
    if fit.has_reference:
        rows["sim_err_pct"] = ["simulation error [%]", result.initial_simulation_error_pct,
                               result.simulation_error_pct]
    rows["best_loss"] = ["best loss", result.first_loss, result.best_loss]
    for name, value in result.parameters.items():
        if name not in E.MATERIAL_PARTS:
            start = np.asarray(record["start_parameters"][name])
            rows[name] = [name, np.array2string(start, precision=4), np.array2string(value, precision=4)]
    header = ["", "start", "warpcloth"]
    seed = job.seed_published()  # None unless this is the seed's own task
    if seed is not None:
        header.append("seed (published, its hanging cloth, mean of 10)")
        for key, row in rows.items():
            row.append(seed.get(key, "-"))
    print()
    _print_table(header, list(rows.values()))
    if truth is not None:
        print("what a motion barely excites (bending, the non-linear stretching rows of a hanging cloth) is barely "
              f"identifiable from it: see {_IDENTIFIABILITY[0]}, '{_IDENTIFIABILITY[1]}', in the source tree")
    if args.json:
        _write_json(args.json, record)
        print(f"wrote {os.path.abspath(args.json)}")
    if args.plot:
        _plot_losses(args.plot, {optimizer: result.losses}, "loss [m^2]", f"material estimation: {task.source}")
        print(f"wrote {os.path.abspath(args.plot)}")
    if args.usd or args.preview:
        sim_frames = fit.trajectory(result.material)[:: fit.frame_stride]
        tris = fit.model.tri_indices.numpy()
        reference = fit.reference  # the true vertices: a vertex recording's own frames, or a point cloud's given ones
        if reference is None and isinstance(fit.observation, VertexFrames):
            reference = fit.observation.frames
        target = [] if reference is None else [("Target", np.stack(reference[: len(sim_frames)]), tris)]
        drawing = dict(triangles=tris, frames=sim_frames, fps=1.0 / (dt * fit.frame_stride), obstacles=target)
        if args.usd:
            write_usd(args.usd, **drawing)
            target = ", the target as /World/Obstacles/Target" if drawing["obstacles"] else ""
            print(f"wrote {os.path.abspath(args.usd)} (the estimate as /World/Cloth{target})")
        if args.preview:
            recorded = _recorded_points(fit.observation, len(sim_frames))
            write_preview(args.preview, **drawing, points=recorded, title=f"estimate of {task.source}")
            target = "; the target translucent" if drawing["obstacles"] else ""
            dots = "; the recorded points as red dots" if recorded is not None else ""
            print(f"wrote {os.path.abspath(args.preview)} (the estimate{target}{dots})")
    return 0


def _recorded_points(observation, frames: int):
    """A point-cloud or marker recording's points in each of its first ``frames`` frames (None where none was seen),
    for a preview; None for a vertex recording."""
    import numpy as np

    from warpcloth.observations import MarkerFrames, PointCloudFrames

    if isinstance(observation, PointCloudFrames):
        return list(observation.points[:frames])
    if isinstance(observation, MarkerFrames):
        return [p[~np.isnan(p).any(axis=1)] for p in observation.positions[:frames]]
    return None


def _run_many(args: argparse.Namespace, jobs: list, columns: list[str], figures, least=None) -> int:
    """Run ``jobs`` (tasks/jobs.py) with --workers/--address, print one row per job (``figures(record)`` under
    ``columns``) and write one JSON whose ``results`` has an entry per job; exit 1 when any failed, 130 on Ctrl-C
    (after writing what finished). ``least(record)``: a loss; of the jobs that differ only in their ``start``, the one
    of least loss is named (the JSON's ``least`` maps each such group's label to that job's index in ``results``)."""
    from warpcloth.tasks.jobs import JobsInterrupted, run_jobs

    if args.workers < 1:
        return _error(f"--workers must be >= 1, got {args.workers}", _USAGE_ERROR)
    for flag in ("usd", "preview"):
        if getattr(args, flag):
            return _error(f"--{flag} writes one run's trajectory; this command runs {len(jobs)} jobs", _USAGE_ERROR)
    where = f"the Ray cluster at {args.address}" if args.address else (
        f"{args.workers} workers" if args.workers > 1 else "this process")
    print(f"{args.command}: {len(jobs)} jobs on {where}")
    t0 = time.perf_counter()
    interrupted = False
    try:
        results = run_jobs(jobs, workers=args.workers, address=args.address, progress=True, device=args.device)
    except ImportError as exc:
        return _error(str(exc), _USAGE_ERROR)
    except JobsInterrupted as exc:
        results, interrupted = exc.results, True
    wall = time.perf_counter() - t0
    print()
    rows = [[r.job.label()] + (figures(r.result) if r.ok else ["failed"] + ["-"] * (len(columns) - 1))
            + [r.seconds if r.seconds == r.seconds else "-"] for r in results]  # "-": interrupted, never ran
    _print_table(["job", *columns, "wall [s]"], rows)
    failed = [r for r in results if not r.ok]
    for r in failed:
        print(f"{r.job.label()}: {r.error}")
    print(f"{len(results) - len(failed)} of {len(results)} jobs finished in {wall:.1f} s wall time")
    chosen = {}
    if least is not None:
        groups: dict = {}
        for i, r in enumerate(results):
            if r.ok and getattr(r.job, "start", None) is not None:
                groups.setdefault(dataclasses.replace(r.job, start=None).label(), []).append(i)
        for what, members in groups.items():
            chosen[what] = min(members, key=lambda i: least(results[i].result))
            print(f"least loss of {what}'s {len(members)} starts: {results[chosen[what]].job.label()}")
    if args.json:
        _write_json(args.json, {"command": args.command, "workers": args.workers, "address": args.address,
                                "wall_s": wall, "interrupted": interrupted,
                                "results": [r.to_json() for r in results],
                                **({"least": chosen} if chosen else {})})
        print(f"wrote {os.path.abspath(args.json)}")
    if args.plot:
        curves = {r.job.label(): r.result.get("errors_pct") or r.result["losses"] for r in results if r.ok}
        _plot_losses(args.plot, curves, "loss" if args.command == "estimate" else "error [%]", args.command)
        print(f"wrote {os.path.abspath(args.plot)}")
    if interrupted:
        return _error("interrupted; wrote the jobs that finished", 130)
    return _RUNTIME_ERROR if failed else 0


def _cmd_control(args: argparse.Namespace) -> int:
    from warpcloth.errors import SimulationError
    from warpcloth.scene import load_scene
    from warpcloth.tasks.control import ControlTask
    from warpcloth.tasks.jobs import ControlJob
    from warpcloth.tasks.specs import check_control_optimizer

    if args.starts < 1:
        return _error(f"--starts must be >= 1, got {args.starts}", _USAGE_ERROR)
    from warpcloth.tasks.specs import GripperControlSpec

    try:
        scene = load_scene(args.scene)
    except (ValueError, OSError) as exc:
        return _error(str(exc), _USAGE_ERROR)
    if isinstance(scene.control, GripperControlSpec):
        return _cmd_control_grippers(args, scene)
    if args.optimizer or args.warm_start is not None:  # refused here, before any job starts
        spec = scene.control
        controller = args.controller or (spec.controller if spec is not None else None)
        if args.optimizer and spec is None:
            return _error(f"--optimizer: scene {scene.name!r} has no [control] table", _USAGE_ERROR)
        if args.optimizer and spec is not None:
            problem = check_control_optimizer(args.optimizer, controller, spec.target_com, spec.regularizer)
            if problem:
                return _error(f"--optimizer: {problem}", _USAGE_ERROR)
        if args.warm_start is not None and (args.warm_start < 0 or controller == "open-loop"):
            return _error(f"--warm-start {args.warm_start}: the MLP controller's warm start, a number of simulations "
                          f">= 0 (this run's controller: {controller})", _USAGE_ERROR)
    jobs = [ControlJob(scene=args.scene, controller=args.controller, iters=args.iters, optimizer=args.optimizer,
                       warm_start=args.warm_start, seed=k or None, device=args.device)
            for k in range(args.starts)]
    if len(jobs) > 1 or args.workers > 1 or args.address:
        return _run_many(args, jobs, ["error [%]", "simulations to reach it", "failed trials"],
                         lambda r: [r["error_pct"], r["simulations"], len(r["failed_trials"])])
    job = jobs[0]
    try:
        task = ControlTask.from_scene(scene, device=args.device)
    except (ValueError, OSError, RuntimeError) as exc:
        return _error(str(exc), _USAGE_ERROR)
    controller, iters = job.settings(task)
    goal = "it to target positions"
    if task.target_com is not None:
        goal = f"its centre of mass to {task.target_com.tolist()}"
    print(f"{scene.name}: {len(task.particles)} particles pushed {task.intervals} times, {task.steps} steps of "
          f"{task.dt:g} s, moving {goal}; controller {controller}"
          f" ({job.optimizer_of(task)}), {iters} simulations")
    _print_solver_note(task.sim)
    try:
        result = task.run(controller=controller, iters=iters, progress=True, **job.start(task))
    except ImportError as exc:
        return _error(str(exc), _USAGE_ERROR)
    except SimulationError as exc:
        return _error(str(exc), _RUNTIME_ERROR)
    except ValueError as exc:  # an optimiser that cannot run in this budget (checked before any simulation)
        return _error(str(exc), _USAGE_ERROR)
    print()
    rows = [["error [%]", result.error_pct], ["simulations to reach it", result.simulations]]
    header = ["", "warpcloth"]
    seed = job.seed_published(controller)  # None unless this is the seed's own task
    if seed is not None:
        header += ["seed (published)", "target"]
        rows[0] += [seed["error_pct"], seed["target_error_pct"]]
        rows[1] += [seed["simulations"], seed["target_simulations"]]
    _print_table(header, rows)
    if result.failed_trials:
        print(f"{len(result.failed_trials)} trial(s) raised and were rejected as bad steps; the first: "
              f"{result.failed_trials[0]}")
    _write_control_outputs(args, scene.name, task.model, task.dt, job.record(task, result),
                           ({controller: result.errors_pct}, "error [%]", "motion control"),
                           lambda: result.trajectory(task))
    return 0


def _write_control_outputs(args: argparse.Namespace, name: str, model, dt: float, record: dict, curves: tuple,
                           trajectory) -> None:
    """A control run's --json (``record``), --plot (``curves``: {label: values}, y label, what) and --usd/--preview
    (``trajectory()``: the result's frames), each where its flag asks."""
    from warpcloth.obstacles import obstacle_meshes_numpy
    from warpcloth.preview import write_preview
    from warpcloth.usd import write_usd

    if args.json:
        _write_json(args.json, record)
        print(f"wrote {os.path.abspath(args.json)}")
    if args.plot:
        values, ylabel, what = curves
        _plot_losses(args.plot, values, ylabel, f"{name}: {what}")
        print(f"wrote {os.path.abspath(args.plot)}")
    if args.usd or args.preview:
        frames = trajectory()
        times = [i * dt for i in range(len(frames))]
        drawing = dict(triangles=model.tri_indices.numpy(), frames=frames, fps=1.0 / dt,
                       obstacles=obstacle_meshes_numpy(model, times))
        if args.usd:
            write_usd(args.usd, **drawing)
            print(f"wrote {os.path.abspath(args.usd)}")
        if args.preview:
            write_preview(args.preview, **drawing, title=name)
            print(f"wrote {os.path.abspath(args.preview)}")


def _goal_score(goal, value: float) -> str:
    """A gripper goal's measure as users read it: coverage in %, a distance in mm."""
    return f"{100.0 * value:.1f} %" if goal.name == "coverage" else f"{1000.0 * value:.2f} mm"


def _cmd_control_grippers(args: argparse.Namespace, scene) -> int:
    """``warpcloth control`` on a scene whose [control] moves grippers (GripperTask)."""
    from warpcloth.errors import CollisionError, SimulationError
    from warpcloth.progress import progress_bar
    from warpcloth.tasks.grippers import GripperTask
    from warpcloth.tasks.specs import GRIPPER_OPTIMIZERS

    refused = [flag for flag, given in (("--controller", args.controller),
                                        ("--warm-start", args.warm_start is not None)) if given]
    if refused:
        return _error(f"{refused[0]}: scene {scene.name!r} moves grippers, not pushes; {refused[0]} applies to "
                      "scenes whose [control] pushes particles", _USAGE_ERROR)
    if args.optimizer and args.optimizer not in GRIPPER_OPTIMIZERS:
        return _error(f"--optimizer {args.optimizer}: scene {scene.name!r} moves grippers; its optimisers are "
                      f"{', '.join(GRIPPER_OPTIMIZERS)}", _USAGE_ERROR)
    if args.starts > 1 or args.workers > 1 or args.address:
        return _error(f"scene {scene.name!r} moves grippers: one run in this process (--starts 1, --workers 1, no "
                      "--address); benchmarks/grippers.py runs several starts", _USAGE_ERROR)
    try:
        task = GripperTask.from_scene(scene, device=args.device)
    except (ValueError, OSError, RuntimeError) as exc:
        return _error(str(exc), _USAGE_ERROR)
    optimizer, iters = args.optimizer or task.optimizer, args.iters or task.iters
    names = ", ".join(g.name for g in task.grippers)
    print(f"{scene.name}: {len(task.grippers)} gripper(s) ({names}){', tied' if task.tied else ''}, "
          f"{task.n_params} parameters, {task.steps} steps of {task.dt:g} s, goal {task.goal.name}; optimizer "
          f"{optimizer}, {iters} simulations")
    _print_solver_note(task.sim)
    try:
        start = task.loss(task.default_params())  # the scripted knots' score (not counted in the run's budget)
        with progress_bar(iters, "control", "sim") as bar:
            result = task.run(optimizer, iters, callback=lambda k, e: bar.update())
    except (SimulationError, CollisionError) as exc:
        return _error(str(exc), _RUNTIME_ERROR)
    print()
    _print_table(["", "scripted knots", "optimised"],
                 [[task.goal.name, _goal_score(task.goal, start.error), _goal_score(task.goal, result.error)],
                  ["loss", start.loss, result.loss], ["simulations", "-", result.simulations],
                  ["wall [s]", "-", result.seconds]])
    record = {"scene": scene.name, "goal": task.goal.name, "optimizer": optimizer, "iters": iters,
              "simulations": result.simulations, "seconds": result.seconds, "start_error": start.error,
              "start_loss": start.loss, "error": result.error, "loss": result.loss, "losses": result.losses,
              "errors": result.errors, "params": result.params.tolist(), "tied": task.tied}
    _write_control_outputs(args, scene.name, task.model, task.dt, record,
                           ({optimizer: result.losses}, "loss", "gripper control"),
                           lambda: task.trajectory(result.params))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the ``warpcloth`` command line.

    Args:
        argv: Arguments without the program name; ``sys.argv[1:]`` when None.

    Returns:
        The exit status: 0 success, 1 a failed simulation (a divergence), 2 a usage error (bad arguments, unknown
        scene, invalid scene file; argparse exits with 2 itself).
    """
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # no module-load lines in the tool's output (Warp logs them at info level)
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command == "simulate":
        return _cmd_simulate(args)
    if args.command == "scenes":
        return _cmd_scenes()
    if args.command in ("estimate", "control"):
        error = _check_outputs(args)
        if error:
            return _error(error, _USAGE_ERROR)
        return _cmd_estimate(args) if args.command == "estimate" else _cmd_control(args)
    parser.print_help(sys.stderr)
    return _USAGE_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
