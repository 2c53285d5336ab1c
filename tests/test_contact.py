"""Proximity repulsion and friction inside the implicit step (warpcloth/solver/proximity.py): closed-form
physics on small scenes, the linear system against a dense solve, and gradients against central differences."""

import math

import numpy as np
import pytest
import warp as wp

import warpcloth as wc

G = 9.8
MATERIAL = wc.preset("gray-interlock")
REST_GAP = 0.00486  # about where a gray-interlock patch rests in the 5 mm repulsion layer (1e6 N/m^3)


def rotation_y(theta):
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def incline(theta_deg, mu, *, res=4, size=0.1, dtype=wp.float64, requires_grad=False, gap=REST_GAP, vel=None,
            shear=0.0, device="cpu"):
    """A square patch lying on a plane tilted by theta about y (downhill: -x of the tilted frame), away from the
    plane's diagonal edge (where edge-edge pairs would add to the vertex-face ones)."""
    R = rotation_y(math.radians(theta_deg))
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_obstacle_plane((4.0, 4.0), rot=R)
    mesh = wc.grid_mesh(res, res, size, size)
    jitter = np.random.default_rng(7).uniform(-shear, shear, (len(mesh.positions), 3)) * [1.0, 1.0, 0.0]
    mesh.positions = (mesh.positions + jitter + [0.5 - size / 2, 1.2 - size / 2, gap]) @ R.T
    if vel is not None:
        mesh.velocities = np.tile(np.asarray(vel, dtype=np.float64), (len(mesh.positions), 1))
    b.add_cloth_mesh(mesh, material=MATERIAL)
    b.set_collision(friction=mu, obstacle_friction=mu)
    return b.finalize(device, dtype=dtype, requires_grad=requires_grad), R


def downhill_travel(theta_deg, mu, steps=100, dt=0.01):
    model, R = incline(theta_deg, mu)
    sim = wc.Simulator(model, dt)
    traj = wc.rollout(sim, model.state(), steps=steps)
    com = np.array([s.particle_x.numpy().mean(axis=0) for s in traj])
    return (com - com[0]) @ (R @ np.array([-1.0, 0.0, 0.0])), sim


def test_patch_below_the_friction_angle_stays_put():
    # atan(0.3) = 16.7 degrees: at 10 degrees static friction holds the patch
    travel, sim = downhill_travel(10.0, 0.3)
    assert sim.proximity.last_count > 0
    assert abs(travel[-1]) < 1.0e-3, f"the patch moved {travel[-1] * 1e3:.3f} mm in 1 s"
    # and without friction it slides: the test can fail
    assert downhill_travel(10.0, 0.0)[0][-1] > 0.1


@pytest.mark.parametrize("fabric", wc.PRESET_NAMES)
def test_static_friction_holds_every_fabric_at_every_size_and_time_step(fabric):
    # 12 degrees, mu 0.3 (friction angle 16.7 degrees): the friction impulse stops every pair exactly, so nothing
    # creeps. Before it was a damper regularised below 1e-4 m/s, and a 0.2 m denim patch slid 4.7 mm in 1 s at 9
    # degrees (dt 0.005).
    theta = math.radians(12.0)
    R = rotation_y(theta)
    for size in (0.1, 0.3):
        for dt in (1.0 / 1000.0, 1.0 / 200.0, 1.0 / 50.0):
            b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
            b.add_obstacle_plane((4.0, 4.0), rot=R)
            mesh = wc.grid_mesh(4, 4, size, size)
            mesh.positions = (mesh.positions + [0.5 - size / 2, 1.2 - size / 2, 0.0049]) @ R.T
            b.add_cloth_mesh(mesh, material=wc.preset(fabric, thicken=2))
            b.set_collision(friction=0.3, obstacle_friction=0.3)
            model = b.finalize("cpu")
            sim = wc.Simulator(model, dt)
            start = model.state()
            end = wc.rollout(sim, start, steps=round(1.0 / dt))[-1]
            assert sim.proximity.last_count >= model.particle_count
            moved = (end.particle_x.numpy() - start.particle_x.numpy()) @ (R @ np.array([-1.0, 0.0, 0.0]))
            assert np.abs(moved).max() < 1.0e-3, f"{size} m patch at dt {dt:g}: slid {moved.max() * 1e3:.3f} mm in 1 s"


def test_a_pair_that_friction_stops_stays_stopped():
    # a patch resting in the repulsion layer of a level plane, launched at 0.3 m/s: friction decelerates it at
    # mu g, it stops after 0.3 / (mu g) = 0.10 s, and then stays put (no reversal, no jitter)
    mu, v0, dt = 0.3, 0.3, 0.005
    model, _ = incline(0.0, mu, vel=(v0, 0.0, 0.0))
    traj = wc.rollout(wc.Simulator(model, dt), model.state(), steps=60)
    vx = np.array([s.particle_v.numpy()[:, 0] for s in traj])
    assert vx.min() >= -1e-12, "friction reversed the motion"
    sliding = vx.mean(axis=1) > mu * G * dt  # steps whose end the patch still slides into
    deceleration = -np.diff(vx.mean(axis=1))[sliding[1:]][2:] / dt  # after two steps settling in the layer
    np.testing.assert_allclose(deceleration, mu * G, rtol=0.01)
    t_stop = v0 / (mu * G)
    stopped = np.arange(len(traj)) * dt > t_stop + dt
    assert np.abs(vx[stopped]).max() < 1e-12  # stopped, to rounding


@pytest.mark.parametrize("theta", [25.0, 40.0])
def test_patch_above_the_friction_angle_slides_with_the_closed_form_acceleration(theta):
    mu, dt = 0.3, 0.01
    travel, _ = downhill_travel(theta, mu, steps=60, dt=dt)  # 0.6 s: it stays clear of the plane's diagonal
    t = np.arange(len(travel)) * dt
    a = 2.0 * np.polyfit(t[10:], travel[10:], 2)[0]  # after the first contact transient
    expected = G * (math.sin(math.radians(theta)) - mu * math.cos(math.radians(theta)))
    assert a == pytest.approx(expected, rel=0.05)


def test_resting_contact_keeps_the_gap_without_jitter():
    model, R = incline(0.0, 0.3, gap=0.02)  # dropped from 2 cm onto a level plane
    sim = wc.Simulator(model, 0.01)
    traj = wc.rollout(sim, model.state(), steps=150)
    z = traj[-1].particle_x.numpy()[:, 2]
    speeds = [np.abs(s.particle_v.numpy()).max() for s in traj[100:]]
    assert max(speeds) < 1.0e-3, f"resting cloth still moves at {max(speeds) * 1e3:.3f} mm/s"
    thickness = model.collision.repulsion_thickness
    assert np.all(z > 0.8 * thickness) and np.all(z < thickness), z  # inside the repulsion layer, not on the plane


@pytest.mark.parametrize("integrator", ["euler", "bdf2"])
def test_cloth_dropped_on_a_sphere_with_friction_stays_on_it(integrator):
    def drop(mu):
        b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
        b.add_cloth_grid((10, 10), (0.6, 0.6), material=wc.preset("gray-interlock", thicken=2),
                         pos=(-0.22, -0.3, 0.32))  # off centre: it would slide off without friction
        b.add_obstacle_sphere(0.3, subdivisions=3)
        b.set_collision(obstacle_friction=mu)
        model = b.finalize("cpu")
        sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(integrator=integrator))
        traj = wc.rollout(sim, model.state(), steps=150)
        return traj[-1].particle_x.numpy()

    x = drop(0.3)
    assert x[:, 2].max() > 0.3 and np.linalg.norm(x.mean(axis=0)[:2]) < 0.15, "the cloth slid off the sphere"
    radius = np.linalg.norm(x, axis=1)
    assert radius.min() > 0.3 - 0.02  # nothing went through (the icosphere's facets lie within 1.5 cm)
    y = drop(0.0)
    assert np.linalg.norm(y.mean(axis=0)[:2]) > np.linalg.norm(x.mean(axis=0)[:2]) + 0.05  # frictionless slides


@pytest.mark.parametrize("push", [0.5, 2.0])
def test_sheet_dragged_over_a_sheet_feels_mu_times_its_load(push):
    # a patch on a pinned sheet, pushed along x with m (mu g + push): friction mu m g leaves push. At 2 m/s^2 it
    # slides at up to 1.2 m/s, edge crossings appear and vanish within a step (the damper-regularised friction felt
    # 1.10 mu load there)
    mu = 0.6
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_cloth_grid((8, 8), (1.0, 0.4), material=MATERIAL, pos=(-0.5, -0.2, 0.0))
    for p in range(81):
        b.add_pin(p)
    b.add_cloth_grid((3, 3), (0.1, 0.1), material=MATERIAL, pos=(-0.3, -0.0513, REST_GAP))
    b.set_collision(self_collision=True, friction=mu)
    model = b.finalize("cpu", dtype=wp.float64)
    control = model.control(particle_force=True)
    force = np.zeros((model.particle_count, 3))
    force[81:, 0] = model.particle_mass()[81:] * (mu * G + push)
    control.particle_force.assign(force)
    traj = wc.rollout(wc.Simulator(model, 0.01), model.state(), control, steps=60)
    x = np.array([s.particle_x.numpy()[81:, 0].mean() for s in traj])
    t = np.arange(len(x)) * 0.01
    a = 2.0 * np.polyfit(t[10:], x[10:], 2)[0]
    friction = mu * G + push - a
    assert friction == pytest.approx(mu * G, rel=0.02)


def test_system_with_pairs_matches_a_dense_solve():
    model, _ = incline(20.0, 0.3, res=3, vel=(0.05, 0.02, 0.0))
    sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(cg_tol=1e-13, cg_atol=1e-30))
    state = model.state()
    A, b = sim.dense_system(state)
    assert sim.proximity.last_count > 0
    np.testing.assert_allclose(A, A.T, atol=1e-12 * np.abs(A).max())
    assert np.linalg.eigvalsh(A).min() > 0.0
    nxt = model.empty_state()
    sim.step(state, nxt)
    np.testing.assert_allclose(nxt.particle_dv.numpy().reshape(-1), np.linalg.solve(A, b), rtol=1e-9,
                               atol=1e-12)


def two_sheets_on_a_plane():
    """A free 0.3 m sheet resting on a plane and a free 0.1 m patch sliding on it: cloth-cloth pairs between free
    particles, whose cross blocks the solver applies matrix-free."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_obstacle_plane((2.0, 2.0))
    b.add_cloth_grid((6, 6), (0.3, 0.3), material=MATERIAL, pos=(-0.15, -0.15, REST_GAP))
    b.add_cloth_grid((3, 3), (0.1, 0.1), material=MATERIAL, pos=(-0.0513, -0.0487, 2.0 * REST_GAP),
                     vel=(0.05, 0.02, 0.0))
    b.set_collision(self_collision=True)
    return b.finalize("cpu", dtype=wp.float64, requires_grad=True)


@pytest.mark.parametrize("backend", ["sequential", "warp"])
def test_cross_blocks_of_cloth_cloth_pairs_match_a_dense_solve(backend):
    # the warp backend (warp.optim.linear.cg, the CUDA path) applies them in a LinearOperator
    model = two_sheets_on_a_plane()
    sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(cg_tol=1e-13, cg_atol=1e-30, cg_backend=backend))
    state = model.state()
    A, b = sim.dense_system(state)
    assert sim.proximity.last_count > 0
    n = model.particle_count
    blocks = np.abs(A.reshape(n, 3, n, 3)).sum(axis=(1, 3)) > 0
    pattern = np.zeros((n, n), dtype=bool)
    rows = np.repeat(np.arange(n), np.diff(model.bsr_offsets.numpy()))
    pattern[rows, model.bsr_columns.numpy()] = True
    assert np.any(blocks & ~pattern), "no cross block outside the pattern: the test would not test them"
    nxt = model.empty_state()
    sim.step(state, nxt)
    np.testing.assert_allclose(nxt.particle_dv.numpy().reshape(-1), np.linalg.solve(A, b), rtol=1e-9, atol=1e-12)


def test_warp_backend_gradients_equal_the_sequential_ones_with_pairs():
    # Both with block Jacobi: the third step is near a kink of the contact response. At cg_tol 1e-13 the multigrid's
    # solution lands on its other side and its gradient differs from block Jacobi's by 2e-9 (by < 1e-10 at cg_tol
    # 1e-11 and 1e-14), so only the same preconditioner on both backends tests the backends at 1e-8.
    grads = {}
    for backend in ("sequential", "warp"):
        model = two_sheets_on_a_plane()
        sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(cg_tol=1e-13, cg_atol=1e-30, cg_backend=backend,
                                                                 preconditioner="block_jacobi"))
        state = model.state()
        tape = wp.Tape()
        with tape:
            final = wc.rollout(sim, state, steps=3)[-1]
        tape.backward(grads={final.particle_x: wp.array(np.ones((model.particle_count, 3)), dtype=wp.vec3d)})
        grads[backend] = (state.particle_v.grad.numpy().copy(), model.contact_friction.grad.numpy().copy())
        assert sim.proximity.last_count > 0
    for a, b in zip(grads["sequential"], grads["warp"]):
        np.testing.assert_allclose(b, a, rtol=1e-8, atol=1e-12 * np.abs(a).max())


@pytest.mark.parametrize("integrator", ["euler", "bdf2"])
def test_cloth_lying_exactly_on_an_obstacle_is_repelled_not_nan(integrator):
    # Every cloth vertex on the plane (gap 0) and cloth edges crossing the plane's edges in its plane: the pairs'
    # gaps have no direction. Before, n = gap / |gap| made the forces NaN (found as BDF2's blend crossed a sphere's
    # edge in benchmarks/tradeoff.py); now the normal comes from the primitives, against the approach.
    def build(stiffness):
        b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
        b.add_cloth_grid((4, 4), (0.2, 0.2), material=MATERIAL, pos=(-0.1, -0.1, 0.0), vel=(0.0, 0.0, -0.1))
        b.add_obstacle_plane((1.0, 1.0))
        b.set_collision(repulsion_stiffness=stiffness)
        return b.finalize("cpu", dtype=wp.float64)

    rhs = {}
    for stiffness in (0.0, 1.0e6):
        model = build(stiffness)
        sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(integrator=integrator))
        _, b, pairs = sim.assemble(model.state())
        rhs[stiffness] = b.numpy()
        assert np.all(np.isfinite(rhs[stiffness]))
    assert pairs.count > 0 and sim.proximity.last_count == pairs.count
    push = rhs[1.0e6] - rhs[0.0]
    # every particle is pushed up, out of the plane, with the force of a full thickness of overlap
    assert np.all(push[:, 2] > 0.0)
    np.testing.assert_allclose(push[:, :2], 0.0, atol=1e-12 * np.abs(push).max())
    # the projection cannot push a sheet that starts on the plane a thickness away (no side to push it to); its
    # second try keeps the start gaps (the sheet may not sink further) and lets the repulsion lift it: after one
    # such step it rests in the repulsion layer
    first = model.empty_state()
    sim.step(model.state(), first)
    report = sim.collision.last
    assert "started the step 0 m apart, inside the collision thickness" in report.kept_start_gaps
    assert report.fail_safe is None
    traj = wc.rollout(sim, first, steps=50)
    z = traj[-1].particle_x.numpy()[:, 2]
    thickness = model.collision.repulsion_thickness
    assert np.all(z > 0.8 * thickness) and np.all(z < thickness), z


def test_zero_stiffness_costs_nothing_and_overflow_names_the_capacity():
    model, _ = incline(10.0, 0.3)
    assert wc.Simulator(model, 0.01).proximity is not None
    b = wc.ModelBuilder()
    b.add_cloth_grid((2, 2), (0.1, 0.1), material=MATERIAL, pos=(-0.05, -0.05, REST_GAP))
    b.add_obstacle_plane((1.0, 1.0))
    b.set_collision(repulsion_stiffness=0.0)
    assert wc.Simulator(b.finalize("cpu"), 0.01).proximity is None
    sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(collision=wc.CollisionOptions(contact_capacity=3)))
    with pytest.raises(wc.CollisionError, match="contact_capacity to at least"):
        sim.step(model.state(), model.empty_state())


@pytest.mark.parametrize("dtype", [wp.float32, wp.float64])
def test_pairs_are_found_out_to_the_search_radius_and_no_further(dtype, device):
    """Pairs at a gap just inside twice the repulsion thickness are found, none just outside it: a square patch over
    a plane (its four vertices over the plane's face: vertex-face pairs), and two strips crossing like a "+", one
    above the other (their edges cross, no vertex lies over a face: edge-edge pairs). The queries' boxes are grown
    by float32 rounding only and the targets' by the radius (kernels/proximity.py primitive_boxes), so a pair just
    inside the radius is what a box too small would miss."""
    radius = 2.0 * 5.0e-3  # twice the default repulsion thickness

    def patch_over_plane(b, gap):
        b.add_cloth_grid((1, 1), (0.1, 0.1), material=MATERIAL, pos=(0.05, 0.07, gap))
        b.add_obstacle_plane((1.0, 1.0), pos=(0.1, 0.1, 0.0))
        b.set_collision()

    def crossing_strips(b, gap):
        b.add_cloth_grid((1, 1), (0.2, 0.02), material=MATERIAL, pos=(-0.1, -0.01, 0.0))
        b.add_cloth_grid((1, 1), (0.02, 0.2), material=MATERIAL, pos=(-0.01, -0.1, gap))
        b.set_collision(self_collision=True)

    for scene, expected in ((patch_over_plane, 4), (crossing_strips, 4)):
        counts = []
        for gap in (radius * (1.0 - 1e-3), radius * (1.0 + 1e-3)):
            b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
            scene(b, gap)
            sim = wc.Simulator(b.finalize(device, dtype=dtype), 0.01)
            counts.append(sim.assemble(sim.model.state())[2].count)
        assert counts[0] >= expected and counts[1] == 0, (scene.__name__, counts)


@wp.kernel
def _linear_loss(x: wp.array(dtype=wp.vec3d), v: wp.array(dtype=wp.vec3d), cx: wp.array(dtype=wp.vec3d),
                 cv: wp.array(dtype=wp.vec3d), loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(x[i], cx[i]) + wp.dot(v[i], cv[i]))


def gradient_check(model, steps, dt, perturbations, *, eps=(1e-6, 1e-7), rtol=1e-4, integrator="euler"):
    """Tape gradient of a random linear loss of the final state against central differences, along each
    perturbation ``(name, array getter, direction)``; the differences at both step sizes must agree."""
    sim = wc.Simulator(model, dt, options=wc.SolverOptions(cg_tol=1e-13, cg_atol=1e-30, integrator=integrator))
    rng = np.random.default_rng(4)
    n = model.particle_count
    cx = wp.array(rng.standard_normal((n, 3)), dtype=wp.vec3d, device=model.device)
    cv = wp.array(1e-2 * rng.standard_normal((n, 3)), dtype=wp.vec3d, device=model.device)

    def run(state=None, control=None, tape=None):
        state = state or model.state()
        out = wp.zeros(1, dtype=wp.float64, device=model.device, requires_grad=True)
        with tape or _null():
            final = wc.rollout(sim, state, control, steps=steps)[-1]
            wp.launch(_linear_loss, n, inputs=[final.particle_x, final.particle_v, cx, cv], outputs=[out])
        return out

    state, control = model.state(), model.control()
    tape = wp.Tape()
    out = run(state, control, tape)
    tape.backward(out)
    arrays = {"x0": state.particle_x, "v0": state.particle_v, "stiffness": model.contact_repulsion_stiffness,
              "friction": model.contact_friction, "transform": control.obstacle_transform}
    grads = {name: a.grad.numpy().copy() for name, a in arrays.items() if a is not None}
    tape.zero()
    results = {}
    for name, direction in perturbations:
        analytic = float(np.sum(np.asarray(grads[name], dtype=np.float64) * direction))
        fds = []
        for h in eps:
            values = []
            for sign in (1.0, -1.0):
                st, ctl = model.state(), model.control()
                target = {"x0": st.particle_x, "v0": st.particle_v, "transform": ctl.obstacle_transform}.get(name)
                if target is None:
                    target = arrays[name]
                base = target.numpy().copy()
                target.assign(base + sign * h * direction.reshape(base.shape))
                values.append(float(run(st, ctl).numpy()[0]))
                target.assign(base)
            fds.append((values[0] - values[1]) / (2.0 * h))
        # the loss's rounding (~1e-15) over 2h = 2e-7 puts a floor of about 5e-9 under the smaller step's difference
        noise = 1e-8
        scale = max(abs(fds[0]), 1e-12)
        assert abs(fds[0] - fds[1]) <= rtol * scale + noise, f"{name}: central differences do not converge {fds}"
        assert abs(analytic - fds[0]) <= rtol * scale, f"{name}: tape {analytic:.9e} vs differences {fds}"
        results[name] = (analytic, fds)
    return results, sim


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def directions(model, rng):
    n = model.particle_count
    return [("x0", 1e-3 * rng.standard_normal((n, 3))), ("v0", rng.standard_normal((n, 3))),
            ("stiffness", np.array([1e6])), ("friction", np.array([0.0, 1.0])),
            ("transform", np.array([[1e-3, -2e-3, 1e-3, 0.0, 0.0, 0.0, 0.0]]))]


@pytest.mark.parametrize("theta, regime", [(10.0, "resting"), (30.0, "sliding")])
def test_cloth_obstacle_gradients_match_central_differences(theta, regime, device):
    # sheared a little: at zero shear the stretching lookup has a kink (see the cloth-cloth test)
    model, _ = incline(theta, 0.3, res=2, requires_grad=True, vel=(0.02, 0.01, 0.0), shear=5e-4, device=device)
    results, sim = gradient_check(model, 6, 0.01, directions(model, np.random.default_rng(1)))
    assert sim.proximity.last_count > 0
    assert all(abs(r[0]) > 0 for r in results.values())


def test_bdf2_repulsion_and_friction_gradients_match_central_differences(device):
    # BDF2's pairs: penalty and friction blocks over its 2/3 dt implicit step, found at its blend
    model, _ = incline(30.0, 0.3, res=2, requires_grad=True, vel=(0.02, 0.01, 0.0), shear=5e-4, device=device)
    results, sim = gradient_check(model, 6, 0.01, directions(model, np.random.default_rng(1)), integrator="bdf2")
    assert sim.proximity.last_count > 0
    assert all(abs(r[0]) > 0 for r in results.values())


def test_cloth_landing_on_a_sphere_gradients_match_central_differences(device):
    # a curved obstacle: an 8x8 cloth lands on a sphere and wraps it for 10 steps (~160 pairs at the end). Longer
    # horizons stop being smooth here: by step 20 pairs appearing and stick/slip switches make dL/d(density) ~1e3
    # and central differences no longer converge (README, contact's known gaps).
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    # sheared and bent a little: off the stretching lookup's kink at zero shear (as above) and the bending lookup's
    # at zero curvature (a flat hinge), where central differences average two one-sided derivatives (1e-4 off here)
    mesh = wc.grid_mesh(8, 8, 0.6, 0.6)
    jitter = np.random.default_rng(7).uniform(-5e-4, 5e-4, mesh.positions.shape) * [1.0, 1.0, 0.3]
    mesh.positions = mesh.positions + jitter + [-0.31, -0.29, 0.31]
    b.add_cloth_mesh(mesh, material=wc.preset("gray-interlock", thicken=2))
    b.add_obstacle_sphere(0.3, 3)
    model = b.finalize(device, requires_grad=True, dtype=wp.float64)
    n = model.particle_count
    rng = np.random.default_rng(2)
    results, sim = gradient_check(model, 10, 0.01, [("x0", 1e-2 * rng.standard_normal((n, 3))),
                                                    ("friction", np.array([0.0, 1.0])),
                                                    ("transform", np.array([[1e-3, -2e-3, 1e-3, 0, 0, 0, 0.0]]))])
    assert sim.proximity.last_count > 100


@pytest.mark.parametrize("regime, mu, vel", [("sliding, frictionless", 0.0, (0.03, 0.01, 0.0)),
                                              ("sliding, friction", 0.6, (0.03, 0.01, 0.0)),
                                              ("resting, friction", 0.6, (0.0, 0.0, 0.0))])
def test_cloth_cloth_gradients_match_central_differences(regime, mu, vel, device):
    # a small free sheet on a larger pinned one, under gravity: cloth-cloth vertex-face and edge-edge pairs
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_cloth_grid((2, 2), (0.2, 0.2), material=MATERIAL, pos=(-0.1, -0.1, 0.0))
    # placed so that no edge crossing sits on a kink of the edge-edge fade (kernels/proximity.py EDGE_FADE), and
    # sheared a little in its plane: at zero shear the stretching lookup (|G01|) has a kink where central differences
    # average two one-sided derivatives (tests/test_gradients.py)
    mesh = wc.grid_mesh(1, 1, 0.04, 0.04)
    jitter = np.random.default_rng(7).uniform(-4e-4, 4e-4, (len(mesh.positions), 3)) * [1.0, 1.0, 0.0]
    mesh.positions = mesh.positions + jitter + [-0.0313, -0.0217, REST_GAP]
    mesh.velocities = np.tile(np.asarray(vel, dtype=np.float64), (len(mesh.positions), 1))
    b.add_cloth_mesh(mesh, material=MATERIAL)
    for p in range(9):
        b.add_pin(p)
    b.set_collision(self_collision=True, friction=mu)
    model = b.finalize(device, dtype=wp.float64, requires_grad=True)
    rng = np.random.default_rng(2)
    n = model.particle_count
    results, sim = gradient_check(model, 5, 0.01, [("x0", 1e-3 * rng.standard_normal((n, 3))),
                                                   ("v0", rng.standard_normal((n, 3))),
                                                   ("stiffness", np.array([1e6]))])
    assert sim.proximity.last_count > 0


def test_scene_collision_table_sets_repulsion_and_friction():
    from warpcloth.scene import scene_from_toml

    text = """
name = "t"
[sim]
dt = 0.01
steps = 1
[cloth]
grid = { res = [2, 2], size = [0.1, 0.1] }
material = "gray-interlock"
[[obstacles]]
shape = "plane"
[collision]
repulsion_thickness = 2e-3
repulsion_stiffness = 5e5
friction = 0.4
obstacle_friction = 0.2
"""
    model, _ = scene_from_toml(text).build("cpu")
    assert model.collision.repulsion_thickness == 2e-3
    np.testing.assert_allclose(model.contact_repulsion_stiffness.numpy(), [5e5])
    np.testing.assert_allclose(model.contact_friction.numpy(), [0.4, 0.2], rtol=1e-6)
    with pytest.raises(ValueError, match="collision.friction"):
        scene_from_toml(text.replace("friction = 0.4", "friction = -1.0"))


def _cloth_on_a_box(scale, dtype, self_collision):
    """A 0.6 m camel-ponte-roma sheet (8x8) dropped from 5 cm onto a 0.4 m box with friction 0.4: it lands, drapes
    over the edges and comes to rest."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_cloth_grid((8, 8), (0.6, 0.6), material=wc.preset("camel-ponte-roma", thicken=2), pos=(-0.3, -0.3, 0.25))
    b.add_obstacle_box((0.2, 0.2, 0.2))
    b.set_collision(obstacle_friction=0.4, self_collision=self_collision)
    model = b.finalize("cpu", dtype=dtype, requires_grad=True)
    model.material_density.assign(model.material_density.numpy() * scale)
    return model


@pytest.mark.slow
@pytest.mark.parametrize("dtype, self_collision", [(wp.float64, False), (wp.float32, False), (wp.float32, True)])
def test_gradients_through_long_resting_contact_stay_bounded(dtype, self_collision):
    # d(mean height)/d(log density) of the resting sheet. With friction a stiff damper (regularised below 1e-4
    # m/s) the tape gave 3.3e3, 1.1e3 and 1.4e12 after 100, 200 and 400 steps of the 16x16 sheet (central
    # differences 0.08 to 6.6), and the float32 backward with self-collision raised at step 16; sticking friction
    # is exact and its derivative moves the particle with its contact point. Central differences at large relative
    # steps (1e-2, 1e-3): the resting state's small contact events make smaller steps meaningless.
    def height(steps, scale, grad=False):
        model = _cloth_on_a_box(scale, dtype, self_collision)
        sim = wc.Simulator(model, 0.01)
        tape = wp.Tape()
        with tape:
            final = wc.rollout(sim, model.state(), steps=steps)[-1]
        z = float(final.particle_x.numpy()[:, 2].astype(np.float64).mean())
        if not grad:
            return z
        seed = np.zeros((model.particle_count, 3))
        seed[:, 2] = 1.0 / model.particle_count
        tape.backward(grads={final.particle_x: wp.array(seed, dtype=final.particle_x.dtype)})
        speed = max(np.abs(final.particle_v.numpy()).max(), 0.0)
        return z, float(model.material_density.grad.numpy()[0] * model.material_density.numpy()[0]), speed

    for steps in (100, 300, 700):
        _, tape_value, speed = height(steps, 1.0, grad=True)
        fds = [(height(steps, math.exp(h)) - height(steps, math.exp(-h))) / (2 * h) for h in (1e-2, 1e-3)]
        assert math.isfinite(tape_value)
        # bounded by the differences, and not vanishing against them (they scatter over a factor 10 between the
        # two steps: the resting sheet's contacts switch)
        assert 0.1 * min(map(abs, fds)) <= abs(tape_value) <= 10.0 * max(map(abs, fds)), \
            f"{steps} steps: tape {tape_value:.3g}, central differences {fds}"
    assert speed < 0.05  # at rest by then (m/s)


def test_friction_set_after_the_simulator_is_built_is_used():
    # a frictionless model's Simulator launches nothing for friction; a coefficient set afterwards is seen
    model, R = incline(10.0, 0.0)
    sim = wc.Simulator(model, 0.01)
    model.contact_friction.assign(np.array([0.3, 0.3]))
    traj = wc.rollout(sim, model.state(), steps=50)
    travel = (traj[-1].particle_x.numpy() - traj[0].particle_x.numpy()).mean(axis=0) @ (R @ [-1.0, 0.0, 0.0])
    assert abs(travel) < 1e-6  # held (frictionless, it slides about 2 cm in 0.5 s)
