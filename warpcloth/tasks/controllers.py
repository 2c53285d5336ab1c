"""The optimisers of a control task: the open loop's (:func:`optimize_open_loop`) and the MLP's (:func:`train_mlp`)."""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

import warpcloth as wc
from warpcloth.progress import progress_bar
from warpcloth.tasks.lockstep import Lockstep, run_in_lockstep
from warpcloth.tasks.optim import (
    MULTISTART_POPULATION,
    SMOOTHED_COPIES,
    FitSummary,
    cmaes,
    cmaes_restarts,
    lbfgs,
    smoothed_descent,
    smoothed_steps,
)
from warpcloth.tasks.specs import SearchSpec, check_control_optimizer, default_control_optimizer

SEARCH_SIGMA = 5.0
"""The global searches' default spread of the pushes [m/s^2] (``SearchSpec.sigma``)."""
CMAES_RESTARTS = False
"""Whether the open loop's CMA-ES restarts with growing populations where a run stalls (IPOP)."""
SMOOTHED_SIGMA = 5.0
"""The smoothed optimiser's default spread [m/s^2] (``SearchSpec.sigma``)."""
SMOOTHED_STEP_FRACTION = 1.0
"""The smoothed optimiser's Adam step is its spread divided by this. Why: docs/decisions.md, "The smoothed control
step equals its spread"."""


@dataclass
class Evaluation:
    """One forward + backward simulation of a control task."""

    loss: float
    """The loss (the regulariser included), or the chosen centre-of-mass coordinate with ``component``."""
    grad: np.ndarray | None
    """d loss / d params, flat (None where a threshold skipped the reverse passes)."""
    com: np.ndarray
    """The centre of mass (mass-weighted, as the loss takes it) at the horizon (3,)."""
    positions: np.ndarray
    """Every particle's position at the horizon (n, 3)."""


class ControlProblem(Protocol):
    """What the optimisers use of a control task: :class:`warpcloth.tasks.control.ControlTask` is one."""

    model: wc.Model
    sim: wc.Simulator
    dt: float
    steps: int
    particles: tuple[int, ...]
    interval_steps: int
    intervals: int
    target_com: np.ndarray | None
    target_positions: np.ndarray | None
    regularizer: float
    waypoints: tuple
    push_mass: float
    com_weights: np.ndarray
    search: SearchSpec
    template: wc.ModelBuilder | None
    simulations: int

    @property
    def n_params(self) -> int: ...
    @property
    def params_shape(self) -> tuple[int, int, int]: ...
    def optimizer_for(self, controller: str) -> str: ...
    def error_pct(self, positions: np.ndarray) -> float: ...
    def loss_of_com(self, com: np.ndarray, params) -> float: ...
    def evaluate(self, params: np.ndarray, *, component: int | None = None) -> Evaluation: ...
    def evaluate_many(self, requests: list[tuple]) -> list[Evaluation | Exception]: ...
    def losses_many(self, points: list) -> list[Evaluation | Exception]: ...
    def trajectory(self, params: np.ndarray) -> list[np.ndarray]: ...


@dataclass
class ControlResult(FitSummary):
    """A control optimisation's result: the pushes of least ``error_pct`` (``ControlTask.error_pct``), found at
    simulation ``simulations``, and every simulation's loss and error (:class:`~warpcloth.tasks.optim.FitSummary`)."""

    params: np.ndarray
    """Pushes [m/s^2], shape (intervals, particles, 3)."""
    losses: list[float] = field(default_factory=list)
    """Loss [m^2] of every simulation (a Gauss-Newton point's rows repeat it; infinite for a failed trial)."""
    errors_pct: list[float] = field(default_factory=list)
    simulations: int = 0
    error_pct: float = math.nan
    seconds: float = 0.0
    """Wall time [s]."""
    failed_trials: list[str] = field(default_factory=list)
    """Messages of trials whose simulation raised (rejected steps, each counted as a simulation)."""

    def trajectory(self, task: ControlProblem) -> list[np.ndarray]:
        """Positions of every step with the best pushes (forward only; the MLP's pushes replayed open-loop)."""
        return task.trajectory(self.params.reshape(-1))


def optimize_open_loop(task: ControlProblem, *, iters: int = 50, max_step: float = 20.0, damping: float = 1e-3,
                       start: np.ndarray | None = None, optimizer: str | None = None, search: SearchSpec | None = None,
                       batch: bool = True, progress: bool = False, callback=None, restarts: bool | None = None,
                       _evaluate=None) -> ControlResult:
    """Optimise the pushes directly; returns the pushes of least ``error_pct`` and the history.

    Args:
        iters: Simulations to spend.
        max_step: How far one step may move any push [m/s^2].
        damping: Gauss-Newton's damping, mu = damping * tr(J J^T) / 3.
        start: The first pushes (n_params numbers [m/s^2]; default zero), halved while their simulation raises.
        optimizer: Default ``task.optimizer_for("open-loop")``. ``"gauss-newton"`` (a centre-of-mass target): steps
            ``(J^T J + (w + mu) I) d = -(J^T r + w p)``, r = com_T - target, w the regulariser, halved until the loss
            drops; three simulations a point (why: docs/decisions.md, "Gauss-Newton for centre-of-mass targets").
            ``"lbfgs"``: one a point. ``"multistart"``: ``search.population`` runs of the local default in lockstep
            (:func:`optimize_open_loop_starts`) from ``start`` and normal random points around it (spread
            ``search.sigma``, default :data:`SEARCH_SIGMA`). ``"cmaes"`` (that spread) and ``"smoothed"`` (Adam on the
            smoothed loss, ``search.population`` copies a step, default 8, spread default :data:`SMOOTHED_SIGMA`) end
            with the local default from their best point for ``search.refine`` simulations (default a fifth).
        search: The global search's settings (default ``task.search``).
        batch: Run a point's three Gauss-Newton simulations as one batch of worlds: the same result, bitwise.
        callback: ``callback(k, loss, error_pct, params)`` after the k-th simulation.
        restarts: CMA-ES restarts with growing populations (:func:`~warpcloth.tasks.optim.cmaes_restarts`); default
            :data:`CMAES_RESTARTS`.

    Raises:
        ValueError: For an optimiser that does not fit the loss, or a search budget that makes no generation or step.
    """
    optimizer = optimizer or task.optimizer_for("open-loop")
    restarts = CMAES_RESTARTS if restarts is None else restarts
    problem = check_control_optimizer(optimizer, "open-loop", task.target_com, task.regularizer)
    if problem is None and optimizer == "gauss-newton" and task.waypoints:
        problem = "gauss-newton fits the horizon's centre of mass only; use lbfgs or a search with waypoints"
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
        optimizer = _local_optimizer(task)

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
        if restarts:
            cmaes_restarts(generation, params, sigma=search.sigma or SEARCH_SIGMA, budget=iters - refine,
                           rng=np.random.default_rng(search.seed), popsize=population)
        else:
            cmaes(generation, params, sigma=search.sigma or SEARCH_SIGMA, generations=generations,
                  rng=np.random.default_rng(search.seed), popsize=population)
        if math.isfinite(result.error_pct):
            params = result.params.reshape(-1).copy()  # the local stage starts from the best point
        optimizer = _local_optimizer(task)

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

    def evaluate(params: np.ndarray, best_loss: float):  # loss, com_T, Jacobian; None's where worse or raised
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
                trial_loss = task.loss_of_com(com, params)
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


# optimizer="multistart": the local runs in lockstep, their histories interleaved (every run's k-th simulation, run
# by run, then the k+1-th)
def _multistart(task: ControlProblem, params: np.ndarray, *, iters: int, search: SearchSpec, batch: bool, callback,
                bar, local: dict) -> ControlResult:
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
        optimizer=_local_optimizer(task), **local)
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


# the local optimiser that ends a search or runs from each start: Gauss-Newton fits the horizon's loss only
def _local_optimizer(task: ControlProblem) -> str:
    if task.waypoints:
        return "lbfgs"
    return default_control_optimizer("open-loop", task.target_com, task.regularizer)


def _evaluate_one(task: ControlProblem, params: np.ndarray, component: int | None) -> Evaluation | Exception:
    try:
        return task.evaluate(params, component=component)
    except (wc.CollisionError, wc.SimulationError) as exc:
        return exc


def optimize_open_loop_starts(task: ControlProblem, starts: list, *, batch: bool = True, iters: int = 50,
                              progress: bool = False, callback_of=None, **kwargs) -> list[ControlResult]:
    """One :func:`optimize_open_loop` from each of ``starts``; with ``batch`` in lockstep, the runs' next simulations
    as one batch of worlds, each result bitwise its run alone. ``callback_of(i)``: run i's callback, or None."""
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


def train_mlp(task: ControlProblem, *, iters: int = 100, optimizer: str | None = None, lr: float = 1e-3,
              hidden: int = 200, seed: int = 0, zero_start: bool = True, damping: float = 1e-3, max_step: float = 20.0,
              warm_start: int = 0, capture: bool = True, progress: bool = False) -> ControlResult:
    """Train a PyTorch MLP controller (Linear -> ReLU -> Linear, ``hidden`` wide, the seed's "Ours + FC") through the
    simulator, mapping the cloth's positions (relative to the target) and velocities at each controlled interval's
    start to its pushes; returns the best simulation's pushes and the history. A simulation that raises is rejected:
    Adam returns to the last weights that simulated and halves its learning rate, Gauss-Newton halves its step.

    Args:
        iters: Simulations to spend, a warm start's included.
        optimizer: ``"adam"`` or ``"gauss-newton"`` (a centre-of-mass target, no regulariser: the least weight change
            ``d = -J^T (J J^T + mu I)^-1 r``); default ``task.optimizer_for("mlp")``.
        seed: Seed of the initial weights (drawn on the CPU in float32: the same start on every device and precision).
        zero_start: Zero the output layer (start from no pushes); else PyTorch's random initialisation.
        damping: As :func:`optimize_open_loop`'s.
        max_step: How far a Gauss-Newton step may change any push [m/s^2].
        warm_start: Simulations of :func:`optimize_open_loop` first, the output layer fit to its best pushes (0: none).
        capture: Replay the simulator's intervals from graphs where it can: the same results.

    Raises:
        ImportError: Without PyTorch.
        ValueError: For an optimiser that does not fit the loss, or a warm start outside [0, iters).
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

    def rollout(fixed=None):  # final positions, pushes and inputs of a closed loop, or of the pushes ``fixed``
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

    def point(theta: torch.Tensor, best_loss: float):  # loss, residual, Jacobian, inputs; None's where rejected
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
