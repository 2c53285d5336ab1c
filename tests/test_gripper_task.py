"""GripperTask: a scene's [control] with controls = "grippers": loss and gradient, replays from graphs, optimisers
and their counts, and the embedded fling and fold scenes."""

import re

import numpy as np
import pytest
import warp as wp

import warpcloth as wc
from warpcloth.scene import load_scene, scene_from_toml
from warpcloth.tasks.grippers import GripperTask
from warpcloth.tasks.specs import GripperControlSpec

TASK = """
name = "tiny-fling"
[sim]
dt = 0.01
steps = 25
[cloth]
grid = { res = [3, 3], size = [0.12, 0.12] }
rot_deg = [90.0, 0.0, 0.0]
pos = [-0.06, 0.0, 0.02]
material = "gray-interlock"
[[obstacles]]
name = "table"
shape = "plane"
size = [1.0, 1.0]
[collision]
obstacle_friction = 0.4
[[grippers]]
grid_vertices = [[0, -1], [-1, -1]]
release = 0.12
max_speed = 2.0
max_acceleration = 30.0
knots = [{ t = 0.0, pos = [0, 0, 0] }, { t = 0.05, pos = [0, 0.0, 0.01] }, { t = 0.1, pos = [0, -0.03, -0.02] },
         { t = 0.15, pos = [0, -0.06, -0.11] }]
[control]
controls = "grippers"
loss = { coverage = { table_height = 0.0 } }
acceleration_weight = 1e-4
path_weight = 1e-2
iters = 4
"""


def tiny_task(**kwargs) -> GripperTask:
    return GripperTask.from_scene(scene_from_toml(TASK), dtype=wp.float64, **kwargs)


def test_scene_spec():
    scene = scene_from_toml(TASK)
    spec = scene.control
    assert isinstance(spec, GripperControlSpec)
    assert spec.loss == ("coverage", {"table_height": 0.0}) and spec.iters == 4 and spec.optimizer == "lbfgs"
    task = tiny_task()
    assert task.n_params == 9 and len(task.grippers) == 1
    assert task.default_params().shape == (9,)


def test_gradient_in_a_random_direction():
    from warpcloth import goals

    scene = scene_from_toml(TASK)
    model = scene.finalize(requires_grad=True, dtype=wp.float64)
    target = model.particle_x0.numpy() * np.array([1.0, 1.0, 0.0]) + np.array([0.0, -0.1, 0.01])
    options = wc.SolverOptions(cg_tol=1e-12, cg_atol=1e-30, cg_max_iters=2000)  # solves exact to rounding
    task = GripperTask(model, scene.dt, steps=scene.steps, goal=goals.TargetPositions(model, target),
                       acceleration_weight=1e-4, path_weight=1e-2, options=options)
    rng = np.random.default_rng(0)
    p = task.default_params() + 0.1 * rng.standard_normal(task.n_params)
    e = task.evaluate(p)
    d = rng.standard_normal(p.size)
    eps = 1e-6
    fd = (task.loss(p + eps * d).loss - task.loss(p - eps * d).loss) / (2 * eps)
    assert float(e.grad @ d) == pytest.approx(fd, rel=1e-4), f"tape {e.grad @ d}, FD {fd}"
    assert task.simulations == 3


def test_replayed_graphs_give_the_uncaptured_results():
    task = tiny_task(capture=True)
    p = task.default_params() + 0.05
    first = task.evaluate(p)  # uncaptured
    task.evaluate(p + 0.1)  # captures
    again = task.evaluate(p)  # replays
    assert again.loss == first.loss and np.array_equal(again.grad, first.grad)
    assert task.loss(p).loss == pytest.approx(first.loss, rel=1e-12)


@pytest.mark.parametrize("optimizer", ["lbfgs", "cmaes", "random"])
def test_optimisers_count_their_simulations(optimizer):
    task = tiny_task()
    result = task.run(optimizer, 6, sigma=0.3)
    assert result.simulations == len(result.losses) <= 6
    assert result.loss == min(result.losses) and result.loss <= result.losses[0]
    assert 0.0 <= result.error <= 1.01


def test_gripper_control_errors():
    with pytest.raises(ValueError, match=r"control.controls: 'grippers' moves the scene's grippers, and it has no"):
        scene_from_toml(TASK.split("[[grippers]]")[0] + "[control]\ncontrols = 'grippers'\n"
                        "loss = { coverage = { table_height = 0.0 } }\n")
    with pytest.raises(ValueError, match=r"control.optimizer: unknown value 'newton'"):
        scene_from_toml(TASK + "optimizer = 'newton'\n")
    no_table = TASK.replace('[[obstacles]]\nname = "table"\nshape = "plane"\nsize = [1.0, 1.0]\n', "")
    with pytest.raises(ValueError, match=r"Coverage: the model has no obstacle, so no table"):
        GripperTask.from_scene(scene_from_toml(no_table))
    with pytest.raises(ValueError, match=r"gripper parameters must be 9 finite numbers, got 3"):
        tiny_task().evaluate(np.zeros(3))


@pytest.mark.parametrize("name", ["fling", "fold"])
def test_embedded_scenes(name):
    scene = load_scene(name)
    assert isinstance(scene.control, GripperControlSpec)
    model = scene.finalize()
    assert model.grippers and model.handle_window is not None


TIED = TASK.replace("""[[grippers]]
grid_vertices = [[0, -1], [-1, -1]]""", """[[grippers]]
name = "left"
grid_vertices = [[0, -1]]
release = 0.12
max_speed = 2.0
max_acceleration = 30.0
knots = [{ t = 0.0, pos = [0, 0, 0] }, { t = 0.05, pos = [0, 0.0, 0.01] }, { t = 0.1, pos = [0, -0.03, -0.02] },
         { t = 0.15, pos = [0, -0.06, -0.11] }]
[[grippers]]
name = "right"
grid_vertices = [[-1, -1]]""").replace("iters = 4", "iters = 4\ntied = true")


def test_tied_grippers_share_parameters_and_their_gradient():
    from warpcloth import goals

    scene = scene_from_toml(TIED)
    assert scene.control.tied
    model = scene.finalize(requires_grad=True, dtype=wp.float64)
    target = model.particle_x0.numpy() * np.array([1.0, 1.0, 0.0]) + np.array([0.0, -0.1, 0.01])
    options = wc.SolverOptions(cg_tol=1e-12, cg_atol=1e-30, cg_max_iters=2000)
    task = GripperTask(model, scene.dt, steps=scene.steps, goal=goals.TargetPositions(model, target),
                       acceleration_weight=1e-4, path_weight=1e-2, options=options, tied=True)
    assert task.n_params == 9 and len(task.grippers) == 2
    rng = np.random.default_rng(1)
    p = task.default_params() + 0.1 * rng.standard_normal(task.n_params)
    left, right = task.trajectory_frames(p)
    np.testing.assert_array_equal(left[0], right[0])  # one trajectory of displacements
    e = task.evaluate(p)
    d = rng.standard_normal(p.size)
    eps = 1e-6
    fd = (task.loss(p + eps * d).loss - task.loss(p - eps * d).loss) / (2 * eps)
    assert float(e.grad @ d) == pytest.approx(fd, rel=1e-4), f"tape {e.grad @ d}, FD {fd}"


def test_tied_grippers_must_match():
    unlike = TIED.replace('grid_vertices = [[-1, -1]]\nrelease = 0.12\nmax_speed = 2.0',
                          'grid_vertices = [[-1, -1]]\nrelease = 0.12\nmax_speed = 1.95')
    with pytest.raises(ValueError, match=r"tied grippers: right differs from left"):
        GripperTask.from_scene(scene_from_toml(unlike))
    with pytest.raises(ValueError, match=r"control.tied: expected true or false, got 'yes'"):
        scene_from_toml(TIED.replace("tied = true", "tied = 'yes'"))


def test_knot_increments_round_trip():
    task = tiny_task()
    p = task.default_params()
    u = task.knot_increments(p)
    np.testing.assert_allclose(np.diff(task.grippers[0].positions, axis=0).reshape(-1), u, atol=1e-15)
    np.testing.assert_allclose(task.params_of_increments(u), p, atol=1e-12)
    far = task.params_of_increments(u + 5.0)  # past the limits: projected into them
    P, _ = task.grippers[0].control_points(far)
    assert np.linalg.norm(task.grippers[0].velocity_points(P), axis=1).max() <= 2.0 * (1 + 1e-12)
    with pytest.raises(ValueError, match=r"knot increments must be 9 finite numbers, got 2"):
        task.params_of_increments([0.0, 1.0])


def test_compass_search_moves_one_increment_at_a_time():
    from warpcloth.tasks.grippers import compass_search

    calls = []

    def loss(x):
        return float(np.sum((x - np.array([0.3, -0.2])) ** 2))

    def f(x):
        calls.append(x.copy())
        return loss(x)

    best, x = compass_search(f, np.zeros(2), step=0.1, budget=40, rng=np.random.default_rng(0))
    assert len(calls) == 40 and best == min(loss(c) for c in calls) == loss(x)
    assert np.allclose(x, [0.3, -0.2], atol=0.02)
    for k in range(1, len(calls)):  # each trial: the best point so far, one coordinate moved
        best_so_far = min(calls[:k], key=loss)
        assert np.count_nonzero(calls[k] - best_so_far) == 1, (k, calls[k], best_so_far)


def _write(tmp_path, text, name="tiny.toml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_cli_runs_a_gripper_scene(tmp_path, capsys):
    import json

    from warpcloth.cli import main

    scene = _write(tmp_path, TASK.replace("iters = 4", "iters = 3\noptimizer = 'compass'\nsigma = 0.02"))
    out = tmp_path / "run.json"
    assert main(["control", scene, "--json", str(out), "--device", "cpu"]) == 0
    text = capsys.readouterr().out
    assert "optimizer compass, 3 simulations" in text and "coverage" in text and "scripted knots" in text
    record = json.loads(out.read_text())
    assert record["simulations"] == len(record["losses"]) == 3 and record["goal"] == "coverage"
    best = int(np.argmin(record["losses"]))
    assert record["error"] == record["errors"][best] and record["loss"] == record["losses"][best]
    assert f"{100 * record['start_error']:.1f} %" in text and f"{100 * record['error']:.1f} %" in text


@pytest.mark.parametrize("flags, match", [
    (["--controller", "mlp"], r"--controller: scene 'tiny-fling' moves grippers, not pushes"),
    (["--optimizer", "gauss-newton"], r"--optimizer gauss-newton: scene 'tiny-fling' moves grippers; its "
                                      r"optimisers are lbfgs, adam, compass, cmaes, random"),
    (["--starts", "2"], r"scene 'tiny-fling' moves grippers: one run in this process \(--starts 1"),
])
def test_cli_refuses_push_options_on_gripper_scenes(tmp_path, capsys, flags, match):
    from warpcloth.cli import main

    assert main(["control", _write(tmp_path, TASK), *flags]) == 2
    assert re.search(match, capsys.readouterr().err)


def test_cli_refuses_gripper_optimisers_on_push_scenes(capsys):
    from warpcloth.cli import main

    assert main(["control", "basket-throw", "--optimizer", "compass"]) == 2
    assert "--optimizer: unknown value 'compass'" in capsys.readouterr().err
