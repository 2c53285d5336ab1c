"""The implicit Euler simulator: one linearised backward-Euler step per time step, differentiable on a wp.Tape.

Per step (SPEC.md §2): assemble the 3x3 block-sparse system A dv = b from per-element kernels, solve it with
preconditioned conjugate gradients, then x <- x + dt (v + dv). The CG iterations are not taped: the solve records a
custom adjoint (one adjoint CG solve with the same matrix, SPEC §4.1), and Warp's autodiff of the assembly kernels
carries the gradient on to positions, velocities, materials, gravity, wind, forces and handle targets.
Scenes with obstacles or self-collision then run the collision stage (warpcloth/collision, SPEC §3).
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np
import warp as wp

from warpcloth.collision import CollisionStage
from warpcloth.collision.proximity import ProximityForces
from warpcloth.errors import SimulationError
from warpcloth.kernels.implicit import implicit_kernels
from warpcloth.model import Control, Model, State
from warpcloth.obstacles import obstacle_points
from warpcloth.solver.assembly import SystemAssembler
from warpcloth.solver.linear import LinearSolver, SolveInfo
from warpcloth.solver.options import SolverOptions
from warpcloth.tape import active_tape

ELONGATED_ASPECT_RATIO = 100.0
"""Rest aspect ratio (longest edge^2 / (2 area)) from which a failed solve or a divergence names the most elongated
triangle: its stiffness relative to its mass, and with it the condition of the system, grows with the ratio."""


class Simulator:
    """Implicit Euler cloth solver with the contract ``step(state_in, state_out, control)``.

    Args:
        model: the Model to simulate.
        dt: time step [s], > 0.
        options: SolverOptions (tolerances, preconditioner, CG backend, divergence guard).
    """

    def __init__(self, model: Model, dt: float, *, options: SolverOptions | None = None):
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
        self.model = model
        self.dt = float(dt)
        self._options = options or SolverOptions()
        self._options.validate()
        self.device = model.device
        self.kernels = implicit_kernels(model.scalar)
        self.assembler = SystemAssembler(model, self.dt)
        """Launches the step's force and Hessian kernels into the system."""
        self.linear_solver = LinearSolver(model, self.options, hint=self._mesh_hint)
        """The CG solver of the implicit system (and of its adjoint)."""
        self.last_solve = SolveInfo(0, 0.0, True)
        """The forward CG solve of the last step (diagnostics only: no step reads it)."""
        self.stats = {"steps": 0, "cg_iterations": 0, "adjoint_cg_iterations": 0}
        """Counters over this simulator's life (diagnostics only: no step reads them)."""
        self._atol_checked = False  # the cg_atol floor is checked at the first skipped solve (_warn_if_below_atol)
        self._assembler_bdf2: SystemAssembler | None = None  # made at the first BDF2 step
        self._bdf2_buffers = None  # the blend and extrapolation of untaped BDF2 steps (_bdf2_start)
        self.phase_seconds = dict.fromkeys(("assembly", "proximity", "solve", "integrate", "collision"), 0.0)
        """Host wall time [s] of each phase of the forward steps over this simulator's life (diagnostics; on CUDA it
        measures launch, not execution, unless the device synchronises)."""
        self._status = wp.zeros(1, dtype=wp.int32, device=self.device)
        # host view of the divergence flag read every step (on the CPU it shares memory: no copy, no launch)
        self._status_host = self._status.numpy() if self.device.is_cpu else None
        self._step_buffers = None
        self._mass = None  # the untaped steps' lumped masses (_lumped_mass)
        self._elongated: tuple[int, float, int] | None = None  # (triangle, aspect ratio, count): _mesh_hint
        self.collision = CollisionStage(model, self.dt, self.options) if model.collision is not None else None
        """The collision stage (detection buffers, BVHs), or None for a scene without collisions."""
        self.proximity = (ProximityForces(model, self.dt, capacity=self.options.collision.contact_capacity)
                          if ProximityForces.needed(model) else None)
        """Proximity repulsion and friction inside the implicit step, or None where the model has neither."""

    # -- public ------------------------------------------------------------------------------------------------------
    @property
    def options(self) -> SolverOptions:
        """The SolverOptions in force; assigning new ones applies them from the next solve on (the backend and the
        preconditioner are chosen once, at construction)."""
        return self._options

    @options.setter
    def options(self, options: SolverOptions) -> None:
        options.validate()
        self._options = options
        self.linear_solver.options = options
        if self.collision is not None:
            self.collision.options = options

    def step(self, state_in: State, state_out: State, control: Control | None = None) -> None:
        """Advance ``state_in`` by one time step into ``state_out`` (records on the active tape, if any).

        The result depends only on the arguments and the model: ``state_in`` carries what the previous step hands
        on (the solve's first guess, the lagged wind normals' positions, the step number), and ``state_out``
        receives the same for the next step. Stepping the same ``state_in`` twice gives bitwise the same result.
        """
        if state_out is state_in:
            raise ValueError("step() needs distinct state_in and state_out (a tape cannot record in-place updates)")
        model = self.model
        self._check_state("state_in", state_in)
        self._check_state("state_out", state_out)
        control = control if control is not None else self._default_control()
        recording = active_tape() is not None and model.requires_grad
        values, rhs, pin_dv = self._buffers(recording)
        dv = self._output_dv(state_out, recording)
        t_next = state_in.time + self.dt
        step = state_in.step + 1  # the step being taken, counted from the start of the trajectory
        k = self.kernels

        clock = _PhaseClock(self.phase_seconds)
        # what the implicit step starts from: state_in, or BDF2's blend of it with the state before it
        start, assembler, explicit = state_in, self.assembler, None
        bdf2 = self.options.integrator == "bdf2"
        if bdf2 and state_in.particle_x_last is not None:
            start, explicit = self._bdf2_start(state_in, recording)
            assembler = self._bdf2_assembler()
        dt = model.scalar(assembler.dt)
        assembler.assemble(start, control, t_next, values, rhs, pin_dv, dv, explicit=explicit)
        clock.lap("assembly")
        obstacles = self._obstacle_points(control, state_in.time) if self.collision is not None else None
        pairs = None
        if self.proximity is not None:
            pairs = self.proximity.assemble(start, *obstacles, pin_dv, dv, values, rhs, recording,
                                            implicit_dt=assembler.dt)
            clock.lap("proximity")
        self._solve(values, rhs, dv, start, state_out, step, pairs)
        clock.lap("solve")
        friction = pairs is not None and pairs.count and self.proximity.friction
        mass = self._lumped_mass(recording) if friction or self.collision is not None else None
        velocity_change = dv
        if friction:
            velocity_change = self.proximity.apply_friction(pairs, dv, mass, recording)
            clock.lap("proximity")

        max_speed = model.scalar(self.options.max_speed)
        if self._status_host is not None:
            self._status_host[0] = 0
        else:
            self._status.zero_()
        if self.collision is None:
            wp.launch(k.integrate, model.particle_count, device=self.device,
                      inputs=[start.particle_x, start.particle_v, velocity_change, dt, max_speed],
                      outputs=[state_out.particle_x, state_out.particle_v, self._status])
        else:
            candidate = model.empty_state()  # x̂, v̂ before the projection (kept for the backward pass)
            x_hat, v_hat = candidate.particle_x, candidate.particle_v
            wp.launch(k.integrate, model.particle_count, device=self.device,
                      inputs=[start.particle_x, start.particle_v, velocity_change, dt, max_speed],
                      outputs=[x_hat, v_hat, self._status])
            # no NaN or runaway particle reaches the collision stage
            self._raise_if_diverged(candidate, t_next, step)
            clock.lap("integrate")
            # detection runs from the true start positions (state_in), BDF2's blend being no configuration
            self.collision.resolve(state_in, x_hat, v_hat, *obstacles, state_out, step, mass,
                                   implicit_dt=assembler.dt)
            wp.launch(self.kernels.check_state, model.particle_count, device=self.device,
                      inputs=[state_out.particle_x, state_out.particle_v, max_speed], outputs=[self._status],
                      record_tape=False)  # the projection's velocity change too
        state_out.time = t_next
        state_out.step = step
        state_out.particle_x_last = state_in.particle_x if bdf2 else None
        state_out.particle_v_last = state_in.particle_v if bdf2 else None
        if bdf2 and self.collision is not None and self.collision.last["contacts"] > 0:
            x_last, v_last = (wp.empty_like(a, requires_grad=recording) for a in (state_in.particle_x,
                                                                                    state_in.particle_v))
            wp.launch(k.bdf2_history, model.particle_count, device=self.device,
                      inputs=[state_in.particle_x, state_in.particle_v, x_hat, state_out.particle_x,
                              state_out.particle_v, model.scalar(self.dt)], outputs=[x_last, v_last])
            state_out.particle_x_last, state_out.particle_v_last = x_last, v_last
        state_out.particle_x_previous = None
        if model.wind_lagged_normals:
            # ARCSim's face normals lag a step, except after a collision response that moved the cloth: it
            # recomputes them then (SPEC §2), so the next step's wind sees the current positions
            moved = self.collision is not None and self.collision.last["contacts"] > 0
            state_out.particle_x_previous = state_out.particle_x if moved else state_in.particle_x
        self.stats["steps"] += 1
        clock.lap("collision" if self.collision is not None else "integrate")
        self._raise_if_diverged(state_out, t_next, step)

    def _lumped_mass(self, recording: bool) -> wp.array:
        """The particles' lumped masses from the model's densities (one taped launch a step: the contact stages'
        adjoints add to its gradient, which Warp carries to the densities). Read at every step, so densities
        changed between rollouts are the ones used."""
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

    def _bdf2_assembler(self) -> SystemAssembler:
        """The assembler of BDF2's steps: a backward Euler step of 2/3 dt (SolverOptions.integrator)."""
        if self._assembler_bdf2 is None:
            self._assembler_bdf2 = SystemAssembler(self.model, 2.0 * self.dt / 3.0)
        return self._assembler_bdf2

    def _bdf2_start(self, state_in: State, recording: bool) -> tuple[State, tuple[wp.array, wp.array] | None]:
        """BDF2's start point (4 x_n - x_{n-1}) / 3, (4 v_n - v_{n-1}) / 3 as a State, and, for a model with wind,
        the extrapolation (2 x_n - x_{n-1}, 2 v_n - v_{n-1}) the explicit force is taken at (None without wind).
        One taped kernel: gradients reach both states. The State hands on state_in's first guess, lagged normals and
        adjoint first guess, so the step reads it as it would read state_in."""
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
        """Kinetic, stretching, bending, gravitational and handle energies [J] of ``state`` (host values).

        Stretching and bending use the stiffness looked up at the current strain, which is the exact elastic energy
        when the material's tables are constant (e.g. ``Material.isotropic``).
        """
        model = self.model
        e = self.assembler.element_energy(state)
        handle = 0.0
        if model.handle_count:
            control = control if control is not None else self._default_control()
            x = state.particle_x.numpy()[model.handle_particle.numpy()]
            target = control.handle_target.numpy() + self.assembler.offsets("handle", state.time).numpy()
            handle = float(0.5 * np.sum(model.handle_stiffness.numpy() * np.sum((x - target) ** 2, axis=1)))
        e["handles"] = handle
        e["total"] = sum(e.values())
        return e

    def assemble(self, state: State, control: Control | None = None):
        """The system ``A dv = b`` of the step from ``state``, in new arrays (not taped): A's blocks on the model's
        block pattern (``bsr_offsets``/``bsr_columns``, mat33), b (vec3), and the proximity pairs whose cross blocks
        A also has (a ``ProximityPairs``, or None). Solve it with ``linear_solver.solve(values, b, x, pairs=pairs)``.
        """
        control = control if control is not None else self._default_control()
        values, rhs, pin_dv = (wp.clone(a) for a in self._buffers(recording=False))
        pairs = None
        with wp.ScopedDevice(self.device):
            self.assembler.assemble(state, control, state.time + self.dt, values, rhs, pin_dv)
            if self.proximity is not None:
                pairs = self.proximity.assemble(state, *self._obstacle_points(control, state.time), pin_dv,
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

    def _obstacle_points(self, control: Control, t_start: float) -> tuple[wp.array, wp.array]:
        """The obstacle vertices at the step's start and end [m], for the proximity forces and the collision stage
        alike (empty arrays where the model has no obstacle collisions)."""
        model = self.model
        if not model.collision.obstacles or model.obstacle_count == 0:
            empty = wp.zeros(0, dtype=model.types.vec3, device=self.device)
            return empty, empty
        return obstacle_points(model, control, t_start), obstacle_points(model, control, t_start + self.dt)

    def _default_control(self) -> Control:
        if not hasattr(self, "_control_default"):
            self._control_default = self.model.control(requires_grad=False)
        return self._control_default

    def _buffers(self, recording: bool):
        """System buffers of one step (A's blocks, b, the pins' velocity change). While a tape records, each step
        gets its own (the backward pass reads them); otherwise they are scratch reused by every step."""
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
        """Raise ValueError if ``state`` is not one of this model's (another particle count, precision or device):
        stepping it would read and write past its arrays."""
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
        """The array the solve writes: ``state_out.particle_dv`` (allocated here when the State has none, or a
        fresh one with a gradient when a tape records), so the next step finds its first guess in its input."""
        dv = state_out.particle_dv
        fits = (dv is not None and dv.shape[0] == self.model.particle_count and dv.dtype == self.model.types.vec3
                and dv.device == self.device)
        if not fits or (recording and not dv.requires_grad):
            # uninitialised: the solve writes every entry (it starts from the first guess or from zero)
            dv = wp.empty(self.model.particle_count, dtype=self.model.types.vec3, device=self.device,
                          requires_grad=recording)
            state_out.particle_dv = dv
        return dv

    def _solve(self, values: wp.array, rhs: wp.array, dv: wp.array, state_in: State, state_out: State,
               step: int, pairs=None) -> None:
        """Solve A dv = b from ``state_in.particle_dv``; on a tape, the implicit adjoint is recorded. Adjoint solves
        run from the last step to the first, each handing its solution to the one before through the State between
        them (``State.solve_adjoint``)."""
        guess = state_in.particle_dv
        warm = self.options.warm_start and guess is not None and guess.shape == dv.shape and guess.dtype == dv.dtype
        recording = active_tape() is not None and values.requires_grad
        if recording:
            state_out.solve_adjoint = wp.zeros_like(dv, requires_grad=False)

        def count_adjoint(info: SolveInfo) -> None:
            self.stats["adjoint_cg_iterations"] += info.iterations

        try:
            info = self.linear_solver.solve_recorded(
                values, rhs, dv, step=step, guess=guess if warm else None,
                adjoint_guess=state_out.solve_adjoint if recording else None,
                adjoint_result=state_in.solve_adjoint, on_adjoint=count_adjoint, pairs=pairs)
        except SimulationError as exc:
            cause = self._non_finite_cause(state_in, values, rhs)
            if cause is None:
                raise
            raise SimulationError(f"step {step}: {cause} ({exc})") from None
        if info.iterations == 0 and not self._atol_checked:
            self._atol_checked = True  # once per Simulator, at its first skipped solve
            self._warn_if_below_atol(step)
        self.last_solve = info
        self.stats["cg_iterations"] += info.iterations

    def _warn_if_below_atol(self, step: int) -> None:
        """Warn when the model is so light that its weight's impulse over a step, dt |g| |m|, is within ten times
        SolverOptions.cg_atol: every solve then stops at once on that absolute floor and the cloth never moves (a
        cloth at rest also skips its solves, rightly: its forces balance, so the test is on the model's scale)."""
        g = max(float(np.linalg.norm(self.model.gravity.numpy())), 1.0)
        impulse = self.dt * g * float(np.linalg.norm(self.model.particle_mass()))
        if impulse <= 10.0 * self.options.cg_atol:
            warnings.warn(
                f"step {step}: the solve stopped after 0 iterations on SolverOptions.cg_atol = "
                f"{self.options.cg_atol:g}, and this model is too light for that floor (its weight's impulse over a "
                f"step is {impulse:.3g} N*s): its solves are skipped and the cloth does not move; lower cg_atol",
                RuntimeWarning, stacklevel=4)

    def _non_finite_cause(self, state_in: State, values: wp.array, rhs: wp.array) -> str | None:
        """What made a solve's residual non-finite, naming the particle: a non-finite or overflowing input state,
        or non-finite forces or stiffness blocks (a material too stiff for the precision); None if none of those."""
        for field, what in (("particle_x", "position"), ("particle_v", "velocity")):
            a = getattr(state_in, field).numpy()
            bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1))
            if bad.size:
                p = int(bad[0])
                return f"particle {p} enters the step with a non-finite {what} {a[p].tolist()}"
        b = rhs.numpy().reshape(self.model.particle_count, -1)
        blocks = values.numpy().reshape(len(values), -1)
        largest = float(np.abs(blocks).max()) if np.all(np.isfinite(blocks)) else math.inf
        overflow = math.sqrt(np.finfo(blocks.dtype).max)  # the CG's products p.Ap overflow above about this
        if np.all(np.isfinite(b)) and largest < overflow:
            return None
        x = state_in.particle_x.numpy()
        far = np.flatnonzero(np.abs(x).max(axis=1) > 1.0e6)
        if far.size:
            p = int(far[0])
            return (f"particle {p} is at {x[p].tolist()}, more than 1e6 m from the origin: its edge vectors lose "
                    f"their precision or overflow in {self.model.scalar.__name__}")
        bad = np.flatnonzero(~np.all(np.isfinite(b), axis=1))
        stiffest = float(np.abs(self.model.material_stretching.numpy()).max())
        which = (f"the forces on particle {int(bad[0])} are not finite" if bad.size else
                 f"the implicit system's largest entry is {largest:.3g}")
        return (f"{which}: the material's stiffness (largest stretching entry {stiffest:.3g}) or the forces "
                f"overflow {self.model.scalar.__name__}")

    def _raise_if_diverged(self, state: State, t: float, step: int) -> None:
        """Raise SimulationError if the divergence guard (``self._status``) flagged a particle of ``state``, the
        result of step number ``step`` at time ``t``."""
        bad = int((self._status_host if self._status_host is not None else self._status.numpy())[0])
        if bad:
            p = bad - 1
            x = state.particle_x.numpy()[p]
            v = state.particle_v.numpy()[p]
            speed = float(np.linalg.norm(v))
            if np.all(np.isfinite(x)) and np.all(np.isfinite(v)):
                raise SimulationError(
                    f"simulation diverged at step {step} (t = {t:.4g} s): particle {p} moves at {speed:.4g} m/s, over "
                    f"SolverOptions.max_speed = {self.options.max_speed:g} m/s (x = {x.tolist()}); lower dt, raise "
                    "damping, or check the material and forces; if the motion really is this fast (a long free fall), "
                    "raise max_speed" + self._wind_hint() + self._mesh_hint())
            raise SimulationError(
                f"simulation diverged at step {step} (t = {t:.4g} s): particle {p} has "
                f"x = {x.tolist()}, v = {v.tolist()}; "
                "lower dt, raise damping, or check the material and forces" + self._wind_hint() + self._mesh_hint())

    def _wind_hint(self) -> str:
        """Why the explicit wind force may have diverged: dt beyond its stability limit (else "").

        The wind force has no Jacobian in the system, so per unit area a face's relative normal velocity u changes by
        -dt (wind density) |u| u / (area density) in a step: it overshoots and grows once dt exceeds
        2 (area density) / ((wind density) |u|); the tangential drag likewise beyond 2 (area density) / drag.
        """
        model = self.model
        if model.wind_velocity is None:
            return ""
        speed = float(np.linalg.norm(model.wind_velocity.numpy()[0]))
        air, drag = float(model.wind_density.numpy()[0]), float(model.wind_drag.numpy()[0])
        cloth = float(np.min(model.material_density.numpy() * model.material_thicken.numpy()))
        limits = {}
        if air * speed > 0.0:
            limits["2*(cloth density)/(wind density*|wind|)"] = 2.0 * cloth / (air * speed)
        if drag > 0.0:
            limits["2*(cloth density)/(wind drag)"] = 2.0 * cloth / drag
        if not limits or self.dt <= min(limits.values()):
            return ""
        formula, limit = min(limits.items(), key=lambda item: item[1])
        return (f"; the wind force is explicit: a {speed:.3g} m/s wind (density {air:g}, drag {drag:g}) on cloth of "
                f"{cloth:.3g} kg/m^2 is stable only for dt < {formula} = {limit:.3g} s: lower dt below that, or the "
                "wind speed")

    def _mesh_hint(self) -> str:
        """Name the most elongated rest triangle when it reaches ELONGATED_ASPECT_RATIO (else "")."""
        model = self.model
        if self._elongated is None:  # computed on the first failure only
            dm = np.linalg.inv(model.tri_inv_dm.numpy().astype(np.float64))  # columns: material-space edges
            e1, e2 = dm[:, :, 0], dm[:, :, 1]
            longest = np.max([np.sum(e * e, axis=1) for e in (e1, e2, e2 - e1)], axis=0)
            aspect = longest / np.abs(np.linalg.det(dm))  # longest^2 / (2 area): 2 for half a square
            t = int(np.argmax(aspect))
            self._elongated = (t, float(aspect[t]), int(np.count_nonzero(aspect >= ELONGATED_ASPECT_RATIO)))
        t, ratio, count = self._elongated
        if ratio < ELONGATED_ASPECT_RATIO:
            return ""
        return (f"; triangle {t} {model.triangles_np[t].tolist()} is elongated (rest aspect ratio {ratio:.3g}; "
                f"{count} triangle(s) at or above {ELONGATED_ASPECT_RATIO:g}), which makes the system ill-conditioned: "
                "remesh it, or use dtype=wp.float64")


class _PhaseClock:
    """Adds the wall time since the last lap to a phase's total."""

    def __init__(self, totals: dict):
        self.totals = totals
        self.last = time.perf_counter()

    def lap(self, phase: str) -> None:
        now = time.perf_counter()
        self.totals[phase] += now - self.last
        self.last = now
