"""Bad inputs raise a ValueError naming the offending element; divergence and failed solves name the step."""

import math
import re
import warnings
from dataclasses import replace

import numpy as np
import pytest
import warp as wp
from conftest import hanging_builder

import warpcloth as wc
from warpcloth.mesh_io import TriangleMesh

NAN, INF = float("nan"), float("inf")
MAT = wc.preset("gray-interlock", thicken=2)


def square(fourth=(0.0, 1.0, 0.0), triangles=((0, 1, 2), (0, 2, 3)), tri_uv=False, extra=()):
    positions = np.array([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1.0, 0.0), fourth, *extra])
    triangles = np.array(triangles, dtype=np.int32)
    uv = positions[triangles][:, :, :2].copy() if tri_uv else None
    return TriangleMesh(positions=positions, triangles=triangles, tri_uv=uv)


def tables(**changes):
    kw = dict(density=0.2, stretching=np.full((6, 4), 10.0), bending=np.full((3, 5), 1.0e-5))
    kw.update(changes)
    return kw


def with_entry(table, index, value):
    table = table.copy()
    table[index] = value
    return table


# -- meshes ------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("tri_uv", [False, True], ids=["initial-shape", "material-coords"])
def test_degenerate_triangle_names_it(tri_uv):
    # vertex 3 on the diagonal 0-2: triangle 1 (0, 2, 3) has zero area
    mesh = square(fourth=(0.5, 0.5, 0.0), tri_uv=tri_uv)
    with pytest.raises(ValueError, match=r"triangle 1 \[0, 2, 3\].*(zero|degenerate)"):
        wc.ModelBuilder().add_cloth_mesh(mesh, material=MAT)


def test_inverted_material_triangle_names_it():
    mesh = square(tri_uv=True)
    mesh.tri_uv[1] = mesh.tri_uv[1][::-1]
    with pytest.raises(ValueError, match=r"triangle 1 .*negative"):
        wc.ModelBuilder().add_cloth_mesh(mesh, material=MAT)


def test_non_manifold_edge_names_it():
    mesh = square(triangles=((0, 1, 2), (1, 0, 3), (0, 1, 4)), extra=[(0.5, 0.5, 1.0)])
    with pytest.raises(ValueError, match=r"non-manifold edge \(0, 1\).*\[0, 1, 2\]"):
        wc.ModelBuilder().add_cloth_mesh(mesh, material=MAT)


def test_index_out_of_range_names_it():
    with pytest.raises(ValueError, match=r"triangle 1 \[0, 2, 7\]: index 7 out of range"):
        wc.ModelBuilder().add_cloth_mesh(square(triangles=((0, 1, 2), (0, 2, 7))), material=MAT)
    b = wc.ModelBuilder()
    b.add_cloth_grid((2, 2), (1.0, 1.0), material=MAT)
    with pytest.raises(ValueError, match=r"add_handle: particle 9 out of range \[0, 9\)"):
        b.add_handle(9)
    with pytest.raises(ValueError, match=r"add_pin: particle -1 out of range"):
        b.add_pin(-1)


# -- non-finite and out-of-range values --------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [NAN, INF, -INF])
def test_non_finite_position(bad):
    with pytest.raises(ValueError, match=r"vertex 3 has a non-finite position"):
        wc.ModelBuilder().add_cloth_mesh(square(fourth=(0.0, bad, 0.0)), material=MAT)
    with pytest.raises(ValueError, match=r"pos has a non-finite component"):
        wc.ModelBuilder().add_cloth_grid((2, 2), (1.0, 1.0), material=MAT, pos=(0.0, 0.0, bad))


@pytest.mark.parametrize("bad", [NAN, INF])
def test_non_finite_velocity_gravity_wind(bad):
    with pytest.raises(ValueError, match=r"vel has a non-finite component"):
        wc.ModelBuilder().add_cloth_grid((2, 2), (1.0, 1.0), material=MAT, vel=(bad, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"vel has a non-finite component"):
        wc.ModelBuilder().add_cloth_mesh(square(), material=MAT, vel=(0.0, bad, 0.0))
    with pytest.raises(ValueError, match=r"gravity has a non-finite component"):
        wc.ModelBuilder(gravity=(0.0, 0.0, bad))
    with pytest.raises(ValueError, match=r"wind velocity has a non-finite component"):
        wc.ModelBuilder().set_wind((0.0, bad, 0.0))
    with pytest.raises(ValueError, match=r"wind density must be finite"):
        wc.ModelBuilder().set_wind((1.0, 0.0, 0.0), density=bad)


@pytest.mark.parametrize("bad", [NAN, INF])
def test_non_finite_material_tables_name_the_entry(bad):
    with pytest.raises(ValueError, match=r"stretching\[2, 1\] is not finite"):
        wc.Material(**tables(stretching=with_entry(np.full((6, 4), 10.0), (2, 1), bad)))
    with pytest.raises(ValueError, match=r"bending\[1, 3\] is not finite"):
        wc.Material(**tables(bending=with_entry(np.full((3, 5), 1e-5), (1, 3), bad)))
    with pytest.raises(ValueError, match=r"density is not finite"):
        wc.Material(**tables(density=bad))


@pytest.mark.parametrize("density", [0.0, -0.1])
def test_non_positive_density(density):
    with pytest.raises(ValueError, match=r"density must be > 0"):
        wc.Material(**tables(density=density))
    with pytest.raises(ValueError, match=r"density must be > 0"):
        wc.Material.isotropic(density=density, stretch_stiffness=10.0, shear_stiffness=1.0, bend_stiffness=1e-5)


def test_negative_stiffness_names_the_entry():
    for col in (0, 2):
        with pytest.raises(ValueError, match=rf"stretching\[4, {col}\] .*must be >= 0, got -1"):
            wc.Material(**tables(stretching=with_entry(np.full((6, 4), 10.0), (4, col), -1.0)))
    # coupling (column 1) and shear (column 3) may be negative in measured data: the model applies relu
    wc.Material(**tables(stretching=with_entry(np.full((6, 4), 10.0), (0, 1), -1.0)))
    with pytest.raises(ValueError, match=r"bending\[2, 0\] must be >= 0"):
        wc.Material(**tables(bending=with_entry(np.full((3, 5), 1e-5), (2, 0), -1e-6)))
    for pname in ("stretch_stiffness", "shear_stiffness", "bend_stiffness"):
        kw = dict(density=0.2, stretch_stiffness=10.0, shear_stiffness=1.0, bend_stiffness=1e-5)
        kw[pname] = -1.0
        with pytest.raises(ValueError, match=rf"isotropic: {pname} must be finite and >= 0"):
            wc.Material.isotropic(**kw)
    b = wc.ModelBuilder()
    b.add_cloth_grid((2, 2), (1.0, 1.0), material=MAT)
    for k in (-1.0, NAN):
        with pytest.raises(ValueError, match=r"handle on particle 4: stiffness must be finite and >= 0"):
            b.add_handle(4, stiffness=k)


def test_unknown_preset_lists_names():
    with pytest.raises(ValueError, match=r"unknown material preset 'grey-interlock'; valid names: .*gray-interlock"):
        wc.preset("grey-interlock")


# -- simulator settings ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_model():
    return hanging_builder(res=2).finalize("cpu")


@pytest.mark.parametrize("dt", [0.0, -1.0, NAN, INF])
def test_non_positive_dt(small_model, dt):
    with pytest.raises(ValueError, match=r"dt must be a finite number > 0"):
        wc.Simulator(small_model, dt)


@pytest.mark.parametrize(
    "field, value",
    [("cg_tol", 0.0), ("cg_tol", -1e-6), ("cg_tol", NAN), ("cg_atol", -1.0), ("max_speed", 0.0), ("max_speed", INF),
     ("cg_max_iters", 0), ("preconditioner", "ilu"), ("cg_backend", "gpu"), ("on_cg_failure", "ignore")],
)
def test_bad_solver_options_name_the_field(small_model, field, value):
    # raised either by SolverOptions itself or, at the latest, by the Simulator that validates it
    with pytest.raises(ValueError, match=rf"SolverOptions\.{field} must"):
        wc.Simulator(small_model, 0.01, options=wc.SolverOptions(**{field: value}))


# -- scenes ------------------------------------------------------------------------------------------------------------


def test_unknown_scene_name_and_key():
    from warpcloth import scene

    with pytest.raises(ValueError, match=r"unknown scene 'no-such-scene'; embedded scenes: .*hanging-wind"):
        scene.load_scene("no-such-scene")
    text = 'name = "t"\n[sim]\ndt = 0.01\nsteps = 2\n[cloth]\ngrid = { res = [2, 2], size = [1.0, 1.0] }\n'
    text += 'material = "gray-interlock"\nthickness = 2.0\n'
    with pytest.raises(ValueError, match=r"t\.toml: cloth\.thickness: unknown key"):
        scene.scene_from_toml(text, source="t.toml")


# -- runtime failures --------------------------------------------------------------------------------------------------


def free_fall_model(dtype=wp.float64):
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    b.add_cloth_grid((2, 2), (0.5, 0.5), material=MAT)
    return b.finalize("cpu", dtype=dtype)


def test_divergence_names_the_step():
    # free fall gains 0.098 m/s per step: it passes a 0.25 m/s speed limit on the third step
    model = free_fall_model()
    sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(max_speed=0.25))
    with pytest.raises(wc.SimulationError, match=r"diverged at step 3 .*particle \d+ moves at 0.29\d+ m/s, over "
                                                 r"SolverOptions.max_speed = 0.25 m/s.*raise max_speed"):
        wc.rollout(sim, model.state(), steps=10)


def test_huge_force_diverges_with_the_particle_named():
    model = hanging_builder(res=2).finalize("cpu")
    control = model.control(particle_force=True)
    control.particle_force.assign(np.array([[0.0, 0.0, 0.0]] * 3 + [[1.0e9, 0.0, 0.0]] * 1 + [[0.0, 0.0, 0.0]] * 5))
    sim = wc.Simulator(model, 0.01)
    with pytest.raises(wc.SimulationError, match=r"step 1 .*particle \d"):
        wc.rollout(sim, model.state(), control, steps=5)


def test_non_finite_state_is_caught_at_the_first_step():
    model = free_fall_model()
    state = model.state()
    x = state.particle_x.numpy()
    x[4, 2] = NAN
    state.particle_x.assign(x)
    with pytest.raises(wc.SimulationError, match=r"step 1: particle 4 enters the step with a non-finite position"):
        wc.rollout(wc.Simulator(model, 0.01), state, steps=1)


def test_overflowing_positions_and_stiffness_are_named():
    model = free_fall_model()
    state = model.state()
    state.particle_x.assign(state.particle_x.numpy() + 1.0e30)
    with pytest.raises(wc.SimulationError, match=r"step 1: particle 0 is at .*more than 1e6 m .*overflow in float64"):
        wc.rollout(wc.Simulator(model, 0.01), state, steps=1)
    b = wc.ModelBuilder()
    b.add_cloth_grid((4, 4), (1.0, 1.0), material=MAT.scaled(stretching=1.0e30))
    b.add_handle(0)
    model = b.finalize("cpu")
    with pytest.raises(wc.SimulationError, match=r"step 1: .*largest stretching entry .*overflow float32"):
        wc.rollout(wc.Simulator(model, 0.01), model.state(), steps=1)


def test_a_model_too_light_for_the_absolute_floor_warns():
    # a 1e-12 kg/m^2 cloth: |b| is below cg_atol, the solve stops at once and the cloth never moves
    b = wc.ModelBuilder()
    b.add_cloth_grid((4, 4), (1.0, 1.0), material=MAT.scaled(density=1.0e-12))
    model = b.finalize("cpu", dtype=wp.float64)
    with pytest.warns(RuntimeWarning, match=r"step 1: .*cg_atol = 1e-12.*too light.*does not move; lower cg_atol"):
        wc.rollout(wc.Simulator(model, 0.01), model.state(), steps=2)
    lighter_floor = wc.Simulator(model, 0.01, options=wc.SolverOptions(cg_atol=1.0e-30))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        traj = wc.rollout(lighter_floor, model.state(), steps=2)
    assert traj[-1].particle_x.numpy()[:, 2].max() < -1e-4  # it falls


def hard_problem(**options):
    """A wind-blown hanging cloth whose system is coupled enough that one CG iteration cannot solve it."""
    model = hanging_builder(res=4).finalize("cpu", requires_grad=True, dtype=wp.float64)
    state = model.state()
    state.particle_v.assign(np.random.default_rng(0).standard_normal((model.particle_count, 3)))
    return model, state, wc.Simulator(model, 0.02, options=wc.SolverOptions(**options))


def residual_in(message):
    m = re.search(r"relative residual (\S+)", message)
    return float(m.group(1)) if m else math.nan


def test_cg_non_convergence_warns_with_the_residual():
    _, state, sim = hard_problem(cg_max_iters=1)
    with pytest.warns(RuntimeWarning, match=r"forward CG solve of step \d+ did not converge") as record:
        wc.rollout(sim, state, steps=1)
    assert residual_in(str(record[0].message)) > sim.options.cg_tol


def test_cg_non_convergence_raises_on_request():
    _, state, sim = hard_problem(cg_max_iters=1, on_cg_failure="raise")
    with pytest.raises(wc.SimulationError, match=r"did not converge: relative residual \d\.\d+e[-+]\d+"):
        wc.rollout(sim, state, steps=1)


def test_forward_solve_and_divergence_name_the_same_step():
    # The k-th call of step() must be called "step k" by both errors (the divergence guard counts from 1).
    model, state, _ = hard_problem()
    steps = {}
    for name, options in (("divergence", dict(max_speed=1e-6)), ("solve", dict(cg_max_iters=1, on_cg_failure="raise"))):
        sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(**options))
        with pytest.raises(wc.SimulationError) as info:
            sim.step(state, model.empty_state())
        steps[name] = int(re.search(r"step (\d+)", str(info.value)).group(1))
    assert steps["solve"] == steps["divergence"] == 1, steps


def test_adjoint_failure_names_its_own_step():
    # The adjoint solves run in reverse after the whole forward pass; each warning must name the step it belongs to.
    model, state, sim = hard_problem(cg_tol=1e-10)
    tape = wp.Tape()
    with tape:
        final = wc.rollout(sim, state, steps=3)[-1]
    sim.options = replace(sim.options, cg_max_iters=1)
    ones = wp.array(np.ones((model.particle_count, 3)), dtype=model.types.vec3)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        tape.backward(grads={final.particle_x: ones})
    named = sorted(int(re.search(r"adjoint CG solve of step (\d+)", str(w.message)).group(1)) for w in record
                   if "adjoint" in str(w.message))
    assert named == [1, 2, 3], f"adjoint warnings name steps {named}"


def test_a_deferred_check_reports_the_first_failed_solve_and_counts_the_rest():
    # sync_every=0: no step reads the failure record; the rollout's end does, once
    _, state, sim = hard_problem(cg_max_iters=1, sync_every=0)
    with pytest.warns(RuntimeWarning, match=r"forward CG solve of step 1 did not converge.*\(2 more solves missed"):
        wc.rollout(sim, state, steps=3)


def test_deferred_adjoint_failures_are_reported_by_check():
    model, state, sim = hard_problem(cg_tol=1e-10, sync_every=0)
    tape = wp.Tape()
    with tape:
        final = wc.rollout(sim, state, steps=3)[-1]
    sim.options = replace(sim.options, cg_max_iters=1, on_cg_failure="raise")
    tape.backward(grads={final.particle_x: wp.array(np.ones((model.particle_count, 3)), dtype=model.types.vec3)})
    # the adjoint solves run from the last step to the first: the first failure latched is step 3's
    with pytest.raises(wc.SimulationError, match=r"adjoint CG solve of step 3 did not converge"):
        sim.check()
    sim.check()  # read and cleared: nothing left to report
