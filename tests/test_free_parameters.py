"""Free scene parameters of an estimation (warpcloth.tasks.parameters): each one's gradient of TrajectoryFit's loss
against central differences (float64), the change of variables with bounds, fits that recover a wind and an obstacle
friction, the scene file and the CLI taking the names, and bad names and bounds refused by name."""

import math

import numpy as np
import pytest
import warp as wp
from conftest import small_scene

import warpcloth as wc
from warpcloth.tasks import estimation as E
from warpcloth.tasks.parameters import NOT_OFFERED, SCENE_PARAMETERS, START_MODES, ParameterTransform

EXACT = wc.SolverOptions(cg_tol=1e-12, cg_atol=1e-30, cg_max_iters=2000)
GRID_TO_YZ = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])




def _rotation_y(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def hanging(wind=(2.0, 0.0, 0.5), damping=(0.5, 2e-3)):
    """A 0.3 m sheet held by two soft handles, in a wind with drag, damped (alpha [1/s], beta [s]), moving at the
    start."""
    b = wc.ModelBuilder()
    mesh = wc.grid_mesh(3, 3, 0.3, 0.3)
    jitter = np.random.default_rng(7).uniform(-1.0, 1.0, mesh.positions.shape) * 2e-3  # off the lookups' kinks
    mesh.positions = (mesh.positions + jitter) @ GRID_TO_YZ.T + [0.0, -0.15, -0.15]
    mesh.velocities = np.tile([0.3, 0.1, 0.0], (len(mesh.positions), 1))
    b.add_cloth_mesh(mesh, material=wc.preset("gray-interlock", thicken=2))
    b.add_handle(12)
    b.add_handle(15)
    b.set_wind(wind, drag=0.5)
    b.set_damping(mass=damping[0], stiffness=damping[1])
    return b.finalize("cpu", requires_grad=True, dtype=wp.float64)


def sliding(friction=0.3, vel=(0.3, 0.1, 0.0)):
    """A 0.1 m patch sliding on a 30-degree plane (repulsion and friction), launched along it."""
    R = _rotation_y(30.0)
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    b.add_obstacle_plane((4.0, 4.0), rot=R)
    mesh = wc.grid_mesh(2, 2, 0.1, 0.1)
    jitter = np.random.default_rng(7).uniform(-1.0, 1.0, mesh.positions.shape) * [5e-4, 5e-4, 1e-4]
    mesh.positions = (mesh.positions + jitter + [0.45, 1.15, 0.0045]) @ R.T
    mesh.velocities = np.tile(np.asarray(vel) @ R.T, (len(mesh.positions), 1))
    b.add_cloth_mesh(mesh, material=wc.preset("gray-interlock", thicken=2))
    b.set_collision(friction=0.0, obstacle_friction=friction)
    return b.finalize("cpu", requires_grad=True, dtype=wp.float64)


def make_fit(model, steps, dt, *, truth=None, noise=0.0, stride=2, capture=False):
    material = wc.preset("gray-interlock", thicken=2)
    targets = E.TrajectoryFit.simulate_targets(model, truth or material, steps=steps, frame_stride=stride, dt=dt)
    rng = np.random.default_rng(3)
    targets = [x + noise * rng.standard_normal(x.shape) for x in targets]
    return E.TrajectoryFit(model, targets, steps=steps, frame_stride=stride, dt=dt, options=EXACT, capture=capture)


def directional_check(fit, names, h_rel=1e-6, seed=0):
    """(tape, central difference) of d loss / d values along a random direction, for each parameter."""
    material = wc.preset("gray-interlock", thicken=2)
    params = fit.bind_scene(names)
    rng = np.random.default_rng(seed)
    out = {}
    fit.loss_and_grad(material)
    grads = dict(fit.scene_grads)
    for p in params:
        base = p.read()
        d = rng.standard_normal(base.shape) * np.broadcast_to(p.scale, base.shape)
        if p.positive:
            d = d * base
        h = h_rel / float(np.max(np.abs(d / np.where(base != 0.0, np.abs(base), 1.0)))) if np.any(base) else h_rel
        h = max(h, h_rel)
        losses = []
        for sign in (1.0, -1.0):
            p.write(base + sign * h * d)
            losses.append(fit.loss(material))
        p.write(base)
        out[p.name] = (float(grads[p.name] @ d), (losses[0] - losses[1]) / (2.0 * h))
    return out


def _rel(pair):
    tape, fd = pair
    return abs(tape - fd) / max(abs(fd), 1e-300)


def test_every_offered_parameter_is_described_and_damping_names_its_two_parts():
    assert {"wind", "obstacle_friction", "handle_stiffness", "damping_mass", "damping_stiffness", "start_placement",
            "start_velocity", "start_deformation", "start_deformation_rate", "obstacle_placement"
            } <= set(SCENE_PARAMETERS)
    assert "damping_mass" in NOT_OFFERED["damping"] and "damping_stiffness" in NOT_OFFERED["damping"]


HANGING = ["wind", "wind_density", "wind_drag", "gravity", "handle_stiffness", "damping_mass", "damping_stiffness",
           "start_placement", "start_velocity", "start_velocities"]


@pytest.mark.parametrize("capture", [False, True])
def test_hanging_cloth_gradients_match_central_differences(capture):
    fit = make_fit(hanging(), 8, 0.01, noise=0.01, capture=capture)
    if capture:  # captured from the third evaluation: the graphs read the parameters written in place
        for _ in range(3):
            fit.loss_and_grad(wc.preset("gray-interlock", thicken=2))
            fit.loss(wc.preset("gray-interlock", thicken=2))
    checks = directional_check(fit, HANGING)
    errors = {name: _rel(pair) for name, pair in checks.items()}
    assert all(abs(pair[1]) > 0.0 for pair in checks.values()), checks
    assert max(errors.values()) < 1e-5, errors


def test_sliding_cloth_gradients_match_central_differences():
    fit = make_fit(sliding(), 6, 0.005, noise=0.002)
    checks = directional_check(fit, ["obstacle_friction", "contact_stiffness", "obstacle_placement",
                                     "start_velocity", "start_placement"])
    errors = {name: _rel(pair) for name, pair in checks.items()}
    assert all(abs(pair[1]) > 0.0 for pair in checks.values()), checks
    assert max(errors.values()) < 1e-3, errors


@pytest.mark.parametrize("h_rel", [1e-6, 1e-4])
def test_start_deformation_gradients_match_central_differences_at_two_steps(h_rel):
    """The start's smooth deformation and its rate, with the rigid placement on top (its rotation turns the
    deformation's gradient), at two step sizes: the gradient through the modes is exact, not a step's artefact."""
    fit = make_fit(hanging(), 8, 0.01, noise=0.01)
    names = ["start_placement", "start_deformation", "start_deformation_rate"]
    params = fit.bind_scene(names)
    params[0].write(np.array([0.05, -0.1, 0.08, 0.01, 0.0, -0.02]))  # a turned start: R differs from the identity
    checks = directional_check(fit, names, h_rel=h_rel, seed=1)
    errors = {name: _rel(pair) for name, pair in checks.items()}
    assert all(abs(pair[1]) > 0.0 for pair in checks.values()), checks
    assert max(errors.values()) < (1e-5 if h_rel == 1e-6 else 1e-3), errors


@pytest.mark.parametrize("steps, h_rel, tol", [(8, 1e-6, 1e-5), (8, 1e-4, 1e-3), (80, 1e-6, 1e-4)])
def test_damping_gradients_converge_and_stay_bounded(steps, h_rel, tol):
    """The damping's gradient at two step sizes, and over a rollout ten times longer (80 steps: the gradient neither
    grows past the differences nor loses them)."""
    fit = make_fit(hanging(), steps, 0.01, noise=0.01)
    checks = directional_check(fit, ["damping_mass", "damping_stiffness"], h_rel=h_rel, seed=2)
    errors = {name: _rel(pair) for name, pair in checks.items()}
    assert all(abs(pair[1]) > 0.0 and np.isfinite(pair[0]) for pair in checks.values()), checks
    assert max(errors.values()) < tol, errors


def test_the_start_deformation_keeps_the_held_particles_and_moves_the_rest():
    model = hanging()
    fit = make_fit(model, 4, 0.01)
    deformation, rate = fit.bind_scene(["start_deformation", "start_deformation_rate"])
    x0, v0 = model.particle_x0.numpy().copy(), model.particle_v0.numpy().copy()
    rng = np.random.default_rng(2)
    deformation.write(rng.standard_normal(deformation.read().shape) * deformation.scale)
    rate.write(rng.standard_normal(rate.read().shape) * rate.scale)
    moved = np.linalg.norm(model.particle_x0.numpy() - x0, axis=1)
    sped = np.linalg.norm(model.particle_v0.numpy() - v0, axis=1)
    held = model.handle_particle.numpy()
    free = np.setdiff1d(np.arange(model.particle_count), held)
    assert np.all(moved[held] < 1e-12) and np.all(sped[held] < 1e-12), (moved[held], sped[held])  # rounding only
    assert moved[free].min() > 0.0 and sped[free].min() > 0.0
    deformation.write(np.zeros_like(deformation.read()))
    np.testing.assert_allclose(model.particle_x0.numpy(), x0, rtol=0.0, atol=1e-12)


@pytest.mark.parametrize("positive, bounds", [(False, None), (True, None), (False, (-1.0, 4.0)),
                                              (True, (0.1, 10.0)), (False, (0.5, math.inf)),
                                              (True, (None, 3.0))])
def test_transform_maps_into_the_bounds_and_its_chain_rule_is_exact(positive, bounds):
    start = np.array([1.0, 2.0])
    tr = ParameterTransform("x", start, positive=positive, scale=0.5, bounds=bounds)
    assert np.allclose(tr.decode(np.zeros(2)), start, rtol=1e-14)
    rng = np.random.default_rng(1)
    for t in (rng.standard_normal(2), 30.0 * rng.standard_normal(2)):
        x = tr.decode(t)
        if bounds is not None:
            low, high = (-math.inf if b is None else b for b in bounds)
            assert np.all((x > low) & (x < high))
        g = rng.standard_normal(2)
        h = 1e-6
        fd = [(g @ tr.decode(t + h * e) - g @ tr.decode(t - h * e)) / (2 * h) for e in np.eye(2)]
        np.testing.assert_allclose(tr.chain(t, g), fd, rtol=1e-6, atol=1e-8 * (1.0 + np.max(np.abs(fd))))


def test_fit_recovers_a_wind_velocity():
    truth = np.array([2.0, 0.0, 0.5])
    fit = make_fit(hanging(wind=truth), 20, 0.01)
    fit.model.wind_velocity.assign(np.array([[0.5, 0.3, 0.0]]))  # the fit's start
    result = E.estimate_material(fit, initial=wc.preset("gray-interlock", thicken=2), free=["wind"], iters=25,
                                 curriculum=None)
    error = np.linalg.norm(result.parameters["wind"] - truth) / np.linalg.norm(truth)
    assert error < 0.1, (result.parameters["wind"], error)
    assert np.allclose(fit.model.wind_velocity.numpy()[0], result.parameters["wind"])  # the model keeps it
    assert set(result.parameters) == {"wind"}


def test_fit_recovers_the_damping():
    truth = (0.5, 2e-3)
    fit = make_fit(hanging(damping=truth), 20, 0.01)
    fit.model.damping_mass.assign(np.array([0.2]))  # the fit's start
    fit.model.damping_stiffness.assign(np.array([5e-3]))
    result = E.estimate_material(fit, initial=wc.preset("gray-interlock", thicken=2),
                                 free=["damping_mass", "damping_stiffness"], iters=25, curriculum=None)
    fitted = [float(result.parameters[n][0]) for n in ("damping_mass", "damping_stiffness")]
    errors = [abs(f - t) / t for f, t in zip(fitted, truth)]
    assert max(errors) < 0.1, (fitted, errors)
    assert fit.model.damping_mass.numpy()[0] == fitted[0]  # the model keeps it


def test_fit_recovers_an_obstacle_friction():
    truth = 0.3
    fit = make_fit(sliding(friction=truth), 40, 0.005, stride=4)
    friction = fit.model.contact_friction.numpy()
    fit.model.contact_friction.assign(np.array([friction[0], 0.15]))
    result = E.estimate_material(fit, initial=wc.preset("gray-interlock", thicken=2), free=["obstacle_friction"],
                                 iters=15, curriculum=None, bounds={"obstacle_friction": [0.01, 2.0]})
    fitted = float(result.parameters["obstacle_friction"][0])
    assert abs(fitted - truth) / truth < 0.1, fitted


def test_material_only_fit_is_unchanged_and_reports_its_parts():
    model = hanging()
    fit = make_fit(model, 8, 0.01, noise=0.01)
    result = E.estimate_material(fit, free=["density"], iters=6)
    assert set(result.parameters) == {"density"}
    assert result.parameters["density"][0] == result.material.density


def test_scene_file_and_task_take_scene_parameters(tmp_path):
    scene = small_scene(tmp_path, '[wind]\nvelocity = [1.0, 0.0, 0.0]\n[estimate]\nfree = ["density", "wind"]\n'
                                  'iters = 4\n[estimate.bounds]\nwind = [-5.0, 5.0]\n[estimate.scales]\nwind = 0.5\n')
    task = E.EstimationTask.from_scene(scene, device="cpu")
    assert task.free == ("density", "wind") and task.bounds == {"wind": [-5.0, 5.0]} and task.scales == {"wind": 0.5}
    result = task.run()
    assert set(result.parameters) == {"density", "wind"} and np.all(np.abs(result.parameters["wind"]) < 5.0)


def test_scene_file_and_cli_take_the_damping(tmp_path):
    import json

    from warpcloth.cli import main

    scene = small_scene(tmp_path, '[damping]\nmass = 0.3\nstiffness = 1e-3\n[estimate]\n'
                                  'free = ["density", "damping_mass", "damping_stiffness"]\niters = 3\n')
    result = E.EstimationTask.from_scene(scene, device="cpu").run()
    assert {"damping_mass", "damping_stiffness"} <= set(result.parameters)
    assert result.parameters["damping_mass"].shape == (1,) and result.parameters["damping_mass"][0] > 0.0
    out = tmp_path / "fit.json"
    assert main(["estimate", str(scene), "--free", "damping_stiffness", "--device", "cpu", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["start_parameters"]["damping_stiffness"] == pytest.approx([1e-3])


def test_scene_file_and_cli_take_the_start_deformation(tmp_path):
    import json

    from warpcloth.cli import main

    scene = small_scene(tmp_path, '[estimate]\nfree = ["density", "start_deformation", "start_deformation_rate"]\n'
                                  'iters = 3\n')
    task = E.EstimationTask.from_scene(scene, device="cpu")
    result = task.run()
    modes = min(START_MODES, 25 - 2)  # the 4x4-cell sheet's 25 particles, 2 held
    assert result.parameters["start_deformation"].shape == (3 * modes,)
    assert result.parameters["start_deformation_rate"].shape == (3 * modes,)
    out = tmp_path / "fit.json"
    assert main(["estimate", str(scene), "--free", "density,start_deformation", "--device", "cpu", "--json",
                 str(out)]) == 0
    assert json.loads(out.read_text())["start_parameters"]["start_deformation"] == [0.0] * (3 * modes)


@pytest.mark.parametrize("extra, message", [
    ('free = ["density", "damping"]', r"estimate.free\[1\]: 'damping' names no one parameter: the Rayleigh"),
    ('free = ["density", "windd"]', r"estimate.free\[1\]: unknown value 'windd'"),
    ('free = ["wind"]\n[estimate.bounds]\ndensity = [0.0, 1.0]', r"estimate.bounds.density: not a free scene"),
    ('free = ["wind"]\n[estimate.bounds]\nwind = [1.0]', r"estimate.bounds.wind: expected \[low, high\]"),
    ('free = ["wind"]\n[estimate.scales]\nwind = -1.0', r"estimate.scales.wind: must be finite and > 0"),
])
def test_bad_free_parameters_in_a_scene_are_named(tmp_path, extra, message):
    with pytest.raises(ValueError, match=message):
        wc.load_scene(small_scene(tmp_path, "[estimate]\n" + extra))


def test_a_parameter_the_scene_lacks_or_bad_bounds_are_named(tmp_path):
    with pytest.raises(ValueError, match=r"free parameter 'obstacle_friction': the scene has no collisions"):
        E.EstimationTask.from_scene(small_scene(tmp_path, '[estimate]\nfree = ["obstacle_friction"]\n'),
                                    device="cpu")
    with pytest.raises(ValueError, match=r"free parameter 'wind': the scene has no wind"):
        E.EstimationTask.from_scene(small_scene(tmp_path, '[estimate]\nfree = ["wind"]\n'), device="cpu")
    fit = make_fit(hanging(), 4, 0.01)
    with pytest.raises(ValueError, match=r"free parameter 'wind': entry 0 starts at 2, not inside its bounds"):
        E.estimate_material(fit, free=["wind"], iters=2, bounds={"wind": [-1.0, 1.0]})
    with pytest.raises(ValueError, match=r"free parameter 'handle_stiffness': bounds need low < high"):
        E.estimate_material(fit, free=["handle_stiffness"], iters=2, bounds={"handle_stiffness": [10.0, 1.0]})
    with pytest.raises(ValueError, match=r"free\[1\]: unknown free parameter 'breeze'"):
        E.estimate_material(fit, free=["density", "breeze"], iters=2)
    with pytest.raises(ValueError, match=r"'damping' names no one parameter: .*damping_mass"):
        E.estimate_material(fit, free=["damping"], iters=2)
    with pytest.raises(ValueError, match=r"bounds: 'gravity' is not a free scene parameter"):
        E.estimate_material(fit, free=["wind"], iters=2, bounds={"gravity": [-20.0, 20.0]})
    undamped = make_fit(hanging(damping=(0.0, 2e-3)), 4, 0.01)
    with pytest.raises(ValueError, match=r"free parameter 'damping_mass': entry 0 starts at 0; it is fitted in log "
                                         r"space and must start > 0"):
        E.estimate_material(undamped, free=["damping_mass"], iters=2)


def test_cli_takes_free_parameters_bounds_and_scales(tmp_path):
    import json

    from warpcloth.cli import main

    scene = small_scene(tmp_path, '[wind]\nvelocity = [1.0, 0.0, 0.0]\n[estimate]\niters = 3\n')
    out = tmp_path / "fit.json"
    assert main(["estimate", str(scene), "--free", "density,wind,handle_stiffness", "--bound", "wind=-5,5",
                 "--scale", "handle_stiffness=0.5", "--device", "cpu", "--json", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["free"] == ["density", "wind", "handle_stiffness"]
    assert len(record["parameters"]["wind"]) == 3 and len(record["parameters"]["handle_stiffness"]) == 2
    assert record["start_parameters"]["wind"] == [1.0, 0.0, 0.0]
    assert main(["estimate", str(scene), "--free", "density,obstacle_friction", "--device", "cpu"]) == 2
    assert main(["estimate", str(scene), "--free", "wind", "--bound", "wind=-5", "--device", "cpu"]) == 2
