"""Gripper control: a goal on the cloth's final state and regularisers on the trajectories, as functions of the
grippers' knots (:class:`GripperTask`), optimised by :mod:`warpcloth.tasks.optim`'s searches."""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

import warpcloth as wc
from warpcloth.grippers import Gripper
from warpcloth.scene import Scene, load_scene
from warpcloth.solver.gradients import GraphCache, default_segment_steps, plan_gradient
from warpcloth.tasks import optim
from warpcloth.tasks.optim import FitSummary
from warpcloth.tasks.specs import GRIPPER_OPTIMIZERS, GripperControlSpec

PATH_EPSILON = 1e-3
"""The path-length regulariser's smoothing speed [m/s]: sqrt(|V|^2 + eps^2) is differentiable at rest."""
_FAILURES = (wc.SimulationError, wc.CollisionError)
_LIMITS = ("max_speed", "max_acceleration", "max_yaw_rate", "max_yaw_acceleration")


@dataclass
class GripperEvaluation:
    """One simulation: ``loss`` (goal plus regularisers), its gradient (None forward only), the goal's ``error``
    (its measure: coverage [-], or a distance [m]) and the final positions (n, 3) [m]."""

    loss: float
    grad: np.ndarray | None
    error: float
    positions: np.ndarray


@dataclass
class GripperResult(FitSummary):
    """A run: the best ``params`` and their ``loss`` and ``error``; ``losses``/``errors`` of every simulation."""

    params: np.ndarray
    loss: float
    error: float
    optimizer: str
    losses: list[float] = field(default_factory=list)
    errors: list[float] = field(default_factory=list)
    simulations: int = 0
    seconds: float = 0.0


class GripperTask:
    """Loss ``goal(x_T) + acceleration_weight * h sum |A_k|^2 + path_weight * h sum sqrt(|V_k|^2 + eps^2)`` over the
    model's grippers (A, V: each gripper's acceleration and velocity control points, :class:`Gripper`), and its
    gradient with respect to the knots' parameters (:meth:`Gripper.control_points`: every vector is within the
    limits).

    Args:
        model: one world with gradients, its grippers added with ``ModelBuilder.add_gripper``.
        dt: time step [s]; steps: the horizon [steps].
        goal: a :mod:`warpcloth.goals` goal (``add(state, out, weight)``, ``measure(positions)``).
        acceleration_weight, path_weight: the regularisers' weights, >= 0.
        options, segment_steps: as :class:`~warpcloth.tasks.control.ControlTask`'s.
        optimizer, iters, sigma, seed: what :meth:`run` does unless told.
        tied: every gripper follows the first's knots (one trajectory's parameters; the grippers need the same knot
            times, limits and first knot).
        capture: replay graphs where the plan allows (off by default: docs/decisions.md, "Gripper tasks run
            uncaptured").

    Raises:
        ValueError: several worlds, no gripper, a gripper whose particles the model holds by no handle, bad steps,
            weights or optimiser, tied grippers unlike the first."""

    def __init__(self, model: wc.Model, dt: float, *, steps: int, goal, acceleration_weight: float = 0.0,
                 path_weight: float = 0.0, options: wc.SolverOptions | None = None, segment_steps: int | None = None,
                 optimizer: str = "lbfgs", iters: int = 50, sigma: float = 0.05, seed: int = 0,
                 capture: bool = False, tied: bool = False):
        if model.world_count != 1:
            raise ValueError(f"a gripper task runs one world; the model has {model.world_count}")
        if not model.grippers:
            raise ValueError("the model has no gripper (ModelBuilder.add_gripper, or [[grippers]] in a scene)")
        if isinstance(steps, bool) or int(steps) != steps or steps < 1:
            raise ValueError(f"steps must be a positive integer, got {steps!r}")
        for name, value in (("acceleration_weight", acceleration_weight), ("path_weight", path_weight)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        if optimizer not in GRIPPER_OPTIMIZERS:
            raise ValueError(f"unknown optimizer {optimizer!r}; one of {', '.join(GRIPPER_OPTIMIZERS)}")
        self.model, self.dt, self.steps, self.goal = model, float(dt), int(steps), goal
        self.grippers: list[Gripper] = list(model.grippers)
        self.tied = bool(tied)
        if self.tied:
            first = self.grippers[0]
            for g in self.grippers[1:]:
                same = (g.knot_count == first.knot_count and np.array_equal(g.times, first.times)
                        and np.array_equal(g.positions[0], first.positions[0]) and g.rotates == first.rotates
                        and all(getattr(g, k) == getattr(first, k) for k in _LIMITS))
                if not same:
                    raise ValueError(f"tied grippers: {g.name} differs from {first.name} in its knot times, limits "
                                     "or first knot (tied grippers follow one trajectory)")
        self.acceleration_weight, self.path_weight = float(acceleration_weight), float(path_weight)
        self.optimizer, self.iters, self.sigma, self.seed = optimizer, int(iters), float(sigma), int(seed)
        self.sim = wc.Simulator(model, dt, options=options)
        self.segment_steps = segment_steps or default_segment_steps(model.particle_count, self.steps)
        self.capture = bool(capture) and getattr(goal, "capturable", True)
        handle_of = {int(p): h for h, p in enumerate(model.handle_particle.numpy())} if model.handle_count else {}
        x0 = model.particle_x0.numpy().astype(np.float64)
        self._handles, self._x0 = [], []
        for g in self.grippers:
            missing = [p for p in g.particles if p not in handle_of]
            if missing:
                raise ValueError(f"{g.name}: particle {missing[0]} has no handle in the model (add grippers with "
                                 "ModelBuilder.add_gripper)")
            self._handles.append(np.array([handle_of[p] for p in g.particles]))
            self._x0.append(x0[list(g.particles)])
        self._sizes = np.cumsum([0] + [g.n_params for g in self._free])
        # the step ending at times[s] holds the targets at times[s]; accumulated as the states' times are
        self.times = np.cumsum(np.full(self.steps, self.dt))
        H = model.handle_count
        self._rest = np.asarray(model.handle_rest_target, dtype=np.float64).reshape(H, 3)
        # the scripted offsets the assembly adds to a control's targets: the task's targets are given net of them
        self._scripted = np.zeros((self.steps, H, 3))
        for h, motion in enumerate(model.handle_motion):
            if motion is not None:
                self._scripted[:, h] = [motion.at(t) for t in self.times]
        self._targets = wp.zeros(self.steps * H, dtype=model.types.vec3, device=model.device, requires_grad=True)
        base = model.control(requires_grad=False)
        self._controls = [wc.Control(None, self._targets[s * H:(s + 1) * H], base.pin_target,
                                     obstacle_transform=base.obstacle_transform) for s in range(self.steps)]
        self._graphs: GraphCache = GraphCache(after=2)
        self.simulations = 0
        """Simulations run (forward only or with a gradient)."""
        self.seconds = 0.0
        self.name = ""

    @classmethod
    def from_scene(cls, scene: str | os.PathLike | Scene, *, device=None, dtype=None,
                   options: wc.SolverOptions | None = None, steps: int | None = None,
                   capture: bool = False) -> GripperTask:
        """The task of a scene's ``[control]`` table with ``controls = "grippers"``; ValueError without one."""
        scene = scene if isinstance(scene, Scene) else load_scene(scene)
        spec = scene.control
        if not isinstance(spec, GripperControlSpec):
            raise ValueError(f"scene {scene.name!r} ({scene.source}) has no [control] table with "
                             "controls = \"grippers\"")
        model = scene.finalize(device=device, requires_grad=True, dtype=dtype)
        task = cls(model, scene.dt, steps=steps or spec.steps, goal=spec.goal(model),
                   acceleration_weight=spec.acceleration_weight, path_weight=spec.path_weight,
                   options=options or scene.solver_options, optimizer=spec.optimizer, iters=spec.iters,
                   sigma=spec.sigma, seed=spec.seed, capture=capture, tied=spec.tied)
        task.name = scene.name
        return task

    # -- parameters ------------------------------------------------------------------------------------------------
    @property
    def _free(self) -> list[Gripper]:
        """The grippers whose knots are parameters (the first only where tied)."""
        return self.grippers[:1] if self.tied else self.grippers

    @property
    def n_params(self) -> int:
        return int(self._sizes[-1])

    def default_params(self) -> np.ndarray:
        """The parameters of the grippers' scripted knots (the first gripper's where tied)."""
        return np.concatenate([g.default_params() for g in self._free])

    def split(self, params) -> list[np.ndarray]:
        """``params`` checked (:attr:`n_params` finite numbers) and cut into each gripper's."""
        p = np.asarray(params, dtype=np.float64).reshape(-1)
        if p.size != self.n_params or not np.all(np.isfinite(p)):
            raise ValueError(f"gripper parameters must be {self.n_params} finite numbers, got {p.size}")
        parts = [p[a:b] for a, b in zip(self._sizes[:-1], self._sizes[1:])]
        return parts * len(self.grippers) if self.tied else parts

    def _join(self, grads: list[np.ndarray]) -> np.ndarray:
        """Per-gripper gradients as one over :attr:`n_params` (summed where tied)."""
        return np.sum(grads, axis=0) if self.tied else np.concatenate(grads)

    def params_of_increments(self, increments) -> np.ndarray:
        """The parameters of knot increments (:meth:`knot_increments`' form, :attr:`n_params` numbers); knots past a
        limit are projected into it (:meth:`Gripper.params_of`)."""
        d = np.asarray(increments, dtype=np.float64).reshape(-1)
        if d.size != self.n_params or not np.all(np.isfinite(d)):
            raise ValueError(f"knot increments must be {self.n_params} finite numbers, got {d.size}")
        out = []
        for g, a, b in zip(self._free, self._sizes[:-1], self._sizes[1:]):
            K = g.knot_count
            P = g.positions[0] + np.concatenate([np.zeros((1, 3)), np.cumsum(d[a:a + 3 * (K - 1)].reshape(-1, 3), 0)])
            yaw = g.yaw[0] + np.concatenate([[0.0], np.cumsum(d[a + 3 * (K - 1):b])]) if g.rotates else None
            out.append(g.params_of(P, yaw))
        return np.concatenate(out)

    def knot_increments(self, params) -> np.ndarray:
        """The free grippers' (the first only where tied) knot increments ``P_k - P_(k-1)`` [m], then yaw
        increments [rad] where a gripper turns, flat (:attr:`n_params`): the space the forward-only searches step
        in, where a step moves every later knot alike."""
        out = []
        for g, p in zip(self._free, self.split(params)):
            P, yaw = g.control_points(p)
            out += [np.diff(P, axis=0).reshape(-1)] + ([np.diff(yaw)] if g.rotates else [])
        return np.concatenate(out)

    def trajectory_frames(self, params) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each gripper's frame displacements (steps, 3) [m] and yaws (steps,) [rad] at the steps' ends."""
        return [g.frames(p, self.times) for g, p in zip(self.grippers, self.split(params))]

    def _set_targets(self, parts: list[np.ndarray]) -> None:
        targets = np.broadcast_to(self._rest, self._scripted.shape).copy()
        for g, p, handles, x0 in zip(self.grippers, parts, self._handles, self._x0):
            targets[:, handles] = g.targets(p, self.times, x0) - self._scripted[:, handles]
        self._targets.assign(targets.reshape(-1, 3).astype(wp.dtype_to_numpy(self.model.scalar)))

    def regularizer(self, params) -> tuple[float, np.ndarray]:
        """The regularisers' value and gradient at ``params``."""
        value, grads = 0.0, []
        for g, p in zip(self.grippers, self.split(params)):
            P, _ = g.control_points(p)
            h = g.knot_interval
            V, A = g.velocity_points(P), g.acceleration_points(P)
            speed = np.sqrt(np.sum(V * V, axis=1) + PATH_EPSILON ** 2)
            value += self.acceleration_weight * h * float(np.sum(A * A)) + self.path_weight * h * float(speed.sum())
            g_A = 2.0 * self.acceleration_weight * h * A
            g_V = self.path_weight * h * V / speed[:, None]
            g_V += (g_A - np.concatenate([g_A[1:], np.zeros((1, 3))])) / h  # A_k = (V_k - V_{k-1}) / h
            g_P = np.zeros_like(P)
            g_P[1:] += g_V / h
            g_P[:-1] -= g_V / h
            grads.append(g.control_points_vjp(p, g_P, None))
        return value, self._join(grads)

    # -- simulations -----------------------------------------------------------------------------------------------
    def evaluate(self, params) -> GripperEvaluation:
        """Loss, gradient (:attr:`n_params`), the goal's error and the final positions at ``params``.

        Raises:
            ValueError: bad parameters. SimulationError, CollisionError: the simulation failed."""
        parts = self.split(params)
        t0 = time.perf_counter()
        self._set_targets(parts)
        self.simulations += 1
        captured = self._captured("evaluate")
        if captured is not None:
            trajectory = captured.run()
            value, final = float(captured.loss.numpy()[0]), trajectory[-1]
        else:
            self._targets.grad.zero_()

            def loss(i, state, out):
                if i == self.steps:
                    self.goal.add(state, out)

            value, final = wc.checkpointed_backward(self.sim, self.model.state(requires_grad=False), self._controls,
                                                    steps=self.steps, loss=loss, segment_steps=self.segment_steps)
        G = self._targets.grad.numpy().astype(np.float64).reshape(self.steps, self.model.handle_count, 3)
        grad = self._join([g.targets_vjp(p, self.times, x0, G[:, handles])
                           for g, p, handles, x0 in zip(self.grippers, parts, self._handles, self._x0)])
        reg, reg_grad = self.regularizer(params)
        positions = final.particle_x.numpy().astype(np.float64)
        self.seconds += time.perf_counter() - t0
        return GripperEvaluation(loss=float(value) + reg, grad=grad + reg_grad, error=self.goal.measure(positions),
                                 positions=positions)

    def loss(self, params) -> GripperEvaluation:
        """:meth:`evaluate` forward only (``grad`` None)."""
        parts = self.split(params)
        t0 = time.perf_counter()
        self._set_targets(parts)
        self.simulations += 1
        captured = self._captured("losses")
        if captured is not None:
            final = captured.run()[-1]
        else:
            final = self.model.state(requires_grad=False)
            with wp.ScopedDevice(self.model.device):
                for s in range(self.steps):
                    nxt = self.model.empty_state(requires_grad=False)
                    self.sim.step(final, nxt, self._controls[s])
                    final = nxt
            self.sim.check((final,))
        out = wp.zeros(1, dtype=self.model.scalar, device=self.model.device)
        self.goal.add(final, out)
        positions = final.particle_x.numpy().astype(np.float64)
        self.seconds += time.perf_counter() - t0
        return GripperEvaluation(loss=float(out.numpy()[0]) + self.regularizer(params)[0], grad=None,
                                 error=self.goal.measure(positions), positions=positions)

    def grad(self, params) -> np.ndarray:
        return self.evaluate(params).grad

    def error(self, params) -> float:
        """The goal's measure at ``params`` (one forward simulation)."""
        return self.loss(params).error

    def _captured(self, kind: str):
        """The rollout as graphs where the plan allows it (made at the second call, again where stale), or None."""
        backward = kind == "evaluate"
        plan = plan_gradient(self.sim, self.steps, segment_steps=self.segment_steps if backward else self.steps,
                             backward=backward, capture=self.capture)
        if not plan.captured:
            return None

        def make():
            def loss(trajectory):
                out = wp.zeros(1, dtype=self.model.scalar, device=self.model.device, requires_grad=True)
                self.goal.add(trajectory[-1], out)
                return out

            return wc.CapturedRollout(self.sim, self.model.state(requires_grad=False), self._controls,
                                      steps=self.steps, loss=loss if backward else None,
                                      segment_steps=self.segment_steps if backward else None)

        return self._graphs.get(kind, make)

    def trajectory(self, params) -> list[np.ndarray]:
        """Positions (n, 3) [m] of every step from a forward pass (the start first)."""
        self._set_targets(self.split(params))
        state = self.model.state(requires_grad=False)
        frames = [state.particle_x.numpy()]
        for s in range(self.steps):
            nxt = self.model.empty_state(requires_grad=False)
            self.sim.step(state, nxt, self._controls[s])
            state = nxt
            frames.append(state.particle_x.numpy())
        self.sim.check((state,))
        return frames

    # -- optimisation ----------------------------------------------------------------------------------------------
    def run(self, optimizer: str | None = None, iters: int | None = None, *, start=None, sigma: float | None = None,
            seed: int | None = None, callback=None) -> GripperResult:
        """Optimise from ``start`` (parameters; default the scripted knots) with ``iters`` simulations: ``lbfgs`` or
        ``adam`` (step 0.1 ``sigma``) on the gradient, or forward only in the knot increments
        (:meth:`knot_increments`, ``sigma`` [m]): ``compass`` (a compass search: steps of +-sigma along one
        increment at a time in a random order, the first that lowers the loss taken, the step halved after a round
        with none), ``cmaes`` (spread sigma) or ``random`` (the start, then the start plus Gaussian steps of
        ``sigma``). The best simulation is kept; one that fails counts with an infinite loss. ``callback(k,
        evaluation)`` after each (evaluation None where it failed)."""
        optimizer = optimizer or self.optimizer
        if optimizer not in GRIPPER_OPTIMIZERS:
            raise ValueError(f"unknown optimizer {optimizer!r}; one of {', '.join(GRIPPER_OPTIMIZERS)}")
        iters = int(iters or self.iters)
        sigma = self.sigma if sigma is None else float(sigma)
        if not (math.isfinite(sigma) and sigma > 0.0):
            raise ValueError(f"sigma must be finite and > 0, got {sigma!r}")
        rng = np.random.default_rng(self.seed if seed is None else seed)
        x0 = self.default_params() if start is None else np.concatenate(self.split(start)[:len(self._free)])
        result = GripperResult(params=x0.copy(), loss=math.inf, error=math.nan, optimizer=optimizer)
        sims0, t0 = self.simulations, time.perf_counter()

        def record(params, e: GripperEvaluation | None) -> float:
            loss = math.inf if e is None else e.loss
            result.losses.append(loss)
            result.errors.append(math.nan if e is None else e.error)
            if loss < result.loss:
                result.params, result.loss, result.error = np.array(params, copy=True), loss, e.error
            if callback is not None:
                callback(len(result.losses), e)
            return loss

        def with_gradient(theta):
            try:
                e = self.evaluate(theta)
            except _FAILURES:
                record(theta, None)
                return math.inf, np.zeros_like(theta)
            return record(theta, e), e.grad

        def forward(u) -> float:  # u: knot increments
            theta = self.params_of_increments(u)
            try:
                e = self.loss(theta)
            except _FAILURES:
                e = None
            return record(theta, e)

        u0 = self.knot_increments(x0)
        if optimizer == "lbfgs":
            optim.lbfgs(with_gradient, x0, iters=iters)
        elif optimizer == "adam":
            optim.adam(with_gradient, x0, iters=iters, lr=0.1 * sigma)
        elif optimizer == "cmaes":
            popsize = max(2, min(4 + int(3 * math.log(max(u0.size, 1))), iters))  # within the budget
            optim.cmaes(lambda points: [forward(p) for p in points], u0, sigma=sigma,
                        generations=max(1, iters // popsize), rng=rng, popsize=popsize)
        elif optimizer == "compass":
            compass_search(forward, u0, step=sigma, budget=iters, rng=rng)
        else:
            forward(u0)
            for _ in range(iters - 1):
                forward(u0 + sigma * rng.standard_normal(u0.size))
        result.simulations = self.simulations - sims0
        result.seconds = time.perf_counter() - t0
        return result


def compass_search(f, x0: np.ndarray, *, step: float, budget: int, rng: np.random.Generator,
                   shrink: float = 0.5) -> tuple[float, np.ndarray]:
    """Compass search (Kolda, Lewis and Torczon 2003, "Optimization by direct search"): from ``x0``, try ``x +-
    step e_i`` one coordinate at a time in a random order and move to the first point that lowers ``f``; after a
    round of all 2n with none, multiply ``step`` by ``shrink``. ``budget`` calls of ``f`` (the first at ``x0``).
    Returns the best (f, x)."""
    x = np.asarray(x0, dtype=np.float64).copy()
    best, calls = f(x), 1
    while calls < budget:
        moved = False
        for i in rng.permutation(x.size):
            for sign in rng.permutation([1.0, -1.0]):
                if calls >= budget:
                    return best, x
                trial = x.copy()
                trial[i] += sign * step
                value = f(trial)
                calls += 1
                if value < best:
                    best, x, moved = value, trial, True
                    break
        if not moved:
            step *= shrink
    return best, x
