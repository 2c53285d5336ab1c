"""Physical checks of the implicit Euler step: closed forms, rest, pins, energy, handle sag (float64)."""

import numpy as np
import pytest
import warp as wp
from conftest import VERTICAL, hanging_builder, top_corners

import warpcloth as wc

TIGHT = wc.SolverOptions(cg_tol=1.0e-12, cg_max_iters=2000)


def run(model, dt, steps, *, control=None, state=None):
    sim = wc.Simulator(model, dt, options=TIGHT)
    traj = wc.rollout(sim, state if state is not None else model.state(), control, steps=steps)
    return sim, traj


def test_free_fall_matches_implicit_euler_closed_form():
    # A flat, unstretched cloth moving rigidly feels no internal force (and H v = 0 for a uniform v), so every
    # particle follows implicit Euler exactly: v_n = v0 + n dt g, x_n = x0 + n dt v0 + dt^2 g n (n + 1) / 2.
    g = np.array([0.0, 0.0, -9.8])
    v0 = np.array([0.3, -0.2, 1.5])
    dt, steps = 0.02, 25
    b = wc.ModelBuilder(gravity=g)
    b.add_cloth_grid((4, 4), (0.5, 0.5), material=wc.preset("gray-interlock", thicken=2), pos=(-0.25, -0.25, 1.0),
                     vel=v0)
    model = b.finalize("cpu", dtype=wp.float64)
    x0 = model.particle_x0.numpy()
    _, traj = run(model, dt, steps)
    for n, state in enumerate(traj):
        x, v = state.numpy()
        x_ref = x0 + n * dt * v0 + dt * dt * g * n * (n + 1) / 2.0
        v_ref = np.broadcast_to(v0 + n * dt * g, v.shape)
        np.testing.assert_allclose(x, x_ref, rtol=0.0, atol=1.0e-9 * np.max(np.abs(x_ref)), err_msg=f"x, step {n}")
        np.testing.assert_allclose(v, v_ref, rtol=0.0, atol=1.0e-9 * np.max(np.abs(v_ref)), err_msg=f"v, step {n}")
    assert traj[-1].time == pytest.approx(steps * dt)


@pytest.fixture(scope="module")
def damped_hanging():
    """A 4x4 cloth hanging from two soft handles (k = 100 N/m) with mass damping, 120 steps of 0.02 s from rest."""
    k = 100.0
    b = hanging_builder(wind=None, gravity=(0.0, 0.0, -9.8), handle_stiffness=k)
    b.set_damping(mass=8.0)
    model = b.finalize("cpu", dtype=wp.float64)
    sim, traj = run(model, 0.02, 120)
    kinetic = np.array([sim.energy(s)["kinetic"] for s in traj])
    return model, traj, kinetic, k


def test_damped_hanging_cloth_comes_to_rest(damped_hanging):
    model, traj, kinetic, _ = damped_hanging
    peak = kinetic.max()
    assert peak > 1.0e-4  # it did swing
    # it swings with a period of ~5.5 steps and loses ~10x per period, down to round-off (~1e-24 J) by step ~100
    assert kinetic[-1] < 1.0e-15 * peak, f"kinetic energy {kinetic[-1]:.3e} J after 2.4 s (peak {peak:.3e} J)"
    windows = kinetic[10:100].reshape(-1, 10).max(axis=1)  # each 10-step window's peak below the previous one's
    assert np.all(np.diff(windows) < 0.0), windows
    assert np.max(np.abs(traj[-1].particle_v.numpy())) < 1.0e-6


def test_soft_handles_carry_the_weight(damped_hanging):
    # At rest the internal forces cancel, so the handles' vertical forces sum to the weight: k * sum(dz) = M g.
    # By symmetry each handle sags by M g / (2 k) (here ~4.6 mm), exactly in the limit of rest.
    model, traj, _, k = damped_hanging
    handles = model.handle_particle.numpy()
    x = traj[-1].particle_x.numpy()
    sag = model.handle_rest_target[:, 2] - x[handles, 2]
    mass = model.particle_mass().sum()
    expected = mass * 9.8 / (2.0 * k)
    np.testing.assert_allclose(sag, expected, rtol=1.0e-6)
    np.testing.assert_allclose(mass, 0.25 * 0.187 * 2)  # area x gray-interlock density x thicken


def test_static_and_moving_pins_follow_their_targets():
    res, dt, steps = 4, 0.01, 30
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    b.add_cloth_grid((res, res), (0.5, 0.5), material=wc.preset("gray-interlock", thicken=2), rot=VERTICAL,
                     pos=(0.0, 0.0, -0.5))
    b.set_wind((0.0, 3.0, 0.0))
    left, right = top_corners(res)
    keys = [(0.0, (0.0, 0.0, 0.0)), (0.1, (0.05, 0.1, 0.0)), (0.2, (0.05, 0.1, 0.08))]
    b.add_pin(left)
    b.add_pin(right, motion=keys)
    model = b.finalize("cpu", dtype=wp.float64)
    x0 = model.particle_x0.numpy()
    _, traj = run(model, dt, steps)
    times = np.array([t for t, _ in keys])
    offsets = np.array([o for _, o in keys])
    previous = x0[right]
    for n, state in enumerate(traj[1:], start=1):
        x, v = state.numpy()
        np.testing.assert_allclose(x[left], x0[left], rtol=0.0, atol=1.0e-12, err_msg=f"static pin, step {n}")
        np.testing.assert_allclose(v[left], 0.0, rtol=0.0, atol=1.0e-10, err_msg=f"static pin, step {n}")
        target = x0[right] + np.array([np.interp(n * dt, times, offsets[:, d]) for d in range(3)])
        np.testing.assert_allclose(x[right], target, rtol=0.0, atol=1.0e-12, err_msg=f"moving pin, step {n}")
        np.testing.assert_allclose(v[right], (target - previous) / dt, rtol=0.0, atol=1.0e-9)
        previous = target
    # the rest of the cloth did move (gravity and wind act on it)
    assert np.max(np.abs(traj[-1].particle_x.numpy() - x0)) > 0.05


def stretched_free_cloth(material, dt=0.002, steps=100):
    """A free cloth (no gravity, handles, wind or damping) released from a 1.2x stretch along x, with a kink."""
    res = 4
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_cloth_grid((res, res), (0.5, 0.5), material=material)
    model = b.finalize("cpu", dtype=wp.float64)
    x = model.particle_x0.numpy() * np.array([1.2, 1.0, 1.0])
    x[:, 2] += 0.05 * np.sin(np.pi * x[:, 0] / 0.6)  # out of plane, so bending is loaded too
    state = model.state()
    state.particle_x.assign(x)
    sim, traj = run(model, dt, steps, state=state)
    return sim, traj


def test_unforced_isotropic_cloth_gains_no_energy():
    # Constant tables make sim.energy the exact potential; implicit Euler must not add energy. dt = 2 ms keeps its
    # numerical dissipation mild (the first step loses ~11%, later ones < 1%), so a spurious gain would show.
    material = wc.Material.isotropic(density=0.2, stretch_stiffness=60.0, shear_stiffness=20.0,
                                     bend_stiffness=1.0e-4)
    sim, traj = stretched_free_cloth(material)
    total = np.array([sim.energy(s)["total"] for s in traj])
    e0 = sim.energy(traj[0])
    assert e0["stretching"] > 0.1 and e0["bending"] > 0.0 and e0["kinetic"] == 0.0
    increase = np.diff(total)
    assert np.all(increase <= 1.0e-9 * total[0]), f"energy rose by {increase.max():.3e} J (E0 = {total[0]:.3e} J)"
    assert total[-1] < total[0]  # it does move and dissipate


def test_unforced_anisotropic_cloth_stays_bounded():
    sim, traj = stretched_free_cloth(wc.preset("gray-interlock", thicken=2))
    total = np.array([sim.energy(s)["total"] for s in traj])
    assert np.all(np.isfinite(total))
    # the preset's energy is only approximate (stiffness looked up at the current strain), so allow slack
    assert total.max() <= 1.05 * total[0], total
    x = traj[-1].particle_x.numpy()
    assert np.all(np.isfinite(x)) and np.ptp(x[:, 0]) < 1.0


def test_two_materials_in_one_model_behave_like_separate_models():
    # two cloths far apart, each with its own material: one model must give each the trajectory it has alone
    dense, light = wc.preset("11oz-black-denim", thicken=2), wc.preset("tango-red-jet-set", thicken=2)

    def add(builder, material, offset):
        first = builder.add_cloth_grid((3, 3), (0.3, 0.3), material=material, rot=VERTICAL,
                                       pos=(offset, 0.0, -0.3))
        builder.add_handle(first + 12)
        builder.add_handle(first + 15)
        return first

    both = wc.ModelBuilder()
    add(both, dense, 0.0)
    second = add(both, light, 5.0)
    model = both.finalize("cpu", dtype=wp.float64)
    assert model.material_count == 2
    x_both = wc.rollout(wc.Simulator(model, 0.02), model.state(), steps=5)[-1].particle_x.numpy()
    for material, offset, rows in ((dense, 0.0, slice(0, second)), (light, 5.0, slice(second, None))):
        alone = wc.ModelBuilder()
        add(alone, material, offset)
        m = alone.finalize("cpu", dtype=wp.float64)
        x_alone = wc.rollout(wc.Simulator(m, 0.02), m.state(), steps=5)[-1].particle_x.numpy()
        np.testing.assert_allclose(x_both[rows], x_alone, atol=1e-9)


def test_absent_components_launch_nothing(monkeypatch):
    import warpcloth.solver.simulator as simulator_module

    launched = []
    real_launch = wp.launch

    def spy(kernel, *args, **kwargs):
        launched.append(kernel.key)
        return real_launch(kernel, *args, **kwargs)

    monkeypatch.setattr(simulator_module.wp, "launch", spy)  # the module object: every wp.launch
    b = wc.ModelBuilder()
    b.add_cloth_grid((3, 3), (0.3, 0.3), material=wc.preset("gray-interlock"))
    model = b.finalize("cpu")
    sim = wc.Simulator(model, 0.01)
    wc.rollout(sim, model.state(), steps=2)
    names = " ".join(launched)
    for absent in ("wind", "handles", "pin_rows", "external_forces", "check_state"):
        assert absent not in names, f"{absent} launched for a scene without it: {launched}"
    # the bare integrator and nothing else: assembly, the one-launch CG and its account in the failure record,
    # the update (with the divergence guard)
    per_step = ["faces", "hinges", "cg_sequential", "account_solve", "integrate"]
    assert [next((k for k in per_step if k in name), name) for name in launched] == per_step * 2, launched
    # and no buffers for what is absent
    assert sim.collision is None and model.collision is None and model.wind_velocity is None
    assert model.handle_count == 0 and model.pin_count == 0


def _wind_sim(lagged, requires_grad=False):
    b = hanging_builder(res=4)
    b.set_wind((0.5, 2.0, 0.0), density=1.0, drag=0.1, lagged_normals=lagged)
    model = b.finalize("cpu", requires_grad=requires_grad, dtype=wp.float64)
    return model, wc.Simulator(model, 0.02, options=wc.SolverOptions(cg_tol=1e-13, cg_atol=1e-30))


def test_lagged_wind_normals_use_the_previous_step_start():
    model, sim = _wind_sim(False)
    current = wc.rollout(sim, model.state(), steps=3)
    model, sim = _wind_sim(True)
    lagged = wc.rollout(sim, model.state(), steps=3)
    # step 1 has no previous step: identical; later steps use the normals of the previous step's start
    np.testing.assert_allclose(lagged[1].particle_x.numpy(), current[1].particle_x.numpy(), atol=1e-14)
    assert np.abs(lagged[2].particle_x.numpy() - current[2].particle_x.numpy()).max() > 1e-7
    # a new rollout with the same simulator starts afresh: no stale positions from the previous trajectory
    again = wc.rollout(sim, model.state(), steps=1)
    np.testing.assert_allclose(again[1].particle_x.numpy(), current[1].particle_x.numpy(), atol=1e-14)


@wp.kernel
def _x_dot_w(x: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(x[i], w[i]))


def test_lagged_wind_normals_gradient_matches_finite_differences():
    # gradients through the lagged normals reach the previous step's positions (here: the initial positions)
    model, sim = _wind_sim(True, requires_grad=True)
    rng = np.random.default_rng(5)
    w = wp.array(rng.standard_normal((model.particle_count, 3)), dtype=wp.vec3d)
    x0 = model.particle_x0.numpy() + 1e-3 * rng.standard_normal((model.particle_count, 3))
    d = rng.standard_normal(x0.shape)

    def loss(x_init, record=False):
        state = model.state(requires_grad=record)
        state.particle_x.assign(x_init)
        out = wp.zeros(1, dtype=wp.float64, requires_grad=record)
        tape = wp.Tape()
        with tape:
            final = wc.rollout(sim, state, steps=4)[-1]
            wp.launch(_x_dot_w, model.particle_count, inputs=[final.particle_x, w], outputs=[out])
        if record:
            tape.backward(out)
            return state.particle_x.grad.numpy()
        return out.numpy()[0]

    eps = 1e-6
    fd = (loss(x0 + eps * d) - loss(x0 - eps * d)) / (2 * eps)
    grad = loss(x0, record=True)
    assert abs(fd) > 1e-3
    assert abs(np.sum(grad * d) - fd) < 1e-5 * abs(fd)
