"""Gradients through the collision response: tape vs central finite differences, QR adjoint vs dense KKT adjoint.

The scenes keep every contact clearly active and every non-contact clearly apart, so the small perturbations of the
finite differences do not change the set of contacts (the one thing the gradient deliberately ignores).
"""

import numpy as np
import pytest
import warp as wp

import warpcloth as wc

MATERIAL = wc.Material.isotropic(density=0.2, stretch_stiffness=200.0, shear_stiffness=20.0, bend_stiffness=2e-5)
TILT = np.array([np.sin(0.001), 0.0, 0.0, np.cos(0.001)])  # 0.002 rad about x


def stretched_grid(b, res, size, *, pos, rot=None, vel=(0.0, 0.0, 0.0), stretch=1.03, material=MATERIAL):
    """A flat grid stretched 3 % in its plane: away from the rest state, where the stretching model's compression
    branch makes the forces non-differentiable (finite differences would see the kink)."""
    mesh = wc.grid_mesh(res, res, size, size)
    rot = np.eye(3) if rot is None else np.asarray(rot)
    mesh.positions = (mesh.positions * [stretch, stretch, 1.0]) @ rot.T + np.asarray(pos)
    b.add_cloth_mesh(mesh, material=material, vel=vel)


def plane_scene():
    """A 0.1 m cloth 0.6 mm over a slightly tilted plane, far from the plane's diagonal edge: all vertex-face."""
    b = wc.ModelBuilder()
    # the plane's height under the cloth's centre (y = -0.4) is -0.4 sin(0.002)
    stretched_grid(b, 3, 0.1, pos=(0.3, -0.45, 0.0006 - 0.4 * np.sin(0.002)))
    b.add_obstacle_plane((2.0, 2.0), rot=TILT)
    b.set_collision(repulsion_stiffness=0.0)  # the projection's gradients alone (tests/test_contact.py: repulsion)
    return b


def layers_scene(top=MATERIAL):
    """Two free sheets in zero gravity: a 2 cm square (of ``top``) moving onto a 20 cm one, inside one of its
    triangles and far from its edges: cloth-cloth vertex-face contacts between free particles on both sides."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    stretched_grid(b, 1, 0.2, pos=(-0.1, -0.1, 0.0))
    stretched_grid(b, 1, 0.02, pos=(-0.01, -0.09, 0.0006), vel=(0.0, 0.0, -0.05), material=top)
    b.set_collision(self_collision=True, repulsion_stiffness=0.0)
    return b


def loss_fn(model, steps, dt, adjoint="qr", solver="numpy", qp_tol=1e-10, integrator="euler"):
    """Build a simulator and a function (x0, v0, transforms) -> (loss, contact counts) with a random linear loss."""
    # cg_atol far below: the solves stop on the relative 1e-12, not on an absolute floor whose stopping iteration
    # can change between the two sides of a finite difference (noise of 5e-6 with the default 1e-12 floor)
    options = wc.SolverOptions(cg_tol=1e-12, cg_atol=1e-30, cg_max_iters=2000, integrator=integrator,
                               collision=wc.CollisionOptions(adjoint=adjoint, solver=solver, qp_tol=qp_tol))
    sim = wc.Simulator(model, dt, options=options)
    rng = np.random.default_rng(3)
    cx = rng.standard_normal((model.particle_count, 3))
    cv = rng.standard_normal((model.particle_count, 3)) * 1e-3

    def run(x0, v0, transforms, tape=None):
        vec3, device = model.types.vec3, model.device
        state = wc.State(wp.array(x0, dtype=vec3, device=device, requires_grad=True),
                         wp.array(v0, dtype=vec3, device=device, requires_grad=True))
        control = model.control(requires_grad=True)
        if transforms is not None:
            control.obstacle_transform = wp.array(transforms, dtype=model.types.transform, device=device,
                                                  requires_grad=True)
        keys = []
        traj = [state]
        for _ in range(steps):
            nxt = model.empty_state()
            sim.step(traj[-1], nxt, control)
            traj.append(nxt)
            keys.append(sim.collision.last.contacts)
        x, v = traj[-1].particle_x.numpy(), traj[-1].particle_v.numpy()
        loss = float(np.sum(cx * x) + np.sum(cv * v))
        if tape is not None:
            weights = (wp.array(cx, dtype=vec3, device=device), wp.array(cv, dtype=vec3, device=device))
            return loss, keys, traj, control, weights
        return loss, keys

    run.bitwise = model.device.is_cpu  # whether two runs give the same loss to the last bit
    return sim, run


def tape_gradients(model, run, x0, v0, transforms):
    tape = wp.Tape()
    with tape:
        loss, keys, traj, control, (cx, cv) = run(x0, v0, transforms, tape=True)
    last = traj[-1]
    tape.backward(grads={last.particle_x: cx, last.particle_v: cv})
    g = {"x0": traj[0].particle_x.grad.numpy().copy(), "v0": traj[0].particle_v.grad.numpy().copy()}
    if transforms is not None:
        g["transform"] = control.obstacle_transform.grad.numpy().copy()
    tape.zero()
    return loss, keys, g


def fd_check(run, base, grads, name, eps, rng, directions=2):
    x0, v0, tf = base
    for _ in range(directions):
        arg = {"x0": x0, "v0": v0, "transform": tf}[name]
        d = rng.standard_normal(arg.shape)

        def at(sign, arg=arg, d=d):
            args = dict(x0=x0, v0=v0, transform=tf)
            args[name] = arg + sign * eps * d
            return run(args["x0"], args["v0"], args["transform"])

        (lp, kp), (lm, km) = at(+1), at(-1)
        assert kp == km, f"the perturbation of {name} changed the contacts ({kp} vs {km}); the test scene is too tight"
        fd = (lp - lm) / (2 * eps)
        an = float(np.sum(grads[name] * d))
        # where two runs differ in their last bits (CUDA: atomic additions), that noise is in the quotient too:
        # measured by running both sides again, it widens the bound by what the quotient cannot resolve (on the
        # CPU runs are bitwise equal, and the bound is the bare one)
        noise = 0.0 if run.bitwise else abs(at(+1)[0] - lp) + abs(at(-1)[0] - lm)
        assert an == pytest.approx(fd, rel=1e-5, abs=1e-9 + noise / eps), \
            f"d loss / d {name}: tape {an}, finite differences {fd} (run-to-run noise {noise:.1e})"


@pytest.mark.parametrize("steps", [1, 3])
def test_obstacle_contact_gradients_match_finite_differences(steps, device):
    model = plane_scene().finalize(device, requires_grad=True, dtype=wp.float64)
    sim, run = loss_fn(model, steps, 0.005)
    x0, v0 = model.particle_x0.numpy(), model.particle_v0.numpy()
    tf = model.obstacle_rest_transform.copy()
    loss, keys, g = tape_gradients(model, run, x0, v0, tf)
    assert keys[0] == model.particle_count  # every vertex in contact with the plane
    rng = np.random.default_rng(0)
    for name, eps in (("x0", 1e-7), ("v0", 1e-4), ("transform", 1e-7)):
        fd_check(run, (x0, v0, tf), g, name, eps, rng)
    assert np.abs(g["transform"]).max() > 0  # the obstacle's placement matters


@pytest.mark.parametrize("solver", ["numpy", "device"])
def test_bdf2_contact_gradients_match_finite_differences(solver, device):
    # BDF2 (steps 2 and 3 blend two states; the response's velocity change is over 2/3 dt): the same adjoints
    model = plane_scene().finalize(device, requires_grad=True, dtype=wp.float64)
    sim, run = loss_fn(model, 3, 0.005, solver=solver, integrator="bdf2")
    x0, v0 = model.particle_x0.numpy(), model.particle_v0.numpy()
    tf = model.obstacle_rest_transform.copy()
    loss, keys, g = tape_gradients(model, run, x0, v0, tf)
    assert min(keys) > 0
    rng = np.random.default_rng(0)
    for name, eps in (("x0", 1e-7), ("v0", 1e-4), ("transform", 1e-7)):
        fd_check(run, (x0, v0, tf), g, name, eps, rng)
    euler_loss = loss_fn(model, 3, 0.005, solver=solver)[1](x0, v0, tf)[0]
    assert abs(loss - euler_loss) > 1e-9 * abs(loss)  # BDF2 was used


def test_cloth_cloth_contact_gradients_match_finite_differences(device):
    model = layers_scene().finalize(device, requires_grad=True, dtype=wp.float64)
    sim, run = loss_fn(model, 1, 0.005)
    x0, v0 = model.particle_x0.numpy(), model.particle_v0.numpy()
    loss, keys, g = tape_gradients(model, run, x0, v0, None)
    assert keys[0] > 0
    rng = np.random.default_rng(1)
    for name, eps in (("x0", 1e-7), ("v0", 1e-4)):
        fd_check(run, (x0, v0, None), g, name, eps, rng)


HEAVY = wc.Material.isotropic(density=0.8, stretch_stiffness=200.0, shear_stiffness=20.0, bend_stiffness=2e-5)


def test_density_gradients_of_two_fabrics_in_contact_match_finite_differences(device):
    # The projection weighs each particle's move by its mass: which fabric gives way depends on both densities.
    # The tape's dL/d(density) includes that dependence (collision/reference/adjoint.py mass_gradient); without it
    # this test fails: the implicit step's share alone is 0.3 % off for the lower sheet.
    model = layers_scene(top=HEAVY).finalize(device, requires_grad=True, dtype=wp.float64)
    assert model.material_density.shape[0] == 2
    sim, run = loss_fn(model, 1, 0.005)
    x0, v0 = model.particle_x0.numpy(), model.particle_v0.numpy()
    base = model.material_density.numpy().copy()
    tape = wp.Tape()
    with tape:
        _, keys, traj, _, (cx, cv) = run(x0, v0, None, tape=True)
    assert keys[0] > 0
    tape.backward(grads={traj[-1].particle_x: cx, traj[-1].particle_v: cv})
    grad = model.material_density.grad.numpy().copy()
    tape.zero()
    eps = 1e-6
    for i in range(2):
        vals = []
        for sign in (1.0, -1.0):
            d = base.copy()
            d[i] += sign * eps
            model.material_density.assign(d)
            loss, k = run(x0, v0, None)
            assert k == keys, "the perturbation changed the contacts"
            vals.append(loss)
        model.material_density.assign(base)
        fd = (vals[0] - vals[1]) / (2 * eps)
        assert grad[i] == pytest.approx(fd, rel=1e-5, abs=1e-9), f"material {i}: tape {grad[i]}, FD {fd}"


@pytest.mark.parametrize("scene", [plane_scene, layers_scene])
def test_qr_adjoint_equals_dense_kkt_adjoint_in_a_step(scene, device):
    grads = {}
    for mode in ("qr", "kkt"):
        model = scene().finalize(device, requires_grad=True, dtype=wp.float64)
        sim, run = loss_fn(model, 2, 0.005, adjoint=mode)
        tf = model.obstacle_rest_transform.copy() if model.obstacle_count else None
        _, _, grads[mode] = tape_gradients(model, run, model.particle_x0.numpy(), model.particle_v0.numpy(), tf)
    for name in grads["qr"]:
        np.testing.assert_allclose(grads["qr"][name], grads["kkt"][name], rtol=1e-8, atol=1e-10 * np.abs(
            grads["kkt"][name]).max())


@pytest.mark.parametrize("scene", [plane_scene, layers_scene, lambda: layers_scene(top=HEAVY)])
def test_device_projection_equals_the_numpy_one(scene, device):
    # CollisionOptions(solver="device"): Warp kernels over all contacts at once, no zones; the same z and, through
    # its CG adjoint on the active set, the same gradients as the zone-by-zone NumPy solver and its QR adjoint
    out = {}
    for solver in ("numpy", "device"):
        model = scene().finalize(device, requires_grad=True, dtype=wp.float64)
        sim, run = loss_fn(model, 2, 0.005, solver=solver, qp_tol=1e-13)  # both solutions exact to round-off
        tf = model.obstacle_rest_transform.copy() if model.obstacle_count else None
        model.material_density.grad.zero_()
        loss, keys, g = tape_gradients(model, run, model.particle_x0.numpy(), model.particle_v0.numpy(), tf)
        g["density"] = model.material_density.grad.numpy().copy()
        assert keys[0] > 0
        out[solver] = (loss, keys, g)
    assert out["device"][1] == out["numpy"][1]
    assert out["device"][0] == pytest.approx(out["numpy"][0], rel=1e-12)
    for name, ref in out["numpy"][2].items():
        np.testing.assert_allclose(out["device"][2][name], ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max(),
                                   err_msg=name)


def sheet_sliding_across_an_edge(device):
    """A 0.3 m sheet landing flat on a frictionless 30-degree plane, across the plane's diagonal edge. Repulsion
    off: the projection alone, and a density that cannot change the motion (the sheet never deforms)."""
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    R = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    b = wc.ModelBuilder()
    b.add_obstacle_plane((4.0, 4.0), rot=R)
    mesh = wc.grid_mesh(10, 10, 0.3, 0.3)
    mesh.positions = (mesh.positions + [-0.15, -0.15, 0.005]) @ R.T
    b.add_cloth_mesh(mesh, material=wc.preset("white-swim-solid", thicken=2))
    b.set_collision(obstacle_friction=0.0, repulsion_stiffness=0.0)
    return b.finalize(device, requires_grad=True, dtype=wp.float64)


@pytest.mark.parametrize("solver", ["numpy", "device"])
def test_density_gradient_is_zero_where_density_cannot_change_the_motion(solver, device):
    # The plane's diagonal used to make edge-edge contacts with every cloth edge across it, dependent on the
    # vertex-face contacts of the edge's ends: the device adjoint's d_lam was 1e10 too large and dL/d(log density)
    # came out 3.6e-4 (central differences: 1e-12); with the dependence damped (kernels/projection.py
    # DEPENDENT_SHIFT) the multipliers' arbitrary split still moved dL/dx0 by 15 %. Flat obstacle edges no longer
    # make contacts (geometry.primitives.contact_edges).
    model = sheet_sliding_across_an_edge(device)
    sim, run = loss_fn(model, 8, 0.01, solver=solver)
    x0, v0 = model.particle_x0.numpy(), model.particle_v0.numpy()
    tape = wp.Tape()
    with tape:
        loss, keys, traj, _, (cx, cv) = run(x0, v0, None, tape=True)
    assert min(keys[4:]) == model.particle_count  # landed: one vertex-face contact a vertex, none on the diagonal
    tape.backward(grads={traj[-1].particle_x: cx, traj[-1].particle_v: cv})
    density = model.material_density.numpy().copy()
    tape_grad = float(model.material_density.grad.numpy()[0] * density[0])
    # the loss's sensitivity to positions, for scale: d loss / d x0 along a unit direction is about |cx| ~ 10
    assert abs(tape_grad) < 1e-8, f"dL/d(log density) = {tape_grad}: the motion does not depend on the density"
    model.material_density.assign(density * np.exp(1e-4))
    moved = run(x0, v0, None)[0]
    assert abs(moved - loss) < 1e-11  # the premise: central differences see nothing


@pytest.mark.parametrize("solver", ["numpy", "device"])
def test_gradients_through_the_rigid_impact_zone_fail_safe_match_finite_differences(solver, device):
    # A patch (of HEAVY) thrown onto a free sheet; the projection is refused (a strain limit of 1e-9 that any
    # projection passes) so the fail-safe moves the particles in contact as one rigid zone: its gradient
    # (kernels/failsafe.py, Warp's autodiff) reaches positions, velocities and both densities.
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    stretched_grid(b, 2, 0.2, pos=(-0.1, -0.1, 0.0))
    stretched_grid(b, 1, 0.06, pos=(-0.03, -0.05, 0.0008), vel=(0.01, 0.02, -0.3), material=HEAVY)
    b.set_collision(self_collision=True, repulsion_stiffness=0.0)
    model = b.finalize(device, requires_grad=True, dtype=wp.float64)
    sim, run = loss_fn(model, 2, 0.005, solver=solver)
    sim.options = wc.SolverOptions(cg_tol=1e-12, cg_atol=1e-30, cg_max_iters=2000,
                                   collision=wc.CollisionOptions(solver=solver, max_projection_strain=1e-9))
    x0, v0 = model.particle_x0.numpy(), model.particle_v0.numpy()
    tape = wp.Tape()
    with tape:
        _, keys, traj, _, (cx, cv) = run(x0, v0, None, tape=True)
    tape.backward(grads={traj[-1].particle_x: cx, traj[-1].particle_v: cv})
    g = {"x0": traj[0].particle_x.grad.numpy().copy(), "v0": traj[0].particle_v.grad.numpy().copy()}
    density_grad = model.material_density.grad.numpy().copy()
    tape.zero()
    steps_before = sim.collision.fail_safe_steps
    run(x0, v0, None)
    assert sim.collision.fail_safe_steps == steps_before + 1  # the first step's projection was given up
    assert keys[0] > 0
    rng = np.random.default_rng(1)
    for name, eps in (("x0", 1e-7), ("v0", 1e-5)):
        fd_check(run, (x0, v0, None), g, name, eps, rng)
    base = model.material_density.numpy().copy()
    for i in range(2):
        vals = []
        for sign in (1.0, -1.0):
            d = base.copy()
            d[i] *= 1.0 + sign * 1e-6
            model.material_density.assign(d)
            vals.append(run(x0, v0, None)[0])
        model.material_density.assign(base)
        fd = (vals[0] - vals[1]) / (2e-6 * base[i])
        assert density_grad[i] == pytest.approx(fd, rel=1e-5, abs=1e-9), f"material {i}: {density_grad[i]} vs {fd}"


SANDWICH_THICKNESS = 5e-4


def sandwich_builder() -> wc.ModelBuilder:
    """A stretched sheet between two planes 0.8 thickness apart, every vertex inside the thickness of both: the
    collision stage's first try (targets of a full thickness) is infeasible, its second, keeping start gaps, is not."""
    delta = SANDWICH_THICKNESS
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    stretched_grid(b, 3, 0.2, pos=(-0.1, -0.1, 0.0))
    b.add_obstacle_plane((1.0, 1.0), pos=(0.0, 0.0, -0.4 * delta))
    b.add_obstacle_plane((1.0, 1.0), pos=(0.0, 0.0, 0.4 * delta), rot=(1.0, 0.0, 0.0, 0.0))  # facing down
    b.set_collision(thickness=delta, repulsion_stiffness=0.0)
    return b


@pytest.mark.parametrize("solver", ["numpy", "device"])
def test_gradients_of_the_second_try_keeping_start_gaps_match_finite_differences(solver, device):
    # A stretched sheet starting between two planes 0.8 thickness apart, every vertex inside the thickness of both:
    # the first try (targets of a full thickness) is infeasible, the second keeps each pair's start gap as its
    # target (kernels/contact.py start_distance, differentiated): gradients reach the start positions through the
    # targets, and the planes' placement.
    delta = SANDWICH_THICKNESS
    model = sandwich_builder().finalize(device, requires_grad=True, dtype=wp.float64)
    sim, run = loss_fn(model, 2, 0.005, solver=solver)
    rng = np.random.default_rng(5)
    x0 = model.particle_x0.numpy() + [0.0, 0.0, 1.0] * rng.uniform(-0.15 * delta, 0.15 * delta, (model.particle_count,
                                                                                                     1))
    v0 = model.particle_v0.numpy()
    tf = model.obstacle_rest_transform.copy()
    loss, keys, g = tape_gradients(model, run, x0, v0, tf)
    assert sim.collision.start_gap_steps >= 1 and sim.collision.fail_safe_steps == 0
    assert sim.collision.last.kept_start_gaps is not None
    # the same agreement at two step sizes: converged, not a coincidence (v0's smaller one also runs a start whose
    # first try once returned NaN positions as converged: the device projection now rejects non-finite results)
    for name, eps, scales in (("x0", 1e-8, (1.0, 0.1)), ("v0", 1e-5, (1.0, 0.1)), ("transform", 1e-8, (1.0, 2.0))):
        for scale in scales:
            fd_check(run, (x0, v0, tf), g, name, eps * scale, rng)
    # the materials, along a relative direction of each: density, stretching and bending tables
    arrays = (model.material_density, model.material_stretching, model.material_bending)
    for array in arrays:  # tape_gradients' backward left its share in them
        array.grad.zero_()
    tape = wp.Tape()
    with tape:
        _, _, traj, _, (cx, cv) = run(x0, v0, tf, tape=True)
    tape.backward(grads={traj[-1].particle_x: cx, traj[-1].particle_v: cv})
    grads = [a.grad.numpy().copy() for a in arrays]
    tape.zero()
    for array, grad in zip(arrays, grads):
        base = array.numpy().copy()
        direction = base * rng.choice([-1.0, 1.0], size=base.shape)
        fds = []
        for h in (1e-5, 1e-6):
            values = []
            for sign in (1.0, -1.0):
                array.assign(base + sign * h * direction)
                values.append(run(x0, v0, tf)[0])
            array.assign(base)
            fds.append((values[0] - values[1]) / (2 * h))
        assert fds[0] == pytest.approx(fds[1], rel=1e-3, abs=1e-9)  # converged at two step sizes
        assert float(np.sum(grad * direction)) == pytest.approx(fds[1], rel=1e-4, abs=1e-9)
