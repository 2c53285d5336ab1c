"""Motion control: find the pushes that move a cloth where a loss says (the seed's throw into a basket, SPEC §5(c),
or any scene's ``[control]`` table).

The control is a schedule of pushes: for each of the first ``intervals`` intervals of ``interval_steps`` steps, one
push per controlled particle, applied every step of the interval as a force ``F = (M / k) p`` on each of the k
particles, with M the cloth's mass. So ``p`` [m/s^2] is the acceleration k equal pushes give the whole cloth: on the
seed's throw ``p = (0, 0, 9.8)`` on every corner holds the cloth up. (The seed adds a velocity increment to each
corner every step, a corner acceleration; this is a fixed linear rescaling of it that puts the parameters on the
scale of gravity.) The loss is taken at the horizon: ``1/2 |com_T - target|^2`` on the centre of mass (mass-weighted:
see :class:`ControlTask`), or ``1/2 mean_i |x_i,T - target_i|^2`` on every particle, plus an optional
``regularizer * 1/2 |p|^2``.
Gradients come from ``wc.checkpointed_backward``: one taped pass where the tape stays small, else a checkpointed
rollout, so long horizons and large batches back-propagate with O(sqrt(T)) stored states.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

import warpcloth as wc
from warpcloth.kernels.losses import loss_kernels
from warpcloth.progress import progress_bar
from warpcloth.scene import (
    CONTROLLERS,
    Scene,
    SearchSpec,
    check_control_optimizer,
    default_control_optimizer,
    load_scene,
)
from warpcloth.tasks.lockstep import Lockstep, run_in_lockstep
from warpcloth.tasks.optim import cmaes, lbfgs

SEARCH_SIGMA = 5.0
"""The global search's default spread of the pushes [m/s^2] (``SearchSpec.sigma``): CMA-ES's initial one, the
multistart's random starts' (half the push that holds the seed's cloth up)."""
MULTISTART_POPULATION = 8
"""The multistart's default number of starts (``SearchSpec.population``)."""

WHOLE_TAPE_PARTICLE_STEPS = 200_000
"""A control task tapes a rollout whole, without checkpoints, up to this many particle-steps (particles of all
worlds times steps): the throw's full tape takes 164 MB for 81 particles and 700 steps, 2.9 kB a particle-step
(README, checkpointing), so this is about 0.6 GB. Beyond it a rollout is checkpointed (``wc.checkpointed_backward``)."""


@dataclass
class Evaluation:
    """One forward + backward simulation of a control task."""

    loss: float
    """The loss (the regulariser included), or the chosen centre-of-mass coordinate with ``component``."""
    grad: np.ndarray | None
    """d loss / d params, flat (None where a request's threshold let :meth:`ControlTask.jacobian_worlds` skip the
    reverse passes)."""
    com: np.ndarray
    """The centre of mass (mass-weighted, as the loss takes it) at the horizon (3,)."""
    positions: np.ndarray
    """Every particle's position at the horizon (n, 3)."""


class ControlTask:
    """Loss, gradient and trajectory of a cloth as functions of its pushes ``p[interval, particle, xyz]`` [m/s^2].

    Args:
        model: The scene's model (with gradients: ``requires_grad=True``): one world, or several equal worlds
            (``ModelBuilder.replicate``), each simulated with its own pushes (:meth:`evaluate_worlds`).
        dt: Time step [s].
        particles: The pushed particles (indices within a world), in the order of the pushes.
        interval_steps: Steps per push.
        intervals: Pushes per particle: the first ``intervals * interval_steps`` steps are controlled (pushes that
            begin at or after the horizon do nothing).
        steps: The horizon [steps].
        target_com: The centre of mass's target [m]; exactly one of it and ``target_positions``. The loss takes the
            mass-weighted centre, sum_i m_i x_i / M, not the vertex mean the seed's loss takes: internal forces cancel
            in the first, so in free flight it moves exactly affinely with the pushes, and so does its tape
            derivative. The vertex mean's derivative there is the tangent of an unstressed sheet, which has no
            membrane stiffness across its plane: on the seed's throw with no pushes, d com_z / d push is 1.57x the
            slope over any push of 1e-2 m/s^2 or more (README, Why the throw's optimisers failed). ``error_pct``
            keeps the seed's vertex mean.
        target_positions: Every particle's target [m], shape (particles of a world, 3).
        regularizer: Weight of ``1/2 |p|^2`` in the loss.
        options: Solver options (default: SolverOptions()). An ``"auto"`` preconditioner is block SSOR here, so
            that a batch of worlds solves each world as one world alone does (multigrid spans one world).
        segment_steps: Checkpoint segment length. By default the whole horizon (one taped forward pass, no
            re-simulation) where the tape stays small, ``particle_count * steps <= WHOLE_TAPE_PARTICLE_STEPS``,
            else ceil(sqrt(steps)) (O(sqrt(T)) stored states; each segment but the last simulated twice).
        controller, optimizer, iters, search, warm_start: What :meth:`run` does when not told otherwise (a scene's
            choices).
        template: The one-world builder ``model`` was finalised from (copies of ``model``); with it
            :meth:`evaluate_many` runs several simulations as one batch of worlds (``ModelBuilder.replicate``).
    """

    def __init__(self, model: wc.Model, dt: float, *, particles, interval_steps: int, intervals: int, steps: int,
                 target_com=None, target_positions=None, regularizer: float = 0.0,
                 options: wc.SolverOptions | None = None, segment_steps: int | None = None,
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
        if controller not in CONTROLLERS:
            raise ValueError(f"unknown controller {controller!r}; one of {', '.join(CONTROLLERS)}")
        options = options or wc.SolverOptions()
        if options.preconditioner == "auto":
            options = dataclasses.replace(options, preconditioner="block_ssor")
        self._args = dict(dt=dt, particles=self.particles, interval_steps=interval_steps, intervals=intervals,
                          steps=steps, target_com=target_com, target_positions=target_positions,
                          regularizer=regularizer, options=options, segment_steps=segment_steps,
                          controller=controller, optimizer=optimizer, iters=iters, search=search,
                          warm_start=warm_start, template=template)
        self.model, self.dt, self.steps = model, float(dt), int(steps)
        self.world_count = model.world_count
        self.world_particles = n
        """Particles of one world."""
        self.interval_steps, self.intervals = int(interval_steps), int(intervals)
        self.target_com = None if target_com is None else np.asarray(target_com, dtype=np.float64).reshape(3)
        self.target_positions = target_positions
        self.regularizer = float(regularizer)
        whole = model.particle_count * self.steps <= WHOLE_TAPE_PARTICLE_STEPS
        self.segment_steps = segment_steps or (self.steps if whole else math.ceil(math.sqrt(self.steps)))
        """Checkpoint segment length of :meth:`evaluate_worlds`' rollouts."""
        self.controller = controller
        self.optimizer = optimizer or default_control_optimizer(controller, self.target_com, self.regularizer)
        problem = check_control_optimizer(self.optimizer, controller, self.target_com, self.regularizer)
        if problem:
            raise ValueError(f"optimizer: {problem}")
        self.iters = iters
        self.search = search or SearchSpec()
        """The global search's settings (``optimizer="cmaes"``)."""
        self.warm_start = int(warm_start)
        """The MLP's warm start (:func:`train_mlp`)."""
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
        """World simulations run (forward + backward), each world of a batch counted (:meth:`jacobian_worlds`: one
        for a world's three rows)."""
        self.reverse_passes = 0
        """Extra reverse passes through recorded rollouts (:meth:`jacobian_worlds`: three a world)."""
        self.batches = 0
        """Simulations of several worlds at once."""
        self.batch_retries = 0
        """Batches run again world by world because one of their simulations raised."""
        self.seconds = 0.0
        self.name = ""
        """The scene's name, where the task comes from one (:meth:`from_scene`)."""
        self._batched: dict[int, ControlTask] = {self.world_count: self}

    @classmethod
    def from_scene(cls, scene: str | os.PathLike | Scene, *, device=None, dtype=None,
                   options: wc.SolverOptions | None = None, steps: int | None = None,
                   segment_steps: int | None = None) -> ControlTask:
        """The task of a scene's ``[control]`` table (a scene name, a path or a loaded Scene).

        Args:
            scene: An embedded scene name (``warpcloth scenes``), a .toml path, or a Scene.
            device, dtype: Of the model (Warp's default device, float32).
            options: Solver options instead of the scene's.
            steps: A horizon instead of the scene's.
            segment_steps: Checkpoint segment length.

        Raises:
            ValueError: for a scene without a ``[control]`` table (and as load_scene does).
        """
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
        """How far the cloth ends from its target, against how far it started, in %: ``|com_T - target| /
        |com_0 - target|`` for a centre-of-mass target, with com the vertex mean as the seed measures it (the loss
        takes the mass-weighted centre: they differ with the cloth's shape, by 6-12 mm on the throw's cloth at rest
        in the basket); the same ratio of RMS distances for target positions.
        100 % ends as far as it started (on the seed's throw not "no better than doing nothing": with no pushes
        the cloth drops outside the wall, with no floor to stop it, to z = -238 m after the 7 s: 5508 %)."""
        positions = np.asarray(positions, dtype=np.float64)
        if self.target_com is not None:
            return 100.0 * float(np.linalg.norm(positions.mean(axis=0) - self.target_com)
                                 / np.linalg.norm(self.com_initial - self.target_com))
        return 100.0 * float(np.linalg.norm(positions - self.target_positions)
                             / np.linalg.norm(self.x_initial - self.target_positions))

    def _forces(self, push: wp.array) -> list[wp.array]:
        m = len(self.particles)
        forces = []
        for s in range(self.intervals):
            f = wp.zeros(self.model.particle_count, dtype=self.model.types.vec3, device=self.model.device,
                         requires_grad=True)
            wp.launch(self._kernels.push_forces, self.world_count * m,
                      inputs=[push, s, self.intervals, self._particles, self._first,
                              self.model.scalar(self.push_mass)], outputs=[f], device=self.model.device)
            forces.append(f)
        return forces

    def _control_fn(self, forces: list[wp.array]):
        base = self.model.control(requires_grad=False)
        controls = [wc.Control(f, base.handle_target, base.pin_target, obstacle_transform=base.obstacle_transform)
                    for f in forces]

        def control(i: int) -> wc.Control:
            s = i // self.interval_steps
            return controls[s] if s < self.intervals else base

        return control

    def _push_array(self, params) -> wp.array:
        """The pushes of every world: ``params`` holds world_count sets of n_params numbers."""
        flat = [np.asarray(p, dtype=np.float64).reshape(-1) for p in params]
        for w, p in enumerate(flat):
            if p.shape != (self.n_params,) or not np.all(np.isfinite(p)):
                where = f" (world {w})" if self.world_count > 1 else ""
                raise ValueError(f"control parameters{where} must be {self.n_params} finite numbers, got shape "
                                 f"{p.shape}")
        return wp.array(np.concatenate(flat).reshape(-1, 3), dtype=self.model.types.vec3, device=self.model.device,
                        requires_grad=True)

    def _loss_fn(self, components: list[int | None], final: dict):
        model, kernels = self.model, self._kernels
        W = self.world_count

        def loss(i: int, state: wc.State, out: wp.array) -> None:
            if i != self.steps:
                return
            final["positions"] = state.particle_x.numpy().astype(np.float64)
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
            wp.launch(kernels.add_sum, 1, inputs=[values], outputs=[out], device=model.device)
            final["values"] = values.numpy().astype(np.float64)

        return loss

    def evaluate(self, params: np.ndarray, *, component: int | None = None) -> Evaluation:
        """One forward + backward simulation: the loss and its gradient at ``params`` (any shape of n_params
        numbers). With ``component`` (0, 1, 2; a centre-of-mass target only) the "loss" is that coordinate of the
        final centre of mass instead, without the regulariser. On a task of one world."""
        if self.world_count != 1:
            raise ValueError(f"evaluate runs one world; this task has {self.world_count}: use evaluate_worlds")
        return self.evaluate_worlds([params], [component])[0]

    def evaluate_worlds(self, params: list, components: list | None = None) -> list[Evaluation]:
        """One forward + backward simulation of every world, world w with ``params[w]`` (n_params numbers) and the
        loss ``components[w]`` (as :meth:`evaluate`'s ``component``; all None or all coordinates). The worlds
        are independent, so each gets what a model of that world alone gives (bitwise: tests/test_worlds.py; the
        collision stage's second try and fail-safe act on the worlds that need them alone)."""
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
        push = self._push_array(params)
        tape = wp.Tape()
        with tape:
            forces = self._forces(push)
        final: dict = {}
        wc.checkpointed_backward(self.sim, self.model.state(requires_grad=False), self._control_fn(forces),
                                 steps=self.steps, loss=self._loss_fn(components, final),
                                 segment_steps=self.segment_steps)
        tape.backward(grads={f: f.grad for f in forces})
        grads = push.grad.numpy().astype(np.float64).reshape(W, -1)
        self.simulations += W
        self.batches += W > 1
        self.seconds += time.perf_counter() - t0
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

    def losses_worlds(self, params: list) -> list[Evaluation]:
        """Forward simulations alone (no tape): every world's loss with ``params[w]`` (``grad`` None), the same
        values :meth:`evaluate_worlds` gives at a third of its cost: what a population method needs."""
        W = self.world_count
        if len(params) != W:
            raise ValueError(f"losses_worlds takes one parameter set per world ({W}), got {len(params)}")
        t0 = time.perf_counter()
        forces = self._forces(self._push_array(params))
        final: dict = {}
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
        self.seconds += time.perf_counter() - t0
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
        """The three centre-of-mass rows of every world, world w with ``params[w]``: ``out[w][c]`` is what
        :meth:`evaluate_worlds` gives with component c, bitwise, from one forward pass and three reverse passes
        through its recording (each adjoint solve's first guess is zeroed once read, so every pass repeats a lone
        one: ``LinearSolver.solve_recorded``). Needs a centre-of-mass target; a rollout that is not taped whole
        (``segment_steps < steps``) runs :meth:`evaluate_worlds` once per row instead. Counts one simulation per
        world (``simulations``) and three reverse passes (``reverse_passes``).

        ``worse_than`` (a loss per world): where every world's loss (1/2 |com_T - target|^2 plus the regulariser's
        term, as an optimiser computes it from ``Evaluation.com``) is at least its threshold, the reverse passes are
        skipped and the rows come back with ``grad=None``: a Gauss-Newton point that is rejected needs no Jacobian."""
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
                self._loss_of_com(centres[w], params[w]) >= worse_than[w] for w in range(W)):
            grads = [[None] * W] * 3
        else:
            grads = self._reverse_rows(tape, outer, com, forces, push)
        self.simulations += W
        self.batches += W > 1
        self.seconds += time.perf_counter() - t0
        return [[Evaluation(loss=float(coms[w, c]), grad=grads[c][w], com=centres[w],
                            positions=positions[model.world_slice(w)]) for c in range(3)] for w in range(W)]

    def _loss_of_com(self, com: np.ndarray, params) -> float:
        """The loss of a centre-of-mass target, as an optimiser computes it on the host."""
        r = com - self.target_com
        p = np.asarray(params, dtype=np.float64).reshape(-1)
        return 0.5 * float(r @ r) + 0.5 * self.regularizer * float(p @ p)

    def _reverse_rows(self, tape: wp.Tape, outer: wp.Tape, com: wp.array, forces: list, push: wp.array) -> list:
        """The three reverse passes of :meth:`jacobian_worlds`: d com_c / d params of every world, c = 0, 1, 2."""
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
        """Forward + backward simulations of several ``(params, component)`` requests (as :meth:`evaluate`'s), run
        as one batch of worlds (:meth:`worlds`, :meth:`evaluate_worlds`) where the task has a ``template``, one
        after another otherwise. Requests that are whole Jacobians, ``(p, 0), (p, 1), (p, 2)`` for each of several
        points p (or of one point without a template, or carrying a threshold), run as :meth:`jacobian_worlds`. A
        request may carry a third entry, a loss threshold (``(p, c, worse_than)``, the same for a point's three
        rows): where every point of such a batch is at least as bad, its rows come back without gradients
        (``grad=None``). A request whose simulation raises (CollisionError, SimulationError) gets the exception in
        its place. Each result is the one :meth:`evaluate` gives; a batch that raised is run again request by
        request, so that the others' results are kept."""
        if self.world_count != 1:
            raise ValueError(f"evaluate_many runs on a task of one world; this one has {self.world_count}")
        if not requests:
            return []
        # Whole Jacobians (a point's three rows): one forward and three reverse passes a point, its worlds batched.
        # The throw's rows of three points took 5.3 s so against 7.7 s as nine worlds, one point's 3.3 s against
        # 2.9 s as three worlds (2026-11-25): a lone point goes this way only with a threshold, whose rejected
        # points then cost the forward pass alone.
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
        """Forward simulations alone of several points (``grad`` None): one batch of worlds (:meth:`worlds`,
        :meth:`losses_worlds`) where the task has a ``template``, one after another otherwise. A point whose
        simulation raises (CollisionError, SimulationError) gets the exception in its place; a batch that raised is
        run again point by point, so that the others' losses are kept. Each loss is the one :meth:`evaluate` gives."""
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

    def _row_triples(self, requests: list) -> tuple[list, list] | None:
        """(points, thresholds) of ``requests`` where they are whole Jacobians, (p, 0), (p, 1), (p, 2) for each point
        p in turn (each with the same optional threshold), on a rollout taped whole (:meth:`jacobian_worlds`); else
        None."""
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
        """Take a batch task's counters over into this task's."""
        self.simulations += batch.simulations
        self.reverse_passes += batch.reverse_passes
        self.batches += batch.batches
        self.seconds += batch.seconds
        batch.simulations = batch.batches = batch.reverse_passes = 0
        batch.seconds = 0.0

    def loss_and_grad(self, params: np.ndarray, *, component: int | None = None
                      ) -> tuple[float, np.ndarray, np.ndarray]:
        """(loss [m^2], d loss / d params (n_params,), final centre of mass (3,)): :meth:`evaluate`, unpacked."""
        e = self.evaluate(params, component=component)
        return e.loss, e.grad, e.com

    def trajectory(self, params: np.ndarray) -> list[np.ndarray]:
        """Positions (n, 3) of every step, from a forward pass only."""
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
        """Optimise with the task's controller (or ``controller``): :func:`optimize_open_loop` or :func:`train_mlp`
        (keyword arguments go to them); ``iters`` simulations (default: :meth:`default_iters`)."""
        controller = controller or self.controller
        if controller not in CONTROLLERS:
            raise ValueError(f"unknown controller {controller!r}; one of {', '.join(CONTROLLERS)}")
        iters = iters or self.default_iters(controller)
        kwargs.setdefault("optimizer", self.optimizer_for(controller))
        if controller == "open-loop":
            return optimize_open_loop(self, iters=iters, progress=progress, **kwargs)
        kwargs.setdefault("warm_start", self.warm_start if controller == self.controller else 0)
        return train_mlp(self, iters=iters, progress=progress, **kwargs)

    def optimizer_for(self, controller: str) -> str:
        """The optimiser of ``controller``: the task's own where it is the task's controller, else that controller's
        default for this loss."""
        if controller == self.controller:
            return self.optimizer
        return default_control_optimizer(controller, self.target_com, self.regularizer)

    def default_iters(self, controller: str) -> int:
        """Simulations a run of ``controller`` spends unless told: the task's ``iters`` where it is the task's own
        controller, else 50 for the open loop and 100 for the MLP."""
        own = self.iters if controller == self.controller else None
        return own or (50 if controller == "open-loop" else 100)


def scene_task_args(scene: Scene, *, steps: int | None = None, options: wc.SolverOptions | None = None,
                    segment_steps: int | None = None) -> dict:
    """ControlTask's arguments after the model, from a scene's checked ``[control]`` table."""
    spec = scene.control
    return dict(dt=scene.dt, particles=spec.particles, interval_steps=spec.interval_steps, intervals=spec.intervals,
                steps=steps or spec.steps, target_com=spec.target_com, target_positions=spec.target_positions,
                regularizer=spec.regularizer, options=options or scene.solver_options, segment_steps=segment_steps,
                controller=spec.controller, optimizer=spec.optimizer, iters=spec.iters, search=spec.search,
                warm_start=spec.warm_start)


@dataclass
class ControlResult:
    params: np.ndarray
    """Pushes [m/s^2], shape (intervals, particles, 3) (see the module docstring)."""
    losses: list[float] = field(default_factory=list)
    errors_pct: list[float] = field(default_factory=list)
    simulations: int = 0
    """Forward + backward simulations until the best result."""
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
        if bar is not None:
            bar.close()
        return _multistart(task, params, iters=iters, search=search or task.search, batch=batch, callback=callback,
                           local=dict(max_step=max_step, damping=damping))
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
        if generations:
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
                local: dict) -> ControlResult:
    """``optimizer="multistart"`` (:func:`optimize_open_loop`): ``search.population`` local runs in lockstep, from
    ``params`` and from random points around it, each with an equal share of ``iters``; their histories interleaved
    in the order the lockstep ran them (every run's k-th simulation, run by run, then the k+1-th)."""
    starts = search.population or MULTISTART_POPULATION
    if iters < starts:
        raise ValueError(f"multistart: {iters} simulations for {starts} starts; give each start one at least")
    rng = np.random.default_rng(search.seed)
    sigma = search.sigma or SEARCH_SIGMA
    points = [params] + [params + rng.normal(scale=sigma, size=task.n_params) for _ in range(starts - 1)]
    seen: list[list] = [[] for _ in points]
    t0 = time.perf_counter()
    runs = optimize_open_loop_starts(
        task, points, batch=batch, iters=iters // starts,
        optimizer=default_control_optimizer("open-loop", task.target_com, task.regularizer),
        callback_of=lambda i: lambda k, loss, err, p: seen[i].append((k, loss, err, np.array(p, dtype=np.float64))),
        **local)
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
    result.seconds = time.perf_counter() - t0
    return result


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
              warm_start: int = 0, progress: bool = False) -> ControlResult:
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
                              particle_force=force)
            x, v = xs[-1], vs[-1]
        rest = task.steps - controlled * task.interval_steps
        if rest > 0:
            xs, _ = simulate(task.sim, x, v, steps=rest, time=controlled * task.interval_steps * task.dt)
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
