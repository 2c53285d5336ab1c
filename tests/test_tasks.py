"""Tasks as data: a scene's [control] and [estimate] tables, the task objects that run them, and the command line.

The seed's two tasks are embedded scenes (basket-throw, material-estimation) and must give what the code-built
scenes gave; a user's scene gets every key checked before anything is simulated, and its tasks' gradients match
central differences for every parameter a user can optimise (the pushes).
"""

import json
import math

import numpy as np
import pytest
import warp as wp
from conftest import SMALL_SCENE, small_scene

import warpcloth as wc
from warpcloth import recordings
from warpcloth.cli import main
from warpcloth.tasks import estimation as E
from warpcloth.tasks import scenes as S
from warpcloth.tasks import throw as C
from warpcloth.tasks.control import ControlTask
from warpcloth.tasks.controllers import ControlResult, optimize_open_loop

# A small hanging sheet: 4x4 cells, two soft handles, no contact; pushes on two lower corners.
CONTROL = """
[control]
grid_vertices = [[0, 0], [-1, 0]]
interval = 0.1
intervals = 2
loss = {loss}
regularizer = {reg}
{more}
"""


def write_obj(path, x: np.ndarray) -> None:
    rows = np.asarray(x, dtype=np.float64).tolist()
    path.write_text("".join(f"v {a!r} {b!r} {c!r}\n" for a, b, c in rows) + "f 1 2 3\n")


def known_final(tmp_path) -> np.ndarray:
    """Where the small sheet ends under known pushes on its two lower corners: a target reachable exactly."""
    model = wc.load_scene(small_scene(tmp_path, name="base.toml")).finalize("cpu", requires_grad=True)
    task = ControlTask(model, 0.02, particles=(0, 4), interval_steps=5, intervals=2, steps=12,
                       target_positions=model.particle_x0.numpy())
    return task.trajectory(np.tile([3.0, 1.0, -2.0], 4))[-1].astype(np.float64)


def positions_target(tmp_path) -> str:
    write_obj(tmp_path / "target.obj", known_final(tmp_path))
    return '{ positions = "target.obj" }'


def com_target(tmp_path) -> str:
    return f"{{ com = {known_final(tmp_path).mean(axis=0).tolist()!r} }}"


# -- the seed's tasks as embedded scenes ------------------------------------------------------------------------------
def test_the_seeds_tasks_are_embedded_scenes():
    assert {"basket-throw": ("control",), "material-estimation": ("estimate",)}.items() <= {
        name: wc.load_scene(name).tasks for name in wc.SCENE_NAMES}.items()


def test_the_estimation_scene_is_the_seeds_hanging_cloth():
    truth = wc.preset("gray-interlock", thicken=2)
    task = E.EstimationTask.from_scene("material-estimation", device="cpu")
    model = S.hanging_cloth(truth, device="cpu")
    fit = E.TrajectoryFit(model, E.TrajectoryFit.simulate_targets(model, truth))
    assert task.fit.steps == E.STEPS and task.fit.frame_stride == E.FRAME_STRIDE and task.fit.sim.dt == E.DT
    np.testing.assert_array_equal(task.fit.observation.frames, fit.observation.frames)
    start = E.initial_guess()
    assert task.fit.loss_and_grad(start)[0] == fit.loss_and_grad(start)[0]  # bitwise: the same scene and solver
    assert task.start.name == start.name and np.array_equal(task.start.stretching, start.stretching)


def test_the_throw_task_is_the_basket_scenes_control_table():
    task = ControlTask.from_scene("basket-throw", device="cpu", steps=60)
    throw = C.ThrowTask(S.basket_scene("cpu"), steps=60)
    assert task.particles == C.CORNERS == (0, 8, 72, 80) and task.n_params == C.N_PARAMS == 36
    params = np.random.default_rng(0).normal(scale=3.0, size=36)
    a, b = task.evaluate(params), throw.evaluate(params)
    assert a.loss == b.loss and np.array_equal(a.grad, b.grad)


def test_a_throw_task_on_another_model_does_not_batch_copies_of_the_scene():
    # batches copy the embedded scene: they must not stand in for a model that is not it
    assert C.ThrowTask(S.basket_scene("cpu", dtype=wp.float64), steps=4).worlds(2) is not None
    builder = wc.ModelBuilder()  # the throw's cloth, higher up, without the basket and the wall
    builder.add_cloth_grid((8, 8), (0.7, 0.7), material=wc.preset("gray-interlock", thicken=2), pos=(-3.7, 0.0, 2.5))
    other = C.ThrowTask(builder.finalize("cpu", requires_grad=True), steps=4)
    assert other.worlds(2) is None
    results = other.evaluate_many([(np.zeros(36), None), (np.ones(36), None)])  # one after another
    assert results[1].com[2] > results[0].com[2] and other.batches == 0 and other.simulations == 2  # pushed up


# -- control tasks on a user's scene ---------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["com", "positions"])
def test_control_gradient_matches_central_differences_for_every_push(tmp_path, kind, device):
    loss = "{ com = [0.1, 0.0, -0.3] }" if kind == "com" else positions_target(tmp_path)
    path = small_scene(tmp_path, CONTROL.format(loss=loss, reg=0.01, more=""))
    task = ControlTask.from_scene(path, device=device, dtype=wp.float64)
    assert task.n_params == 12 and task.steps == 12 and task.interval_steps == 5
    params = np.random.default_rng(1).normal(scale=2.0, size=task.n_params)
    value, grad, _ = task.loss_and_grad(params)
    for k in range(task.n_params):  # every push; both intervals act within the 12-step horizon
        for eps in (1e-4, 1e-5):  # central differences converge: the same slope at two step sizes
            e = np.zeros(task.n_params)
            e[k] = eps
            fd = (task.loss_and_grad(params + e)[0] - task.loss_and_grad(params - e)[0]) / (2 * eps)
            assert grad[k] == pytest.approx(fd, rel=1e-5, abs=1e-12), (k, eps)
    assert np.all(grad != 0.0)



def test_a_push_bound_keeps_every_push_within_it_and_its_gradient_matches_central_differences(tmp_path):
    from warpcloth.tasks.control import scene_task_args

    scene = wc.load_scene(small_scene(tmp_path, CONTROL.format(loss="{ com = [0.1, 0.0, -0.3] }", reg=0.0, more="")))
    args = scene_task_args(scene)
    def model():
        return scene.finalize(device="cpu", requires_grad=True, dtype=wp.float64)

    bounded, free = ControlTask(model(), **{**args, "push_bound": 3.0}), ControlTask(model(), **args)
    params = np.random.default_rng(2).normal(scale=4.0, size=bounded.n_params)  # some pushes past the bound
    applied = bounded.applied_pushes(params)
    lengths = np.linalg.norm(applied, axis=-1)
    assert np.all(lengths < 3.0) and np.any(np.linalg.norm(params.reshape(applied.shape), axis=-1) > 3.0)
    assert np.allclose(bounded.applied_pushes(1e-3 * params), 1e-3 * params.reshape(applied.shape), rtol=1e-4)
    value, grad, _ = bounded.loss_and_grad(params)
    assert value == pytest.approx(free.loss_and_grad(applied)[0], rel=1e-12)  # the bound acts through the pushes
    for k in range(bounded.n_params):
        for eps in (1e-4, 1e-5):
            e = np.zeros(bounded.n_params)
            e[k] = eps
            fd = (bounded.loss_and_grad(params + e)[0] - bounded.loss_and_grad(params - e)[0]) / (2 * eps)
            assert grad[k] == pytest.approx(fd, rel=1e-5, abs=1e-12), (k, eps)
    with pytest.raises(ValueError, match="push_bound"):
        ControlTask(free.model, **{**args, "push_bound": -1.0})


def test_a_scenes_waypoints_reach_the_task_and_make_lbfgs_its_default(tmp_path):
    more = "waypoints = [[0.1, [0.0, 0.0, 0.2], 2.0]]"
    task = ControlTask.from_scene(small_scene(tmp_path, CONTROL.format(loss="{ com = [0.1, 0.0, -0.3] }", reg=0.0,
                                                                       more=more)), device="cpu")
    (step, target, weight), = task.waypoints
    assert step == round(0.1 / task.dt) and target.tolist() == [0.0, 0.0, 0.2] and weight == 2.0
    assert task.optimizer == "lbfgs"

FREE_FLIGHT = """
name = "free-flight"
[sim]
dt = 0.01
steps = 100
[solver]
cg_tol = 1e-12
[cloth]
grid = { res = [6, 6], size = [0.6, 0.6] }
material = "gray-interlock"
thicken = 2.0
[control]
grid_vertices = [[0, 0], [-1, 0], [0, -1], [-1, -1]]
interval = 0.2
intervals = 2
loss = { com = [1.0, 0.5, 2.0] }
"""


def test_the_centre_of_mass_moves_with_the_pushes_as_a_point_mass_in_free_flight(tmp_path):
    # Internal forces cancel in the centre of mass, in the tape's tangent dynamics too, so its Jacobian is the
    # ballistic one whatever the sheet does: each push's force (M/k) p, held for its interval, moves com_T by
    # (1/k) dt^2 sum_i (T - i). A flat sheet pushed across its plane is where the vertex mean's derivative is not
    # that (the unstressed sheet's tangent has no membrane stiffness across the plane); start there.
    path = tmp_path / "free.toml"
    path.write_text(FREE_FLIGHT)
    task = ControlTask.from_scene(path, device="cpu", dtype=wp.float64)
    k, dt, T = len(task.particles), task.dt, task.steps
    ballistic = np.zeros((3, *task.params_shape))
    for s in range(task.intervals):
        lever = sum(T - i for i in range(s * task.interval_steps, (s + 1) * task.interval_steps))
        for axis in range(3):
            ballistic[axis, s, :, axis] = dt * dt * lever / k
    for params in (np.zeros(task.n_params), np.random.default_rng(3).normal(scale=5.0, size=task.n_params)):
        jac = np.stack([task.evaluate(params, component=axis).grad for axis in range(3)])
        np.testing.assert_allclose(jac, ballistic.reshape(3, -1), rtol=0, atol=1e-9 * np.abs(ballistic).max())


def test_the_open_loop_fits_target_positions_with_lbfgs(tmp_path):
    path = small_scene(tmp_path, CONTROL.format(loss=positions_target(tmp_path), reg=0.0, more="iters = 6"))
    task = ControlTask.from_scene(path, device="cpu")
    assert task.optimizer == "lbfgs" and task.iters == 6
    result = task.run()
    assert len(result.errors_pct) == 6 and result.errors_pct[0] > 90.0  # zero pushes: it only sags
    assert result.error_pct < 0.3 * result.errors_pct[0]
    assert result.params.shape == (2, 2, 3)


def test_the_mlp_controller_takes_a_scenes_task(tmp_path):
    pytest.importorskip("torch")
    path = small_scene(tmp_path, CONTROL.format(loss=positions_target(tmp_path), reg=0.01, more=""))
    task = ControlTask.from_scene(path, device="cpu")
    result = task.run(controller="mlp", iters=3, lr=1e-2)
    assert len(result.errors_pct) == 3 and result.errors_pct[-1] < result.errors_pct[0]
    assert result.params.shape == (2, 2, 3)


def test_gauss_newton_with_a_regulariser_keeps_pushes_small(tmp_path):
    # the com target is reachable; the regulariser (about a tenth of |J|^2 here) trades error for smaller pushes
    norms = []
    for reg in (0.0, 3e-5):
        path = small_scene(tmp_path, CONTROL.format(loss=com_target(tmp_path), reg=reg, more=""))
        result = optimize_open_loop(ControlTask.from_scene(path, device="cpu"), iters=12)
        assert result.error_pct < 20.0
        norms.append(np.linalg.norm(result.params))
    assert norms[1] < 0.9 * norms[0]


# -- estimation tasks on a user's scene ------------------------------------------------------------------------------
def test_estimate_frees_only_what_the_scene_says(tmp_path):
    path = small_scene(tmp_path, '[estimate]\nfree = ["density"]\nstart = "white-swim-solid"\niters = 4\n')
    task = E.EstimationTask.from_scene(path, device="cpu")
    result = task.run()
    start = wc.preset("white-swim-solid", thicken=2)
    assert np.array_equal(result.material.stretching, start.stretching)
    assert np.array_equal(result.material.bending, start.bending)
    assert result.material.density != start.density and min(result.losses) < result.losses[0]
    whole = [loss for loss, steps in zip(result.losses, result.horizons) if steps == max(result.horizons)]
    assert result.evaluations == 4 and result.first_loss == result.losses[0] and result.best_loss == min(whole)


def test_estimate_fits_recorded_frames(tmp_path):
    start = E.initial_guess()  # the default start; the truth is 1.5 times as heavy
    truth = wc.Material(density=1.5 * start.density, stretching=start.stretching, bending=start.bending, thicken=2)
    model = wc.load_scene(small_scene(tmp_path, name="base.toml")).finalize("cpu", requires_grad=True)
    frames = E.TrajectoryFit.simulate_targets(model, truth, steps=12, frame_stride=3, dt=0.02)
    (tmp_path / "frames").mkdir()
    for k, x in enumerate(frames):
        write_obj(tmp_path / "frames" / f"{k}.obj", x)
    path = small_scene(tmp_path, '[estimate]\ntargets = "frames"\nframe_stride = 3\nfree = ["density"]\niters = 5\n')
    task = E.EstimationTask.from_scene(path, device="cpu")
    assert task.truth is None and task.fit.observation.frame_count == 5
    result = task.run()
    error = abs(result.material.density - truth.density) / truth.density
    assert error < 0.5 * abs(task.start.density - truth.density) / truth.density
    with pytest.raises(ValueError, match="recorded targets"):
        E.EstimationTask.from_scene(path, device="cpu", truth=truth)


def test_a_recordings_frame_rate_sets_its_frame_stride(tmp_path):
    """frame_rate = 25 at dt 0.02 s: a frame every 2 steps, as frame_stride = 2 gives; the scene's dt then stays
    (its frames fall on its steps); frame_stride_of refuses a period that is not a whole number of steps."""
    scene = wc.load_scene(small_scene(tmp_path, "[estimate]\nframe_rate = 25\nfree = ['density']\n"))
    assert scene.estimate.frame_stride == 2 and scene.estimate.frame_rate == 25.0
    assert E.EstimationTask.from_scene(scene, device="cpu").fit.frame_stride == 2
    with pytest.raises(ValueError, match="recording's frames \\(25 a second\\) fall on its steps of 0.02 s"):
        scene.set_dt(0.01)
    scene.set_dt(0.02)  # the same step is no change
    assert recordings.frame_stride_of(30, 1 / 60) == 2 and recordings.frame_stride_of(50.0, 0.02) == 1
    for rate, dt in ((30, 0.02), (100, 0.02)):
        with pytest.raises(ValueError, match="its frames must fall on steps"):
            recordings.frame_stride_of(rate, dt)
    for rate, dt in ((0, 0.02), (True, 0.02), (30, float("nan"))):
        with pytest.raises(ValueError, match="must be a finite number > 0"):
            recordings.frame_stride_of(rate, dt)


# -- every key checked, before anything is simulated -----------------------------------------------------------------
BAD_CONTROL = [
    ("grid_vertices = [[0, 0]]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\nspeed = 1",
     r"control.speed: unknown key"),
    ("particles = [0, 25]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }",
     r"control.particles\[1\]: particle 25 out of range: the cloth has 25 particles"),
    ("grid_vertices = [[0, 5]]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }",
     r"control.grid_vertices\[0\]\[1\]: index 5 out of range"),
    ("particles = [3, 3]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }",
     r"control.particles\[1\]: particle 3 is pushed twice"),
    ("particles = [1]\ninterval = 0.03\nintervals = 2\nloss = { com = [0, 0, 0] }",
     r"control.interval: 0.03 s is not a whole number of sim.dt = 0.02 s steps"),
    ("particles = [1]\ninterval = 0.1\nintervals = 3\nloss = { com = [0, 0, 0] }",
     r"control.intervals: 3 pushes of 5 steps outlast the horizon of 12 steps"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0] }",
     r"control.loss.com: expected an array of 3 numbers"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = {}", r"control.loss: give exactly one of 'com'"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { positions = 'few.obj' }",
     r"control.loss.positions: few.obj has 3 vertices, the cloth has 25"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { positions = 'missing.obj' }",
     r"control.loss.positions: file not found: .*missing.obj"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\noptimizer = 'newton'",
     r"control.optimizer: unknown value 'newton'; one of: gauss-newton, lbfgs"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\ncontroller = 'mlp'\n"
     "optimizer = 'lbfgs'", r"control.optimizer: unknown value 'lbfgs'; one of: gauss-newton, adam"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\ncontroller = 'mlp'\n"
     "regularizer = 0.1\noptimizer = 'gauss-newton'", r"control.optimizer: gauss-newton trains the MLP without a "),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\nregularizer = -1",
     r"control.regularizer: must be >= 0"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\ncontroller = 'ppo'",
     r"control.controller: unknown value 'ppo'; one of: open-loop, mlp"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\niters = 'many'",
     r"control.iters: expected an integer, got string"),
    ("particles = [5]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }",
     r"control.particles\[0\]: particle 5 is pinned by pins\[0\]"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\npush_bound = 0.0",
     r"control.push_bound: must be > 0"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\nwaypoints = [[0.105, [0, 0, 0], 1]]",
     r"control.waypoints: waypoint 0: time 0.105 s is not a whole step"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\nwaypoints = [[0.1, [0, 0], 1]]",
     r"control.waypoints\[0\]\[1\]"),
    ("particles = [1]\ninterval = 0.1\nintervals = 2\nloss = { com = [0, 0, 0] }\nwaypoints = [[0.1, [0, 0, 0], 1]]"
     "\noptimizer = 'gauss-newton'", r"control.optimizer: gauss-newton fits the horizon's centre of mass only"),
]
BAD_ESTIMATE = [
    ("free = ['density', 'windy']", r"estimate.free\[1\]: unknown value 'windy'; one of: density, stretching, bending"),
    ("free = ['density', 'density']", r"estimate.free\[1\]: names 'density' a second time"),
    ("free = ['density']\noptimizer = 'seed-sgd'", r"estimate.optimizer: seed-sgd fits the whole material"),
    ("free = []", r"estimate.free: expected a non-empty array"),
    ("frame_stride = 5", r"estimate.frame_stride: the 12 steps compared are not a whole number of frames of 5"),
    ("frame_rate = 30", r"estimate.frame_rate: a recording at 30 frames/s has a frame every 1.667 steps of 0.02 s; "
                        r"its frames must fall on steps: set dt to 0.0166667 s \(a frame every 2 steps\)"),
    ("frame_rate = 0", r"estimate.frame_rate: must be > 0"),
    ("frame_rate = 25\nframe_stride = 3", r"estimate.frame_stride: 3 steps a frame, but frame_rate 25 at dt 0.02 s "
                                          r"is 2; give one of them"),
    ("frame_rate = 10", r"estimate.frame_rate: the 12 steps compared are not a whole number of frames of 5"),
    ("targets = 'missing'", r"estimate.targets: sequence directory .* does not exist"),
    ("targets = 'few'", r"estimate.targets: its frames have 3 vertices, the cloth has 25"),
    ("targets = 'short'\nframe_stride = 3", r"estimate.targets: 12 steps compare 5 frames .* holds 2"),
    ("optimizer = 'newton'", r"estimate.optimizer: unknown value 'newton'"),
    ("start = 'silk'", r"estimate.start: unknown"),
    ("iters = 0", r"estimate.iters: must be >= 1"),
    ("horizon = 3", r"estimate.horizon: unknown key"),
]


@pytest.mark.parametrize("table,message", [("[control]\n" + t, m) for t, m in BAD_CONTROL]
                         + [("[estimate]\n" + t, m) for t, m in BAD_ESTIMATE])
def test_bad_task_keys_are_named(tmp_path, table, message):
    write_obj(tmp_path / "few.obj", np.eye(3))
    for name, count in (("few", 3), ("short", 25)):
        (tmp_path / name).mkdir()
        for k in range(2):
            write_obj(tmp_path / name / f"{k}.obj", np.zeros((count, 3)))
    pin = "[[pins]]\nparticle = 5\n" if "particles = [5]" in table else ""
    with pytest.raises(ValueError, match=message):
        wc.load_scene(small_scene(tmp_path, pin + table))


@pytest.mark.parametrize("controller, loss, regularizer, optimizer", [
    ("open-loop", "com", 0.0, "gauss-newton"), ("open-loop", "com", 0.1, "gauss-newton"),
    ("open-loop", "positions", 0.0, "lbfgs"), ("mlp", "com", 0.0, "gauss-newton"), ("mlp", "com", 0.1, "adam"),
    ("mlp", "positions", 0.0, "adam")])
def test_each_controller_gets_its_default_optimizer(tmp_path, controller, loss, regularizer, optimizer):
    write_obj(tmp_path / "t.obj", np.zeros((25, 3)))
    target = "{ com = [0, 0, 0] }" if loss == "com" else "{ positions = 't.obj' }"
    table = (f"[control]\nparticles = [1]\ninterval = 0.1\nintervals = 2\nloss = {target}\n"
             f"controller = '{controller}'\nregularizer = {regularizer}\n")
    scene = wc.load_scene(small_scene(tmp_path, table))
    assert scene.control.optimizer == optimizer
    task = ControlTask.from_scene(scene, device="cpu")
    assert task.optimizer == optimizer and task.optimizer_for(controller) == optimizer
    other = "mlp" if controller == "open-loop" else "open-loop"  # run(controller=other) takes other's default
    assert task.optimizer_for(other) == ("gauss-newton" if loss == "com" and (other == "open-loop" or not regularizer)
                                         else "lbfgs" if other == "open-loop" else "adam")


def test_gauss_newton_needs_a_com_target(tmp_path):
    write_obj(tmp_path / "t.obj", np.zeros((25, 3)))
    table = "[control]\nparticles = [1]\ninterval = 0.1\nintervals = 2\nloss = { positions = 't.obj' }\n"
    with pytest.raises(ValueError, match="control.optimizer: gauss-newton fits a centre-of-mass target"):
        wc.load_scene(small_scene(tmp_path, table + "optimizer = 'gauss-newton'\n"))


def test_a_scene_without_the_task_is_refused(tmp_path, capsys):
    with pytest.raises(ValueError, match=r"scene 'small' .* has no \[control\] table"):
        ControlTask.from_scene(small_scene(tmp_path))
    with pytest.raises(ValueError, match=r"has no \[estimate\] table"):
        E.EstimationTask.from_scene("hanging-wind")
    assert main(["control", str(small_scene(tmp_path))]) == 2
    assert "has no [control] table" in capsys.readouterr().err


# -- the command line ------------------------------------------------------------------------------------------------
def test_cli_runs_a_scenes_tasks(tmp_path, capsys):
    path = small_scene(tmp_path, CONTROL.format(loss="{ com = [0.1, 0.0, -0.3] }", reg=0.0, more="")
                       + '[estimate]\nfree = ["density"]\n')
    out = tmp_path / "c.json"
    assert main(["control", str(path), "--iters", "4", "--json", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["scene"] == "small" and len(record["errors_pct"]) == 4 and np.shape(record["params"]) == (2, 2, 3)
    assert "seed (published)" not in capsys.readouterr().out  # the seed's figures are for its own throw only
    out = tmp_path / "e.json"
    assert main(["estimate", str(path), "--iters", "2", "--material", "royal-target", "--json", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["free"] == ["density"] and len(record["losses"]) == 2 and "density_err_pct" in record
    assert "royal-target simulated by warpcloth" in record["source"]
    assert main(["estimate", str(path), "--target", str(tmp_path)]) == 2
    assert "or --target, not both" in capsys.readouterr().err
    assert main(["estimate", str(path), "--optimizer", "seed-sgd", "--iters", "1"]) == 2  # it fits every part
    assert "seed-sgd optimiser fits the whole material" in capsys.readouterr().err
    # a global search's trials as worlds of one batch: the same search as without --batch
    records = []
    for batch in ([], ["--batch"]):
        assert main(["estimate", str(path), "--optimizer", "smoothed", "--iters", "16", "--material", "royal-target",
                     "--json", str(out), *batch]) == 0
        records.append(json.loads(out.read_text()))
    assert [r["batch"] for r in records] == [False, True]
    assert records[0]["losses"] == records[1]["losses"] and records[0]["estimate"] == records[1]["estimate"]
    assert main(["estimate", str(path), "--batch", "--iters", "2"]) == 2  # lbfgs: no trials to batch
    assert "batch=True simulates a global search's trials" in capsys.readouterr().err


def test_cli_lists_the_scenes_tasks(capsys):
    assert main(["scenes"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()}
    assert lines["basket-throw"].split()[1] == "control"
    assert lines["material-estimation"].split()[1] == "estimate"
    assert lines["free-fall"].split()[1] == "-"


def test_estimation_targets_are_simulated_with_the_scenes_solver(tmp_path):
    """A scene's solver options (here BDF2) make its targets too, so its own material fits them exactly."""
    path = tmp_path / "bdf2.toml"
    path.write_text(SMALL_SCENE.format(extra='[estimate]\nfree = ["density"]\n').replace(
        "cg_tol = 1e-12", 'cg_tol = 1e-12\nintegrator = "bdf2"'))
    task = E.EstimationTask.from_scene(path, dtype=wp.float64)
    assert task.fit.sim.options.integrator == "bdf2"
    euler = E.TrajectoryFit.simulate_targets(task.fit.model, task.truth, steps=12, dt=0.02)  # another integrator
    mismatch = sum(float(np.sum((a - b) ** 2)) for a, b in zip(euler, task.fit.observation.frames))
    assert task.fit.loss(task.truth) < 1e-6 * mismatch


# -- what a fit's result says ----------------------------------------------------------------------------------------
def test_a_fits_result_names_its_first_and_best_loss():
    r = ControlResult(params=np.zeros((1, 1, 3)), losses=[4e-4, math.inf, 2e-4, 3e-5, 3e-5, 5e-5])
    assert (r.first_loss, r.best_loss, r.best_evaluation, r.evaluations) == (4e-4, 3e-5, 4, 6)
    assert r.summary() == "best loss 3.00e-05 at evaluation 4 of 6 (first 4.00e-04)"
    # a curriculum's shorter horizons take fewer frames: only the longest horizon's losses compare
    m = wc.preset("gray-interlock", thicken=2)
    e = E.EstimationResult(material=m, initial=m, losses=[1e-5, 2e-4, 1e-4, 3e-4], horizons=[20, 50, 50, 50])
    assert (e.first_loss, e.best_loss, e.best_evaluation, e.evaluations) == (1e-5, 1e-4, 3, 4)
    assert e.summary() == "best loss 1.00e-04 at evaluation 3 of 4 (first 1.00e-05, over 20 of 50 steps)"
    empty = ControlResult(params=np.zeros((1, 1, 3)))
    assert (empty.evaluations, empty.best_evaluation, empty.summary()) == (0, 0, "no evaluations")
    assert math.isnan(empty.first_loss) and math.isnan(empty.best_loss)
