"""Many independent jobs (fits, control runs, rollouts) at once: in this process, or on Ray's workers.

A job is plain settings (names, paths, numbers: it pickles without Warp arrays or kernels) with a ``run()`` that
builds its task, runs it and returns a record of plain values (the dict the CLI's ``--json`` writes for one run).
:func:`run_jobs` runs a list of them and returns one :class:`JobResult` per job, in submission order, each with its
wall time and either its record or its error:

* ``workers=1`` (and no cluster address): one after another in this process; Ray is not needed.
* ``workers=N``: a pool of N Ray actors on this machine, one CPU each (Warp's CPU kernels run on one thread; each
  worker also gets one BLAS thread). The kernels are compiled here first, so the workers load them from the kernel
  cache they share; each worker keeps its Warp modules loaded from one job to the next.
* ``address=`` (or ``RAY_ADDRESS`` set): a Ray cluster; ``workers`` defaults to its CPU count. Each machine compiles
  the kernels once into its own cache, at its workers' first job.

Ray is an optional extra (``pip install 'warpcloth[ray]'``) imported only by a run with workers or an address.

A job that raises (a bad target directory, a diverging fit, a worker that died) gets its error, and the others go
on. Ctrl-C stops the workers: :func:`run_jobs` then raises :class:`JobsInterrupted`, which carries the results of
the jobs that finished.
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from dataclasses import asdict, dataclass, is_dataclass, replace
from typing import Any

import numpy as np

__all__ = ["ControlJob", "EstimateJob", "JobResult", "JobsInterrupted", "RolloutJob", "compile_kernels", "run_jobs"]

START_SIGMA = 5.0
"""Standard deviation [m/s^2] of a :class:`ControlJob`'s random start pushes (``seed``)."""

ESTIMATE_SCENE = "material-estimation"
"""The scene of an :class:`EstimateJob` that names none (the seed's hanging cloth in the wind)."""
CONTROL_SCENE = "basket-throw"
"""The scene of a :class:`ControlJob` that names none (the seed's throw into a basket)."""


ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""Environment of a Ray worker: one BLAS/OpenMP thread (each worker has one CPU)."""


@dataclass
class EstimateJob:
    """A material estimation, as ``warpcloth estimate`` runs it: a scene's ``[estimate]`` task (``scene``, by
    default the seed's hanging cloth; with ``material`` the targets are simulated with that fabric instead), or the
    seed's hanging cloth fitted to an OBJ sequence (``target``, handles ``handles``), or the seed's hanging cloth on
    an OBJ ``mesh`` fitted to targets simulated with ``material`` (the seed's Table 2)."""

    scene: str | None = None
    target: str | None = None
    material: str | None = None
    mesh: str | None = None
    handles: tuple[int, ...] = (2, 3)
    optimizer: str | None = None
    iters: int | None = None
    steps: int | None = None
    device: str | None = None
    batch: bool = False

    def task(self):
        """The EstimationTask; ValueError or OSError for settings that do not make one (before any fit)."""
        from warpcloth.materials import preset
        from warpcloth.mesh_io import load_obj_sequence, obj_sequence_files
        from warpcloth.scene import load_scene
        from warpcloth.tasks import estimation as E
        from warpcloth.tasks.scenes import THICKEN, hanging_cloth_builder

        if sum(x is not None for x in (self.scene, self.target, self.mesh)) > 1:
            raise ValueError("an estimation job takes one of scene, target and mesh")
        if self.target is not None:
            if self.material is not None:
                raise ValueError("a target sequence is the truth: no material with target")
            files = obj_sequence_files(self.target)
            builder = hanging_cloth_builder(E.initial_guess(), mesh_path=files[0], handles=list(self.handles))
            model = builder.finalize(self.device, requires_grad=True)
            fit = E.TrajectoryFit(model, load_obj_sequence(files), steps=self.steps or E.STEPS, template=builder)
            return E.EstimationTask(fit, source=self.target)
        if self.mesh is not None:
            if self.material is None:
                raise ValueError("an estimation job on a mesh needs the material that makes its targets")
            truth = preset(self.material, thicken=THICKEN)
            builder = hanging_cloth_builder(truth, mesh_path=self.mesh, handles=list(self.handles))
            model = builder.finalize(self.device, requires_grad=True)
            steps = self.steps or E.STEPS
            fit = E.TrajectoryFit(model, E.TrajectoryFit.simulate_targets(model, truth, steps=steps), steps=steps,
                                  template=builder)
            return E.EstimationTask(fit, truth=truth, source=f"{truth.name} simulated by warpcloth")
        scene = load_scene(self.scene or ESTIMATE_SCENE)
        truth = None if self.material is None else preset(self.material, thicken=scene.cloth_material.thicken)
        return E.EstimationTask.from_scene(scene, device=self.device, truth=truth, steps=self.steps)

    def settings(self, task) -> tuple[str, int]:
        """(optimizer, iters) of the run: the job's, else the task's."""
        return self.optimizer or task.optimizer, self.iters or task.iters

    def record(self, task, result) -> dict:
        """The run's figures (what ``warpcloth estimate --json`` writes)."""
        from warpcloth.tasks import estimation as E

        optimizer, iters = self.settings(task)
        m = result.material
        record = {"source": task.source, "optimizer": optimizer, "iters": iters, "batch": self.batch,
                  "steps": task.fit.steps, "free": list(task.free),
                  "runtime_s_per_step_iter": result.seconds_per_step_iter,
                  "sim_err_pct_initial": result.initial_simulation_error_pct,
                  "sim_err_pct": result.simulation_error_pct, "losses": result.losses,
                  "scan": [list(p) for p in result.scan], "scan_factors": result.scan_factors,
                  "estimate": {"density": m.density, "stretching": m.stretching.tolist(),
                               "bending": m.bending.tolist()}}
        if task.truth is not None:
            record.update(E.parameter_errors(m, task.truth))
        return record

    def run(self, progress: bool = False) -> dict:
        task = self.task()
        optimizer, iters = self.settings(task)
        return self.record(task, task.run(optimizer=optimizer, iters=iters, batch=self.batch, progress=progress))

    def label(self) -> str:
        what = self.target or self.mesh or self.scene or ESTIMATE_SCENE
        return f"{what} ({self.material})" if self.material else what


@dataclass
class ControlJob:
    """A motion control run, as ``warpcloth control`` runs it: a scene's ``[control]`` task (by default the seed's
    throw). ``seed``: the start; for the open loop None is zero pushes (the seed's start) and a number random pushes
    (normal, :data:`START_SIGMA`, from ``numpy.random.default_rng(seed)``); for the MLP the seed of its initial
    weights (None: 0). With a global search (``optimizer="multistart"``, ``"cmaes"`` or ``"smoothed"``) the seed
    also seeds the search.
    ``optimizer``: the controller's optimiser (default: the task's, ``ControlTask.optimizer_for``);
    ``warm_start``: the MLP's (``train_mlp``; default: the task's)."""

    scene: str | None = None
    controller: str | None = None
    iters: int | None = None
    seed: int | None = None
    optimizer: str | None = None
    warm_start: int | None = None
    steps: int | None = None
    device: str | None = None

    def task(self):
        from warpcloth.tasks.control import ControlTask

        return ControlTask.from_scene(self.scene or CONTROL_SCENE, device=self.device, steps=self.steps)

    def settings(self, task) -> tuple[str, int]:
        """(controller, iters) of the run: the job's, else the task's (ControlTask.default_iters)."""
        controller = self.controller or task.controller
        return controller, self.iters or task.default_iters(controller)

    def optimizer_of(self, task) -> str:
        """The run's optimiser: the job's, else the task's for the run's controller."""
        return self.optimizer or task.optimizer_for(self.settings(task)[0])

    def start(self, task) -> dict:
        """The optimiser's arguments: its start, and the job's optimiser where it names one."""
        chosen = {"optimizer": self.optimizer} if self.optimizer else {}
        if self.settings(task)[0] != "open-loop":
            if self.warm_start is not None:
                chosen["warm_start"] = self.warm_start
            return {**chosen, "seed": self.seed or 0}
        if self.seed is None:
            return chosen
        from warpcloth.scene import GLOBAL_OPTIMIZERS

        if self.optimizer_of(task) in GLOBAL_OPTIMIZERS:
            chosen["search"] = replace(task.search, seed=self.seed)
        return {**chosen, "start": np.random.default_rng(self.seed).normal(scale=START_SIGMA, size=task.n_params)}

    def record(self, task, result) -> dict:
        """The run's figures (what ``warpcloth control --json`` writes)."""
        controller, iters = self.settings(task)
        return {"scene": task.name, "controller": controller, "optimizer": self.optimizer_of(task),
                "seed": self.seed,
                "error_pct": result.error_pct, "simulations": result.simulations, "iters": iters,
                "seconds": result.seconds, "losses": result.losses, "errors_pct": result.errors_pct,
                "failed_trials": result.failed_trials, "params": result.params.tolist()}

    def run(self, progress: bool = False) -> dict:
        task = self.task()
        controller, iters = self.settings(task)
        return self.record(task, task.run(controller=controller, iters=iters, progress=progress, **self.start(task)))

    def label(self) -> str:
        start = "zero pushes" if self.seed is None else f"seed {self.seed}"
        return f"{self.scene or CONTROL_SCENE} ({start})"


@dataclass
class RolloutJob:
    """A forward simulation of a scene (``steps``: the scene's by default); its record holds the final positions
    (an (n, 3) NumPy array) and the CG iterations."""

    scene: str | None = None
    steps: int | None = None
    device: str | None = None

    def run(self, progress: bool = False) -> dict:
        from warpcloth.scene import DEFAULT_SCENE, load_scene

        scene = load_scene(self.scene or DEFAULT_SCENE)
        steps = self.steps or scene.steps
        model, sim = scene.build(device=self.device)
        state, nxt, control = model.state(), model.empty_state(), model.control()
        for _ in range(steps):
            sim.step(state, nxt, control)
            state, nxt = nxt, state
        return {"scene": scene.name, "steps": steps, "final_positions": state.particle_x.numpy().astype(np.float64),
                "cg_iterations": sim.stats["cg_iterations"]}

    def label(self) -> str:
        return self.scene or "default scene"


@dataclass
class JobResult:
    """One job's outcome."""

    job: Any
    result: dict | None = None
    """The job's record; None where it failed or did not run."""
    error: str | None = None
    """Why it failed ("TypeName: message"), or that it did not run; None where it finished."""
    seconds: float = math.nan
    """Its wall time on its worker."""

    @property
    def ok(self) -> bool:
        return self.error is None

    def to_json(self) -> dict:
        """The job's settings, wall time and record or error, as JSON values."""
        settings = asdict(self.job) if is_dataclass(self.job) else {"label": self.job.label()}
        out = {"job": {"kind": type(self.job).__name__, **_plain(settings)}, "seconds": self.seconds}
        if self.ok:
            out.update(_plain(self.result))
        else:
            out["error"] = self.error
        return out


class JobsInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`run_jobs`; ``results`` holds every job's result, those that did not finish with the
    error "interrupted"."""

    def __init__(self, results: list[JobResult]):
        super().__init__("interrupted")
        self.results = results


def compile_kernels(device: str | None = None) -> None:
    """Load (compile where the kernel cache lacks them) every warpcloth kernel module on ``device``."""
    import importlib
    import pkgutil

    import warp as wp

    import warpcloth.kernels as kernels

    for module in pkgutil.iter_modules(kernels.__path__):
        importlib.import_module(f"warpcloth.kernels.{module.name}")
    wp.load_module("warpcloth.kernels", device=device, recursive=True)


def run_one(job) -> JobResult:
    """Run ``job`` here; its exception (any) becomes its error."""
    t0 = time.perf_counter()
    try:
        return JobResult(job, result=job.run(), seconds=time.perf_counter() - t0)
    except Exception as exc:  # a job's failure is its result; the others go on
        return JobResult(job, error=f"{type(exc).__name__}: {exc}", seconds=time.perf_counter() - t0)


def run_jobs(jobs: list, *, workers: int | None = 1, address: str | None = None, progress: bool = False,
             device: str | None = None) -> list[JobResult]:
    """Run independent ``jobs`` (objects with ``run() -> dict``, picklable) and return their results in submission
    order (module docstring).

    Args:
        jobs: The jobs.
        workers: Processes working at once: 1 runs them here, one after another; N > 1 starts N Ray workers on this
            machine (or on the cluster at ``address``). None: 1 here, the cluster's CPU count on a cluster.
        address: A Ray cluster's address (``ray.init(address=...)``); None: ``RAY_ADDRESS`` where set, else this
            machine.
        progress: Show one progress bar over the jobs.
        device: The Warp device the kernels are compiled for before the fan-out (Warp's default).

    Raises:
        ImportError: workers > 1 or a cluster without Ray installed (it names the extra to install).
        JobsInterrupted: Ctrl-C; it carries the finished results.
    """
    jobs = list(jobs)
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
    if not jobs:
        return []
    address = address or os.environ.get("RAY_ADDRESS") or None
    results: list[JobResult | None] = [None] * len(jobs)
    bar = None
    if progress:
        from warpcloth.progress import progress_bar

        bar = progress_bar(len(jobs), "jobs", "job")
    try:
        if address is None and (workers or 1) == 1:
            for i, job in enumerate(jobs):
                results[i] = run_one(job)
                if bar is not None:
                    bar.update()
        else:
            _run_on_ray(jobs, results, workers, address, device, bar)
    except KeyboardInterrupt:
        raise JobsInterrupted(_finish(jobs, results)) from None
    finally:
        if bar is not None:
            bar.close()
    return _finish(jobs, results)


def _finish(jobs: list, results: list) -> list[JobResult]:
    return [r if r is not None else JobResult(job, error="interrupted") for job, r in zip(jobs, results)]


def _import_ray(workers):
    try:
        import ray
    except ImportError:
        raise ImportError(f"running on {workers or 'a cluster of'} workers needs Ray: pip install 'warpcloth[ray]' "
                          "(or run with one worker)") from None
    return ray


class _Worker:
    """A Ray actor: one process that runs jobs one at a time, its Warp modules loaded once."""

    def __init__(self, device):
        import warp as wp

        wp.config.quiet = True
        wp.config.log_level = wp.LOG_WARNING
        compile_kernels(device)

    def run(self, job) -> JobResult:
        return run_one(job)


def _run_on_ray(jobs, results, workers, address, device, bar) -> None:
    """Run ``jobs`` on a pool of Ray actors, filling ``results`` as they finish."""
    ray = _import_ray(workers)
    started = not ray.is_initialized()
    if started:
        ray.init(address=address, num_cpus=None if address else workers, include_dashboard=False,
                 logging_level="ERROR", log_to_driver=False)
    if workers is None:
        workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
    compile_kernels(device)  # here, before the fan-out: workers on this machine load them from the cache
    actor = ray.remote(num_cpus=1, runtime_env={"env_vars": ONE_THREAD})(_Worker)
    pool = [actor.remote(device) for _ in range(min(workers, len(jobs)))]
    queue, running = deque(range(len(jobs))), {}
    try:
        while queue or running:
            while queue and pool:
                worker, i = pool.pop(), queue.popleft()
                running[worker.run.remote(jobs[i])] = (i, worker)
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                i, worker = running.pop(ref)
                try:
                    results[i] = ray.get(ref)
                except ray.exceptions.RayActorError as exc:  # the worker died (killed, out of memory): a new one
                    results[i] = JobResult(jobs[i], error=f"the worker died: {exc}")
                    ray.kill(worker)
                    worker = actor.remote(device)
                pool.append(worker)
                if bar is not None:
                    bar.update()
    finally:
        for worker in pool + [w for _, w in running.values()]:
            ray.kill(worker)
        if started:
            ray.shutdown()


def _plain(value):
    """``value`` with NumPy arrays and scalars as lists and numbers (for JSON)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
