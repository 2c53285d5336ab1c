"""Solver presets, their use in scene files, and the separate tolerance of the adjoint solve."""

import textwrap

import numpy as np
import pytest
import warp as wp

import warpcloth as wc
from warpcloth.scene import scene_from_toml

SCENE = """\
name = "test"
[sim]
dt = {dt}
steps = 2
[cloth]
grid = {{ res = [4, 3], size = [1.0, 0.5] }}
material = "gray-interlock"
"""


def _scene(solver: str, dt: float = 0.0025):
    return scene_from_toml(SCENE.format(dt=dt) + textwrap.dedent(solver), source="t.toml")


@pytest.mark.parametrize("name", wc.PRESET_SOLVER_NAMES)
def test_preset_time_step_divides_frames_and_respects_its_ceiling(name):
    preset = wc.solver_preset(name)
    for frame in (0.04, 0.02, 1.0 / 60.0, 0.001):
        dt = preset.dt(frame)
        steps = round(frame / dt)
        assert frame / dt == pytest.approx(steps, abs=1e-9) and dt <= preset.max_dt * (1 + 1e-12)
        assert steps == 1 or frame / (steps - 1) > preset.max_dt  # one step fewer would be too long


def test_presets_order_by_accuracy():
    fast, balanced, accurate = (wc.solver_preset(n) for n in ("fast", "balanced", "accurate"))
    assert fast.max_dt >= balanced.max_dt >= accurate.max_dt
    assert fast.options.cg_tol >= balanced.options.cg_tol >= accurate.options.cg_tol


def test_unknown_preset_and_bad_frame_time():
    with pytest.raises(ValueError, match="unknown solver preset 'quick'; one of: fast, balanced, accurate"):
        wc.solver_preset("quick")
    with pytest.raises(ValueError, match="frame_dt must be a finite number > 0"):
        wc.solver_preset("fast").dt(0.0)


def test_preset_with_options_overrides_one_field():
    p = wc.solver_preset("accurate").with_options(on_cg_failure="raise")
    assert p.options.on_cg_failure == "raise" and p.options.cg_tol == wc.solver_preset("accurate").options.cg_tol


def test_scene_preset_sets_options_and_keys_override_it():
    scene = _scene('[solver]\npreset = "balanced"\ncg_max_iters = 77\n', dt=0.01)
    expected = wc.solver_preset("balanced").options
    assert scene.solver_options.cg_tol == expected.cg_tol
    assert scene.solver_options.collision.rounds == expected.collision.rounds
    assert scene.solver_options.cg_max_iters == 77


@pytest.mark.parametrize("solver, dt, match", [
    ('preset = "accurate"', 0.02, r"solver.preset: the 'accurate' preset steps at most 0.0025 s but sim.dt is 0.02"),
    ('preset = "precise"', 0.001, r"solver.preset: unknown preset 'precise'; one of: fast, balanced, accurate"),
    ("preset = 3", 0.001, r"solver.preset: expected a string, got integer"),
    ('adjoint_cg_tol = "tight"', 0.001, r"solver.adjoint_cg_tol: expected a number, got string"),
    ("adjoint_cg_tol = -1.0", 0.001, r"adjoint_cg_tol must be finite and > 0"),
    ("cg_max_iters = 1.5", 0.001, r"solver.cg_max_iters: expected an integer, got float"),
    ("warm_start = 1", 0.001, r"solver.warm_start: expected a boolean, got integer"),
])
def test_scene_solver_table_errors_name_the_key(solver, dt, match):
    with pytest.raises(ValueError, match=match):
        _scene("[solver]\n" + solver + "\n", dt=dt)


def _hanging(requires_grad=True):
    b = wc.ModelBuilder()
    b.add_cloth_grid((6, 6), (0.5, 0.5), material=wc.preset("gray-interlock", thicken=2),
                     rot=np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), pos=(0.0, -0.25, -0.25))
    b.add_handle(6 * 7)
    b.add_handle(6 * 7 + 6)
    b.set_wind((3.0, 0.0, 0.0))
    return b.finalize("cpu", requires_grad=requires_grad, dtype=wp.float64)


def _wind_gradient(options):
    model = _hanging()
    sim = wc.Simulator(model, 0.02, options=options)
    tape = wp.Tape()
    with tape:
        traj = wc.rollout(sim, model.state(), steps=10)
    tape.backward(grads={traj[-1].particle_x: wp.ones_like(traj[-1].particle_x, requires_grad=False)})
    return model.wind_velocity.grad.numpy().copy(), sim.stats


def test_adjoint_tolerance_is_separate_from_the_forward_one():
    exact, exact_stats = _wind_gradient(wc.SolverOptions(cg_tol=1e-12, warm_start=False))
    loose, loose_stats = _wind_gradient(wc.SolverOptions(cg_tol=1e-12, adjoint_cg_tol=1e-2, warm_start=False))
    # the forward solves are the same; only the adjoint ones stop early, and the gradient shows it
    assert loose_stats["cg_iterations"] == exact_stats["cg_iterations"]
    assert loose_stats["adjoint_cg_iterations"] < exact_stats["adjoint_cg_iterations"]
    err = np.linalg.norm(loose - exact) / np.linalg.norm(exact)
    assert 1e-8 < err < 0.1
    tight, _ = _wind_gradient(wc.SolverOptions(cg_tol=1e-12, adjoint_cg_tol=1e-10, warm_start=False))
    assert np.linalg.norm(tight - exact) / np.linalg.norm(exact) < 1e-7
