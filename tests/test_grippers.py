"""Grippers: limits that every parameter vector keeps, gradients with respect to every knot through the grasp, the
flight after the release and the landing on a table, handles switched on and off, and the errors of bad grippers."""

import numpy as np
import pytest
import warp as wp

import warpcloth as wc
from warpcloth.grippers import Gripper
from warpcloth.tasks.grippers import GripperTask


@wp.kernel
def _weighted_sum(x: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(out, 0, wp.dot(w[i], x[i]))


class LinearGoal:
    """sum_i w_i . x_i of the final positions: a goal whose gradient reaches every particle."""

    def __init__(self, model, rng):
        self.w = rng.standard_normal((model.particle_count, 3))
        self._w = wp.array(self.w, dtype=wp.vec3d, device=model.device)

    def add(self, state, out, weight=1.0):
        wp.launch(_weighted_sum, len(self.w), inputs=[state.particle_x, self._w], outputs=[out])

    def measure(self, positions):
        return float(np.sum(self.w * positions))


def line_gripper(**kwargs):
    args = dict(particles=(0, 1, 2), times=[0.0, 0.04, 0.08, 0.12], yaw=[0.0, 0.05, 0.15, 0.2],
                positions=[[0.0, 0.0, 0.0], [0.0, 0.0, 0.01], [0.01, 0.01, 0.03], [0.02, 0.01, 0.04]],
                grasp=0.02, release=0.1, max_speed=1.0, max_acceleration=20.0, max_yaw_rate=3.0,
                max_yaw_acceleration=80.0, stiffness=2000.0, name="line")
    args.update(kwargs)
    return Gripper(**args)


def table_model(gripper=None, *, dtype=wp.float64, table=True):
    """A 0.1 m cloth of 3 x 3 cells 2 cm above a table, held along its first row."""
    b = wc.ModelBuilder()
    b.add_cloth_grid((3, 3), (0.1, 0.1), material=wc.preset("gray-interlock"), pos=(0.0, 0.0, 0.02))
    if table:
        b.add_obstacle_plane((1.0, 1.0), name="table")
        b.set_collision(obstacle_friction=0.4)
    b.add_gripper(gripper or line_gripper())
    return b.finalize(requires_grad=True, dtype=dtype)


def test_limits_hold_for_random_parameters():
    g = line_gripper(times=np.arange(7) * 0.1, positions=np.zeros((7, 3)), yaw=np.zeros(7), max_speed=0.8,
                     max_acceleration=5.0, max_yaw_rate=2.0, max_yaw_acceleration=9.0)
    rng = np.random.default_rng(3)
    t = np.linspace(-0.3, 1.2, 30001)
    dt = t[1] - t[0]
    for trial in range(20):
        p = rng.standard_normal(g.n_params) * (0.5 if trial % 2 else 4.0)  # inside and far outside the limits
        c, yaw = g.frames(p, t)
        v = np.diff(c, axis=0) / dt
        a = np.diff(v, axis=0) / dt
        assert np.linalg.norm(v, axis=1).max() <= 0.8 * (1 + 1e-6), trial
        assert np.linalg.norm(a, axis=1).max() <= 5.0 * (1 + 1e-3), trial
        assert np.abs(np.diff(yaw) / dt).max() <= 2.0 * (1 + 1e-6), trial
        assert np.abs(np.diff(yaw, 2) / dt ** 2).max() <= 9.0 * (1 + 1e-3), trial
        # the control polygon's bounds, which the curve's obey (convex hull)
        P, _ = g.control_points(p)
        assert np.linalg.norm(g.velocity_points(P), axis=1).max() <= 0.8 * (1 + 1e-12)
        assert np.linalg.norm(g.acceleration_points(P), axis=1).max() <= 5.0 * (1 + 1e-12)


def test_default_parameters_reproduce_the_knots():
    g = line_gripper()
    P, yaw = g.control_points(g.default_params())
    np.testing.assert_allclose(P, g.positions, atol=1e-15)
    np.testing.assert_allclose(yaw, g.yaw, atol=1e-15)


@pytest.mark.parametrize("spread", [0.3, 3.0], ids=["inside", "projected"])
def test_parametrisation_gradient(spread):
    g = line_gripper()
    rng = np.random.default_rng(0)
    p = g.default_params() + spread * rng.standard_normal(g.n_params)
    x0 = rng.standard_normal((3, 3)) * 0.05
    times = np.linspace(0.0, 0.3, 31)
    G = rng.standard_normal((31, 3, 3))
    grad = g.targets_vjp(p, times, x0, G)
    eps = 1e-6
    fd = np.array([np.sum(G * (g.targets(p + e, times, x0) - g.targets(p - e, times, x0))) / (2 * eps)
                   for e in np.eye(p.size) * eps])
    err = np.abs(grad - fd).max() / np.abs(fd).max()
    assert err < 1e-7, f"relative error {err:.2e}"


def test_gradient_of_every_knot_through_grasp_flight_and_landing():
    """Central differences on every parameter (positions and yaw of every knot after the first) of a rollout that
    grasps at step 2, lifts and turns the cloth, releases it at step 10 and lets it land on the table."""
    model = table_model()
    rng = np.random.default_rng(1)
    options = wc.SolverOptions(cg_tol=1e-12, cg_atol=1e-30, cg_max_iters=2000)  # solves exact to rounding
    task = GripperTask(model, 0.01, steps=30, goal=LinearGoal(model, rng), options=options, capture=False)
    p = task.default_params() + 0.2 * rng.standard_normal(task.n_params)
    frames = task.trajectory(p)
    z = np.array([f[:, 2] for f in frames])
    assert z[9, :3].min() > 0.03, "the gripper lifts its particles"
    assert np.median(z[-1]) < 0.006 and z[-1, :3].max() < z[10, :3].min(), "the cloth lands on the table"
    e = task.evaluate(p)
    for eps in (1e-6, 3e-7):  # the same slope at two step sizes (at 1e-5 the landing's contacts change: 3.6e-3)
        fd = np.array([(task.loss(p + d).loss - task.loss(p - d).loss) / (2 * eps) for d in np.eye(p.size) * eps])
        err = np.abs(e.grad - fd).max() / np.abs(fd).max()
        assert err < 1e-4, f"step {eps}: relative error {err:.2e}: {e.grad} vs {fd}"


def test_handles_switch_on_at_grasp_and_off_at_release():
    model = table_model(line_gripper(grasp=0.03, release=0.07), table=False)
    sim = wc.Simulator(model, 0.01)
    traj = wc.rollout(sim, model.state(), model.control(), steps=10)
    x = np.array([s.particle_x.numpy() for s in traj])
    free = x[:, 3:].mean(axis=1)  # the particles no gripper holds
    held = x[:, :3].mean(axis=1)
    # before the grasp everything falls alike; held, the gripper lifts its row; released, it falls again
    np.testing.assert_allclose(held[:4, 2], free[:4, 2], atol=1e-5)
    assert held[7, 2] > held[3, 2]
    vz = np.diff(held[:, 2]) / 0.01
    assert vz[-1] < vz[7]


def test_windows_that_always_hold_change_nothing():
    """Handles with a window around the whole run give bitwise the results and gradients of handles without one
    (and so of the solver before windows existed: the kernel multiplies the stiffness by 1)."""

    def run(window):
        b = wc.ModelBuilder()
        b.add_cloth_grid((3, 3), (0.2, 0.2), material=wc.preset("gray-interlock"), rot=np.diag([1.0, -1.0, -1.0]))
        b.add_handle(0, stiffness=500.0, window=window)
        b.add_handle(3, stiffness=500.0, motion=[(0.0, (0, 0, 0)), (0.1, (0.0, 0.0, 0.02))])
        model = b.finalize(requires_grad=True, dtype=wp.float64)
        sim = wc.Simulator(model, 0.01)
        control = model.control()
        tape = wp.Tape()
        with tape:
            traj = wc.rollout(sim, model.state(), control, steps=8)
        traj[-1].particle_x.grad.fill_(1.0)
        tape.backward()
        return traj[-1].particle_x.numpy(), control.handle_target.grad.numpy(), model.handle_stiffness.grad.numpy()

    for a, b in zip(run(None), run((-1.0, 1e9))):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("kwargs, match", [
    (dict(release=0.01, grasp=0.02), r"line: release \(0.01 s\) must come after grasp \(0.02 s\)"),
    (dict(times=[0.0, 0.04, 0.02, 0.12]), r"line: knot 2 at 0.02 s is not after knot 1"),
    (dict(times=[0.0, 0.04, 0.08, 0.13]), r"line: knot 3 at 0.13 s; .* equally spaced"),
    (dict(max_speed=0.2), r"line: knots 0 and 1 make a speed of 0.25 m/s, past max 0.2 .*past its limits at the start"),
    (dict(max_acceleration=5.0), r"line: the acceleration from rest to knot 1 is 6.25 .* past max 5"),
    (dict(max_yaw_acceleration=10.0), r"line: the yaw acceleration from rest to knot 1 .* past max 10"),
    (dict(particles=(0, 0)), r"line: particle 0 is listed twice"),
    (dict(positions=np.zeros((3, 3))), r"line: knot positions must be \(4, 3\)"),
])
def test_bad_gripper(kwargs, match):
    with pytest.raises(ValueError, match=match):
        line_gripper(**kwargs)


def test_gripper_on_missing_or_held_particles():
    b = wc.ModelBuilder()
    b.add_cloth_grid((3, 3), (0.1, 0.1), material=wc.preset("gray-interlock"))
    with pytest.raises(ValueError, match=r"line: particle 16 out of range: the cloth has 16 particles"):
        b.add_gripper(line_gripper(particles=(15, 16)))
    b.add_gripper(line_gripper())
    with pytest.raises(ValueError, match=r"second: particle 2 is held by line already"):
        b.add_gripper(line_gripper(particles=(2, 3), name="second"))
    b.add_handle(5)
    with pytest.raises(ValueError, match=r"third: particle 5 has a handle already"):
        b.add_gripper(line_gripper(particles=(5,), name="third"))


SCENE = """
name = "tiny-grip"
[sim]
dt = 0.01
steps = 20
[cloth]
grid = {{ res = [3, 3], size = [0.1, 0.1] }}
material = "gray-interlock"
{extra}
[[grippers]]
{gripper}
"""
GRIPPER = """grid_vertices = [[0, 0], [-1, 0]]
release = 0.15
knots = [{ t = 0.0, pos = [0, 0, 0] }, { t = 0.1, pos = [0, 0, 0.02] }, { t = 0.2, pos = [0, 0, 0.02] }]"""


@pytest.mark.parametrize("gripper, extra, match", [
    ("particles = [16]\nknots = []", "", r"grippers\[0\].particles\[0\]: particle 16 out of range"),
    (GRIPPER.replace("release = 0.15", "release = 0.0"), "", r"grippers\[0\]: release \(0 s\) must come after"),
    (GRIPPER.replace("t = 0.1", "t = 0.3"), "", r"grippers\[0\]: knot 2 at 0.2 s is not after knot 1"),
    (GRIPPER + "\nmax_acceleration = 0.5", "", r"grippers\[0\]: the acceleration from rest to knot 1 is 2 "),
    (GRIPPER.replace("{ t = 0.0, pos = [0, 0, 0] }", "{ t = 0.0, pos = [0, 0, 0], yaw = 0.0 }"), "",
     r"grippers\[0\].knots\[1\].yaw: give yaw \[rad\] at every knot"),
    (GRIPPER, "[[handles]]\ngrid_vertex = [0, 0]", r"grippers\[0\]: particle 0 is also held by handles\[0\]"),
    (GRIPPER, "[control]\ncontrols = 'grippers'\nloss = { coverage = { table_height = 0.0 } }\nspeed = 1",
     r"control.speed: unknown key"),
])
def test_bad_gripper_tables(gripper, extra, match):
    from warpcloth.scene import scene_from_toml

    with pytest.raises(ValueError, match=match):
        scene_from_toml(SCENE.format(gripper=gripper, extra=extra))


def test_scene_gripper_follows_its_knots():
    from warpcloth.scene import scene_from_toml

    scene = scene_from_toml(SCENE.format(gripper=GRIPPER, extra=""))
    model, sim = scene.build(dtype=wp.float64)
    (gripper,) = model.grippers
    x0 = model.particle_x0.numpy()[list(gripper.particles)]
    traj = wc.rollout(sim, model.state(), model.control(), steps=12)
    target = gripper.targets(gripper.default_params(), [0.12], x0)[0]
    held = traj[-1].particle_x.numpy()[list(gripper.particles)]
    assert np.abs(held - target).max() < 2e-3  # the handles' lag under the cloth's weight
    assert held[:, 2].min() > x0[:, 2].max() + 0.01


def test_params_of_knots_round_trip_and_projection():
    g = line_gripper()
    rng = np.random.default_rng(4)
    p = 0.3 * rng.standard_normal(g.n_params)  # within the limits' balls
    P, yaw = g.control_points(p)
    np.testing.assert_allclose(g.params_of(P, yaw), p, atol=1e-12)
    far = g.params_of(P + np.linspace(0.0, 5.0, g.knot_count)[:, None], yaw)  # 5 m in 0.12 s: past the limits
    Q, _ = g.control_points(far)
    assert np.linalg.norm(g.velocity_points(Q), axis=1).max() <= g.max_speed * (1 + 1e-12)
    with pytest.raises(ValueError, match=r"line: knot positions must be \(4, 3\) finite numbers, got shape \(3, 3\)"):
        g.params_of(P[:3])
    with pytest.raises(ValueError, match=r"line: yaw must be 4 finite angles"):
        g.params_of(P, [0.0, np.nan, 0.0, 0.0])
