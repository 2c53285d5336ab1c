"""Assembly of the linearised implicit Euler system A dv = b (SPEC.md §2) and the state update.

One step, after Baraff and Witkin 1998 / ARCSim ``implicit_update``:
    A = (1 + dt alpha) M + dt (dt + beta) H + sum_handles dt^2 k I
    b = dt (f + m g - alpha M v) - dt (dt + beta) H v - sum_handles dt k ((x - x_target) + dt v)
with H = -J the PSD stiffness of stretching and bending (Rayleigh damping alpha [1/s], beta [s]).
Hard pins prescribe dv on their rows; their columns move to the right-hand side so A stays symmetric.
Kernels add 3x3 blocks into precomputed BSR slots (the sparsity is fixed for a mesh).
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.bending import bending_funcs
from warpcloth.kernels.status import DIVERGED, ERROR, latch
from warpcloth.kernels.stretching import stretching_funcs
from warpcloth.kernels.types import per_precision, types


@per_precision
def implicit_kernels(scalar):
    t = types(scalar)
    vec2, vec3, mat22, mat33 = t.vec2, t.vec3, t.mat22, t.mat33
    st = stretching_funcs(scalar)
    bd = bending_funcs(scalar)

    @wp.func
    def add_block(
        values: wp.array(dtype=mat33),
        rhs: wp.array(dtype=vec3),
        pin_dv: wp.array(dtype=vec3),
        slot: int,
        row: int,
        col: int,
        row_pinned: bool,
        col_pinned: bool,
        block: mat33,
    ):
        # A pinned row is identity (set by pin_rows); a pinned column is eliminated onto the right-hand side.
        if not row_pinned:
            if col_pinned:
                wp.atomic_sub(rhs, row, block * pin_dv[col])
            else:
                wp.atomic_add(values, slot, block)

    @wp.struct
    class FaceData:
        # What the face kernels read from the Model (warpcloth/model.py documents each array). A struct, so the
        # kernels that assemble, differentiate and measure the faces share one argument list; gradients reach the
        # differentiable members (materials, gravity, damping) through the tape's adjoint struct.
        indices: wp.array2d(dtype=wp.int32)
        material: wp.array(dtype=wp.int32)
        inv_dm: wp.array(dtype=mat22)
        area: wp.array(dtype=scalar)
        block_slot: wp.array2d(dtype=wp.int32)
        particle_pin: wp.array(dtype=wp.int32)
        density: wp.array(dtype=scalar)
        stretching: wp.array3d(dtype=scalar)
        thicken: wp.array(dtype=scalar)
        lut_weight: wp.array(dtype=vec3)
        lut_row: wp.array(dtype=wp.int32)
        gravity: wp.array(dtype=vec3)  # per world
        particle_world: wp.array(dtype=wp.int32)
        damping_mass: wp.array(dtype=scalar)  # (1,)
        damping_stiffness: wp.array(dtype=scalar)  # (1,)

    @wp.struct
    class HingeData:
        # What the hinge kernels read from the Model.
        indices: wp.array2d(dtype=wp.int32)
        material: wp.array(dtype=wp.int32)
        rest_angle: wp.array(dtype=scalar)
        rest_length: wp.array(dtype=scalar)
        rest_area: wp.array(dtype=scalar)
        direction: wp.array(dtype=vec2)
        block_slot: wp.array2d(dtype=wp.int32)
        particle_pin: wp.array(dtype=wp.int32)
        bending: wp.array3d(dtype=scalar)
        thicken: wp.array(dtype=scalar)
        damping_stiffness: wp.array(dtype=scalar)  # (1,)

    @wp.struct
    class ElementState:
        # The per-step inputs of the element kernels: the state, the pins' prescribed velocity change, and (for
        # the adjoint potential only, held constant) lam = dL/db and the solve's solution dv.
        x: wp.array(dtype=vec3)
        v: wp.array(dtype=vec3)
        pin_dv: wp.array(dtype=vec3)
        lam: wp.array(dtype=vec3)
        dv: wp.array(dtype=vec3)
        dt: scalar

    @wp.func
    def face_element(f: int, indices: wp.array2d(dtype=wp.int32), material: wp.array(dtype=wp.int32),
                     inv_dms: wp.array(dtype=mat22), areas: wp.array(dtype=scalar), density: wp.array(dtype=scalar),
                     stretching: wp.array3d(dtype=scalar), thickens: wp.array(dtype=scalar),
                     lut_weight: wp.array(dtype=vec3), lut_row: wp.array(dtype=wp.int32), x: wp.array(dtype=vec3)):
        """Everything a face kernel needs: nodes, shape gradients, F's columns, Green strain, stiffness [N/m],
        rest area and each node's lumped mass (a third of the face's, ARCSim compute_masses)."""
        idx = wp.vec3i(indices[f, 0], indices[f, 1], indices[f, 2])
        mat = material[f]
        area = areas[f]
        thicken = thickens[mat]
        inv_dm = inv_dms[f]
        du, dv = st.shape_gradients(inv_dm)
        xu, xv, G00, G11, G01 = st.deformation(x[idx[0]], x[idx[1]], x[idx[2]], inv_dm)
        k = thicken * st.stiffness(stretching, lut_weight, lut_row, mat, G00, G11, G01)
        node_mass = area * density[mat] * thicken / scalar(3.0)
        return idx, du, dv, xu, xv, G00, G11, G01, k, area, node_mass

    @wp.func
    def hinge_element(e: int, hinge: HingeData, x: wp.array(dtype=vec3)):
        """Nodes, dihedral angle [rad] and kappa = -ke l^2 / (4 (A0 + A1)) of a hinge (Bridson et al. 2003 as in
        ARCSim): the bending energy is -kappa/2 (theta - rest)^2."""
        idx = wp.vec4i(hinge.indices[e, 0], hinge.indices[e, 1], hinge.indices[e, 2], hinge.indices[e, 3])
        mat = hinge.material[e]
        length = hinge.rest_length[e]
        area = hinge.rest_area[e]
        theta = bd.dihedral_angle(x[idx[0]], x[idx[1]], x[idx[2]], x[idx[3]])
        ke = hinge.thicken[mat] * bd.stiffness(hinge.bending, mat, hinge.direction[e], theta, length / area)
        return idx, theta, -ke * length * length / (scalar(4.0) * area)

    @wp.func
    def flag_divergence(i: int, x: vec3, v: vec3, max_speed: scalar, step: int, record: wp.array(dtype=wp.int32)):
        # a NaN/inf, or a particle faster than max_speed: latched in the failure record (kernels/status.py)
        if not (wp.isfinite(x) and wp.isfinite(v)) or wp.length(v) > max_speed:
            latch(record, ERROR, step, DIVERGED, i)

    @wp.kernel
    def pin_rows(
        # Model:
        pin_particle: wp.array(dtype=wp.int32),
        particle_diag_slot: wp.array(dtype=wp.int32),
        # State in:
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        # Control:
        pin_target: wp.array(dtype=vec3),
        pin_offset: wp.array(dtype=vec3),
        dt: scalar,
        # out:
        pin_dv: wp.array(dtype=vec3),
        values: wp.array(dtype=mat33),
        rhs: wp.array(dtype=vec3),
    ):
        q = wp.tid()
        p = pin_particle[q]
        # the velocity change that puts the particle on its target at the end of the step
        dv = (pin_target[q] + pin_offset[q] - x[p]) / dt - v[p]
        pin_dv[p] = dv
        wp.atomic_add(values, particle_diag_slot[p], wp.identity(n=3, dtype=scalar))
        wp.atomic_add(rhs, p, dv)

    def element_kernel_pair(mode: str):
        """The face and hinge kernels of one use (``mode``), with one argument list for all uses:

        - ``"assemble"``: add the elements' blocks to A (``values``) and their share of b (``rhs``);
        - ``"potential"``: add phi = sum_a lam_a . b_a - sum_ab lam_a^T A_ab w_b to ``scalars[0]``, whose gradient
          (lam and w = v + dv held constant) is the elements' share of the solve's adjoint: the backward pass
          differentiates this instead of the assembly (SPEC §4.1);
        - ``"energy"``: add kinetic, stretching and gravitational energy (faces) and bending energy (hinges) to
          ``scalars`` [J].
        Arrays a mode does not use may be passed as None. Each kernel is named for its mode: Warp's CPU graphs find a
        kernel by its name within its module, so two modes under one name in one graph would replay one's code.
        """

        @wp.kernel(name=f"faces_{mode}")
        def faces(
            face: FaceData,
            s: ElementState,
            # out:
            values: wp.array(dtype=mat33),
            rhs: wp.array(dtype=vec3),
            scalars: wp.array(dtype=scalar),
        ):
            f = wp.tid()
            x, v, pin_dv, lam, dv, dt = s.x, s.v, s.pin_dv, s.lam, s.dv, s.dt
            damping_mass = face.damping_mass[0]
            particle_pin, gravity = face.particle_pin, face.gravity
            idx, du, dw, xu, xv, G00, G11, G01, k, area, node_mass = face_element(
                f, face.indices, face.material, face.inv_dm, face.area, face.density, face.stretching, face.thicken,
                face.lut_weight, face.lut_row, x)
            c = dt * (dt + face.damping_stiffness[0])
            g = gravity[face.particle_world[idx[0]]]
            if wp.static(mode == "assemble"):
                eye = wp.identity(n=3, dtype=scalar)
                for a in range(3):
                    pa = particle_pin[idx[a]] >= 0
                    hv = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
                    for b in range(3):
                        h_ab = st.hessian_block(a, b, du, dw, xu, xv, k, G00, G11, area)
                        hv += h_ab * v[idx[b]]
                        add_block(values, rhs, pin_dv, face.block_slot[f, 3 * a + b], idx[a], idx[b], pa,
                                  particle_pin[idx[b]] >= 0, c * h_ab)
                    if not pa:
                        fa = st.node_force(a, du, dw, xu, xv, k, G00, G11, G01, area)
                        b_a = dt * (fa + node_mass * g - damping_mass * node_mass * v[idx[a]]) - c * hv
                        wp.atomic_add(rhs, idx[a], b_a)
                        wp.atomic_add(values, face.block_slot[f, 4 * a],
                                      ((scalar(1.0) + dt * damping_mass) * node_mass) * eye)
            if wp.static(mode == "potential"):
                # The 3x3 blocks never form: with Lu = sum_a du_a lam_a (etc.), sum_ab lam_a^T H_ab w_b contracts to
                # a few dot products (SPEC §1.2 H).
                zero3 = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
                Lu = zero3
                Lv = zero3
                Wu = zero3
                Wv = zero3
                inertia = scalar(0.0)
                for a in range(3):
                    p = idx[a]
                    la = zero3
                    if particle_pin[p] < 0:
                        la = lam[p]
                    w = v[p] + wp.where(particle_pin[p] < 0, dv[p], pin_dv[p])
                    Lu += du[a] * la
                    Lv += dw[a] * la
                    Wu += du[a] * w
                    Wv += dw[a] * w
                    inertia += wp.dot(la, dt * g - dt * damping_mass * v[p]
                                      - (scalar(1.0) + dt * damping_mass) * dv[p])
                Lxu = wp.dot(Lu, xu)
                Lxv = wp.dot(Lv, xv)
                Wxu = wp.dot(Wu, xu)
                Wxv = wp.dot(Wv, xv)
                g00 = wp.max(G00, scalar(0.0))
                g11 = wp.max(G11, scalar(0.0))
                # sum_a lam_a . f_a (stretching force, SPEC §1.2)
                force = -area * (k[0] * G00 * Lxu + k[2] * G11 * Lxv + k[1] * (G00 * Lxv + G11 * Lxu)
                                 + k[3] * G01 * (wp.dot(Lu, xv) + wp.dot(Lv, xu)))
                # sum_ab lam_a^T H_ab w_b
                hess = area * (
                    k[0] * (Lxu * Wxu + g00 * wp.dot(Lu, Wu))
                    + k[2] * (Lxv * Wxv + g11 * wp.dot(Lv, Wv))
                    + k[1] * (Lxu * Wxv + Lxv * Wxu + g00 * wp.dot(Lv, Wv) + g11 * wp.dot(Lu, Wu))
                    + scalar(0.5) * k[3] * (wp.dot(Lu, xv) + wp.dot(Lv, xu)) * (wp.dot(Wu, xv) + wp.dot(Wv, xu))
                )
                wp.atomic_add(scalars, 0, dt * force + node_mass * inertia - c * hess)
            if wp.static(mode == "energy"):
                v0 = v[idx[0]]
                v1 = v[idx[1]]
                v2 = v[idx[2]]
                wp.atomic_add(scalars, 0, scalar(0.5) * node_mass * (wp.dot(v0, v0) + wp.dot(v1, v1) + wp.dot(v2, v2)))
                wp.atomic_add(scalars, 1, area * st.energy_density(k, G00, G11, G01))
                wp.atomic_add(scalars, 2, -node_mass * wp.dot(g, x[idx[0]] + x[idx[1]] + x[idx[2]]))

        @wp.kernel(name=f"hinges_{mode}")
        def hinges(
            hinge: HingeData,
            s: ElementState,
            # out:
            values: wp.array(dtype=mat33),
            rhs: wp.array(dtype=vec3),
            scalars: wp.array(dtype=scalar),
        ):
            e = wp.tid()
            x, v, pin_dv, lam, dv, dt = s.x, s.v, s.pin_dv, s.lam, s.dv, s.dt
            particle_pin = hinge.particle_pin
            idx, theta, kappa = hinge_element(e, hinge, x)
            d = theta - hinge.rest_angle[e]
            c = dt * (dt + hinge.damping_stiffness[0])
            if wp.static(mode == "energy"):
                # E = ke l^2 / (8 (A0 + A1)) (theta - rest)^2 = -kappa/2 (theta - rest)^2
                wp.atomic_add(scalars, 0, scalar(-0.5) * kappa * d * d)
            if wp.static(mode != "energy"):
                # f = kappa (theta - rest) dtheta; H = -kappa dtheta dtheta^T (Gauss-Newton): everything is rank one
                g0, g1, g2, g3 = bd.angle_gradient(x[idx[0]], x[idx[1]], x[idx[2]], x[idx[3]])
                grads = wp.matrix_from_rows(g0, g1, g2, g3)
                if wp.static(mode == "assemble"):
                    gv = wp.dot(g0, v[idx[0]]) + wp.dot(g1, v[idx[1]]) + wp.dot(g2, v[idx[2]]) + wp.dot(g3, v[idx[3]])
                    for a in range(4):
                        ga = grads[a]
                        pa = particle_pin[idx[a]] >= 0
                        if not pa:
                            wp.atomic_add(rhs, idx[a], dt * kappa * d * ga + (c * kappa * gv) * ga)
                        for b in range(4):
                            blk = (-c * kappa) * wp.outer(ga, grads[b])
                            add_block(values, rhs, pin_dv, hinge.block_slot[e, 4 * a + b], idx[a], idx[b], pa,
                                      particle_pin[idx[b]] >= 0, blk)
                if wp.static(mode == "potential"):
                    lam_g = scalar(0.0)
                    w_g = scalar(0.0)
                    for a in range(4):
                        p = idx[a]
                        if particle_pin[p] < 0:
                            lam_g += wp.dot(lam[p], grads[a])
                        w_g += wp.dot(grads[a], v[p] + wp.where(particle_pin[p] < 0, dv[p], pin_dv[p]))
                    wp.atomic_add(scalars, 0, kappa * lam_g * (dt * d + c * w_g))

        return faces, hinges

    faces, hinges = element_kernel_pair("assemble")
    faces_potential, hinges_potential = element_kernel_pair("potential")
    face_energy, hinge_energy = element_kernel_pair("energy")

    @wp.kernel
    def wind(
        # Model:
        tri_indices: wp.array2d(dtype=wp.int32),
        tri_area: wp.array(dtype=scalar),
        particle_pin: wp.array(dtype=wp.int32),
        particle_world: wp.array(dtype=wp.int32),
        wind_velocity: wp.array(dtype=vec3),  # per world, as wind_density and wind_drag
        wind_density: wp.array(dtype=scalar),
        wind_drag: wp.array(dtype=scalar),
        # State in: (x_normal: positions the face normals are taken from)
        x_normal: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        dt: scalar,
        # out:
        rhs: wp.array(dtype=vec3),
    ):
        # ARCSim wind_force (SPEC §1.4): normal pressure rho A |vn| vn n plus tangential drag; no Jacobian.
        f = wp.tid()
        i0 = tri_indices[f, 0]
        i1 = tri_indices[f, 1]
        i2 = tri_indices[f, 2]
        n = wp.normalize(wp.cross(x_normal[i1] - x_normal[i0], x_normal[i2] - x_normal[i0]))
        world = particle_world[i0]
        v_rel = wind_velocity[world] - (v[i0] + v[i1] + v[i2]) / scalar(3.0)
        vn = wp.dot(n, v_rel)
        area = tri_area[f]
        force = wind_density[world] * area * wp.abs(vn) * vn * n + wind_drag[world] * area * (v_rel - vn * n)
        share = (dt / scalar(3.0)) * force
        if particle_pin[i0] < 0:
            wp.atomic_add(rhs, i0, share)
        if particle_pin[i1] < 0:
            wp.atomic_add(rhs, i1, share)
        if particle_pin[i2] < 0:
            wp.atomic_add(rhs, i2, share)

    @wp.kernel
    def handles(
        # Model:
        handle_particle: wp.array(dtype=wp.int32),
        handle_stiffness: wp.array(dtype=scalar),
        particle_diag_slot: wp.array(dtype=wp.int32),
        # Model at the step's end: 1 or 0 for each handle (a gripper's grasp and release); empty: all hold
        handle_active: wp.array(dtype=scalar),
        # State in:
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        # Control:
        handle_target: wp.array(dtype=vec3),
        handle_offset: wp.array(dtype=vec3),
        dt: scalar,
        # out:
        values: wp.array(dtype=mat33),
        rhs: wp.array(dtype=vec3),
    ):
        # soft penalty spring 1/2 k |x - target|^2 (ARCSim EqCon per axis), linearised implicitly
        h = wp.tid()
        p = handle_particle[h]
        k = handle_stiffness[h]
        if handle_active.shape[0] > 0:
            k = k * handle_active[h]
        c = x[p] - (handle_target[h] + handle_offset[h])
        wp.atomic_add(values, particle_diag_slot[p], (dt * dt * k) * wp.identity(n=3, dtype=scalar))
        wp.atomic_sub(rhs, p, (dt * k) * (c + dt * v[p]))

    @wp.kernel
    def external_forces(
        particle_pin: wp.array(dtype=wp.int32),
        # Control:
        particle_force: wp.array(dtype=vec3),
        dt: scalar,
        # out:
        rhs: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        if particle_pin[i] < 0:
            wp.atomic_add(rhs, i, dt * particle_force[i])

    @wp.kernel
    def integrate(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        dv: wp.array(dtype=vec3),
        dt: scalar,
        max_speed: scalar,
        step: int,
        # out:
        x_out: wp.array(dtype=vec3),
        v_out: wp.array(dtype=vec3),
        record: wp.array(dtype=wp.int32),
    ):
        # v <- v + dv; x <- x + dt v (ARCSim step_mesh)
        i = wp.tid()
        v_new = v[i] + dv[i]
        x_new = x[i] + dt * v_new
        v_out[i] = v_new
        x_out[i] = x_new
        # the divergence guard, here rather than in a launch of its own
        flag_divergence(i, x_new, v_new, max_speed, step, record)

    @wp.kernel
    def bdf2_blend(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        x_last: wp.array(dtype=vec3),
        v_last: wp.array(dtype=vec3),
        # out:
        x_out: wp.array(dtype=vec3),
        v_out: wp.array(dtype=vec3),
        x_ahead: wp.array(dtype=vec3),
        v_ahead: wp.array(dtype=vec3),
    ):
        # BDF2's start point: x~ = (4 x_n - x_{n-1}) / 3, v~ = (4 v_n - v_{n-1}) / 3; a backward Euler step of
        # 2/3 dt from (x~, v~) is then BDF2's step (SolverOptions.integrator). The explicit (wind) force is taken at
        # the extrapolation to the step's end, 2 x_n - x_{n-1}, 2 v_n - v_{n-1} (as in IMEX BDF2): at the blend,
        # which lags the end by 2/3 dt, it would make the scheme first order
        i = wp.tid()
        third = scalar(1.0) / scalar(3.0)  # in the model's precision: scalar(1.0 / 3.0) rounds 1/3 to float32 first
        x_out[i] = third * (scalar(4.0) * x[i] - x_last[i])
        v_out[i] = third * (scalar(4.0) * v[i] - v_last[i])
        if x_ahead.shape[0] > 0:  # empty without explicit forces (no wind): nothing to extrapolate
            x_ahead[i] = scalar(2.0) * x[i] - x_last[i]
            v_ahead[i] = scalar(2.0) * v[i] - v_last[i]

    @wp.kernel
    def bdf2_history(
        x_prev: wp.array(dtype=vec3),
        v_prev: wp.array(dtype=vec3),
        x_hat: wp.array(dtype=vec3),
        x_new: wp.array(dtype=vec3),
        v_new: wp.array(dtype=vec3),
        dt: scalar,
        # out:
        x_last: wp.array(dtype=vec3),
        v_last: wp.array(dtype=vec3),
    ):
        # The history BDF2's next step blends. A particle the collision response moved (x_new != x^) changed its
        # velocity inelastically: its real previous state would make the next blend (4 v_new - v_prev) / 3 send it
        # back off the obstacle at a third of its impact speed. It
        # restarts from a history that moved at its new velocity, x_new - dt v_new: the blend then advances it by dt
        # at that velocity, as a backward Euler step would.
        i = wp.tid()
        if wp.length(x_new[i] - x_hat[i]) > scalar(0.0):
            x_last[i] = x_new[i] - dt * v_new[i]
            v_last[i] = v_new[i]
        else:
            x_last[i] = x_prev[i]
            v_last[i] = v_prev[i]

    @wp.kernel
    def check_state(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        max_speed: scalar,
        step: int,
        # out: the failure record (kernels/status.py)
        record: wp.array(dtype=wp.int32),
    ):
        # the divergence guard alone (after the collision response has changed the state)
        i = wp.tid()
        flag_divergence(i, x[i], v[i], max_speed, step, record)

    @wp.kernel
    def lumped_mass(
        triangles: wp.array2d(dtype=wp.int32),
        area: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        density: wp.array(dtype=scalar),
        thicken: wp.array(dtype=scalar),
        # out:
        mass: wp.array(dtype=scalar),
    ):
        # a third of each triangle's mass to each corner (Model.particle_mass), differentiated to the densities: the
        # masses of the contact stages (friction, the projection), whose adjoints add to mass.grad
        f = wp.tid()
        third = area[f] * density[material[f]] * thicken[material[f]] / scalar(3.0)
        for c in range(3):
            wp.atomic_add(mass, triangles[f, c], third)

    return SimpleNamespace(
        FaceData=FaceData, HingeData=HingeData, ElementState=ElementState,
        pin_rows=pin_rows, handles=handles, external_forces=external_forces, wind=wind,
        faces=faces, hinges=hinges, faces_potential=faces_potential, hinges_potential=hinges_potential,
        face_energy=face_energy, hinge_energy=hinge_energy, integrate=integrate, check_state=check_state,
        bdf2_blend=bdf2_blend, bdf2_history=bdf2_history, lumped_mass=lumped_mass, flag_divergence=flag_divergence,
    )

