"""Search that follows contact: waypoint terms of a control task's loss (their values and gradients against the
trajectory and central differences, through whole and checkpointed rollouts, captured or not), their checks, how a
task's time splits between capturing, replaying and uncaptured evaluations, and CMA-ES's restarts with growing
populations."""

import math

import numpy as np
import pytest
import warp as wp
from conftest import small_scene

import warpcloth as wc
from warpcloth.tasks.control import EVALUATION_KINDS, ControlTask, scene_task_args
from warpcloth.tasks.controllers import optimize_open_loop
from warpcloth.tasks.optim import cmaes, cmaes_restarts

CONTROL = """
[control]
grid_vertices = [[0, 0], [-1, 0]]
interval = 0.1
intervals = 2
loss = { com = [0.1, 0.0, -0.3] }
"""
WAYPOINTS = [(0.1, (0.05, 0.1, -0.1), 2.0), (0.16, (0.0, -0.1, -0.2), 0.5), (0.24, (0.2, 0.0, 0.0), 1.0)]
"""Steps 5, 8 and 12 (the horizon) of the small sheet's 12 steps of 0.02 s."""


def task_of(tmp_path, *, waypoints=(), segment_steps=None, **more) -> ControlTask:
    scene = wc.load_scene(small_scene(tmp_path, CONTROL))
    args = {**scene_task_args(scene, segment_steps=segment_steps), "optimizer": "lbfgs", "waypoints": waypoints,
            **more}
    return ControlTask(scene.finalize(device="cpu", requires_grad=True, dtype=wp.float64), **args,
                       template=scene.model_builder)


@pytest.mark.parametrize("segment_steps", [None, 5])
def test_waypoint_terms_add_to_the_loss_and_their_gradient_matches_central_differences(tmp_path, segment_steps):
    task = task_of(tmp_path, waypoints=WAYPOINTS, segment_steps=segment_steps)
    plain = task_of(tmp_path, segment_steps=segment_steps)
    params = np.random.default_rng(3).normal(scale=2.0, size=task.n_params)
    frames = plain.trajectory(params)
    expected = plain.evaluate(params).loss + sum(
        0.5 * w * float(np.sum((task.com_weights @ frames[round(t / 0.02)] - np.asarray(x)) ** 2))
        for t, x, w in WAYPOINTS)
    value, grad, _ = task.loss_and_grad(params)
    assert value == pytest.approx(expected, rel=1e-12)
    assert task.losses_many([params])[0].loss == pytest.approx(expected, rel=1e-12)  # forward only: the same terms
    for k in range(task.n_params):
        for eps in (1e-4, 1e-5):  # the later calls replay graphs: the central differences check those too
            e = np.zeros(task.n_params)
            e[k] = eps
            fd = (task.loss_and_grad(params + e)[0] - task.loss_and_grad(params - e)[0]) / (2 * eps)
            assert grad[k] == pytest.approx(fd, rel=1e-5, abs=1e-12), (k, eps, grad[k], fd, abs(grad[k] / fd - 1))
    assert task.loss_and_grad(params)[0] == pytest.approx(value, rel=1e-12)
    assert np.abs(grad - plain.evaluate(params).grad).max() > 1e-3  # the waypoints pull


def test_bad_waypoints_and_gauss_newton_with_waypoints_are_refused(tmp_path):
    for waypoints, match in [([(0.11, (0, 0, 0), 1.0)], "waypoint 0: time 0.11 s is not a whole step"),
                             ([(0.26, (0, 0, 0), 1.0)], "within the horizon"),
                             ([(0.0, (0, 0, 0), 1.0)], "within the horizon"),
                             ([(0.1, (0, 0, 0), 1.0), (0.1, (0, math.nan, 0), 1.0)], "waypoint 1: target"),
                             ([(0.1, (0, 0, 0), -1.0)], "weight must be finite and >= 0"),
                             ([(0.1, (0, 0), 1.0)], r"waypoint 0: give \(time")]:
        with pytest.raises(ValueError, match=match):
            task_of(tmp_path, waypoints=waypoints)
    with pytest.raises(ValueError, match="gauss-newton fits the horizon's centre of mass only"):
        task_of(tmp_path, waypoints=WAYPOINTS, optimizer="gauss-newton")
    task = task_of(tmp_path, waypoints=WAYPOINTS)
    with pytest.raises(ValueError, match="gauss-newton fits the horizon's centre of mass only"):
        optimize_open_loop(task, iters=3, optimizer="gauss-newton")
    assert task.optimizer_for("open-loop", own=False) == "lbfgs"
    with pytest.raises(ValueError, match="the MLP controller fits the horizon's loss only"):
        task.run(controller="mlp", iters=2)


def test_a_search_with_waypoints_ends_with_lbfgs_and_judges_by_the_horizon(tmp_path):
    task = task_of(tmp_path, waypoints=WAYPOINTS, optimizer="cmaes")
    result = task.run(iters=10, search=wc.tasks.specs.SearchSpec(population=4, refine=2))
    assert len(result.losses) == 10 and result.failed_trials == []
    assert result.error_pct == min(result.errors_pct)  # the best by the horizon's error, not the loss with waypoints


def test_a_tasks_time_splits_into_captures_replays_and_uncaptured_runs(tmp_path):
    task = task_of(tmp_path)
    params = np.ones(task.n_params)
    task.evaluate(params)  # the first ask runs uncaptured
    task.evaluate(params)  # the second captures
    task.evaluate(params)  # the third replays
    split = task.seconds_by_kind
    assert set(split) == set(EVALUATION_KINDS) and all(split[k] > 0.0 for k in EVALUATION_KINDS), split
    assert sum(split.values()) == pytest.approx(task.seconds, rel=1e-9)
    task.losses_many([params, 2 * params])  # a batch of worlds: its own task's time, counted here
    assert sum(task.seconds_by_kind.values()) == pytest.approx(task.seconds, rel=1e-9)


def test_cmaes_restarts_grow_their_population_stay_within_budget_and_leave_basins_one_run_stays_in():
    # 2-D Rastrigin from (3, -3), a population of 6: one run of 200 generations ends in a neighbouring basin for
    # each of six seeds; restarted with doubled populations, half of them reach the origin in the same budget
    def rastrigin(x):
        return 20.0 + float(np.sum(x * x - 10.0 * np.cos(2.0 * np.pi * x)))

    one_run, restarted = [], []
    for seed in range(6):
        sizes = []

        def losses(points, sizes=sizes):
            sizes.append(len(points))
            return [rastrigin(p) for p in points]

        start = np.array([3.0, -3.0])
        one_run.append(rastrigin(cmaes(losses, start, sigma=1.0, popsize=6, generations=200,
                                       rng=np.random.default_rng(seed))))
        sizes.clear()
        restarted.append(rastrigin(cmaes_restarts(losses, start, sigma=1.0, popsize=6, budget=1200,
                                                  rng=np.random.default_rng(seed))))
        assert 1200 - max(sizes) < sum(sizes) <= 1200, sizes
        assert sorted(set(sizes))[:3] == [6, 12, 24] and sizes == sorted(sizes), sizes
    assert sum(v < 1e-6 for v in restarted) >= 3 and not any(v < 1e-6 for v in one_run), (one_run, restarted)
    with pytest.raises(ValueError, match="makes no generation of 6"):
        cmaes_restarts(losses, start, sigma=1.0, popsize=6, budget=5, rng=np.random.default_rng(0))
