"""The implicit Euler simulator: one linearised backward-Euler step per time step, differentiable on a wp.Tape.

Per step (SPEC.md §2): assemble the 3x3 block-sparse system A dv = b from per-element kernels, solve it with
preconditioned conjugate gradients, then x <- x + dt (v + dv). The CG iterations are not taped: the solve records a
custom adjoint (one adjoint CG solve with the same matrix, SPEC §4.1), and Warp's autodiff of the assembly kernels
carries the gradient on to positions, velocities, materials, gravity, wind, forces and handle targets.
Scenes with obstacles or self-collision then run the collision stage (warpcloth/collision.py, SPEC §3).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from warpcloth.collision import CollisionStage
from warpcloth.errors import SimulationError
from warpcloth.kernels.implicit import implicit_kernels
from warpcloth.kernels.linear import linear_kernels
from warpcloth.model import Control, Model, State
from warpcloth.tape import active_tape, record_adjoint


ELONGATED_ASPECT_RATIO = 100.0
"""Rest aspect ratio (longest edge^2 / (2 area)) from which a failed solve or a divergence names the most elongated
triangle: its stiffness relative to its mass, and with it the condition of the system, grows with the ratio."""


@dataclass(frozen=True)
class SolverOptions:
    """Options of the linear solve and of the divergence guard."""

    cg_tol: float = 1.0e-5
    """Relative residual tolerance |b - A dv| <= cg_tol |b| of the forward CG solve (and of the adjoint one, unless
    ``adjoint_cg_tol`` is given)."""
    adjoint_cg_tol: float | None = None
    """Relative residual tolerance of the adjoint CG solve of the backward pass; None: the same as ``cg_tol``.
    The gradient's error follows it as the trajectory's follows cg_tol (benchmarks/tradeoff.py)."""
    cg_atol: float = 1.0e-12
    """Absolute residual floor (in the units of b, N*s)."""
    cg_max_iters: int = 1000
    """Iteration cap of each CG solve."""
    preconditioner: str = "auto"
    """``"block_jacobi"`` (inverse 3x3 diagonal blocks), ``"jacobi"`` (inverse scalar diagonal), ``"block_ssor"``
    (symmetric block Gauss-Seidel sweeps; sequential backend only: ~3x fewer iterations than block Jacobi at 64x64,
    benchmarks/cg_solvers.py) or ``"auto"`` (block_ssor with the sequential backend, block_jacobi with warp's)."""
    ssor_omega: float = 1.5
    """Relaxation factor of the block SSOR preconditioner, in (0, 2)."""
    cg_backend: str = "auto"
    """``"sequential"`` (whole CG in one launch: fastest on the CPU), ``"warp"`` (``warp.optim.linear.cg``:
    for CUDA), or ``"auto"`` (sequential on the CPU, warp on CUDA). See benchmarks/cg_solvers.py."""
    on_cg_failure: str = "warn"
    """What a solve that misses its tolerance does: ``"warn"`` (with the residual) or ``"raise"``."""
    warm_start: bool = True
    """Start each CG solve from the previous solution (forward: the previous step's velocity change; adjoint: the
    later step's adjoint): fewer iterations, and results that differ only within the tolerance."""
    max_speed: float = 1.0e3
    """A particle faster than this [m/s], or a NaN/inf, raises SimulationError naming the step."""
    collision_rounds: int = 20
    """Most detect -> project rounds per step; a step still finding new contacts after them raises CollisionError."""
    contact_capacity: int = 0
    """Contacts one detection may find (0: 16 per cloth particle and obstacle vertex); more raises CollisionError
    with the capacity needed."""
    collision_adjoint: str = "qr"
    """Adjoint of the collision projection: ``"qr"`` (QR of the active constraints, SPEC §4.2) or ``"kkt"`` (the
    dense KKT system of the whole zone: the seed's baseline, for comparison)."""
    max_projection_strain: float = 0.5
    """Most an edge may lengthen in the collision projection of one step, in rest lengths; more raises
    CollisionError saying to lower dt: contact resolved that coarsely pumps energy into the cloth
    (warpcloth/collision.py, _check_projection_strain)."""
    qp_tol: float = 1.0e-10
    """Tolerance [m] of the projection's KKT conditions (constraint violation and complementarity)."""

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        """Raise ValueError naming the first option out of range."""
        for name in ("cg_tol", "cg_atol", "max_speed", "qp_tol", "adjoint_cg_tol", "max_projection_strain"):
            val = getattr(self, name)
            if name == "adjoint_cg_tol" and val is None:
                continue
            if not math.isfinite(val) or val <= 0.0:
                raise ValueError(f"SolverOptions.{name} must be finite and > 0, got {val}")
        if not 0.0 < self.ssor_omega < 2.0:
            raise ValueError(f"SolverOptions.ssor_omega must be in (0, 2), got {self.ssor_omega}")
        for name, low in (("cg_max_iters", 1), ("collision_rounds", 1), ("contact_capacity", 0)):
            val = getattr(self, name)
            if isinstance(val, bool) or int(val) != val or val < low:
                raise ValueError(f"SolverOptions.{name} must be an integer >= {low}, got {val!r}")
        choices = {
            "preconditioner": ("auto", "block_jacobi", "jacobi", "block_ssor"),
            "cg_backend": ("auto", "sequential", "warp"),
            "on_cg_failure": ("warn", "raise"),
            "collision_adjoint": ("qr", "kkt"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"SolverOptions.{name} must be one of {allowed}, got {getattr(self, name)!r}")


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
        self.options = options or SolverOptions()
        self.options.validate()
        self.device = model.device
        self.kernels = implicit_kernels(model.scalar)
        self.linear = linear_kernels(model.scalar)
        backend = self.options.cg_backend
        if backend == "auto":
            backend = "sequential" if self.device.is_cpu else "warp"
        self.cg_backend = backend
        preconditioner = self.options.preconditioner
        if preconditioner == "auto":
            preconditioner = "block_ssor" if backend == "sequential" else "block_jacobi"
        if preconditioner == "block_ssor" and backend != "sequential":
            raise ValueError("SolverOptions.preconditioner 'block_ssor' needs cg_backend 'sequential' (its sweeps are "
                             "sequential); use 'block_jacobi' or 'jacobi' with the warp backend")
        self.preconditioner = preconditioner
        self.element_adjoint = "contracted"
        """How the stretching/bending assembly is differentiated: "contracted" (the rank-one potential, fast) or
        "autodiff" (Warp's adjoint of the assembly kernels: the reference the contracted one is tested against)."""
        self.step_count = 0
        """Steps taken by this simulator (names the step in error messages)."""
        self.last_cg_iterations = 0
        self.last_cg_residual = 0.0
        self.stats = {"steps": 0, "cg_iterations": 0, "adjoint_cg_iterations": 0}
        n = model.particle_count
        vec3, mat33 = model.types.vec3, model.types.mat33
        # scratch that no gradient reads: reused every step
        self._cg_scratch = [wp.empty(n, dtype=vec3, device=self.device) for _ in range(4)]
        self._precond = wp.empty(n, dtype=mat33, device=self.device)
        self._cg_info = wp.zeros(3, dtype=wp.float64, device=self.device)
        self._status = wp.zeros(1, dtype=wp.int32, device=self.device)
        # host views of the two arrays read every step (on the CPU they share memory: no copy, no launch per read)
        self._cg_info_host = self._cg_info.numpy() if self.device.is_cpu else None
        self._status_host = self._status.numpy() if self.device.is_cpu else None
        self._adjoint_solution = wp.zeros(n, dtype=vec3, device=self.device)
        self._step_buffers = None
        self._previous_dv = None
        self._previous_in: State | None = None  # state_in and state_out of the last step (ARCSim's lagged normals)
        self._previous_out: State | None = None
        self._warp_matrix = None
        self._elongated: tuple[int, float, int] | None = None  # (triangle, aspect ratio, count): _mesh_hint
        self.collision = CollisionStage(model, self.dt, self.options) if model.collision is not None else None
        """The collision stage (detection buffers, BVHs), or None for a scene without collisions."""
        self._zero_offsets = {
            "handle": wp.zeros(model.handle_count, dtype=vec3, device=self.device),
            "pin": wp.zeros(model.pin_count, dtype=vec3, device=self.device),
        }

    # -- public ------------------------------------------------------------------------------------------------------
    def step(self, state_in: State, state_out: State, control: Control | None = None) -> None:
        """Advance ``state_in`` by one time step into ``state_out`` (records on the active tape, if any)."""
        if state_out is state_in:
            raise ValueError("step() needs distinct state_in and state_out (a tape cannot record in-place updates)")
        model = self.model
        control = control if control is not None else self._default_control()
        dt = model.scalar(self.dt)
        values, rhs, dv, pin_dv = self._buffers()
        t_next = state_in.time + self.dt
        k = self.kernels

        self._assemble(state_in, control, t_next, values, rhs, pin_dv, dv)
        self._solve_recorded(values, rhs, dv)

        max_speed = model.scalar(self.options.max_speed)
        if self._status_host is not None:
            self._status_host[0] = 0
        else:
            self._status.zero_()
        if self.collision is None:
            wp.launch(k.integrate, model.particle_count, device=self.device,
                      inputs=[state_in.particle_x, state_in.particle_v, dv, dt, max_speed],
                      outputs=[state_out.particle_x, state_out.particle_v, self._status])
        else:
            candidate = model.empty_state()  # x̂, v̂ before the projection (kept for the backward pass)
            x_hat, v_hat = candidate.particle_x, candidate.particle_v
            wp.launch(k.integrate, model.particle_count, device=self.device,
                      inputs=[state_in.particle_x, state_in.particle_v, dv, dt, max_speed],
                      outputs=[x_hat, v_hat, self._status])
            # no NaN or runaway particle reaches the collision stage
            self._raise_if_diverged(candidate, t_next, self.step_count + 1)
            self.collision.resolve(state_in, x_hat, v_hat, control, state_in.time, state_out, self.step_count + 1)
            wp.launch(self.linear.check_state, model.particle_count, device=self.device,
                      inputs=[state_out.particle_x, state_out.particle_v, max_speed], outputs=[self._status],
                      record_tape=False)  # the projection's velocity change too
        state_out.time = t_next
        self._previous_in, self._previous_out = state_in, state_out
        self.step_count += 1
        self.stats["steps"] += 1
        self._raise_if_diverged(state_out, t_next, self.step_count)

    def energy(self, state: State, control: Control | None = None) -> dict[str, float]:
        """Kinetic, stretching, bending, gravitational and handle energies [J] of ``state`` (host values).

        Stretching and bending use the stiffness looked up at the current strain, which is the exact elastic energy
        when the material's tables are constant (e.g. ``Material.isotropic``).
        """
        model = self.model
        out = wp.zeros(3, dtype=model.scalar, device=self.device)
        wp.launch(self.kernels.face_energy, model.tri_count, device=self.device,
                  inputs=[model.tri_indices, model.tri_material, model.tri_inv_dm, model.tri_area,
                          model.material_density, model.material_stretching, model.material_thicken,
                          model.lut_weight, model.lut_row, model.gravity, state.particle_x, state.particle_v],
                  outputs=[out], record_tape=False)
        bend = wp.zeros(1, dtype=model.scalar, device=self.device)
        if model.hinge_count:
            wp.launch(self.kernels.hinge_energy, model.hinge_count, device=self.device,
                      inputs=[model.hinge_indices, model.hinge_material, model.hinge_rest_angle,
                              model.hinge_rest_length, model.hinge_rest_area, model.hinge_direction,
                              model.material_bending, model.material_thicken, state.particle_x],
                      outputs=[bend], record_tape=False)
        kinetic, stretching, gravity = (float(e) for e in out.numpy())
        handle = 0.0
        if model.handle_count:
            control = control if control is not None else self._default_control()
            x = state.particle_x.numpy()[model.handle_particle.numpy()]
            target = control.handle_target.numpy() + self._offsets("handle", state.time).numpy()
            handle = float(0.5 * np.sum(model.handle_stiffness.numpy() * np.sum((x - target) ** 2, axis=1)))
        e = {"kinetic": kinetic, "stretching": stretching, "bending": float(bend.numpy()[0]),
             "gravity": gravity, "handles": handle}
        e["total"] = sum(e.values())
        return e

    def dense_system(self, state: State, control: Control | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The step's system A (3n x 3n) and b (3n) as dense NumPy arrays, for inspection and tests (small n)."""
        control = control if control is not None else self._default_control()
        values, rhs, _, pin_dv = self._buffers()
        with wp.ScopedDevice(self.device):
            self._assemble(state, control, state.time + self.dt, values, rhs, pin_dv)
        n = self.model.particle_count
        offsets, columns = self.model.bsr_offsets.numpy(), self.model.bsr_columns.numpy()
        blocks = values.numpy()
        A = np.zeros((n, 3, n, 3))
        for i in range(n):
            for s in range(offsets[i], offsets[i + 1]):
                A[i, :, columns[s], :] = blocks[s]
        return A.reshape(3 * n, 3 * n), rhs.numpy().reshape(-1).astype(np.float64)

    # -- internals -----------------------------------------------------------------------------------------------

    def _assemble(self, state_in: State, control: Control, t_next: float, values, rhs, pin_dv, dv=None) -> None:
        """Fill ``values`` (BSR blocks of A) and ``rhs`` (b) of the implicit system for one step.

        ``dv`` is the buffer the solve will write; given while recording, the element kernels' adjoint uses it.
        """
        model = self.model
        dt = model.scalar(self.dt)
        k = self.kernels
        rhs.zero_()
        values.zero_()
        if model.pin_count:
            pin_dv.zero_()
            wp.launch(k.pin_rows, model.pin_count, device=self.device,
                      inputs=[model.pin_particle, model.particle_diag_slot, state_in.particle_x, state_in.particle_v,
                              control.pin_target, self._offsets("pin", t_next), dt],
                      outputs=[pin_dv, values, rhs])
        face_inputs = [model.tri_indices, model.tri_material, model.tri_inv_dm, model.tri_area,
                       model.tri_block_slot, model.particle_pin, model.material_density, model.material_stretching,
                       model.material_thicken, model.lut_weight, model.lut_row, model.gravity,
                       state_in.particle_x, state_in.particle_v, pin_dv, dt,
                       model.scalar(model.damping_mass), model.scalar(model.damping_stiffness)]
        hinge_inputs = [model.hinge_indices, model.hinge_material, model.hinge_rest_angle, model.hinge_rest_length,
                        model.hinge_rest_area, model.hinge_direction, model.hinge_block_slot, model.particle_pin,
                        model.material_bending, model.material_thicken, state_in.particle_x, state_in.particle_v,
                        pin_dv, dt, model.scalar(model.damping_stiffness)]
        # Warp's autodiff of these two kernels costs ~10x their forward; when recording, their adjoint is the
        # contracted potential of _record_element_adjoint instead (tested against Warp's in tests/test_solve.py).
        custom = (dv is not None and values.requires_grad and self.element_adjoint == "contracted"
                  and active_tape() is not None)
        wp.launch(k.faces, model.tri_count, device=self.device, inputs=face_inputs, outputs=[values, rhs],
                  record_tape=not custom)
        if model.hinge_count:
            wp.launch(k.hinges, model.hinge_count, device=self.device, inputs=hinge_inputs, outputs=[values, rhs],
                      record_tape=not custom)
        if custom:
            self._record_element_adjoint(state_in, pin_dv, rhs, dv)
        if model.wind_velocity is not None:
            x_normal = state_in.particle_x
            if model.wind_lagged_normals and state_in is self._previous_out:
                x_normal = self._previous_in.particle_x  # continuing a trajectory: the previous step's start
            wp.launch(k.wind, model.tri_count, device=self.device,
                      inputs=[model.tri_indices, model.tri_area, model.particle_pin, model.wind_velocity,
                              model.wind_density, model.wind_drag, x_normal, state_in.particle_v, dt],
                      outputs=[rhs])
        if model.handle_count:
            wp.launch(k.handles, model.handle_count, device=self.device,
                      inputs=[model.handle_particle, model.handle_stiffness, model.particle_diag_slot,
                              state_in.particle_x, state_in.particle_v, control.handle_target,
                              self._offsets("handle", t_next), dt],
                      outputs=[values, rhs])
        if control.particle_force is not None:
            wp.launch(k.external_forces, model.particle_count, device=self.device,
                      inputs=[model.particle_pin, control.particle_force, dt], outputs=[rhs])

    def _record_element_adjoint(self, state_in: State, pin_dv, rhs, dv) -> None:
        """Record the adjoint of the stretching and bending assembly for one step.

        The only consumer of A and b is the solve, whose adjoint gives dL/db = lam and dL/dA_ab = -lam_a dv_b^T.
        So the elements' share of dL/d(inputs) is the gradient of the scalar
        phi = sum_a lam_a . b_a - sum_ab lam_a^T A_ab dv_b with lam and dv held fixed, which contracts to a few dot
        products per element (kernels/implicit.py faces_potential, hinges_potential). Warp differentiates phi.
        """
        model = self.model
        k = self.kernels
        dt = model.scalar(self.dt)

        def grad(a):
            return a.grad if isinstance(a, wp.array) and a.requires_grad else None

        def adjoint():
            lam = rhs.grad
            phi = wp.zeros(1, dtype=model.scalar, device=self.device)
            seed = wp.ones(1, dtype=model.scalar, device=self.device)
            x, v = state_in.particle_x, state_in.particle_v
            launches = [(k.faces_potential, model.tri_count,
                         [model.tri_indices, model.tri_material, model.tri_inv_dm, model.tri_area, model.particle_pin,
                          model.material_density, model.material_stretching, model.material_thicken,
                          model.lut_weight, model.lut_row, model.gravity, x, v, pin_dv, lam, dv, dt,
                          model.scalar(model.damping_mass), model.scalar(model.damping_stiffness)])]
            if model.hinge_count:
                launches.append((k.hinges_potential, model.hinge_count,
                                 [model.hinge_indices, model.hinge_material, model.hinge_rest_angle,
                                  model.hinge_rest_length, model.hinge_rest_area, model.hinge_direction,
                                  model.particle_pin, model.material_bending, model.material_thicken, x, v, pin_dv,
                                  lam, dv, dt, model.scalar(model.damping_stiffness)]))
            for kernel, dim, inputs in launches:
                # lam and dv are constants of phi: no adjoint arrays for them
                adj_inputs = [None if (a is lam or a is dv) else grad(a) for a in inputs]
                wp.launch(kernel, dim, device=self.device, inputs=inputs, outputs=[phi], adj_inputs=adj_inputs,
                          adj_outputs=[seed], adjoint=True, record_tape=False)

        record_adjoint(adjoint, arrays=[rhs, dv, pin_dv])

    def _default_control(self) -> Control:
        if not hasattr(self, "_control_default"):
            self._control_default = self.model.control(requires_grad=False)
        return self._control_default

    def _buffers(self):
        """System buffers of one step. While a tape records, each step gets its own (the backward pass reads them)."""
        model = self.model
        vec3, mat33 = model.types.vec3, model.types.mat33
        recording = active_tape() is not None and model.requires_grad
        if not recording and self._step_buffers is not None:
            return self._step_buffers
        n = model.particle_count
        bufs = (
            wp.empty(model.bsr_nnz, dtype=mat33, device=self.device, requires_grad=recording),
            wp.empty(n, dtype=vec3, device=self.device, requires_grad=recording),
            wp.zeros(n, dtype=vec3, device=self.device, requires_grad=recording),
            wp.zeros(n, dtype=vec3, device=self.device, requires_grad=recording),
        )
        if not recording:
            self._step_buffers = bufs
        return bufs

    def _offsets(self, kind: str, t: float) -> wp.array:
        """Scripted target offsets of the handles or pins at time ``t`` (a shared zero array when none move)."""
        motions = self.model.handle_motion if kind == "handle" else self.model.pin_motion
        if not any(m is not None for m in motions):
            return self._zero_offsets[kind]
        values = np.array([np.zeros(3) if m is None else m.at(t) for m in motions])
        return wp.array(values, dtype=self.model.types.vec3, device=self.device)

    def _solve_recorded(self, values: wp.array, rhs: wp.array, dv: wp.array) -> None:
        """Solve A dv = b; on a tape, record the implicit adjoint instead of the CG iterations."""
        warm = self.options.warm_start and self._previous_dv is not None
        if warm and self._previous_dv is not dv:
            wp.launch(self.linear.copy_guess, self.model.particle_count, device=self.device,
                      inputs=[self._previous_dv], outputs=[dv], record_tape=False)
        iters, residual, converged = self._cg(values, rhs, dv, warm_start=warm)
        self._previous_dv = dv
        self.last_cg_iterations, self.last_cg_residual = iters, residual
        self.stats["cg_iterations"] += iters
        step = self.step_count + 1  # the step being taken, as the divergence guard counts it
        self._check_solve("forward", step, iters, residual, converged)
        if active_tape() is None or not values.requires_grad:
            return

        def adjoint():
            # A is symmetric: solve A lam = dL/d(dv) with the same solver; dL/db = lam, dL/dA_ij = -lam_i dv_j^T.
            # The backward pass runs steps in reverse; the later step's lam (still in the buffer) is the warm start.
            lam = self._adjoint_solution
            if not self.options.warm_start:
                lam.zero_()
            it, res, ok = self._cg(values, dv.grad, lam, warm_start=self.options.warm_start, adjoint=True)
            self.stats["adjoint_cg_iterations"] += it
            self._check_solve("adjoint", step, it, res, ok)
            wp.launch(self.linear.solve_adjoint_scatter, self.model.particle_count, device=self.device,
                      inputs=[self.model.bsr_offsets, self.model.bsr_columns, lam, dv],
                      outputs=[values.grad, rhs.grad], record_tape=False)

        record_adjoint(adjoint, arrays=[values, rhs, dv])

    def _cg(self, values: wp.array, b: wp.array, x: wp.array, *, warm_start: bool = False, adjoint: bool = False
            ) -> tuple[int, float, bool]:
        """Solve A x = b; with ``warm_start`` x holds the initial guess on entry.

        Returns the iterations, the relative residual |b - A x| / |b| and whether the tolerance was met.
        """
        opt = self.options
        tol = opt.adjoint_cg_tol if adjoint and opt.adjoint_cg_tol is not None else opt.cg_tol
        model = self.model
        kind = {"jacobi": 0, "block_jacobi": 1, "block_ssor": 2}[self.preconditioner]
        if self.cg_backend == "sequential":
            r, z, p, q = self._cg_scratch
            wp.launch(self.linear.cg_sequential, 1, device=self.device,
                      inputs=[model.bsr_offsets, model.bsr_columns, values, model.particle_diag_slot, b,
                              float(tol), float(opt.cg_atol), int(opt.cg_max_iters), kind,
                              model.scalar(opt.ssor_omega), int(warm_start),
                              r, z, p, q, self._precond],
                      outputs=[x, self._cg_info], record_tape=False)
            info = self._cg_info_host if self._cg_info_host is not None else self._cg_info.numpy()
            return int(info[0]), float(info[1]), bool(info[2])
        return self._cg_warp(values, b, x, tol, warm_start=warm_start)

    def _cg_warp(self, values, b, x, tol: float, *, warm_start: bool = False) -> tuple[int, float, bool]:
        """``warp.optim.linear.cg`` on a BSR view of ``values`` (the CUDA path)."""
        import warp.optim.linear as wl
        import warp.sparse as ws

        model = self.model
        if self._warp_matrix is None:
            A = ws.bsr_zeros(model.particle_count, model.particle_count, model.types.mat33, device=self.device)
            rows = np.repeat(np.arange(model.particle_count, dtype=np.int32), np.diff(model.bsr_offsets.numpy()))
            ws.bsr_set_from_triplets(
                A, wp.array(rows, dtype=wp.int32, device=self.device), model.bsr_columns,
                wp.zeros(model.bsr_nnz, dtype=model.types.mat33, device=self.device), prune_numerical_zeros=False)
            if not np.array_equal(A.columns.numpy()[: model.bsr_nnz], model.bsr_columns.numpy()):
                raise RuntimeError("warp.sparse reordered the block structure; the slot map would be wrong")
            self._warp_matrix = A
        A = self._warp_matrix
        A.values = values
        if not warm_start:
            x.zero_()
        M = wl.preconditioner(A, "block_jacobi_direct" if self.preconditioner == "block_jacobi" else "diag")
        opt = self.options
        # warp's cg tests |r| <= max(tol |b|, atol); check_every=1 reports the exact iteration count
        iters, residual, threshold = wl.cg(A, b, x, tol=tol, atol=opt.cg_atol, maxiter=opt.cg_max_iters,
                                           M=M, check_every=1, use_cuda_graph=False)
        bnorm = float(np.linalg.norm(b.numpy()))
        return int(iters), float(residual) / max(bnorm, 1e-300), bool(residual <= threshold)

    def _check_solve(self, which: str, step: int, iters: int, residual: float, converged: bool) -> None:
        opt = self.options
        if not converged:
            name, tol = "cg_tol", opt.cg_tol
            if which == "adjoint" and opt.adjoint_cg_tol is not None:
                name, tol = "adjoint_cg_tol", opt.adjoint_cg_tol
            msg = (f"{which} CG solve of step {step} did not converge: relative residual {residual:.3e} "
                   f"after {iters} iterations ({name} {tol:g}); raise cg_max_iters or lower dt, or loosen {name} or "
                   "use dtype=wp.float64 if float32 rounding is the floor (around 1e-6 on large meshes)"
                   + self._mesh_hint())
            if not math.isfinite(residual) or opt.on_cg_failure == "raise":
                raise SimulationError(msg)
            warnings.warn(msg, RuntimeWarning, stacklevel=3)
        elif not math.isfinite(residual):
            raise SimulationError(f"{which} CG solve of step {step} produced a non-finite residual; "
                                  "the system is not positive definite or the state is already invalid")

    def _raise_if_diverged(self, state: State, t: float, step: int) -> None:
        """Raise SimulationError if the divergence guard (``self._status``) flagged a particle of ``state``, the
        result of step number ``step`` at time ``t``."""
        bad = int((self._status_host if self._status_host is not None else self._status.numpy())[0])
        if bad:
            self._previous_dv = None  # a diverged step's solution must not warm-start the next solve
            p = bad - 1
            x = state.particle_x.numpy()[p]
            v = state.particle_v.numpy()[p]
            raise SimulationError(
                f"simulation diverged at step {step} (t = {t:.4g} s): particle {p} has "
                f"x = {x.tolist()}, v = {v.tolist()} (speed limit {self.options.max_speed:g} m/s); "
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
