"""Assembly of a step's implicit system A dv = b: the one place that knows kernels/implicit.py's argument lists."""

from __future__ import annotations

import numpy as np
import warp as wp

from warpcloth.kernels.implicit import implicit_kernels
from warpcloth.model import Control, Model, State
from warpcloth.tape import active_tape, record_adjoint


class SystemAssembler:
    """Launches the force and Hessian kernels of one step, ``dt`` [s], into A's blocks and b."""

    def __init__(self, model: Model, dt: float):
        self.model = model
        self.dt = float(dt)
        self.device = model.device
        self.kernels = implicit_kernels(model.scalar)
        self.element_adjoint = "contracted"
        """How the stretching/bending assembly is differentiated: "contracted" (the rank-one potential, fast) or
        "autodiff" (Warp's adjoint of the assembly kernels: the reference the contracted one is tested against)."""
        k = self.kernels
        # The Model's arrays as the element kernels read them. Built once: the Model's arrays are updated in place
        # (assign/copy), never rebound.
        m = model
        self.face_data = k.FaceData()
        for name, array in (("indices", m.tri_indices), ("material", m.tri_material), ("inv_dm", m.tri_inv_dm),
                            ("area", m.tri_area), ("block_slot", m.tri_block_slot), ("particle_pin", m.particle_pin),
                            ("density", m.material_density), ("stretching", m.material_stretching),
                            ("thicken", m.material_thicken), ("lut_weight", m.lut_weight), ("lut_row", m.lut_row),
                            ("gravity", m.gravity), ("particle_world", m.particle_world),
                            ("damping_mass", m.damping_mass), ("damping_stiffness", m.damping_stiffness)):
            setattr(self.face_data, name, array)
        self.hinge_data = k.HingeData()
        for name, array in (("indices", m.hinge_indices), ("material", m.hinge_material),
                            ("rest_angle", m.hinge_rest_angle), ("rest_length", m.hinge_rest_length),
                            ("rest_area", m.hinge_rest_area), ("direction", m.hinge_direction),
                            ("block_slot", m.hinge_block_slot), ("particle_pin", m.particle_pin),
                            ("bending", m.material_bending), ("thicken", m.material_thicken),
                            ("damping_stiffness", m.damping_stiffness)):
            setattr(self.hinge_data, name, array)
        vec3 = model.types.vec3
        self._none = wp.empty(0, dtype=vec3, device=self.device)
        self._motion_offsets: dict[tuple[str, float], wp.array] = {}  # offsets() of scripted motions
        self._active: dict[float, wp.array] = {}  # handles_active() of handles with windows
        self._always = wp.empty(0, dtype=model.scalar, device=self.device)
        self._zero_offsets = {
            "handle": wp.zeros(model.handle_count, dtype=vec3, device=self.device),
            "pin": wp.zeros(model.pin_count, dtype=vec3, device=self.device),
        }

    # -- the element kernels' arguments ----------------------------------------------------------------------------
    def element_state(self, x, v, pin_dv=None, lam=None, dv=None):
        """The per-step inputs of the element kernels (``kernels.implicit`` ElementState)."""
        m = self.model
        es = self.kernels.ElementState()
        # an empty array, not None, where a use needs no input: the tape's adjoint of a struct reads every member
        es.x, es.v, es.pin_dv, es.lam, es.dv = (self._none if a is None else a for a in (x, v, pin_dv, lam, dv))
        es.dt = m.scalar(self.dt)
        return es

    def element_launches(self, kernels: tuple, element_state) -> list:
        """(kernel, dim, inputs) of the face and hinge kernels in ``kernels`` (hinges only when the mesh has any)."""
        launches = [(kernels[0], self.model.tri_count, [self.face_data, element_state])]
        if self.model.hinge_count:
            launches.append((kernels[1], self.model.hinge_count, [self.hinge_data, element_state]))
        return launches

    # -- assembly --------------------------------------------------------------------------------------------------
    def assemble(self, state_in: State, control: Control, t_next: float, values, rhs, pin_dv, dv=None,
                 explicit=None) -> None:
        """Fill ``values`` (A's blocks) and ``rhs`` (b) for one step. ``dv``: the buffer the solve will write, for the
        recorded adjoint; ``explicit``: where the wind force is taken (BDF2's extrapolation), None: ``state_in``."""
        model = self.model
        dt = model.scalar(self.dt)
        k = self.kernels
        x, v = state_in.particle_x, state_in.particle_v
        rhs.zero_()
        values.zero_()
        if model.pin_count:
            pin_dv.zero_()
            wp.launch(k.pin_rows, model.pin_count, device=self.device,
                      inputs=[model.pin_particle, model.particle_diag_slot, x, v, control.pin_target,
                              self.offsets("pin", t_next), dt],
                      outputs=[pin_dv, values, rhs])
        # when recording, the element kernels' adjoint is the contracted potential of _record_element_adjoint, far
        # cheaper than Warp's autodiff of them (tested against it in tests/test_solve.py)
        custom = (dv is not None and values.requires_grad and self.element_adjoint == "contracted"
                  and active_tape() is not None)
        for kernel, dim, inputs in self.element_launches((k.faces, k.hinges), self.element_state(x, v, pin_dv)):
            wp.launch(kernel, dim, device=self.device, inputs=inputs, outputs=[values, rhs, None],
                      record_tape=not custom)
        if custom:
            self._record_element_adjoint(state_in, pin_dv, rhs, dv)
        if model.wind_velocity is not None:
            x_wind, v_wind = explicit if explicit is not None else (x, v)
            x_normal = x_wind
            if model.wind_lagged_normals and state_in.particle_x_previous is not None:
                x_normal = state_in.particle_x_previous  # continuing a trajectory: the previous step's start
            wp.launch(k.wind, model.tri_count, device=self.device,
                      inputs=[model.tri_indices, model.tri_area, model.particle_pin, model.particle_world,
                              model.wind_velocity, model.wind_density, model.wind_drag, x_normal, v_wind, dt],
                      outputs=[rhs])
        if model.handle_count:
            wp.launch(k.handles, model.handle_count, device=self.device,
                      inputs=[model.handle_particle, model.handle_stiffness, model.particle_diag_slot,
                              self.handles_active(t_next), x, v, control.handle_target,
                              self.offsets("handle", t_next), dt],
                      outputs=[values, rhs])
        if control.particle_force is not None:
            wp.launch(k.external_forces, model.particle_count, device=self.device,
                      inputs=[model.particle_pin, control.particle_force, dt], outputs=[rhs])

    def _record_element_adjoint(self, state_in: State, pin_dv, rhs, dv) -> None:
        """Record the adjoint of the stretching and bending assembly for one step: the gradient of
        phi = sum_a lam_a . b_a - sum_ab lam_a^T A_ab dv_b with lam and dv held fixed (the solve's adjoint gives
        dL/db = lam, dL/dA_ab = -lam_a dv_b^T), by Warp's adjoint of the "potential" element kernels."""
        model = self.model
        k = self.kernels

        def grad(a):
            return a.grad if isinstance(a, wp.array) and a.requires_grad else None

        # Everything the adjoint launches read is made here, when the step is recorded, and held by the closure:
        # a backward pass captured as a graph replays these launches long after a temporary would have been freed.
        x, v = state_in.particle_x, state_in.particle_v
        phi = wp.zeros(1, dtype=model.scalar, device=self.device)
        seed = wp.ones(1, dtype=model.scalar, device=self.device)
        element_state = self.element_state(x, v, pin_dv, rhs.grad, dv)
        # lam and dv are constants of phi: no adjoint arrays for them
        adj_state = self.kernels.ElementState()
        adj_state.x, adj_state.v, adj_state.pin_dv = grad(x), grad(v), grad(pin_dv)
        # the recording tape's own adjoint struct: tape.zero() then zeroes the materials' and gravity's gradients
        tape = active_tape()
        launches = [(kernel, dim, inputs, tape.get_adjoint(inputs[0])) for kernel, dim, inputs in
                    self.element_launches((k.faces_potential, k.hinges_potential), element_state)]

        def adjoint():
            for kernel, dim, inputs, adj_data in launches:
                wp.launch(kernel, dim, device=self.device, inputs=inputs, outputs=[None, None, phi],
                          adj_inputs=[adj_data, adj_state], adj_outputs=[None, None, seed],
                          adjoint=True, record_tape=False)

        record_adjoint(adjoint, arrays=[rhs, dv, pin_dv])

    # -- energy ----------------------------------------------------------------------------------------------------
    def element_energy(self, state: State) -> dict[str, float]:
        """Kinetic, stretching, gravitational and bending energies [J] of ``state`` (host values)."""
        model = self.model
        k = self.kernels
        faces = wp.zeros(3, dtype=model.scalar, device=self.device)
        bend = wp.zeros(1, dtype=model.scalar, device=self.device)
        launches = self.element_launches((k.face_energy, k.hinge_energy),
                                         self.element_state(state.particle_x, state.particle_v))
        for (kernel, dim, inputs), out in zip(launches, (faces, bend)):
            wp.launch(kernel, dim, device=self.device, inputs=inputs, outputs=[None, None, out], record_tape=False)
        kinetic, stretching, gravity = (float(e) for e in faces.numpy())
        return {"kinetic": kinetic, "stretching": stretching, "bending": float(bend.numpy()[0]), "gravity": gravity}

    def offsets(self, kind: str, t: float) -> wp.array:
        """Scripted target offsets of the handles (``kind="handle"``) or pins (``"pin"``) at time ``t`` (a shared
        zero array when none move)."""
        motions = self.model.handle_motion if kind == "handle" else self.model.pin_motion
        if not any(m is not None for m in motions):
            return self._zero_offsets[kind]
        # kept per time: a step recorded in a graph reads its offsets from an array made before the capture (by
        # the ordinary run before it), never from host memory the capture would copy from after it is gone
        key = (kind, float(t))
        if key not in self._motion_offsets:
            values = np.array([np.zeros(3) if m is None else m.at(t) for m in motions])
            self._motion_offsets[key] = wp.array(values, dtype=self.model.types.vec3, device=self.device)
        return self._motion_offsets[key]

    def handles_active(self, t_end: float) -> wp.array:
        """1 or 0 for each handle in the step that ends at ``t_end`` [s]: held where ``Model.handle_window`` puts
        ``t_end`` in (on, off]; an empty array where no handle has a window (every handle holds)."""
        windows = self.model.handle_window
        if windows is None:
            return self._always
        key = float(t_end)
        if key not in self._active:  # kept per time, as offsets()
            eps = 1e-6 * self.dt  # step ends accumulate rounding: t_end = n dt to within this
            on = (windows[:, 0] + eps < t_end) & (t_end <= windows[:, 1] + eps)
            self._active[key] = wp.array(on.astype(np.float64), dtype=self.model.scalar, device=self.device)
        return self._active[key]
