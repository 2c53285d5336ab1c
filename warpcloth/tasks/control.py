"""Motion control (the seed's throw into a basket, SPEC §5(c), or any scene's ``[control]`` table): a cloth's loss at
the horizon and its gradient as functions of pushes on some of its particles (:class:`ControlTask`)."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import time

import numpy as np
import warp as wp

import warpcloth as wc
from warpcloth.kernels.losses import loss_kernels
from warpcloth.scene import Scene, load_scene
from warpcloth.solver.gradients import GraphCache, default_segment_steps, plan_gradient
from warpcloth.tasks.controllers import ControlResult, Evaluation, optimize_open_loop, train_mlp
from warpcloth.tasks.specs import (
    CONTROLLERS,
    SearchSpec,
    check_control_optimizer,
    check_waypoints,
    default_control_optimizer,
)


class ControlTask:
    """Loss, gradient and trajectory of a cloth as functions of its pushes ``p[interval, particle, xyz]`` [m/s^2], each
    a force ``push_mass * p`` on its particle for ``interval_steps`` steps (why accelerations: docs/decisions.md,
    "Control pushes are accelerations"). The loss at the horizon is ``1/2 |com_T - target|^2`` on the mass-weighted
    centre of mass, or ``1/2 mean_i |x_i,T - target_i|^2``, plus ``regularizer * 1/2 |p|^2`` and each waypoint's
    ``weight * 1/2 |com_t - target|^2``.

    Args:
        model: The scene's model, with gradients: one world, or several equal worlds each with its own pushes.
        dt: Time step [s].
        particles: The pushed particles (indices within a world), in the order of the pushes.
        intervals: Pushes per particle (pushes that begin at or after the horizon do nothing).
        steps: The horizon [steps].
        target_com: The centre of mass's target [m]; exactly one of it and ``target_positions``. Why mass-weighted:
            docs/decisions.md, "The control loss takes the mass-weighted centre".
        target_positions: Every particle's target [m], shape (particles of a world, 3).
        options: Default SolverOptions(); ``"auto"`` preconditioning is block SSOR here. Why: docs/decisions.md,
            "Block SSOR for control tasks".
        segment_steps: Checkpoint segment length [steps]; default
            :func:`warpcloth.solver.gradients.default_segment_steps` (the whole horizon where the tape stays small).
        push_bound: The longest push [m/s^2], or None: a parameter p then pushes with ``bound tanh(|p| / bound) p /
            |p|`` (:meth:`applied_pushes`; p itself while short), so every optimiser's point is within it.
        waypoints: ``(time [s], centre-of-mass target [m], weight)`` terms of the loss at whole steps in (0, horizon];
            they guide a search, ``error_pct`` still measures the horizon only. Not with Gauss-Newton.
        controller, optimizer, iters, search, warm_start: What :meth:`run` does unless told otherwise.
        template: The one-world builder ``model`` was finalised from: with it :meth:`evaluate_many` batches worlds.

    Raises:
        ValueError: For worlds of different sizes, bad particles or step counts, not exactly one target, a negative
            regulariser or push bound, a bad waypoint, or an unknown controller or optimiser.
    """

    def __init__(self, model: wc.Model, dt: float, *, particles, interval_steps: int, intervals: int, steps: int,
                 target_com=None, target_positions=None, regularizer: float = 0.0, push_bound: float | None = None,
                 waypoints=(), options: wc.SolverOptions | None = None, segment_steps: int | None = None,
                 controller: str = "open-loop", optimizer: str | None = None, iters: int | None = None,
                 search: SearchSpec | None = None, warm_start: int = 0, template: wc.ModelBuilder | None = None):
        starts = np.asarray(model.world_particle_start)
        sizes = np.diff(starts)
        if np.any(sizes != sizes[0]):
            raise ValueError(f"a control task's worlds must be copies of one scene; their particle counts differ: "
                             f"{sizes.tolist()}")
        n = int(sizes[0])
        self.particles = tuple(int(p) for p in particles)
        if not self.particles or len(set(self.particles)) != len(self.particles):
            raise ValueError(f"particles must be distinct particle indices, got {list(particles)}")
        for p in self.particles:
            if not 0 <= p < n:
                raise ValueError(f"particles: particle {p} out of range for a model of {n} particles")
        for name, value in (("interval_steps", interval_steps), ("intervals", intervals), ("steps", steps)):
            if int(value) != value or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if (target_com is None) == (target_positions is None):
            raise ValueError("give exactly one of target_com and target_positions")
        if target_positions is not None:
            target_positions = np.asarray(target_positions, dtype=np.float64)
            if target_positions.shape != (n, 3) or not np.all(np.isfinite(target_positions)):
                raise ValueError(f"target_positions must be finite, of shape ({n}, 3), got {target_positions.shape}")
        if not (regularizer >= 0.0 and math.isfinite(regularizer)):
            raise ValueError(f"regularizer must be finite and >= 0, got {regularizer!r}")
        if push_bound is not None and not (push_bound > 0.0 and math.isfinite(push_bound)):
            raise ValueError(f"push_bound must be finite and > 0 [m/s^2] (or None), got {push_bound!r}")
        if controller not in CONTROLLERS:
            raise ValueError(f"unknown controller {controller!r}; one of {', '.join(CONTROLLERS)}")
        self.waypoints = check_waypoints(waypoints, float(dt), int(steps))
        """The waypoints as ``(step, target (3,), weight)``."""
        options = options or wc.SolverOptions()
        if options.preconditioner == "auto":
            options = dataclasses.replace(options, preconditioner="block_ssor")
        self._args = dict(dt=dt, particles=self.particles, interval_steps=interval_steps, intervals=intervals,
                          steps=steps, target_com=target_com, target_positions=target_positions,
                          regularizer=regularizer, push_bound=push_bound, waypoints=waypoints, options=options,
                          segment_steps=segment_steps,
                          controller=controller, optimizer=optimizer, iters=iters, search=search,
                          warm_start=warm_start, template=template)
        self.model, self.dt, self.steps = model, float(dt), int(steps)
        self.world_count = model.world_count
        self.world_particles = n
        self.interval_steps, self.intervals = int(interval_steps), int(intervals)
        self.target_com = None if target_com is None else np.asarray(target_com, dtype=np.float64).reshape(3)
        self.target_positions = target_positions
        self.regularizer = float(regularizer)
        self.push_bound = None if push_bound is None else float(push_bound)
        self.segment_steps = segment_steps or default_segment_steps(model.particle_count, self.steps)
        self.controller = controller
        self.optimizer = optimizer or self.optimizer_for(controller, own=False)
        problem = check_control_optimizer(self.optimizer, controller, self.target_com, self.regularizer)
        if problem is None and self.waypoints and self.optimizer == "gauss-newton":
            problem = "gauss-newton fits the horizon's centre of mass only; use lbfgs or a search with waypoints"
        if problem:
            raise ValueError(f"optimizer: {problem}")
        self.iters = iters
        self.search = search or SearchSpec()
        self.warm_start = int(warm_start)
        self.template = template
        self.sim = wc.Simulator(model, dt, options=options)
        self._kernels = loss_kernels(model.scalar)
        device = model.device
        self._particles = wp.array(self.particles, dtype=wp.int32, device=device)
        self._first = wp.array(starts[:-1], dtype=wp.int32, device=device)
        first_world = model.world_slice(0)
        self.push_mass = float(model.particle_mass()[first_world].sum()) / len(self.particles)
        """The mass one push accelerates: F = push_mass * p [kg]."""
        if self.target_com is not None:
            self._target_com = model.types.vec3(*self.target_com)
        else:
            self._target_positions = wp.array(target_positions, dtype=model.types.vec3, device=device)
        mass = model.particle_mass()
        world_mass = np.add.reduceat(mass, starts[:-1])
        self.com_weights = mass[first_world] / world_mass[0]
        """m_i / M of one world's particles: the centre of mass is ``com_weights @ x``."""
        self._com_weights = wp.array(mass / world_mass[np.asarray(model.particle_world.numpy())], dtype=model.scalar,
                                     device=device)
        self.x_initial = model.particle_x0.numpy()[first_world].astype(np.float64)
        self.com_initial = self.x_initial.mean(axis=0)
        self.simulations = 0
        """World simulations run, each world of a batch counted (one for a world's three Jacobian rows)."""
        self.reverse_passes = 0
        """Extra reverse passes through recorded rollouts (:meth:`jacobian_worlds`)."""
        self.batches = 0
        """Simulations of several worlds at once."""
        self.batch_retries = 0
        """Batches run again world by world because one of their simulations raised."""
        self.seconds = 0.0
        self.seconds_by_kind = dict.fromkeys(EVALUATION_KINDS, 0.0)
        """Of ``seconds``, the evaluations that captured graphs, replayed them, or ran uncaptured
        (:data:`EVALUATION_KINDS`)."""
        self.name = ""
        """The scene's name, where the task comes from one (:meth:`from_scene`)."""
        self._batched: dict[int, ControlTask] = {self.world_count: self}
        self._graphs: GraphCache = GraphCache(after=2)  # _captured's, by kind
        self._kind = "uncaptured"  # how the evaluation under way runs (_captured's)

    @classmethod
    def from_scene(cls, scene: str | os.PathLike | Scene, *, device=None, dtype=None,
                   options: wc.SolverOptions | None = None, steps: int | None = None,
                   segment_steps: int | None = None) -> ControlTask:
        """The task of a scene's ``[control]`` table (a scene name, .toml path or Scene); ``options``, ``steps`` and
        ``segment_steps`` replace the scene's. ValueError for a scene without the table."""
        scene = scene if isinstance(scene, Scene) else load_scene(scene)
        spec = scene.control
        if spec is None:
            raise ValueError(f"scene {scene.name!r} ({scene.source}) has no [control] table")
        model = scene.finalize(device=device, requires_grad=True, dtype=dtype)
        task = cls(model, **scene_task_args(scene, steps=steps, options=options, segment_steps=segment_steps),
                   template=scene.model_builder)
        task.name = scene.name
        return task

    @property
    def n_params(self) -> int:
        return self.intervals * len(self.particles) * 3

    @property
    def params_shape(self) -> tuple[int, int, int]:
        return self.intervals, len(self.particles), 3

    def error_pct(self, positions: np.ndarray) -> float:
        """How far the cloth ends from its target against how far it started [%]: ``|com_T - target| / |com_0 -
        target|`` with com the vertex mean (as the seed measures it), or the same ratio of RMS distances."""
        positions = np.asarray(positions, dtype=np.float64)
        if self.target_com is not None:
            return 100.0 * float(np.linalg.norm(positions.mean(axis=0) - self.target_com)
                                 / np.linalg.norm(self.com_initial - self.target_com))
        return 100.0 * float(np.linalg.norm(positions - self.target_positions)
                             / np.linalg.norm(self.x_initial - self.target_positions))

    # each interval's forces from the pushes, into new arrays or into an earlier call's
    def _forces(self, push: wp.array, forces: list[wp.array] | None = None) -> list[wp.array]:
        m = len(self.particles)
        if forces is None:
            forces = [wp.zeros(self.model.particle_count, dtype=self.model.types.vec3, device=self.model.device,
                               requires_grad=True) for _ in range(self.intervals)]
        for s, f in enumerate(forces):
            wp.launch(self._kernels.push_forces, self.world_count * m,
                      inputs=[push, s, self.intervals, self._particles, self._first,
                              self.model.scalar(self.push_mass), self.model.scalar(self.push_bound or 0.0)],
                      outputs=[f], device=self.model.device)
        return forces

    def applied_pushes(self, params) -> np.ndarray:
        """The pushes [m/s^2] that parameters ``params`` (n_params numbers) apply, shape ``params_shape``: the
        parameters themselves without a push bound."""
        p = np.asarray(params, dtype=np.float64).reshape(self.params_shape)
        if self.push_bound is None:
            return p.copy()
        r = np.linalg.norm(p, axis=-1, keepdims=True)
        small = r <= self.push_bound * 1e-6
        return np.where(small, p, p * self.push_bound * np.tanh(r / self.push_bound) / np.where(small, 1.0, r))

    def _control_fn(self, forces: list[wp.array]):
        base = self.model.control(requires_grad=False)
        controls = [wc.Control(f, base.handle_target, base.pin_target, obstacle_transform=base.obstacle_transform)
                    for f in forces]

        def control(i: int) -> wc.Control:
            s = i // self.interval_steps
            return controls[s] if s < self.intervals else base

        return control

    # every world's pushes as (world_count n_params / 3, 3) numbers, checked
    def _push_values(self, params) -> np.ndarray:
        flat = [np.asarray(p, dtype=np.float64).reshape(-1) for p in params]
        for w, p in enumerate(flat):
            if p.shape != (self.n_params,) or not np.all(np.isfinite(p)):
                where = f" (world {w})" if self.world_count > 1 else ""
                raise ValueError(f"control parameters{where} must be {self.n_params} finite numbers, got shape "
                                 f"{p.shape}")
        return np.concatenate(flat).reshape(-1, 3)

    def _push_array(self, params) -> wp.array:
        return wp.array(self._push_values(params), dtype=self.model.types.vec3, device=self.model.device,
                        requires_grad=True)

    # launch every world's loss on the final state (no read): the losses and, for a com target, the centres of mass;
    # the waypoints' terms too where ``trajectory`` (every step's state) is given and no component is asked for
    def _loss_values(self, state: wc.State, components: list[int | None],
                     trajectory: list[wc.State] | None = None) -> tuple[wp.array, wp.array | None]:
        model, kernels = self.model, self._kernels
        W = self.world_count
        com = None
        values = wp.zeros(W, dtype=model.scalar, device=model.device, requires_grad=True)
        if self.target_positions is not None:
            n = self.world_particles
            wp.launch(kernels.world_squared_distance, model.particle_count,
                      inputs=[state.particle_x, self._target_positions, model.particle_world, self._first,
                              model.scalar(0.5 / n)], outputs=[values], device=model.device)
        else:  # the loss squares the mean: accumulate the mean first, then square it
            com = wp.zeros(W, dtype=model.types.vec3, device=model.device, requires_grad=True)
            wp.launch(kernels.centre_of_mass, model.particle_count,
                      inputs=[state.particle_x, model.particle_world, self._com_weights],
                      outputs=[com], device=model.device)
            if components[0] is None:
                wp.launch(kernels.point_squared_distance, W, inputs=[com, self._target_com, model.scalar(0.5)],
                          outputs=[values], device=model.device)
            else:
                wp.launch(kernels.add_component, W, outputs=[values], device=model.device,
                          inputs=[com, wp.array(components, dtype=wp.int32, device=model.device)])
        if trajectory is not None and components[0] is None:
            for k, (step, _, _) in enumerate(self.waypoints):
                self._add_waypoint(k, trajectory[step], values)
        return values, com

    # values[w] += waypoint k's term of world w at ``state``
    def _add_waypoint(self, k: int, state: wc.State, values: wp.array) -> None:
        model = self.model
        _, target, weight = self.waypoints[k]
        com = wp.zeros(self.world_count, dtype=model.types.vec3, device=model.device, requires_grad=True)
        wp.launch(self._kernels.centre_of_mass, model.particle_count,
                  inputs=[state.particle_x, model.particle_world, self._com_weights], outputs=[com],
                  device=model.device)
        wp.launch(self._kernels.point_squared_distance, self.world_count,
                  inputs=[com, model.types.vec3(*target), model.scalar(0.5 * weight)], outputs=[values],
                  device=model.device)

    def _loss_fn(self, components: list[int | None], final: dict):
        passed = {}  # each waypoint's values, by waypoint (a checkpointed rollout passes a step twice)

        def loss(i: int, state: wc.State, out: wp.array) -> None:
            for k, (step, _, _) in enumerate(self.waypoints if components[0] is None else ()):
                if step == i:
                    values = wp.zeros(self.world_count, dtype=self.model.scalar, device=self.model.device,
                                      requires_grad=True)
                    self._add_waypoint(k, state, values)
                    wp.launch(self._kernels.add_sum, 1, inputs=[values], outputs=[out], device=self.model.device)
                    passed[k] = values.numpy().astype(np.float64)
            if i != self.steps:
                return
            final["positions"] = state.particle_x.numpy().astype(np.float64)
            values, _ = self._loss_values(state, components)
            wp.launch(self._kernels.add_sum, 1, inputs=[values], outputs=[out], device=self.model.device)
            final["values"] = values.numpy().astype(np.float64) + sum(passed.values(), np.zeros(self.world_count))

        return loss

    def evaluate(self, params: np.ndarray, *, component: int | None = None) -> Evaluation:
        """The loss and its gradient at ``params`` (n_params numbers, any shape) of a task of one world. With
        ``component`` (0, 1, 2; a centre-of-mass target) the "loss" is that coordinate of the final centre of mass,
        without the regulariser."""
        if self.world_count != 1:
            raise ValueError(f"evaluate runs one world; this task has {self.world_count}: use evaluate_worlds")
        return self.evaluate_worlds([params], [component])[0]

    def evaluate_worlds(self, params: list, components: list | None = None) -> list[Evaluation]:
        """:meth:`evaluate` of every world in one simulation, world w with ``params[w]`` and ``components[w]`` (all None
        or all coordinates), each bitwise what a model of it alone gives."""
        W = self.world_count
        components = [None] * W if components is None else list(components)
        if len(params) != W or len(components) != W:
            raise ValueError(f"evaluate_worlds takes one parameter set and one component per world ({W}), got "
                             f"{len(params)} and {len(components)}")
        if any(c is not None for c in components):
            if self.target_com is None:
                raise ValueError("component needs a centre-of-mass target")
            if any(c not in (0, 1, 2) for c in components):
                raise ValueError(f"components must all be None or all 0, 1 or 2, got {components}")
        t0 = time.perf_counter()
        pushes = self._push_values(params)  # checked before anything runs
        captured = self._captured("evaluate") if all(c is None for c in components) else None
        if captured is None:
            self._kind = "uncaptured"
        if captured is not None:
            final = captured.run(pushes)
            grads = final["grads"]
        else:
            push = wp.array(pushes, dtype=self.model.types.vec3, device=self.model.device, requires_grad=True)
            tape = wp.Tape()
            with tape:
                forces = self._forces(push)
            final = {}
            wc.checkpointed_backward(self.sim, self.model.state(requires_grad=False), self._control_fn(forces),
                                     steps=self.steps, loss=self._loss_fn(components, final),
                                     segment_steps=self.segment_steps)
            tape.backward(grads={f: f.grad for f in forces})
            grads = push.grad.numpy().astype(np.float64).reshape(W, -1)
        self.simulations += W
        self.batches += W > 1
        self._spent(t0)
        out = []
        for w in range(W):
            value, grad = float(final["values"][w]), grads[w]
            if self.regularizer and components[w] is None:
                p = np.asarray(params[w], dtype=np.float64).reshape(-1)
                value += 0.5 * self.regularizer * float(p @ p)
                grad = grad + self.regularizer * p
            positions = final["positions"][self.model.world_slice(w)]
            out.append(Evaluation(loss=value, grad=grad, com=self.com_weights @ positions, positions=positions))
        return out

    # The rollout of evaluate_worlds (kind "evaluate") or losses_worlds ("losses") as graphs where the plan says it
    # can be (plan_gradient), made at the second call that can use it and again where it went stale.
    def _captured(self, kind: str = "evaluate") -> _CapturedEvaluation | _CapturedLosses | None:
        backward = kind == "evaluate"
        self._kind = "uncaptured"
        if not plan_gradient(self.sim, self.steps, segment_steps=self.segment_steps if backward else self.steps,
                             backward=backward).captured:
            return None
        make = _CapturedEvaluation if backward else _CapturedLosses
        made = self._graphs.made
        captured = self._graphs.get(kind, lambda: make(self), lambda captured: captured.current())
        if captured is not None:
            self._kind = "capture" if self._graphs.made > made else "replay"
        return captured

    # an evaluation begun at t0 ends: its time, by how it ran (_captured's)
    def _spent(self, t0: float) -> None:
        seconds = time.perf_counter() - t0
        self.seconds += seconds
        self.seconds_by_kind[self._kind] += seconds

    @property
    def rerun_steps(self) -> list[int]:
        """The steps of the last captured evaluation that ran uncaptured (``wc.CapturedRollout.rerun_steps``)."""
        captured = self._graphs.peek("evaluate")
        return [] if captured is None else list(captured.rollout.rerun_steps)

    def losses_worlds(self, params: list) -> list[Evaluation]:
        """:meth:`evaluate_worlds`'s losses, forward only (``grad`` None)."""
        W = self.world_count
        if len(params) != W:
            raise ValueError(f"losses_worlds takes one parameter set per world ({W}), got {len(params)}")
        t0 = time.perf_counter()
        pushes = self._push_values(params)  # checked before anything runs
        captured = self._captured("losses")
        if captured is not None:
            final = captured.run(pushes)
        else:
            forces = self._forces(wp.array(pushes, dtype=self.model.types.vec3, device=self.model.device))
            final = {}
            loss = self._loss_fn([None] * W, final)
            out = wp.zeros(1, dtype=self.model.scalar, device=self.model.device)
            control = self._control_fn(forces)
            trajectory = [self.model.state(requires_grad=False)]
            for i in range(self.steps):
                trajectory.append(self.model.empty_state(requires_grad=False))
                self.sim.step(trajectory[-2], trajectory[-1], control(i))
                loss(i + 1, trajectory[-1], out)
                trajectory[-2] = None  # keep only the last state
        self.simulations += W
        self.batches += W > 1
        self._spent(t0)
        out_list = []
        for w in range(W):
            value = float(final["values"][w])
            if self.regularizer:
                p = np.asarray(params[w], dtype=np.float64).reshape(-1)
                value += 0.5 * self.regularizer * float(p @ p)
            positions = final["positions"][self.model.world_slice(w)]
            out_list.append(Evaluation(loss=value, grad=None, com=self.com_weights @ positions, positions=positions))
        return out_list

    def jacobian_worlds(self, params: list, worse_than: list | None = None) -> list[list[Evaluation]]:
        """The three centre-of-mass rows of every world, ``out[w][c]`` bitwise :meth:`evaluate_worlds` with component
        c, from one forward and three reverse passes, skipped (``grad=None``) where every world's :meth:`loss_of_com`
        is no better than its ``worse_than``. ValueError without a centre-of-mass target."""
        if self.target_com is None:
            raise ValueError("jacobian_worlds needs a centre-of-mass target")
        W = self.world_count
        if len(params) != W:
            raise ValueError(f"jacobian_worlds takes one parameter set per world ({W}), got {len(params)}")
        if worse_than is not None and len(worse_than) != W:
            raise ValueError(f"worse_than takes one loss per world ({W}), got {len(worse_than)}")
        if self.segment_steps < self.steps:
            rows = [self.evaluate_worlds(params, [c] * W) for c in range(3)]
            return [[rows[c][w] for c in range(3)] for w in range(W)]
        t0 = time.perf_counter()
        model = self.model
        pushes = self._push_values(params)  # checked before anything runs
        captured = self._captured("evaluate")
        if captured is not None:
            out = captured.run(pushes, backward=False)
            positions = out["positions"]
            coms = captured.com.numpy().astype(np.float64)
            centres = [self.com_weights @ positions[model.world_slice(w)] for w in range(W)]
            skip = worse_than is not None and all(
                self.loss_of_com(centres[w], params[w]) >= worse_than[w] for w in range(W))
            grads = [[None] * W] * 3 if skip else captured.com_rows()
            self.reverse_passes += 0 if skip else 3 * W
            self.simulations += W
            self.batches += W > 1
            self._spent(t0)
            return [[Evaluation(loss=float(coms[w, c]), grad=grads[c][w], com=centres[w],
                                positions=positions[model.world_slice(w)]) for c in range(3)] for w in range(W)]
        push = self._push_array(params)
        outer = wp.Tape()
        with outer:
            forces = self._forces(push)
        control = self._control_fn(forces)
        # as checkpointed_backward's one taped segment, and its loss as _loss_fn's before the component is taken
        state = model.state(requires_grad=False).clone(requires_grad=True)
        state.solve_adjoint = wp.zeros_like(state.particle_x, requires_grad=False)
        com = wp.zeros(W, dtype=model.types.vec3, device=model.device, requires_grad=True)
        tape = wp.Tape()
        with tape:
            for i in range(self.steps):
                nxt = model.empty_state(requires_grad=True)
                self.sim.step(state, nxt, control(i))
                state = nxt
            wp.launch(self._kernels.centre_of_mass, model.particle_count,
                      inputs=[state.particle_x, model.particle_world, self._com_weights], outputs=[com],
                      device=model.device)
        positions = state.particle_x.numpy().astype(np.float64)
        coms = com.numpy().astype(np.float64)
        centres = [self.com_weights @ positions[model.world_slice(w)] for w in range(W)]
        if worse_than is not None and all(
                self.loss_of_com(centres[w], params[w]) >= worse_than[w] for w in range(W)):
            grads = [[None] * W] * 3
        else:
            grads = self._reverse_rows(tape, outer, com, forces, push)
        self.simulations += W
        self.batches += W > 1
        self._spent(t0)
        return [[Evaluation(loss=float(coms[w, c]), grad=grads[c][w], com=centres[w],
                            positions=positions[model.world_slice(w)]) for c in range(3)] for w in range(W)]

    def loss_of_com(self, com: np.ndarray, params) -> float:
        """The loss of a centre-of-mass target at final centre ``com`` and pushes ``params``, computed on the host."""
        r = com - self.target_com
        p = np.asarray(params, dtype=np.float64).reshape(-1)
        return 0.5 * float(r @ r) + 0.5 * self.regularizer * float(p @ p)

    def _reverse_rows(self, tape: wp.Tape, outer: wp.Tape, com: wp.array, forces: list, push: wp.array) -> list:
        W = self.world_count
        grads = []
        for c in range(3):
            tape.zero()
            outer.zero()
            seed = np.zeros((W, 3))
            seed[:, c] = 1.0
            com.grad.assign(seed)
            tape.backward()
            outer.backward(grads={f: f.grad for f in forces})
            grads.append(push.grad.numpy().astype(np.float64).reshape(W, -1))
        self.reverse_passes += 3 * W
        return grads

    def worlds(self, count: int) -> ControlTask | None:
        """This task over ``count`` copies of its scene (made once, then kept), or None without a ``template``."""
        if count not in self._batched:
            if self.template is None:
                return None
            builder = wc.ModelBuilder()
            builder.replicate(self.template, count)
            model = builder.finalize(device=self.model.device, requires_grad=True, dtype=self.model.scalar)
            self._batched[count] = ControlTask(model, **self._args)
        return self._batched[count]

    def evaluate_many(self, requests: list[tuple]) -> list[Evaluation | Exception]:
        """:meth:`evaluate` of several ``(params, component)`` requests of a task of one world, one batch of worlds with
        a ``template``; whole Jacobians (``(p, 0), (p, 1), (p, 2)``, thresholds ``(p, c, worse_than)``) run as
        :meth:`jacobian_worlds`. A request whose simulation raises (CollisionError, SimulationError) gets the exception
        in its place; a batch that raised runs again request by request."""
        if self.world_count != 1:
            raise ValueError(f"evaluate_many runs on a task of one world; this one has {self.world_count}")
        if not requests:
            return []
        # Whole Jacobians: one forward and three reverse passes a point, its points batched; a lone point only with a
        # threshold. Why: docs/decisions.md, "Jacobian rows share a forward pass".
        triples = self._row_triples(requests)
        if triples is not None and (len(triples[0]) > 1 or self.template is None or triples[1][0] is not None):
            points, thresholds = triples
            batch = self.worlds(len(points)) if len(points) > 1 else None
            groups = ([(batch, points, thresholds)] if batch is not None
                      else [(self, [p], [t]) for p, t in zip(points, thresholds)])
            out = []
            try:
                for task, part, limits in groups:
                    worse_than = None if any(t is None for t in limits) else limits
                    out += [e for rows in task.jacobian_worlds(part, worse_than=worse_than) for e in rows]
                    if task is not self:
                        self._count(task)
                return out
            except (wc.CollisionError, wc.SimulationError):
                task.simulations += len(part)
                if task is not self:
                    self._count(task)
                self.batch_retries += 1
        requests = [(r[0], r[1]) for r in requests]  # thresholds only save reverse passes: every row is computed
        batch = self.worlds(len(requests)) if len(requests) > 1 else None
        if batch is not None:
            try:
                out = batch.evaluate_worlds([p for p, _ in requests], [c for _, c in requests])
                self._count(batch)
                return out
            except (wc.CollisionError, wc.SimulationError):
                batch.simulations += len(requests)
            self._count(batch)
            self.batch_retries += 1
        out = []
        for params, component in requests:
            try:
                out.append(self.evaluate(params, component=component))
            except (wc.CollisionError, wc.SimulationError) as exc:
                self.simulations += 1
                out.append(exc)
        return out

    def losses_many(self, points: list) -> list[Evaluation | Exception]:
        """As :meth:`evaluate_many`, forward only (``grad`` None), of several points of a task of one world."""
        if self.world_count != 1:
            raise ValueError(f"losses_many runs on a task of one world; this one has {self.world_count}")
        batch = self.worlds(len(points)) if len(points) > 1 else None
        if batch is not None:
            try:
                out = batch.losses_worlds(points)
                self._count(batch)
                return out
            except (wc.CollisionError, wc.SimulationError):
                batch.simulations += len(points)
            self._count(batch)
            self.batch_retries += 1
        out = []
        for params in points:
            try:
                out += self.losses_worlds([params])
            except (wc.CollisionError, wc.SimulationError) as exc:
                self.simulations += 1
                out.append(exc)
        return out

    # (points, thresholds) where the requests are whole Jacobians on a rollout taped whole, else None
    def _row_triples(self, requests: list) -> tuple[list, list] | None:
        if self.target_com is None or self.segment_steps < self.steps or len(requests) % 3:
            return None
        points, thresholds = [], []
        for k in range(0, len(requests), 3):
            rows = [(r[0], r[1], r[2] if len(r) > 2 else None) for r in requests[k:k + 3]]
            p, _, worse_than = rows[0]
            if [c for _, c, _ in rows] != [0, 1, 2] or any(not np.array_equal(p, q) or t != worse_than
                                                           for q, _, t in rows[1:]):
                return None
            points.append(p)
            thresholds.append(worse_than)
        return points, thresholds

    def _count(self, batch: ControlTask) -> None:
        self.simulations += batch.simulations
        self.reverse_passes += batch.reverse_passes
        self.batches += batch.batches
        self.seconds += batch.seconds
        for kind, seconds in batch.seconds_by_kind.items():
            self.seconds_by_kind[kind] += seconds
        batch.seconds_by_kind = dict.fromkeys(EVALUATION_KINDS, 0.0)
        batch.simulations = batch.batches = batch.reverse_passes = 0
        batch.seconds = 0.0

    def loss_and_grad(self, params: np.ndarray, *, component: int | None = None
                      ) -> tuple[float, np.ndarray, np.ndarray]:
        """(loss [m^2], gradient (n_params,), final centre of mass (3,)): :meth:`evaluate`, unpacked."""
        e = self.evaluate(params, component=component)
        return e.loss, e.grad, e.com

    def trajectory(self, params: np.ndarray) -> list[np.ndarray]:
        """Positions (n, 3) of every step of a task of one world, from a forward pass."""
        if self.world_count != 1:
            raise ValueError(f"trajectory replays one world; this task has {self.world_count}")
        control = self._control_fn(self._forces(self._push_array([params])))
        state = self.model.state(requires_grad=False)
        frames = [state.particle_x.numpy()]
        for i in range(self.steps):
            nxt = self.model.empty_state(requires_grad=False)
            self.sim.step(state, nxt, control(i))
            state = nxt
            frames.append(state.particle_x.numpy())
        return frames

    def run(self, *, controller: str | None = None, iters: int | None = None, progress: bool = False,
            **kwargs) -> ControlResult:
        """Optimise with the task's controller, or ``controller``: :func:`optimize_open_loop` or :func:`train_mlp`
        (keyword arguments go to them), ``iters`` simulations (default :meth:`default_iters`)."""
        controller = controller or self.controller
        if controller not in CONTROLLERS:
            raise ValueError(f"unknown controller {controller!r}; one of {', '.join(CONTROLLERS)}")
        if controller == "mlp" and self.waypoints:
            raise ValueError("the MLP controller fits the horizon's loss only; use the open loop with waypoints")
        iters = iters or self.default_iters(controller)
        kwargs.setdefault("optimizer", self.optimizer_for(controller))
        if controller == "open-loop":
            return optimize_open_loop(self, iters=iters, progress=progress, **kwargs)
        kwargs.setdefault("warm_start", self.warm_start if controller == self.controller else 0)
        return train_mlp(self, iters=iters, progress=progress, **kwargs)

    def optimizer_for(self, controller: str, *, own: bool = True) -> str:
        """The task's optimiser where ``controller`` is its own (and ``own``), else that controller's default for this
        loss (L-BFGS for the open loop's waypoints)."""
        if own and controller == self.controller:
            return self.optimizer
        default = default_control_optimizer(controller, self.target_com, self.regularizer)
        return "lbfgs" if self.waypoints and default == "gauss-newton" and controller == "open-loop" else default

    def default_iters(self, controller: str) -> int:
        """Simulations ``controller``'s run spends unless told: the task's ``iters`` for its own, else 50 (MLP: 100)."""
        own = self.iters if controller == self.controller else None
        return own or (50 if controller == "open-loop" else 100)


# What both captured forms share: fixed arrays of pushes and forces, which the graphs read, and the model's default
# targets and placements at capture (a user may edit them between evaluations: current() compares them).
class _Captured:

    def __init__(self, task: ControlTask, *, requires_grad: bool):
        model = task.model
        self.task = task
        self.defaults = _control_defaults(model)
        self.push = wp.zeros(task.world_count * task.n_params // 3, dtype=model.types.vec3, device=model.device,
                             requires_grad=requires_grad)
        self.tape = wp.Tape() if requires_grad else None  # the forces' launches: their gradients back to the pushes
        with self.tape or contextlib.nullcontext():
            self.forces = task._forces(self.push)
        self.rollout: wc.CapturedRollout | None = None

    def set_pushes(self, push: np.ndarray) -> None:
        self.push.assign(push)
        self.task._forces(self.push, self.forces)

    def current(self) -> bool:
        return self.rollout.current() and all(
            np.array_equal(a, b) for a, b in zip(self.defaults, _control_defaults(self.task.model)))


def _control_defaults(model: wc.Model) -> list[np.ndarray]:
    return [np.array(a) for a in (model.handle_rest_target, model.pin_rest_target, model.obstacle_rest_transform)
            if a is not None]


# An evaluation as graphs: the rollout and loss as a wc.CapturedRollout, the backward pass carried on to the pushes
# by the forces' tape; com_rows() gives the three centre-of-mass rows by three reverse passes of the last run.
class _CapturedEvaluation(_Captured):

    def __init__(self, task: ControlTask):
        super().__init__(task, requires_grad=True)
        model, W = task.model, task.world_count
        self.com: wp.array | None = None  # the centres of mass the loss is made from (a centre-of-mass target)

        def loss(trajectory):
            values, self.com = task._loss_values(trajectory[-1], [None] * W, trajectory)  # the last call's: the graph's
            return values

        self.rollout = wc.CapturedRollout(task.sim, model.state(requires_grad=False), task._control_fn(self.forces),
                                          steps=task.steps, loss=loss, segment_steps=task.segment_steps)

    def run(self, push: np.ndarray, *, backward: bool = True) -> dict:
        self.set_pushes(push)
        self.rollout.run(backward=backward)
        out = {"values": self.rollout.loss.numpy().astype(np.float64),
               "positions": self.rollout.trajectory[-1].particle_x.numpy().astype(np.float64)}
        if backward:
            out["grads"] = self.push_gradients()
        return out

    def push_gradients(self) -> np.ndarray:
        self.push.grad.zero_()
        self.tape.backward(grads={f: f.grad for f in self.forces})
        return self.push.grad.numpy().astype(np.float64).reshape(self.task.world_count, -1)

    def com_rows(self) -> list[np.ndarray]:
        W = self.task.world_count
        rows = []
        for c in range(3):
            seed = np.zeros((W, 3))
            seed[:, c] = 1.0
            self.rollout.backward({self.com: seed})
            rows.append(self.push_gradients())
        return rows


# Forward simulations as graphs: the rollout without a loss, the loss launched after each replay.
class _CapturedLosses(_Captured):

    def __init__(self, task: ControlTask):
        super().__init__(task, requires_grad=False)
        model = task.model
        self.rollout = wc.CapturedRollout(task.sim, model.state(requires_grad=False), task._control_fn(self.forces),
                                          steps=task.steps)

    def run(self, push: np.ndarray) -> dict:
        task = self.task
        self.set_pushes(push)
        trajectory = self.rollout.run()
        final = trajectory[-1]
        values, _ = task._loss_values(final, [None] * task.world_count, trajectory)
        return {"values": values.numpy().astype(np.float64),
                "positions": final.particle_x.numpy().astype(np.float64)}


EVALUATION_KINDS = ("capture", "replay", "uncaptured")
"""How a :class:`ControlTask`'s evaluation ran (``seconds_by_kind``): capturing its graphs (a capture costs several
uncaptured runs), replaying them, or uncaptured."""


def scene_task_args(scene: Scene, *, steps: int | None = None, options: wc.SolverOptions | None = None,
                    segment_steps: int | None = None) -> dict:
    """ControlTask's arguments after the model, from a scene's checked ``[control]`` table."""
    spec = scene.control
    return dict(dt=scene.dt, particles=spec.particles, interval_steps=spec.interval_steps, intervals=spec.intervals,
                steps=steps or spec.steps, target_com=spec.target_com, target_positions=spec.target_positions,
                regularizer=spec.regularizer, options=options or scene.solver_options, segment_steps=segment_steps,
                controller=spec.controller, optimizer=spec.optimizer, iters=spec.iters, search=spec.search,
                warm_start=spec.warm_start, push_bound=spec.push_bound, waypoints=spec.waypoints)
