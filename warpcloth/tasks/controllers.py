"""The optimisers of a control task (:class:`warpcloth.tasks.control.ControlTask`): the open loop's (damped
Gauss-Newton on the centre of mass, L-BFGS, and the global searches over worlds: a multistart in lockstep and CMA-ES)
and the MLP controller's training through the simulator. The generic algorithms they share with material estimation
live in :mod:`warpcloth.tasks.optim` (L-BFGS, Adam, CMA-ES, the smoothed gradient), the lockstep scheduler in
:mod:`warpcloth.tasks.lockstep`.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

import warpcloth as wc
from warpcloth.progress import progress_bar
from warpcloth.scene import SearchSpec, check_control_optimizer, default_control_optimizer
from warpcloth.tasks.lockstep import Lockstep, run_in_lockstep
from warpcloth.tasks.optim import MULTISTART_POPULATION, SMOOTHED_COPIES, cmaes, lbfgs, smoothed_descent, smoothed_steps

if TYPE_CHECKING:
    from warpcloth.tasks.control import ControlTask, Evaluation

SEARCH_SIGMA = 5.0
"""The global search's default spread of the pushes [m/s^2] (``SearchSpec.sigma``): CMA-ES's initial one, the
multistart's random starts' (half the push that holds the seed's cloth up)."""
SMOOTHED_SIGMA = 5.0
"""The smoothed optimiser's default spread [m/s^2] (``SearchSpec.sigma``), and its Adam step
(:data:`SMOOTHED_STEP_FRACTION`)."""
SMOOTHED_STEP_FRACTION = 1.0
"""The smoothed optimiser's Adam step is its spread divided by this. Measured on ``tall-wall-throw``, 240
simulations, the error at the end of the smoothed stage (its best copy) and after Gauss-Newton (2026-11-27, from zero
pushes unless said): spread 5, step 5: 703 % then 1.9 %, and from random starts (seeds 1, 2) 398 and 366 % then 2.0
and 0.9 %; spread 2.5, step 5: 9.3e3 % then 4.7 %; spread 10, step 5: 3.0e3 % then 11 %; spread 2.5, step 2.5:
7.2e3 % then 95 %; spread 2.5, step 0.625: 9.3e3, 9.2e3 and 8.6e3 % then 0.75, 1.5 and 8.6e3 % (zero pushes:
1.1e4 %). With the small step the smoothed stage never left where it started; the spread and the step both
matter."""


@dataclass
class ControlResult:
    params: np.ndarray
    """Pushes [m/s^2], shape (intervals, particles, 3) (:mod:`warpcloth.tasks.control` defines them)."""
    losses: list[float] = field(default_factory=list)
    errors_pct: list[float] = field(default_factory=list)
    simulations: int = 0
    """Simulations until the best result (forward + backward, or forward only in a global search's populations)."""
    error_pct: float = math.nan
    seconds: float = 0.0
    failed_trials: list[str] = field(default_factory=list)
    """Messages of trial steps whose simulation raised (a CollisionError or a SimulationError): each is rejected as a
    bad step, counted as a simulation, and the run goes on."""

    def trajectory(self, task: ControlTask) -> list[np.ndarray]:
        """Positions of every step with the best pushes (forward only; the MLP's pushes replayed open-loop)."""
        return task.trajectory(self.params.reshape(-1))


def optimize_open_loop(task: ControlTask, *, iters: int = 50, max_step: float = 20.0, damping: float = 1e-3,
                       start: np.ndarray | None = None, optimizer: str | None = None, search: SearchSpec | None = None,
                       batch: bool = True, progress: bool = False, callback=None, _evaluate=None) -> ControlResult:
    """Optimise the pushes directly, from zero (the seed's start) or ``start`` (n_params pushes [m/s^2]).
    ``iters`` bounds the simulations spent; returns the best iterate and the simulations spent to reach it. A start
    whose simulation raises is halved towards zero until one runs.

    ``optimizer`` (default: the task's):

    * ``"gauss-newton"`` (a centre-of-mass target): damped Gauss-Newton on r = com_T - target (3 numbers). Without
      contact the centre of mass moves affinely with the pushes (they are external forces; the internal ones
      cancel, in the tape's tangent dynamics too), so a Gauss-Newton step lands where its model says and makes most
      of the way where first-order methods crawl; contacts make it nonlinear, and a step is halved until the loss
      drops. Each point costs three simulations (one reverse pass per coordinate of com_T: the 3 x n_params
      Jacobian), cut short when its loss is worse. The step solves ``(J^T J + (w + mu) I) d = -(J^T r + w p)``
      (w the regulariser, mu = damping * tr(J J^T) / 3).
    * ``"lbfgs"``: L-BFGS (``warpcloth.tasks.optim.lbfgs``) on the loss; one simulation per point.
    * ``"multistart"``: ``search.population`` runs of the local default (Gauss-Newton with a centre-of-mass
      target, else L-BFGS) in lockstep (:func:`optimize_open_loop_starts`: their simulations as batches of worlds),
      from ``start`` and from random points around it (normal, ``search.sigma`` [m/s^2], default
      :data:`SEARCH_SIGMA`), each with an equal share of ``iters``; the best of them. Their histories are
      interleaved in the order the lockstep ran them, and ``simulations`` counts every run's up to the best.
    * ``"cmaes"``: a global search, then the local default (Gauss-Newton with a centre-of-mass target, else
      L-BFGS) from the best point it found, for ``search.refine`` simulations (default a fifth of ``iters``). The
      search is CMA-ES (``warpcloth.tasks.optim.cmaes``) around ``start`` with ``search.sigma`` [m/s^2] (default
      :data:`SEARCH_SIGMA`); each generation of ``search.population`` points runs forward only as one batch of
      worlds (:meth:`ControlTask.losses_many`), a simulation per point. Where Gauss-Newton settles in the first basin
      it meets (holding the cloth above a wall rather than throwing it over), the population sees the others.
    * ``"smoothed"``: Adam on the Gaussian-smoothed loss L_s(p) = E[L(p + sigma eps)], then the local default from
      the best point it met, for ``search.refine`` simulations (default a fifth of ``iters``). Each Adam step's
      gradient is the mean of the tape gradients of ``search.population`` (default 8) perturbed copies of the
      pushes, antithetic pairs of spread ``search.sigma`` [m/s^2] (default :data:`SMOOTHED_SIGMA`), run as one batch
      of worlds (``warpcloth.tasks.optim.smoothed_descent``); a copy counts a simulation, and each is a point the
      result may be. Adam's step is ``sigma`` / :data:`SMOOTHED_STEP_FRACTION`: the smoothing is the scale on
      which the gradient is worth following.

    ``max_step`` [m/s^2] bounds how far one step moves any push. ``search``: the global search's settings (default:
    the task's, ``task.search``).

    ``batch``: run a point's three Gauss-Newton simulations as one batch of three worlds
    (:meth:`ControlTask.evaluate_many`; the task needs a ``template``). The result is the same as one at a time,
    bitwise, and so is the history (a point whose loss is worse counts one simulation, as when cut short); the two
    simulations such a point did not need are counted in ``task.simulations`` only.
    """
    optimizer = optimizer or task.optimizer_for("open-loop")
    problem = check_control_optimizer(optimizer, "open-loop", task.target_com, task.regularizer)
    if problem:
        raise ValueError(f"optimizer: {problem}")
    run = _evaluate or (task.evaluate_many if batch else lambda requests: [_evaluate_one(task, *r) for r in requests])
    # ask for a point's three Jacobian rows at once where they run as one batch
    together = (batch and task.template is not None) or _evaluate is not None
    result = ControlResult(params=np.zeros(task.params_shape))
    bar = progress_bar(iters, f"control (open-loop, {optimizer})", "sim") if progress else None
    t0 = time.perf_counter()

    def record(params, loss: float, err: float) -> None:
        result.losses.append(loss)
        result.errors_pct.append(err)
        k = len(result.losses)
        if not err >= result.error_pct:  # the first recorded point (error_pct is NaN until then) or a better one
            result.params = np.asarray(params, dtype=np.float64).reshape(task.params_shape).copy()
            result.simulations, result.error_pct = k, err
        if bar is not None:
            bar.update()
            bar.set_postfix(loss=f"{loss:.3e}", err=f"{err:.1f}%")
        if callback is not None:
            callback(k, loss, err, params)

    def failed(exc: Exception) -> None:
        result.failed_trials.append(f"{type(exc).__name__}: {exc}")
        result.losses.append(math.inf)
        result.errors_pct.append(math.inf)
        if bar is not None:
            bar.update()

    params = np.zeros(task.n_params) if start is None else np.array(start, dtype=np.float64).reshape(task.n_params)
    if optimizer == "multistart":
        return _multistart(task, params, iters=iters, search=search or task.search, batch=batch, callback=callback,
                           bar=bar, local=dict(max_step=max_step, damping=damping))
    if optimizer == "smoothed":
        search = search or task.search
        refine = iters // 5 if search.refine is None else min(search.refine, iters)
        copies = search.population or SMOOTHED_COPIES
        sigma = search.sigma or SMOOTHED_SIGMA
        try:
            steps = smoothed_steps(iters, refine, copies, unit="simulations", local="the local optimiser")
        except ValueError:
            if bar is not None:
                bar.close()
            raise

        def batch(requests: list) -> list:
            out = run(requests)
            for (point, _), e in zip(requests, out):
                if isinstance(e, Exception):
                    failed(e)
                else:
                    record(point, e.loss, task.error_pct(e.positions))
            return out

        smoothed_descent(batch, params, sigma=sigma, step=sigma / SMOOTHED_STEP_FRACTION, copies=copies,
                         steps=steps, rng=np.random.default_rng(search.seed),
                         failures=(wc.SimulationError, wc.CollisionError))
        if math.isfinite(result.error_pct):
            params = result.params.reshape(-1).copy()  # the local stage starts from the best point
        optimizer = default_control_optimizer("open-loop", task.target_com, task.regularizer)

    if optimizer == "cmaes":
        search = search or task.search
        refine = iters // 5 if search.refine is None else min(search.refine, iters)
        population = search.population or 4 + int(3 * math.log(task.n_params))

        def generation(points: list) -> list[float]:
            losses = []
            for point, e in zip(points, task.losses_many(points)):
                if isinstance(e, Exception):  # a rejected trial: an infinite loss
                    failed(e)
                    losses.append(math.inf)
                else:
                    record(point, e.loss, task.error_pct(e.positions))
                    losses.append(e.loss)
            return losses

        generations = (iters - refine) // population
        if not generations:
            if bar is not None:
                bar.close()
            raise ValueError(f"cmaes: {iters} simulations, {refine} of them left to the local optimiser, make no "
                             f"generation of {population} points; raise iters or lower search.population/refine")
        cmaes(generation, params, sigma=search.sigma or SEARCH_SIGMA, generations=generations,
              rng=np.random.default_rng(search.seed), popsize=population)
        if math.isfinite(result.error_pct):
            params = result.params.reshape(-1).copy()  # the local stage starts from the best point
        optimizer = default_control_optimizer("open-loop", task.target_com, task.regularizer)

    if optimizer == "lbfgs":
        def objective(theta: np.ndarray) -> tuple[float, np.ndarray]:
            e = run([(theta, None)])[0]
            if isinstance(e, Exception):  # a rejected trial: an infinite loss
                failed(e)
                return math.inf, np.zeros(task.n_params)
            record(theta, e.loss, task.error_pct(e.positions))
            return e.loss, e.grad

        if len(result.losses) >= iters:
            return _finish(result, bar, t0)
        loss, grad = objective(params)
        while not math.isfinite(loss) and len(result.losses) < iters:  # the start raised: pull it in
            params = 0.5 * params
            loss, grad = objective(params)
        if math.isfinite(loss) and len(result.losses) < iters:  # lbfgs counts the start among its evaluations
            lbfgs(objective, params, iters=iters - len(result.losses) + 1, max_step=max_step, first=(loss, grad))
        return _finish(result, bar, t0)

    w = task.regularizer

    def evaluate(params: np.ndarray, best_loss: float):
        """Loss, com_T and the Jacobian at params: three simulations (one reverse pass per coordinate); stops early
        at a worse loss. A simulation that raises (CollisionError, SimulationError) counts as an infinite loss: the
        step is rejected and halved."""
        jac = np.zeros((3, task.n_params))
        com = None
        if len(result.losses) >= iters:
            return math.inf, None, None
        # the rows at once, with the loss they are needed below (a worse point's batch may skip its reverse passes)
        rows = run([(params, k, best_loss) for k in range(3)]) if together else None
        for k in range(3):
            if len(result.losses) >= iters:
                return math.inf, None, None
            e = rows[k] if together else run([(params, k)])[0]
            if isinstance(e, Exception):
                failed(e)
                return math.inf, None, None
            if k == 0:
                com = e.com
                trial_loss = task._loss_of_com(com, params)
                record(params, trial_loss, task.error_pct(e.positions))
                if trial_loss >= best_loss:
                    return trial_loss, None, None
            jac[k] = e.grad
            if k > 0:  # the same point again: keep the per-simulation history aligned
                result.losses.append(result.losses[-1])
                result.errors_pct.append(result.errors_pct[-1])
                if bar is not None:
                    bar.update()
        return trial_loss, com, jac

    best_loss, com, jac = evaluate(params, math.inf)
    while com is None and len(result.losses) < iters:  # the start raised (or the budget is spent): pull it in
        params = 0.5 * params
        best_loss, com, jac = evaluate(params, math.inf)
    step = None
    while com is not None and len(result.losses) < iters:
        if step is None:
            r = com - task.target_com
            mu = damping * float(np.sum(jac * jac)) / 3
            lhs = jac.T @ jac + (w + mu) * np.eye(task.n_params)
            step = -np.linalg.solve(lhs, jac.T @ r + w * params)
            step *= min(1.0, max_step / max(np.abs(step).max(), 1e-30))
        trial_loss, trial_com, trial_jac = evaluate(params + step, best_loss)
        if trial_com is not None:  # accepted: a lower loss with its Jacobian
            params, best_loss, com, jac, step = params + step, trial_loss, trial_com, trial_jac, None
        else:
            step = 0.5 * step
    return _finish(result, bar, t0)


def _multistart(task: ControlTask, params: np.ndarray, *, iters: int, search: SearchSpec, batch: bool, callback,
                bar, local: dict) -> ControlResult:
    """``optimizer="multistart"`` (:func:`optimize_open_loop`): ``search.population`` local runs in lockstep, from
    ``params`` and from random points around it, each with an equal share of ``iters``; their histories interleaved
    in the order the lockstep ran them (every run's k-th simulation, run by run, then the k+1-th)."""
    starts = search.population or MULTISTART_POPULATION
    if iters < starts:
        raise ValueError(f"multistart: {iters} simulations for {starts} starts; give each start one at least")
    rng = np.random.default_rng(search.seed)
    sigma = search.sigma or SEARCH_SIGMA
    points = [params] + [params + rng.normal(scale=sigma, size=task.n_params) for _ in range(starts - 1)]
    seen: list[list] = [[] for _ in points]  # each run's recorded points: (its simulation k, loss, error, point)
    t0 = time.perf_counter()

    def recorder(i: int):
        def record(k, loss, err, point):
            if bar is not None:  # the simulations run i spent since its last recorded point
                bar.update(k - (seen[i][-1][0] if seen[i] else 0))
            seen[i].append((k, loss, err, np.array(point, dtype=np.float64)))
        return record

    runs = optimize_open_loop_starts(
        task, points, batch=batch, iters=iters // starts, callback_of=recorder,
        optimizer=default_control_optimizer("open-loop", task.target_com, task.regularizer), **local)
    result = ControlResult(params=np.zeros(task.params_shape))
    position = {}  # (run, its simulation k) -> the simulation's place in the interleaved history
    for k in range(max(len(r.losses) for r in runs)):
        for i, run in enumerate(runs):
            if k >= len(run.losses):
                continue
            result.losses.append(run.losses[k])
            result.errors_pct.append(run.errors_pct[k])
            position[i, k + 1] = len(result.losses)
            if k + 1 == run.simulations and not run.error_pct >= result.error_pct:  # this run's best, and better
                result.params, result.error_pct, result.simulations = run.params, run.error_pct, len(result.losses)
    for run in runs:
        result.failed_trials += run.failed_trials
    if callback is not None:  # the recorded points in the interleaved order
        for n, loss, err, point in sorted((position[i, k], loss, err, point) for i, points in enumerate(seen)
                                          for k, loss, err, point in points):
            callback(n, loss, err, point)
    return _finish(result, bar, t0)


def _evaluate_one(task: ControlTask, params: np.ndarray, component: int | None) -> Evaluation | Exception:
    try:
        return task.evaluate(params, component=component)
    except (wc.CollisionError, wc.SimulationError) as exc:
        return exc


def optimize_open_loop_starts(task: ControlTask, starts: list, *, batch: bool = True, iters: int = 50,
                              progress: bool = False, callback_of=None, **kwargs) -> list[ControlResult]:
    """:func:`optimize_open_loop` from each of ``starts`` (None: zero pushes), with ``batch`` in lockstep: every
    round the simulations that all the runs ask for next go as one batch of worlds (:meth:`ControlTask.evaluate_many`),
    so random restarts cost little more wall time than one run on a CPU whose launches, not its arithmetic, bound a
    small cloth's step (benchmarks/worlds.py). Each run's result equals its run alone, bitwise. Without ``batch``
    the runs go one after another. ``callback_of(i)``: run i's callback (:func:`optimize_open_loop`), or None."""
    callback_of = callback_of or (lambda i: None)
    if not batch:
        return [optimize_open_loop(task, start=s, iters=iters, batch=False, progress=progress, callback=callback_of(i),
                                   **kwargs) for i, s in enumerate(starts)]
    def evaluate(requests: dict[int, list]) -> dict[int, list]:  # the runs' requests as one batch, answers split
        flat = task.evaluate_many([r for rows in requests.values() for r in rows])
        answers = {}
        for run, rows in requests.items():
            answers[run], flat = flat[:len(rows)], flat[len(rows):]
        return answers

    lockstep = Lockstep(len(starts), evaluate)
    results = run_in_lockstep(lockstep, len(starts), lambda i: optimize_open_loop(
        task, start=starts[i], iters=iters, progress=progress, callback=callback_of(i),
        _evaluate=lambda requests: lockstep.ask(i, requests), **kwargs))
    for r in results:
        if isinstance(r, BaseException):
            raise r
    return results


def _finish(result: ControlResult, bar, t0: float) -> ControlResult:
    if bar is not None:
        bar.close()
    result.seconds = time.perf_counter() - t0
    return result


def train_mlp(task: ControlTask, *, iters: int = 100, optimizer: str | None = None, lr: float = 1e-3, hidden: int = 200,
              seed: int = 0, zero_start: bool = True, damping: float = 1e-3, max_step: float = 20.0,
              warm_start: int = 0, capture: bool = True, progress: bool = False) -> ControlResult:
    """Train a PyTorch MLP controller through the simulator (warpcloth.torch): at the start of every controlled
    interval the MLP maps the cloth's state (positions relative to the target and velocities of all particles) to
    the interval's pushes (the seed's "Ours + FC": Linear -> ReLU -> Linear).

    ``optimizer``:

    * ``"adam"``: Adam on the weights; each iteration is one forward + backward simulation of the whole horizon.
    * ``"gauss-newton"`` (a centre-of-mass target, no regulariser): damped Gauss-Newton on the weights, as the open
      loop's on the pushes (:func:`optimize_open_loop`). A point costs one forward pass and three reverse passes
      through its recorded rollout (``retain_graph``: the 3 x n_weights Jacobian of com_T), counted as three
      simulations, or one when its loss is worse (the step then halves). With more weights than residuals the step
      is the smallest change of the weights that the damped linear model asks for,
      ``d = -J^T (J J^T + mu I)^-1 r`` (mu = damping * tr(J J^T) / 3), scaled so that no push at the current
      trajectory's states changes by more than ``max_step`` [m/s^2].

    ``warm_start`` (simulations, 0: none): first optimise the pushes themselves (:func:`optimize_open_loop` from zero,
    the open loop's default optimiser) with that many simulations, then set the output layer so that the network
    gives those pushes at the states their rollout passes through (one forward simulation: the least-norm solution
    for the output layer's weights and bias, the hidden layer kept as initialised), and train from there. The
    network's first simulation then repeats the open loop's best one (to rounding), whatever its initial weights:
    training starts in the open loop's basin instead of where a random network throws the cloth. Every simulation
    counts towards ``iters``.

    A simulation that raises (CollisionError, SimulationError) is a rejected step (``ControlResult.failed_trials``)
    and the run goes on: Adam goes back to the last weights that simulated and halves its learning rate;
    Gauss-Newton halves its step (and a start that raises, its output layer: its pushes, towards zero).

    The network and every tensor take the model's torch device and dtype (``warpcloth.torch.torch_device`` and
    ``torch_dtype``); the initial weights are drawn on the CPU in float32 whatever they are, so a seed gives the same
    start on every device and precision.

    Args:
        task: The control task (its model, simulator, schedule, horizon and loss).
        iters: Simulations to spend (each Adam iteration is one).
        optimizer: ``"adam"`` or ``"gauss-newton"`` (default: the task's, ``task.optimizer_for("mlp")``).
        lr: Adam's learning rate.
        hidden: Width of the hidden layer.
        seed: Seed of torch's generator for the initial weights.
        zero_start: Zero the output layer, so training starts from no pushes (as the open loop does); else it keeps
            PyTorch's random initialisation (a random start). A warm start sets the output layer either way.
        damping, max_step: Gauss-Newton's damping and step bound.
        warm_start: Simulations of the open-loop optimisation the network is first fitted to (0: none).
        capture: Replay the simulator's intervals from graphs (``warpcloth.torch.simulate(capture=True)``) where
            the task's steps can be captured (``wc.CapturedRollout.unsupported``): the same results (bitwise on the
            CPU) for a fraction of the launch overhead.
        progress: Show a progress bar (tqdm).

    Returns:
        The pushes of the best iteration (replayed open-loop by ``ControlResult.trajectory``) and the history.

    Raises:
        ImportError: When PyTorch is not installed.
        ValueError: For an unknown optimizer, or Gauss-Newton without a centre-of-mass target or with a regulariser.
    """
    import torch

    from warpcloth.torch import simulate, torch_device, torch_dtype

    optimizer = optimizer or task.optimizer_for("mlp")
    problem = check_control_optimizer(optimizer, "mlp", task.target_com, task.regularizer)
    if problem:
        raise ValueError(f"optimizer: {problem}")
    if int(warm_start) != warm_start or not 0 <= warm_start < iters:
        raise ValueError(f"warm_start must be a whole number of simulations in [0, iters = {iters}), got "
                         f"{warm_start!r}")
    torch.manual_seed(seed)
    model = task.model
    device, dtype = torch_device(model), torch_dtype(model)
    n, k = model.particle_count, len(task.particles)
    net = torch.nn.Sequential(torch.nn.Linear(6 * n, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, 3 * k))
    if zero_start:
        with torch.no_grad():  # start from "no push", as the open-loop optimisation does
            net[2].weight.zero_()
            net[2].bias.zero_()
    net = net.to(device=device, dtype=dtype)
    x0 = torch.tensor(model.particle_x0.numpy(), dtype=dtype, device=device)
    v0 = torch.tensor(model.particle_v0.numpy(), dtype=dtype, device=device)
    if task.target_com is not None:
        target = torch.tensor(task.target_com, dtype=dtype, device=device)
    else:
        target = torch.tensor(task.target_positions, dtype=dtype, device=device)
    pushed = torch.tensor(task.particles, device=device)
    com_weights = torch.tensor(task.com_weights, dtype=dtype, device=device)
    push_scale = 10.0  # network outputs of order one -> pushes of order gravity [m/s^2]
    controlled = min(task.intervals, -(-task.steps // task.interval_steps))
    capture = capture and wc.CapturedRollout.unsupported(task.sim) is None

    def features(x, v):
        return torch.cat([(x - target).reshape(-1), 0.1 * v.reshape(-1)])

    def rollout(fixed=None):
        """The final positions, the pushes and the network's inputs of one closed-loop simulation (or of the
        open-loop pushes ``fixed``, (controlled, k, 3), where given)."""
        x, v = x0, v0
        pushes, inputs = [], []
        for s in range(controlled):
            f = features(x, v)  # the push depends on the state: the gradient flows through it (closed loop)
            inputs.append(f.detach())
            push = push_scale * net(f).reshape(k, 3) if fixed is None else fixed[s]
            pushes.append(push)
            steps = min(task.interval_steps, task.steps - s * task.interval_steps)
            force = torch.zeros((n, 3), dtype=dtype, device=device).index_put((pushed,), task.push_mass * push)
            xs, vs = simulate(task.sim, x, v, steps=steps, time=s * task.interval_steps * task.dt,
                              particle_force=force, capture=capture)
            x, v = xs[-1], vs[-1]
        rest = task.steps - controlled * task.interval_steps
        if rest > 0:
            xs, _ = simulate(task.sim, x, v, steps=rest, time=controlled * task.interval_steps * task.dt,
                             capture=capture)
            x = xs[-1]
        return x, pushes, inputs

    def loss_of(x, pushes):
        if task.target_com is not None:
            loss = 0.5 * ((com_weights @ x - target) ** 2).sum()
        else:
            loss = 0.5 * ((x - target) ** 2).sum() / n
        if task.regularizer:
            loss = loss + 0.5 * task.regularizer * sum((p**2).sum() for p in pushes)
        return loss

    result = ControlResult(params=np.zeros(task.params_shape))
    t0 = time.perf_counter()
    if warm_start:
        opened = optimize_open_loop(task, iters=warm_start, progress=progress)
        result.losses, result.errors_pct = list(opened.losses), list(opened.errors_pct)
        result.failed_trials = list(opened.failed_trials)
        result.params, result.simulations, result.error_pct = opened.params, opened.simulations, opened.error_pct
    bar = progress_bar(iters - len(result.losses), f"control (mlp, {optimizer})", "sim") if progress else None

    def record(x, pushes, loss: float) -> None:
        task.simulations += 1
        err = task.error_pct(x.detach().cpu().numpy().astype(np.float64))
        result.losses.append(loss)
        result.errors_pct.append(err)
        if not err >= result.error_pct:  # the first recorded point (error_pct is NaN until then) or a better one
            params = np.zeros(task.params_shape)
            params[: len(pushes)] = torch.stack(pushes).detach().cpu().numpy().astype(np.float64)
            result.params = params
            result.simulations, result.error_pct = len(result.losses), err
        if bar is not None:
            bar.update()
            bar.set_postfix(loss=f"{loss:.3e}", err=f"{err:.1f}%")

    def failed(exc: Exception) -> None:
        task.simulations += 1
        result.failed_trials.append(f"{type(exc).__name__}: {exc}")
        result.losses.append(math.inf)
        result.errors_pct.append(math.inf)
        if bar is not None:
            bar.update()

    if warm_start:  # the output layer that gives the open loop's pushes at its rollout's states
        fixed = torch.tensor(result.params[:controlled], dtype=dtype, device=device)
        try:
            with torch.no_grad():
                x, pushes, inputs = rollout(fixed)
            loss = float(loss_of(x, pushes))
        except (wc.CollisionError, wc.SimulationError) as exc:
            failed(exc)
        else:
            record(x, pushes, loss)
            with torch.no_grad():
                hidden_out = torch.relu(net[0](torch.stack(inputs))).double()
                lhs = torch.cat([hidden_out, torch.ones_like(hidden_out[:, :1])], dim=1)
                out = torch.linalg.pinv(lhs) @ (fixed.reshape(controlled, -1).double() / push_scale)
                net[2].weight.copy_(out[:-1].T.to(dtype))
                net[2].bias.copy_(out[-1].to(dtype))

    if optimizer == "adam":
        opt = torch.optim.Adam(net.parameters(), lr=lr)
        last_good = copy.deepcopy(net.state_dict())  # the weights of the last simulation that ran through
        while len(result.losses) < iters:
            try:
                x, pushes, _ = rollout()
                loss = loss_of(x, pushes)
                opt.zero_grad()
                loss.backward()
            except (wc.CollisionError, wc.SimulationError) as exc:
                # a rejected step: back to the last weights that simulated, with half the learning rate
                failed(exc)
                net.load_state_dict(last_good)
                for group in opt.param_groups:
                    group["lr"] *= 0.5
                continue
            last_good = copy.deepcopy(net.state_dict())
            opt.step()
            record(x, pushes, float(loss.detach()))
        return _finish(result, bar, t0)

    weights = list(net.parameters())

    def point(theta: torch.Tensor, best_loss: float):
        """Loss, residual, Jacobian and the network's inputs at the weights theta; (loss, None, None, None) when
        the loss is worse or the simulation raised (a rejected step) or the budget ran out."""
        torch.nn.utils.vector_to_parameters(theta, weights)
        try:
            x, pushes, inputs = rollout()
            com = com_weights @ x
            r = com - target
            loss = 0.5 * float(r.detach() @ r.detach())
            record(x, pushes, loss)
            if loss >= best_loss:
                return loss, None, None, None
            rows = []
            for c in range(3):
                if c > 0:  # the same point again: one simulation per row, as the open loop counts
                    if len(result.losses) >= iters:
                        return math.inf, None, None, None
                    result.losses.append(loss)
                    result.errors_pct.append(result.errors_pct[-1])
                    task.simulations += 1
                    if bar is not None:
                        bar.update()
                grads = torch.autograd.grad(com[c], weights, retain_graph=c < 2)
                rows.append(torch.cat([g.reshape(-1) for g in grads]))
        except (wc.CollisionError, wc.SimulationError) as exc:
            failed(exc)
            return math.inf, None, None, None
        return loss, r.detach(), torch.stack(rows), inputs

    def gn_step(theta, r, jac, inputs):
        jjt = (jac @ jac.T).double()
        mu = damping * float(torch.trace(jjt)) / 3
        y = torch.linalg.solve(jjt + mu * torch.eye(3, dtype=jjt.dtype, device=jjt.device), r.double())
        step = -(jac.T @ y.to(jac.dtype))
        with torch.no_grad():  # the pushes this step would give at the current trajectory's states
            torch.nn.utils.vector_to_parameters(theta, weights)
            before = [net(f) for f in inputs]
            torch.nn.utils.vector_to_parameters(theta + step, weights)
            change = max(float((net(f) - b).abs().max()) for f, b in zip(inputs, before)) * push_scale
        return step * min(1.0, max_step / max(change, 1e-30))

    theta = torch.nn.utils.parameters_to_vector(weights).detach().clone()
    best_loss, r, jac, inputs = point(theta, math.inf)
    while jac is None and result.failed_trials and len(result.losses) < iters:  # the start raised: halve its pushes
        with torch.no_grad():
            torch.nn.utils.vector_to_parameters(theta, weights)
            net[2].weight.mul_(0.5)
            net[2].bias.mul_(0.5)
            theta = torch.nn.utils.parameters_to_vector(weights).detach().clone()
        best_loss, r, jac, inputs = point(theta, math.inf)
    step = None
    while jac is not None and len(result.losses) < iters:
        if step is None:
            step = gn_step(theta, r, jac, inputs)
        trial_loss, trial_r, trial_jac, trial_inputs = point(theta + step, best_loss)
        if trial_jac is not None:  # accepted: a lower loss with its Jacobian
            theta, best_loss, r, jac, inputs, step = theta + step, trial_loss, trial_r, trial_jac, trial_inputs, None
        else:
            step = 0.5 * step
    return _finish(result, bar, t0)
