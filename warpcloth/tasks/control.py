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

import contextlib
import dataclasses
import math
import os
import time
from dataclasses import dataclass

import numpy as np
import warp as wp

import warpcloth as wc
from warpcloth.kernels.losses import loss_kernels
from warpcloth.scene import (
    CONTROLLERS,
    Scene,
    SearchSpec,
    check_control_optimizer,
    default_control_optimizer,
    load_scene,
)
from warpcloth.tasks.controllers import ControlResult, optimize_open_loop, train_mlp

WHOLE_TAPE_PARTICLE_STEPS = 200_000
"""A control task tapes a rollout whole, without checkpoints, up to this many particle-steps (particles of all
worlds times steps): the throw's full tape takes 164 MB for 81 particles and 700 steps, 2.9 kB a particle-step
(README, checkpointing), so this is about 0.6 GB. Beyond it a rollout is checkpointed (``wc.checkpointed_backward``)."""
CAPTURED_SEGMENTS_PARTICLE_STEPS = 2_000_000
"""A checkpointed rollout is replayed from graphs in segments (``wc.CapturedRollout(segment_steps=...)``) up to this
many particle-steps: the replay keeps every State (168 B a particle-step in float64: about 0.34 GB here) besides
Warp's record of the graphs (0.3-1 MB a step), where ``wc.checkpointed_backward`` keeps a segment's. 16 throw worlds
(0.9 million) replay; 64 (3.6 million) run uncaptured."""


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
        options: Solver options (default: SolverOptions()). An ``"auto"`` preconditioner is block SSOR here: a
            batch of worlds solves each world as one world alone does with it (on CUDA too), and on the throw it is
            the faster one (64 worlds 5.5k world-steps/s against 4.7k with a multigrid per world, one world 1709
            against 1648: benchmarks/worlds.py, 2026-11-27).
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
        self._captures: dict = {}  # _captured's, by kind
        self._uncaptured: dict[str, int] = {}  # calls that could have been captured, by kind (_captured)

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

    def _forces(self, push: wp.array, forces: list[wp.array] | None = None) -> list[wp.array]:
        """Each interval's forces from the pushes: into new arrays, or into ``forces`` (made by an earlier call: it
        writes the pushed particles' entries, the others stay zero)."""
        m = len(self.particles)
        if forces is None:
            forces = [wp.zeros(self.model.particle_count, dtype=self.model.types.vec3, device=self.model.device,
                               requires_grad=True) for _ in range(self.intervals)]
        for s, f in enumerate(forces):
            wp.launch(self._kernels.push_forces, self.world_count * m,
                      inputs=[push, s, self.intervals, self._particles, self._first,
                              self.model.scalar(self.push_mass)], outputs=[f], device=self.model.device)
        return forces

    def _control_fn(self, forces: list[wp.array]):
        base = self.model.control(requires_grad=False)
        controls = [wc.Control(f, base.handle_target, base.pin_target, obstacle_transform=base.obstacle_transform)
                    for f in forces]

        def control(i: int) -> wc.Control:
            s = i // self.interval_steps
            return controls[s] if s < self.intervals else base

        return control

    def _push_values(self, params) -> np.ndarray:
        """The pushes of every world as (world_count n_params / 3, 3) numbers: ``params`` holds world_count sets of
        n_params numbers."""
        flat = [np.asarray(p, dtype=np.float64).reshape(-1) for p in params]
        for w, p in enumerate(flat):
            if p.shape != (self.n_params,) or not np.all(np.isfinite(p)):
                where = f" (world {w})" if self.world_count > 1 else ""
                raise ValueError(f"control parameters{where} must be {self.n_params} finite numbers, got shape "
                                 f"{p.shape}")
        return np.concatenate(flat).reshape(-1, 3)

    def _push_array(self, params) -> wp.array:
        """The pushes of every world (:meth:`_push_values`) as a new array."""
        return wp.array(self._push_values(params), dtype=self.model.types.vec3, device=self.model.device,
                        requires_grad=True)

    def _loss_values(self, state: wc.State, components: list[int | None]) -> tuple[wp.array, wp.array | None]:
        """Launch the loss of every world on the final ``state`` into a new array of world_count values (no read);
        returns it and, for a centre-of-mass target, the centres of mass it is made from."""
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
        return values, com

    def _loss_fn(self, components: list[int | None], final: dict):
        def loss(i: int, state: wc.State, out: wp.array) -> None:
            if i != self.steps:
                return
            final["positions"] = state.particle_x.numpy().astype(np.float64)
            values, _ = self._loss_values(state, components)
            wp.launch(self._kernels.add_sum, 1, inputs=[values], outputs=[out], device=self.model.device)
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
        pushes = self._push_values(params)  # checked before anything runs
        captured = self._captured("evaluate") if all(c is None for c in components) else None
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

    def _captured(self, kind: str = "evaluate") -> _CapturedEvaluation | _CapturedLosses | None:
        """The rollout of :meth:`evaluate_worlds` (``kind="evaluate"``: forward and backward) or of
        :meth:`losses_worlds` (``"losses"``: forward) recorded as graphs (``wc.CapturedRollout``: one graph a
        step, following the contacts it met before, in a scene with contact) where that can be: the forward pass on
        any device, the backward pass on the CPU (on CUDA its graph does not replay yet: capture.py) for a rollout
        taped whole, or checkpointed up to CAPTURED_SEGMENTS_PARTICLE_STEPS (replayed in segments). Made at the
        second call that can use it (and again where the solver's options or an array of
        the model were replaced since): the evaluation that captures costs about five uncaptured ones (the throw:
        1.0-1.1 s uncaptured, 4.6-5.0 s capturing, 0.23-0.29 s replayed; benchmarks/graph_step.py), so a task
        evaluated once is not made to capture."""
        segmented = kind == "evaluate" and self.segment_steps < self.steps
        if wc.CapturedRollout.unsupported(self.sim) is not None or kind == "evaluate" and (
                not self.model.device.is_cpu or segmented and (
                    wc.CapturedRollout.segments_unsupported(self.sim) is not None
                    or self.model.particle_count * self.steps > CAPTURED_SEGMENTS_PARTICLE_STEPS)):
            return None
        captured = self._captures.get(kind)
        if captured is None or not captured.current():
            self._captures[kind] = None
            self._uncaptured[kind] = self._uncaptured.get(kind, 0) + 1
            if self._uncaptured[kind] < 2:
                return None
            captured = self._captures[kind] = (_CapturedEvaluation if kind == "evaluate" else _CapturedLosses)(self)
        return captured

    @property
    def rerun_steps(self) -> list[int]:
        """The steps of the last captured evaluation that ran uncaptured, their contacts not those their graphs
        expected (``wc.CapturedRollout``'s ``rerun_steps``); empty where no evaluation was captured yet."""
        captured = self._captures.get("evaluate")
        return [] if captured is None else list(captured.rollout.rerun_steps)

    def losses_worlds(self, params: list) -> list[Evaluation]:
        """Forward simulations alone (no tape): every world's loss with ``params[w]`` (``grad`` None), the same
        values :meth:`evaluate_worlds` gives at a third of its cost: what a population method needs."""
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
        pushes = self._push_values(params)  # checked before anything runs
        captured = self._captured("evaluate")
        if captured is not None:
            out = captured.run(pushes, backward=False)
            positions = out["positions"]
            coms = captured.com.numpy().astype(np.float64)
            centres = [self.com_weights @ positions[model.world_slice(w)] for w in range(W)]
            skip = worse_than is not None and all(
                self._loss_of_com(centres[w], params[w]) >= worse_than[w] for w in range(W))
            grads = [[None] * W] * 3 if skip else captured.com_rows()
            self.reverse_passes += 0 if skip else 3 * W
            self.simulations += W
            self.batches += W > 1
            self.seconds += time.perf_counter() - t0
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


class _Captured:
    """What both captured forms share: fixed arrays for the pushes and forces, which the graphs read, and the model's
    default targets and placements the controls were made from (host arrays a user may edit between evaluations;
    the graphs hold the values they had)."""

    def __init__(self, task: ControlTask, *, requires_grad: bool):
        model = task.model
        self.task = task
        self.defaults = _control_defaults(model)
        self.push = wp.zeros(task.world_count * task.n_params // 3, dtype=model.types.vec3, device=model.device,
                             requires_grad=requires_grad)
        """The pushes the forces are made from (assigned at each run)."""
        self.tape = wp.Tape() if requires_grad else None
        """The forces' launches, recorded once: they carry the forces' gradients back to the pushes."""
        with self.tape or contextlib.nullcontext():
            self.forces = task._forces(self.push)
        self.rollout: wc.CapturedRollout | None = None

    def set_pushes(self, push: np.ndarray) -> None:
        """Write ``push`` into the pushes and their forces into the forces the graphs read."""
        self.push.assign(push)
        self.task._forces(self.push, self.forces)

    def current(self) -> bool:
        """Whether the graphs still hold what an uncaptured evaluation would read now."""
        return self.rollout.current() and all(
            np.array_equal(a, b) for a, b in zip(self.defaults, _control_defaults(self.task.model)))


def _control_defaults(model: wc.Model) -> list[np.ndarray]:
    return [np.array(a) for a in (model.handle_rest_target, model.pin_rest_target, model.obstacle_rest_transform)
            if a is not None]


class _CapturedEvaluation(_Captured):
    """A task's evaluation as graphs: the rollout with its loss as a ``wc.CapturedRollout``, its backward pass
    carried on to the pushes by the forces' tape."""

    def __init__(self, task: ControlTask):
        super().__init__(task, requires_grad=True)
        model, W = task.model, task.world_count
        self.com: wp.array | None = None  # the centres of mass the loss is made from (a centre-of-mass target)

        def loss(trajectory):
            values, self.com = task._loss_values(trajectory[-1], [None] * W)  # the last call's are the graph's
            return values

        self.rollout = wc.CapturedRollout(task.sim, model.state(requires_grad=False), task._control_fn(self.forces),
                                          steps=task.steps, loss=loss, segment_steps=task.segment_steps)

    def run(self, push: np.ndarray, *, backward: bool = True) -> dict:
        """The loss of every world, the final positions and (with ``backward``) the gradients with respect to the
        pushes."""
        self.set_pushes(push)
        self.rollout.run(backward=backward)
        out = {"values": self.rollout.loss.numpy().astype(np.float64),
               "positions": self.rollout.trajectory[-1].particle_x.numpy().astype(np.float64)}
        if backward:
            out["grads"] = self.push_gradients()
        return out

    def push_gradients(self) -> np.ndarray:
        """The pushes' gradients from the forces' (what the rollout's backward pass left), one row a world."""
        self.push.grad.zero_()
        self.tape.backward(grads={f: f.grad for f in self.forces})
        return self.push.grad.numpy().astype(np.float64).reshape(self.task.world_count, -1)

    def com_rows(self) -> list[np.ndarray]:
        """d com_c / d pushes of every world, c = 0, 1, 2: three reverse passes of the last run."""
        W = self.task.world_count
        rows = []
        for c in range(3):
            seed = np.zeros((W, 3))
            seed[:, c] = 1.0
            self.rollout.backward({self.com: seed})
            rows.append(self.push_gradients())
        return rows


class _CapturedLosses(_Captured):
    """A task's forward simulations as graphs (:meth:`ControlTask.losses_worlds`): fixed arrays for the pushes and
    forces, the rollout as a ``wc.CapturedRollout`` without a loss, the loss launched after each replay."""

    def __init__(self, task: ControlTask):
        super().__init__(task, requires_grad=False)
        model = task.model
        self.rollout = wc.CapturedRollout(task.sim, model.state(requires_grad=False), task._control_fn(self.forces),
                                          steps=task.steps)

    def run(self, push: np.ndarray) -> dict:
        """The loss of every world and the final positions."""
        task = self.task
        self.set_pushes(push)
        final = self.rollout.run()[-1]
        values, _ = task._loss_values(final, [None] * task.world_count)
        return {"values": values.numpy().astype(np.float64),
                "positions": final.particle_x.numpy().astype(np.float64)}


def scene_task_args(scene: Scene, *, steps: int | None = None, options: wc.SolverOptions | None = None,
                    segment_steps: int | None = None) -> dict:
    """ControlTask's arguments after the model, from a scene's checked ``[control]`` table."""
    spec = scene.control
    return dict(dt=scene.dt, particles=spec.particles, interval_steps=spec.interval_steps, intervals=spec.intervals,
                steps=steps or spec.steps, target_com=spec.target_com, target_positions=spec.target_positions,
                regularizer=spec.regularizer, options=options or scene.solver_options, segment_steps=segment_steps,
                controller=spec.controller, optimizer=spec.optimizer, iters=spec.iters, search=spec.search,
                warm_start=spec.warm_start)
