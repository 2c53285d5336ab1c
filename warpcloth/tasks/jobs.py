"""Many independent jobs at once, here or on Ray's workers (:func:`run_jobs`); guide: docs/concepts/jobs.md."""

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
    """A material estimation, as ``warpcloth estimate`` runs it: a scene's ``[estimate]`` task (``scene``, default
    :data:`ESTIMATE_SCENE`; ``material`` simulates the targets), the seed's hanging cloth fitted to an OBJ sequence
    (``target``, held by ``handles``), or that cloth on an OBJ ``mesh`` fitted to targets of ``material``."""

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
    free: tuple[str, ...] | None = None
    """Parameters to fit instead of the task's (material parts and scene parameters), with the scene parameters'
    ``bounds`` and ``scales`` by name (``EstimationTask.with_free``)."""
    bounds: dict | None = None
    scales: dict | None = None
    start: int | None = None
    """Which of several starts (``estimation.varied_start``; 0 is the task's own), or None: the task's own, one of
    one."""

    def task(self):
        """The EstimationTask; ValueError or OSError for settings that do not make one (before any fit)."""
        from warpcloth.tasks.estimation import varied_start

        task = self._task()
        if self.free is None:
            if self.bounds or self.scales:
                raise ValueError("an estimation job's bounds and scales apply to its free parameters; give free")
        else:
            task = task.with_free(self.free, bounds=self.bounds, scales=self.scales)
        if self.start:  # a varied bending would stay fixed at its wrong value where the fit does not free it
            if "bending" not in task.free:
                raise ValueError(f"start {self.start} varies the bending, which this fit does not free (free: "
                                 f"{', '.join(task.free)}); fit from one start")
            task = replace(task, start=varied_start(task.start, self.start))
        return task

    def _task(self):
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

    def simulations(self) -> int:
        """The run's evaluations (its ``iters``, else its scene's or the task's default), without building it."""
        if self.iters:
            return self.iters
        if self.target is None and self.mesh is None:
            from warpcloth.scene import load_scene

            return load_scene(self.scene or ESTIMATE_SCENE).estimate.iters
        from warpcloth.tasks.estimation import EstimationTask

        return EstimationTask.iters

    def seed_published(self) -> dict | None:
        """``estimation.SEED_PUBLISHED`` where this is the seed's own task (:data:`ESTIMATE_SCENE`), else None."""
        if self.target is None and self.mesh is None and (self.scene or ESTIMATE_SCENE) == ESTIMATE_SCENE:
            from warpcloth.tasks.estimation import SEED_PUBLISHED

            return SEED_PUBLISHED
        return None

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
                  "best_loss": result.best_loss, "start": self.start, "start_material": task.start.name,
                  "scan": [list(p) for p in result.scan], "scan_factors": result.scan_factors,
                  "estimate": {"density": m.density, "stretching": m.stretching.tolist(),
                               "bending": m.bending.tolist()},
                  "parameters": {name: np.asarray(v).tolist() for name, v in result.parameters.items()},
                  "start_parameters": {name: np.asarray(v).tolist() for name, v in result.initial_parameters.items()}}
        if task.truth is not None:
            record.update(E.parameter_errors(m, task.truth))
        return record

    def run(self, progress: bool = False) -> dict:
        task = self.task()
        optimizer, iters = self.settings(task)
        return self.record(task, task.run(optimizer=optimizer, iters=iters, batch=self.batch, progress=progress))

    def label(self) -> str:
        what = self.target or self.mesh or self.scene or ESTIMATE_SCENE
        what = f"{what} ({self.material})" if self.material else what
        if self.start is None:
            return what
        from warpcloth.tasks.estimation import start_bending_factor

        return f"{what}, start {self.start} (bending x{start_bending_factor(self.start):g})"


@dataclass
class ControlJob:
    """A motion control run, as ``warpcloth control`` runs it: a scene's ``[control]`` task (default
    :data:`CONTROL_SCENE`), None taking the task's setting. ``seed`` seeds the open loop's normal start pushes
    (:data:`START_SIGMA`; None: zero pushes), the MLP's initial weights (None: 0) and a global search."""

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

    def simulations(self) -> int:
        """The run's simulations (its ``iters``, else its scene's for its controller), without building it."""
        from warpcloth.scene import load_scene
        from warpcloth.tasks.specs import DEFAULT_CONTROL_ITERS

        if self.iters:
            return self.iters
        spec = load_scene(self.scene or CONTROL_SCENE).control
        controller = self.controller or spec.controller
        return spec.iters if controller == spec.controller else DEFAULT_CONTROL_ITERS[controller]

    def seed_published(self, controller: str) -> dict | None:
        """``throw.SEED_PUBLISHED[controller]`` where this is the seed's own task (:data:`CONTROL_SCENE`), else None."""
        if (self.scene or CONTROL_SCENE) != CONTROL_SCENE:
            return None
        from warpcloth.tasks.throw import SEED_PUBLISHED

        return SEED_PUBLISHED.get(controller)

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
        from warpcloth.tasks.specs import GLOBAL_OPTIMIZERS

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
    """A forward simulation of a scene; its record holds the final positions (n, 3) and the CG iterations."""

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
    """One job's outcome: its ``result`` record, or its ``error`` ("TypeName: message", or "interrupted"), and its
    wall time on its worker, ``seconds``."""

    job: Any
    result: dict | None = None
    error: str | None = None
    seconds: float = math.nan

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
    """Ctrl-C during :func:`run_jobs`; ``results`` holds every job's result ("interrupted" where unfinished)."""

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


def run_one(job, sink=None) -> JobResult:
    """Run ``job`` here, its exception its error; with ``sink``, a job with ``simulations()`` reports to ``sink(n)``."""
    t0 = time.perf_counter()
    try:
        if sink is not None and hasattr(job, "simulations"):
            from warpcloth.progress import forward_progress

            with forward_progress(sink):
                result = job.run(progress=True)
        else:
            result = job.run()
        return JobResult(job, result=result, seconds=time.perf_counter() - t0)
    except Exception as exc:  # a job's failure is its result; the others go on
        return JobResult(job, error=f"{type(exc).__name__}: {exc}", seconds=time.perf_counter() - t0)


def run_jobs(jobs: list, *, workers: int | None = 1, address: str | None = None, progress: bool = False,
             device: str | None = None) -> list[JobResult]:
    """Run independent ``jobs`` and return one :class:`JobResult` each, in submission order.

    A job is plain settings (it pickles) with ``label()`` and a ``run()`` returning a record of plain values (what the
    CLI's ``--json`` writes); with ``simulations()`` (its budget) it reports progress through ``warpcloth.progress``. A
    job that raises, or whose worker dies, gets its error; the others go on.

    Args:
        workers: 1 runs the jobs here, one after another, without Ray; N > 1 on N Ray actors of one CPU and one BLAS
            thread each, on this machine or the cluster at ``address``; None: 1 here, a cluster's CPU count there.
        address: A Ray cluster's address; None: ``RAY_ADDRESS`` where set, else this machine.
        progress: One bar over all jobs' simulations; a job without ``simulations()`` counts one, at its end.
        device: The Warp device the kernels are compiled for before the fan-out (Warp's default).

    Raises:
        ImportError: Workers or a cluster without Ray (the optional extra ``warpcloth[ray]``).
        JobsInterrupted: Ctrl-C; it stops the workers and carries the finished results.
    """
    jobs = list(jobs)
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
    if not jobs:
        return []
    address = address or os.environ.get("RAY_ADDRESS") or None
    results: list[JobResult | None] = [None] * len(jobs)
    bar = _JobsBar(jobs) if progress else None
    try:
        if address is None and (workers or 1) == 1:
            for i, job in enumerate(jobs):
                results[i] = run_one(job, sink=None if bar is None else lambda n, i=i: bar.advance(i, n))
                if bar is not None:
                    bar.finish(i)
        else:
            _run_on_ray(jobs, results, workers, address, device, bar)
    except KeyboardInterrupt:
        raise JobsInterrupted(_finish(jobs, results)) from None
    finally:
        if bar is not None:
            bar.close()
    return _finish(jobs, results)


class _JobsBar:
    """One bar over all jobs' simulations; a job's count is clipped to its budget, and filled up to it at its end."""

    def __init__(self, jobs: list):
        from warpcloth.progress import progress_bar

        self.budgets = [_budget(job) for job in jobs]
        self.counts = [0] * len(jobs)
        self.finished = 0
        self.bar = progress_bar(sum(self.budgets), f"{len(jobs)} jobs", "sim")
        self.bar.set_postfix(jobs=f"0/{len(jobs)}")

    def advance(self, i: int, n: int) -> None:
        self.set(i, self.counts[i] + n)

    def set(self, i: int, count: int) -> None:
        count = min(count, self.budgets[i])
        if count > self.counts[i]:
            self.bar.update(count - self.counts[i])
            self.counts[i] = count

    def finish(self, i: int) -> None:
        self.set(i, self.budgets[i])
        self.finished += 1
        self.bar.set_postfix(jobs=f"{self.finished}/{len(self.budgets)}")

    def close(self) -> None:
        self.bar.close()


def _budget(job) -> int:
    """The simulations ``job`` will run (``job.simulations()``), or 1 for a job that cannot say."""
    try:
        return max(1, int(job.simulations()))
    except Exception:  # no such method, or settings that fail: the job's run reports the failure
        return 1


def _finish(jobs: list, results: list) -> list[JobResult]:
    return [r if r is not None else JobResult(job, error="interrupted") for job, r in zip(jobs, results)]


def _import_ray(workers):
    try:
        import ray
    except ImportError:
        raise ImportError(f"running on {workers or 'a cluster of'} workers needs Ray: pip install 'warpcloth[ray]' "
                          "(or run with one worker)") from None
    return ray


POLL_SECONDS = 0.5
"""How often the driver asks the Ray workers how many simulations their jobs have run (with progress)."""


class _Worker:
    """A Ray actor that runs jobs one at a time, its Warp modules loaded once; a second thread answers :meth:`count`."""

    def __init__(self, device):
        import warp as wp

        wp.config.quiet = True
        wp.config.log_level = wp.LOG_WARNING
        compile_kernels(device)
        self._job, self._count = None, 0

    def run(self, job, index: int, progress: bool) -> JobResult:
        self._job, self._count = index, 0
        return run_one(job, sink=self._add if progress else None)

    def _add(self, n: int) -> None:
        self._count += n

    def count(self) -> tuple[int | None, int]:
        """(the index of the job it runs or last ran, the simulations that job has run)."""
        return self._job, self._count


def _run_on_ray(jobs, results, workers, address, device, bar) -> None:
    ray = _import_ray(workers)
    started = not ray.is_initialized()
    if started:
        ray.init(address=address, num_cpus=None if address else workers, include_dashboard=False,
                 logging_level="ERROR", log_to_driver=False)
    if workers is None:
        workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
    compile_kernels(device)  # here, before the fan-out: workers on this machine load them from the cache
    actor = ray.remote(num_cpus=1, max_concurrency=2, runtime_env={"env_vars": ONE_THREAD})(_Worker)
    pool = [actor.remote(device) for _ in range(min(workers, len(jobs)))]
    queue, running = deque(range(len(jobs))), {}
    try:
        while queue or running:
            while queue and pool:
                worker, i = pool.pop(), queue.popleft()
                running[worker.run.remote(jobs[i], i, bar is not None)] = (i, worker)
            done, _ = ray.wait(list(running), num_returns=1, timeout=None if bar is None else POLL_SECONDS)
            if bar is not None and not done:
                _poll(ray, running, bar)
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
                    bar.finish(i)
    finally:
        for worker in pool + [w for _, w in running.values()]:
            ray.kill(worker)
        if started:
            ray.shutdown()


def _poll(ray, running: dict, bar: _JobsBar) -> None:
    """Advance ``bar`` by the counts the busy workers report (a worker that does not answer is skipped)."""
    for ref in [worker.count.remote() for _, worker in running.values()]:
        try:
            index, count = ray.get(ref, timeout=POLL_SECONDS)
        except ray.exceptions.RayError:  # a dead or busy worker: its job's end settles its count
            continue
        if index is not None and any(i == index for i, _ in running.values()):
            bar.set(index, count)


def _plain(value):
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
