"""The implicit Euler simulator (docs/concepts/step.md): a step is the model's list of stages over one ``_Step``."""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import warp as wp

from warpcloth.collision import CollisionStage
from warpcloth.collision.stage import CollisionReport
from warpcloth.kernels import status as ks
from warpcloth.kernels.implicit import implicit_kernels
from warpcloth.model import Control, Model, State
from warpcloth.obstacles import obstacle_motion, obstacle_points
from warpcloth.solver.assembly import SystemAssembler
from warpcloth.solver.diagnostics import StepDiagnostics
from warpcloth.solver.linear import LinearSolver, SolveInfo
from warpcloth.solver.options import SolverOptions
from warpcloth.solver.proximity import ProximityForces, ProximityPairs
from warpcloth.solver.status import StepStatus
from warpcloth.tape import StepArrays, active_tape, capturing


class Simulator:
    """Implicit Euler cloth solver with the contract ``step(state_in, state_out, control)``.

    The model's arrays are read at every step (in-place changes and rebound arrays apply from the next); pins,
    handles, collision settings or contact materials edited in place need :meth:`notify_model_changed`.

    Args:
        dt: time step [s], > 0.
        options: None: the defaults.

    Raises:
        ValueError: ``dt`` not finite and > 0, or an option out of range."""

    def __init__(self, model: Model, dt: float, *, options: SolverOptions | None = None):
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
        self.model = model
        self.dt = float(dt)
        self._options = options or SolverOptions()
        self._options.validate()
        self.device = model.device
        self.kernels = implicit_kernels(model.scalar)
        self.status = StepStatus(self.device)
        """The failure record the step's kernels latch into, and the CG iteration totals (read at sync points)."""
        self._steps = 0
        self._no_flag = wp.zeros(1, dtype=wp.int32, device=self.device)  # never raised: _note_plan_miss's stand-in
        self.phase_seconds = dict.fromkeys(("assembly", "proximity", "solve", "integrate", "collision"), 0.0)
        """Host wall time [s] of each phase of the forward steps so far (on CUDA: launch time unless synchronised)."""
        self.notify_model_changed()

    # -- public ------------------------------------------------------------------------------------------------------
    def notify_model_changed(self) -> None:
        """Rebuild what derives from the model after in-place edits of pins, handles or collision settings."""
        model = self.model
        self.diagnostics = StepDiagnostics(model, self.dt)
        self.assembler = SystemAssembler(model, self.dt)
        self._assembler_bdf2: SystemAssembler | None = None  # made at the first BDF2 step
        self.linear_solver = LinearSolver(model, self.options, hint=self.diagnostics.mesh_hint, status=self.status)
        """The CG solver of the implicit system and its adjoint."""
        self.collision = CollisionStage(model, self.dt, self.options) if model.collision is not None else None
        """The collision stage, or None for a scene without collisions."""
        if self.collision is not None:  # its divergence guard latches here; its detection stops at an error
            self.collision.record = self.status.record
            self.collision.detector.skip = self.status.record[ks.ERROR:ks.ERROR + 1]
        self.proximity = (ProximityForces(model, self.dt, capacity=self.options.collision.contact_capacity,
                                          rebuild_bvh=self.options.collision.bvh == "rebuild")
                          if ProximityForces.needed(model) else None)
        """Proximity repulsion and friction inside the implicit step, or None where the model has neither."""
        self._atol_checked = False  # the cg_atol floor is checked at the first skipped solve
        self._bdf2_buffers = None  # the blend and extrapolation of untaped BDF2 steps (_bdf2_start)
        self._step_buffers = None
        self._mass = None  # the untaped steps' lumped masses (_lumped_mass)
        self._candidate = None  # the untaped steps' x̂, v̂ before the collision stage (_integrate)
        self._arrays = StepArrays(self.device)  # the obstacles' vertices of a step (_obstacle_points)
        self._control_default = None
        self._static_motion = None  # the obstacles' motion where none moves (_obstacle_motion)
        self._motion_store: dict[float, wp.array] | None = None  # where moving ones are kept (_keeping_motions)
        # The step, as the stages this model needs, each with the phase it is timed under.
        stages = [("assembly", self._assemble)]
        if self.proximity is not None:
            stages.append(("proximity", self._proximity_forces))
        stages.append(("solve", self._solve))
        if self.proximity is not None:
            stages.append(("proximity", self._friction))
        stages.append(("integrate", self._integrate))
        if self.collision is not None:
            stages.append(("collision", self._collide))
        stages.append(("integrate", self._hand_on))
        self._stages = stages
        self._model_arrays = model_arrays(model)

    @property
    def options(self) -> SolverOptions:
        """The SolverOptions in force; new ones apply from the next solve (the backend and preconditioner stay)."""
        return self._options

    @options.setter
    def options(self, options: SolverOptions) -> None:
        options.validate()
        self._options = options
        self.linear_solver.options = options
        if self.collision is not None:
            self.collision.options = options

    @property
    def stats(self) -> dict:
        """Steps, and forward and adjoint CG iterations so far (the most of any world per solve); reads the device."""
        forward, adjoint = self.status.iterations()
        return {"steps": self._steps, "cg_iterations": forward, "adjoint_cg_iterations": adjoint}

    @property
    def last_solve(self) -> SolveInfo:
        """The last forward CG solve (diagnostics only: reading it reads the device)."""
        return self.linear_solver.info() if self._steps else SolveInfo(0, 0.0, True)

    def check(self, states=()) -> None:
        """Read the failure record latched since the last check; RuntimeWarning for solves that missed their
        tolerance. ``states`` (the trajectory) may hold the failing step's result, for the message to quote.

        Raises:
            SimulationError: a diverged particle, a non-finite or (``on_cg_failure="raise"``) unconverged solve,
                naming the step and the particle or world."""
        self._check(states)

    def step(self, state_in: State, state_out: State, control: Control | None = None) -> None:
        """Advance ``state_in`` by one step into ``state_out`` (recorded on the active tape); bitwise a function of
        the arguments and the model. ``state_out`` receives what the next step reads.

        Raises:
            ValueError: ``state_out is state_in``, or a State of another model's size, precision or device.
            SimulationError: as :meth:`check`, at the steps that check."""
        if state_out is state_in:
            raise ValueError("step() needs distinct state_in and state_out (a tape cannot record in-place updates)")
        self._check_state("state_in", state_in)
        self._check_state("state_out", state_out)
        if model_arrays(self.model) != self._model_arrays:  # an array of the model was rebound
            self.notify_model_changed()
        recording = active_tape() is not None and self.model.requires_grad
        s = _Step(state_in=state_in, state_out=state_out,
                  control=control if control is not None else self._default_control(), recording=recording,
                  number=state_in.step + 1, t_next=state_in.time + self.dt)
        clock = _PhaseClock(self.phase_seconds)
        for phase, stage in self._stages:
            stage(s)
            clock.lap(phase)
        if not capturing(self.device):  # a captured step runs at its replays (CapturedRollout counts them)
            self._steps += 1
        if self._sync_due(s.number):
            self._check((state_out,), s)

    # -- the stages of a step ----------------------------------------------------------------------------------------
    def _assemble(self, s: _Step) -> None:
        """A dv = b at the implicit step's start: ``state_in``, or BDF2's blend of it with the state before it."""
        s.values, s.rhs, s.pin_dv = self._buffers(s.recording)
        s.dv = self._output_dv(s.state_out, s.recording)
        s.start, s.assembler, explicit = s.state_in, self.assembler, None
        if self.options.integrator == "bdf2" and s.state_in.particle_x_last is not None:
            s.start, explicit = self._bdf2_start(s.state_in, s.recording)
            s.assembler = self._bdf2_assembler()
        s.assembler.assemble(s.start, s.control, s.t_next, s.values, s.rhs, s.pin_dv, s.dv, explicit=explicit)
        if self.collision is not None:
            s.obstacles = self._obstacle_points(s.control, s.state_in.time, s.recording)

    def _proximity_forces(self, s: _Step) -> None:
        obstacles = s.obstacles if s.obstacles is not None else \
            self._obstacle_points(s.control, s.state_in.time, s.recording)
        s.pairs = self.proximity.assemble(s.start, *obstacles, s.pin_dv, s.dv, s.values, s.rhs, s.recording,
                                          implicit_dt=s.assembler.dt)

    def _solve(self, s: _Step) -> None:
        """Solve A dv = b from ``state_in.particle_dv``; on a tape, record the adjoint (``State.solve_adjoint``)."""
        state_in, state_out, dv = s.start, s.state_out, s.dv
        guess = state_in.particle_dv
        warm = self.options.warm_start and guess is not None and guess.shape == dv.shape and guess.dtype == dv.dtype
        recording = s.recording and s.values.requires_grad
        if recording:  # the later step's adjoint hands its solution on here; a State stepped again keeps its array
            adjoint = state_out.solve_adjoint
            if adjoint is not None and adjoint.shape == dv.shape and adjoint.dtype == dv.dtype \
                    and adjoint.device == dv.device:
                adjoint.zero_()
            else:
                state_out.solve_adjoint = wp.zeros_like(dv, requires_grad=False)

        def after_adjoint() -> None:
            if self._sync_due(s.number):
                self._check()

        self.linear_solver.solve_recorded(
            s.values, s.rhs, dv, step=s.number, guess=guess if warm else None,
            adjoint_guess=state_out.solve_adjoint if recording else None,
            adjoint_result=state_in.solve_adjoint, after_adjoint=after_adjoint, pairs=s.pairs)
        s.velocity_change = dv

    def _friction(self, s: _Step) -> None:
        if s.pairs is not None and s.pairs.count and self.proximity.friction:
            s.mass = self._lumped_mass(s.recording)
            s.velocity_change = self.proximity.apply_friction(s.pairs, s.dv, s.mass, s.recording)

    def _integrate(self, s: _Step) -> None:
        """x = start + dt (v + dv): the step's result, or, with a collision stage, its candidate x̂, v̂."""
        model = self.model
        if self.collision is None:
            out = s.state_out
        elif s.recording:
            out = model.empty_state()  # x̂, v̂ before the projection (kept for the backward pass)
        else:  # scratch, as _buffers: an untaped step's x̂, v̂ are read within the step
            if self._candidate is None:
                self._candidate = model.empty_state(requires_grad=False)
            out = self._candidate
        wp.launch(self.kernels.integrate, model.particle_count, device=self.device,
                  inputs=[s.start.particle_x, s.start.particle_v, s.velocity_change, model.scalar(s.assembler.dt),
                          model.scalar(self.options.max_speed), s.number],
                  outputs=[out.particle_x, out.particle_v, self.status.record])
        if self.collision is not None:
            # the collision stage is driven from the host (its detection reads the device anyway): no NaN or
            # runaway particle may reach it, and the step's inputs still tell why (the error names the particle).
            # Not while a graph is captured: there a latched error makes detection find nothing (detector.skip)
            if not capturing(self.device):
                self._check((out,), s)
            s.x_hat, s.v_hat = out.particle_x, out.particle_v

    def _collide(self, s: _Step) -> None:
        """The collision stage from x̂, v̂ into ``state_out`` (detection from state_in, not BDF2's blend)."""
        # the lumped masses (friction's, or made where the stage finds contacts: one taped launch fewer a step)
        mass = s.mass if s.mass is not None else (lambda: self._lumped_mass(s.recording))
        # its last launch runs the divergence guard on the result (the projection's velocity change too)
        s.report = self.collision.resolve(s.state_in, s.x_hat, s.v_hat, *s.obstacles, s.state_out, s.number, mass,
                                          implicit_dt=s.assembler.dt)

    def _hand_on(self, s: _Step) -> None:
        """What the next step reads from ``state_out``: time, step number, BDF2's history, the lagged normals."""
        model, state_in, state_out = self.model, s.state_in, s.state_out
        bdf2 = self.options.integrator == "bdf2"
        moved = s.report is not None and s.report.contacts > 0
        state_out.time = s.t_next
        state_out.step = s.number
        state_out.particle_x_last = state_in.particle_x if bdf2 else None
        state_out.particle_v_last = state_in.particle_v if bdf2 else None
        if bdf2 and moved:
            x_last, v_last = (wp.empty_like(a, requires_grad=s.recording) for a in (state_in.particle_x,
                                                                                      state_in.particle_v))
            wp.launch(self.kernels.bdf2_history, model.particle_count, device=self.device,
                      inputs=[state_in.particle_x, state_in.particle_v, s.x_hat, state_out.particle_x,
                              state_out.particle_v, model.scalar(self.dt)], outputs=[x_last, v_last])
            state_out.particle_x_last, state_out.particle_v_last = x_last, v_last
        state_out.particle_x_previous = None
        if model.wind_lagged_normals:
            # ARCSim's face normals lag a step, except after a collision response that moved the cloth: it
            # recomputes them then (SPEC §2), so the next step's wind sees the current positions
            state_out.particle_x_previous = state_out.particle_x if moved else state_in.particle_x

    def _lumped_mass(self, recording: bool) -> wp.array:
        """The particles' lumped masses from the model's densities (taped: contact adjoints reach the densities)."""
        model = self.model
        if recording or self._mass is None:
            mass = wp.zeros(model.particle_count, dtype=model.scalar, device=self.device, requires_grad=recording)
            if not recording:
                self._mass = mass
        else:
            mass = self._mass
            mass.zero_()
        wp.launch(self.kernels.lumped_mass, model.tri_count, device=self.device,
                  inputs=[model.tri_indices, model.tri_area, model.tri_material, model.material_density,
                          model.material_thicken], outputs=[mass])
        return mass

    def _bdf2_assembler(self) -> SystemAssembler:  # BDF2's step: backward Euler over 2/3 dt
        if self._assembler_bdf2 is None:
            self._assembler_bdf2 = SystemAssembler(self.model, 2.0 * self.dt / 3.0)
        return self._assembler_bdf2

    def _bdf2_start(self, state_in: State, recording: bool) -> tuple[State, tuple[wp.array, wp.array] | None]:
        """BDF2's start point as a State that hands on state_in's first guesses and lagged normals, and, with wind,
        the extrapolation (2 x_n - x_{n-1}, 2 v_n - v_{n-1}) the explicit force is taken at (else None)."""
        model = self.model
        ahead = model.particle_count if model.wind_velocity is not None else 0
        if recording or self._bdf2_buffers is None:  # a taped step keeps its own; otherwise scratch, as _buffers
            n, vec3 = model.particle_count, model.types.vec3
            buffers = tuple(wp.empty(size, dtype=vec3, device=self.device, requires_grad=recording)
                            for size in (n, n, ahead, ahead))
            if not recording:
                self._bdf2_buffers = buffers
        else:
            buffers = self._bdf2_buffers
        x, v, x_ahead, v_ahead = buffers
        wp.launch(self.kernels.bdf2_blend, model.particle_count, device=self.device,
                  inputs=[state_in.particle_x, state_in.particle_v, state_in.particle_x_last,
                          state_in.particle_v_last], outputs=[x, v, x_ahead, v_ahead])
        start = State(x, v, state_in.time, step=state_in.step, particle_dv=state_in.particle_dv,
                      particle_x_previous=state_in.particle_x_previous)
        start.solve_adjoint = state_in.solve_adjoint
        return start, ((x_ahead, v_ahead) if ahead else None)

    def energy(self, state: State, control: Control | None = None) -> dict[str, float]:
        """Kinetic, stretching, bending, gravitational and handle energies [J] of ``state``, and their ``"total"``.
        Elastic terms use the stiffness at the current strain (exact for ``Material.isotropic``)."""
        model = self.model
        e = self.assembler.element_energy(state)
        handle = 0.0
        if model.handle_count:
            control = control if control is not None else self._default_control()
            x = state.particle_x.numpy()[model.handle_particle.numpy()]
            target = control.handle_target.numpy() + self.assembler.offsets("handle", state.time).numpy()
            stiffness = model.handle_stiffness.numpy()
            active = self.assembler.handles_active(state.time).numpy()
            if active.size:  # the handles that held in the step that ended at state.time
                stiffness = stiffness * active
            handle = float(0.5 * np.sum(stiffness * np.sum((x - target) ** 2, axis=1)))
        e["handles"] = handle
        e["total"] = sum(e.values())
        return e

    def assemble(self, state: State, control: Control | None = None):
        """The step's ``A dv = b`` from ``state`` in new, untaped arrays: A's mat33 blocks on ``bsr_offsets`` /
        ``bsr_columns``, b (vec3), and the proximity pairs of A's cross blocks (or None; valid until the next step),
        for ``linear_solver.solve(values, b, x, pairs=pairs)``."""
        control = control if control is not None else self._default_control()
        values, rhs, pin_dv = (wp.clone(a) for a in self._buffers(recording=False))
        pairs = None
        with wp.ScopedDevice(self.device):
            self.assembler.assemble(state, control, state.time + self.dt, values, rhs, pin_dv)
            if self.proximity is not None:
                pairs = self.proximity.assemble(state, *self._obstacle_points(control, state.time, False), pin_dv,
                                                wp.zeros_like(rhs), values, rhs, False)
        return values, rhs, pairs

    def dense_system(self, state: State, control: Control | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The step's system A (3n x 3n) and b (3n) as dense NumPy arrays, for inspection and tests (small n)."""
        values, rhs, pairs = self.assemble(state, control)
        n = self.model.particle_count
        offsets, columns = self.model.bsr_offsets.numpy(), self.model.bsr_columns.numpy()
        blocks = values.numpy()
        A = np.zeros((n, 3, n, 3))
        for i in range(n):
            for s in range(offsets[i], offsets[i + 1]):
                A[i, :, columns[s], :] = blocks[s]
        if pairs is not None:  # the pairs' cross blocks, which the solver applies matrix-free
            nodes, w, K = pairs.nodes.numpy(), pairs.weights.numpy(), pairs.stiffness.numpy()
            for k in range(pairs.count):
                for a in range(4):
                    for b in range(4):
                        if a != b and w[k, a] != 0.0 and w[k, b] != 0.0:
                            A[nodes[k, a], :, nodes[k, b], :] += w[k, a] * w[k, b] * K[k]
        return A.reshape(3 * n, 3 * n), rhs.numpy().reshape(-1).astype(np.float64)

    # -- internals -----------------------------------------------------------------------------------------------

    def _obstacle_points(self, control: Control, t_start: float, recording: bool) -> tuple[wp.array, wp.array]:
        """The obstacle vertices at the step's start and end [m] (empty without obstacle collisions)."""
        model = self.model
        if not model.collision.obstacles or model.obstacle_count == 0:
            empty = self._arrays.empty("no_obstacle", 0, model.types.vec3, False)
            return empty, empty
        times = (("obstacle_start", t_start), ("obstacle_end", t_start + self.dt))
        if not any(m is not None for m in model.obstacle_motion):
            times = times[:1]  # no scripted motion: the end is the start, one launch (and one adjoint) a step
        points = tuple(obstacle_points(model, control, t, motion=self._obstacle_motion(t),
                                       out=self._arrays.empty(name, model.obstacle_vertex_count, model.types.vec3,
                                                              recording))
                       for name, t in times)
        return points[0], points[-1]

    def _obstacle_motion(self, t: float) -> wp.array:
        model = self.model
        if not any(m is not None for m in model.obstacle_motion):
            if self._static_motion is None:
                self._static_motion = obstacle_motion(model, 0.0)
            return self._static_motion
        store = self._motion_store
        if store is None:
            return obstacle_motion(model, t)
        if float(t) not in store:
            store[float(t)] = obstacle_motion(model, t)
        return store[float(t)]

    @contextmanager
    def _keeping_motions(self, store: dict):
        """Steps inside take the obstacles' motions from ``store``, so captured steps read arrays made before."""
        self._motion_store = store
        try:
            yield
        finally:
            self._motion_store = None

    def _default_control(self) -> Control:
        """``model.control()``, made again when the model's default targets or placements changed."""
        model = self.model
        defaults = [np.asarray(a) for a in (model.handle_rest_target, model.pin_rest_target,
                                            model.obstacle_rest_transform) if a is not None]
        if self._control_default is None or not all(
                np.array_equal(a, b) for a, b in zip(defaults, self._control_default[0])):
            self._control_default = ([a.copy() for a in defaults], model.control(requires_grad=False))
        return self._control_default[1]

    def _buffers(self, recording: bool):
        """A's blocks, b and the pins' dv of one step: new ones while a tape records, else shared scratch."""
        model = self.model
        vec3, mat33 = model.types.vec3, model.types.mat33
        if not recording and self._step_buffers is not None:
            return self._step_buffers
        n = model.particle_count
        bufs = (
            wp.empty(model.bsr_nnz, dtype=mat33, device=self.device, requires_grad=recording),
            wp.empty(n, dtype=vec3, device=self.device, requires_grad=recording),
            wp.zeros(n, dtype=vec3, device=self.device, requires_grad=recording),
        )
        if not recording:
            self._step_buffers = bufs
        return bufs

    def _check_state(self, name: str, state: State) -> None:
        model = self.model
        for field in ("particle_x", "particle_v"):
            array = getattr(state, field)
            if array.shape[0] != model.particle_count or not wp.types.types_equal(array.dtype, model.types.vec3) \
                    or array.device != model.device:
                raise ValueError(
                    f"step(): {name}.{field} holds {array.shape[0]} {wp.types.type_repr(array.dtype)} on "
                    f"{array.device}, but the model has {model.particle_count} particles of "
                    f"{wp.types.type_repr(model.types.vec3)} on {model.device}; use model.state() / "
                    "model.empty_state() of the Simulator's model")

    def _output_dv(self, state_out: State, recording: bool) -> wp.array:
        """``state_out.particle_dv``, made anew where it does not fit or lacks the gradient a recording needs."""
        dv = state_out.particle_dv
        fits = (dv is not None and dv.shape[0] == self.model.particle_count and dv.dtype == self.model.types.vec3
                and dv.device == self.device)
        if not fits or (recording and not dv.requires_grad):
            # uninitialised: the solve writes every entry (it starts from the first guess or from zero)
            dv = wp.empty(self.model.particle_count, dtype=self.model.types.vec3, device=self.device,
                          requires_grad=recording)
            state_out.particle_dv = dv
        return dv

    def _sync_due(self, step: int) -> bool:
        """Whether step ``step`` reads the failure record (SolverOptions.sync_every; never inside a capture)."""
        every = self.options.sync_every
        return bool(every) and step % every == 0 and not capturing(self.device)

    @contextmanager
    def _speculating(self, pair_budget: int = 0, contact_plan: list[int] | None = None):
        """Steps inside follow a plan without reading the device: detection rounds find ``contact_plan``'s counts
        and at most ``pair_budget`` proximity pairs (what wc.CapturedRollout captures)."""
        if self.collision is not None:
            self.collision.speculative, self.collision.plan = True, list(contact_plan or [])
        if self.proximity is not None:
            self.proximity.budget = min(int(pair_budget), self.proximity.capacity)
        try:
            yield
        finally:
            if self.collision is not None:
                self.collision.speculative, self.collision.plan = False, []
            if self.proximity is not None:
                self.proximity.budget = None

    def _note_plan_miss(self, index: int, first: wp.array) -> None:
        """Launch the check of a speculating step: ``first[0] = min(first[0], index)`` where it left its plan."""
        collision = self.collision.mismatch if self.collision is not None else self._no_flag
        pairs = self.proximity.spill if self.proximity is not None else self._no_flag
        wp.launch(ks.note_plan_miss, 1, device=self.device, inputs=[collision, pairs, int(index)], outputs=[first],
                  record_tape=False)

    def _pairs_needed(self) -> int:
        return 0 if self.proximity is None else self.proximity.last_count

    def _contact_plan(self) -> list[int] | None:
        """The last uncaptured step's contacts per round ([]: none), or None where they cannot be planned."""
        report = None if self.collision is None else self.collision.last
        if report is None or not (report.contacts or report.rounds):
            return []
        if report.solver != "device" or report.kept_start_gaps is not None or report.fail_safe is not None:
            return None
        return list(report.found)

    def _check_replayed_adjoints(self) -> None:
        """Warn where an adjoint solve of a replayed backward pass did not converge (read once after it)."""
        if self.collision is not None:
            self.collision.check_adjoints()

    def _count_replayed(self, steps: int) -> None:
        self._steps += steps

    def _check(self, states=(), s: _Step | None = None) -> None:
        """Simulator.check; ``s``: the step being taken, whose inputs can still tell why a solve went non-finite."""
        self._report(*self.status.take(), states, s)

    def _discard_failures_from(self, number: int, states=()) -> None:
        """Forget the failures of steps ``number`` and after (they run again); report earlier ones as :meth:`check`."""
        error, warning, skipped = self.status.take()
        self._report(error if error is not None and error.step < number else None,
                     warning if warning is not None and warning.step < number else None,
                     skipped if skipped < number else 0, states)

    def _report(self, error, warning, skipped: int, states=(), s: _Step | None = None) -> None:
        if skipped and not self._atol_checked:
            self._atol_checked = True  # once per Simulator, at its first skipped solve
            self.diagnostics.warn_if_below_atol(skipped, self.options.cg_atol)
        if warning is not None:
            self.linear_solver.check_failure(warning)
        if error is None:
            return
        if error.diverged:
            state = next((st for st in states if st is not None and st.step == error.step), None)
            if state is None and s is not None and error.step == s.number:
                state = states[0] if states else None  # the step's own (still unnumbered) result
            t = state.time if state is not None and state.step == error.step else (
                s.t_next if s is not None and error.step == s.number else None)
            raise self.diagnostics.divergence_error(state, error.index, t, error.step, self.options.max_speed)
        cause = None
        if s is not None and error.step == s.number and not error.adjoint and error.non_finite:
            cause = self.diagnostics.non_finite_cause(s.start, s.values, s.rhs)
        self.linear_solver.check_failure(error, cause=cause)


@dataclass
class _Step:
    """What the stages of one step read and write."""

    state_in: State
    state_out: State
    control: Control
    recording: bool
    number: int  # the step being taken, counted from the start of the trajectory
    t_next: float
    start: State | None = None  # state_in, or BDF2's blend
    assembler: SystemAssembler | None = None
    values: wp.array | None = None
    rhs: wp.array | None = None
    pin_dv: wp.array | None = None
    dv: wp.array | None = None
    obstacles: tuple[wp.array, wp.array] | None = None  # obstacle vertices at the step's start and end
    pairs: ProximityPairs | None = None
    mass: wp.array | None = None  # the taped lumped masses (friction and the collision stage)
    velocity_change: wp.array | None = None
    x_hat: wp.array | None = None
    v_hat: wp.array | None = None
    report: CollisionReport | None = None


def model_arrays(model: Model) -> tuple:
    """The identity of every array the model holds (a rebound array changes it)."""
    return tuple(id(value) for value in vars(model).values() if isinstance(value, wp.array))


class _PhaseClock:

    def __init__(self, totals: dict):
        self.totals = totals
        self.last = time.perf_counter()

    def lap(self, phase: str) -> None:
        now = time.perf_counter()
        self.totals[phase] += now - self.last
        self.last = now
