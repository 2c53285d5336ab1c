"""Many worlds in one model (ModelBuilder.add_world / replicate): N worlds simulated together give each world what a
model of that world alone gives (states and gradients, with and without contact), worlds never touch each other
even where they overlap in space, and a failing world is named."""

import numpy as np
import pytest
import warp as wp
from conftest import DEVICES, hanging_builder

import warpcloth as wc

# Each world's solve runs on its own; to compare with single-world runs both use the same preconditioner (a
# single world's "auto" is multigrid, which spans one world).
SSOR = dict(preconditioner="block_ssor", cg_tol=1e-10)
TILED = {**SSOR, "preconditioner": "block_jacobi", "cg_backend": "tiled"}
"""The GPU's CG backend (one thread block per world; one thread on the CPU): the same per-world independence."""
MULTIGRID = {**SSOR, "preconditioner": "multigrid", "cg_backend": "sequential"}
"""The CPU's default: a multigrid hierarchy per world, each world's V-cycle on its world's thread."""
TILED_MULTIGRID = {**TILED, "preconditioner": "multigrid"}
"""The multigrid's parallel form in the GPU's CG backend: each world's V-cycle on its world's thread block."""


@wp.kernel
def weighted_sum(x: wp.array(dtype=wp.vec3d), weight: wp.array(dtype=wp.vec3d), loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(x[i], weight[i]))


def equal_on(device, rtol):
    """An assertion that two results are equal: bitwise on the CPU, to ``rtol`` (and 1e-12 of their scale) on
    CUDA, whose atomic additions sum in no set order."""
    if device == "cpu":
        return np.testing.assert_array_equal
    return lambda a, b: np.testing.assert_allclose(a, b, rtol=rtol, atol=1e-12 * max(np.abs(b).max(), 1.0))


def loss_and_grads(model, sim, steps, weights, control=None, params=()):
    """L = sum_i w_i . x_i after ``steps`` steps, and dL/d(each array in ``params``)."""
    tape = wp.Tape()
    with wp.ScopedDevice(model.device), tape:
        traj = wc.rollout(sim, model.state(), control, steps=steps)
        loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        wp.launch(weighted_sum, model.particle_count, inputs=[traj[-1].particle_x,
                  wp.array(weights, dtype=wp.vec3d)], outputs=[loss])
    tape.backward(loss)
    grads = [p.grad.numpy().copy() for p in params]
    tape.zero()
    return traj[-1].particle_x.numpy(), grads


def pushed_gradients(model, forces, weights, *, dt, steps, options):
    """A forced rollout's final positions and the gradients of ``sum_i w_i . x_i`` with respect to (0) the forces,
    (1) x0, (2) v0, (3) the obstacles' placement, (4) density, (5) stretching, (6) bending; and its Simulator."""
    control = model.control(particle_force=True)
    control.particle_force.assign(forces)
    sim = wc.Simulator(model, dt, options=options)
    x, grads = loss_and_grads(model, sim, steps, weights, control, params=(
        control.particle_force, model.particle_x0, model.particle_v0, control.obstacle_transform,
        model.material_density, model.material_stretching, model.material_bending))
    return x, grads, sim


def hanging_world(name, wind, gravity):
    return hanging_builder(material=wc.preset(name, thicken=2), wind=wind, gravity=gravity)


WORLDS = [("gray-interlock", (0.5, 2.0, 0.0), (0.0, 0.0, -2.0)),
          ("11oz-black-denim", None, (0.0, 0.0, -9.8)),
          ("tango-red-jet-set", (1.0, -1.0, 0.5), (0.3, 0.0, -5.0))]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("solve", [SSOR, TILED, MULTIGRID, TILED_MULTIGRID],
                         ids=["sequential", "tiled", "multigrid", "tiled-multigrid"])
def test_worlds_without_contact_equal_single_runs_states_and_gradients(solve, device):
    """Per-world materials, wind and gravity: each world's state and gradients (its material, wind, gravity and
    initial velocities) equal a single-world model's, bitwise on the CPU (the same kernels, and each world's CG on
    its own; on CUDA the assembly's atomic additions differ in the last bits from run to run)."""
    steps, rng = 8, np.random.default_rng(1)
    composed = wc.ModelBuilder()
    singles = []
    for name, wind, gravity in WORLDS:
        builder = hanging_world(name, wind, gravity)
        composed.add_world(builder)
        model = builder.finalize(device, requires_grad=True, dtype=wp.float64)
        singles.append(model)
    batch = composed.finalize(device, requires_grad=True, dtype=wp.float64)
    assert batch.world_count == 3 and batch.material_count == 3
    weights = rng.standard_normal((batch.particle_count, 3))
    batch_sim = wc.Simulator(batch, 0.02, options=wc.SolverOptions(**solve))
    x, (g_density, g_gravity, g_wind, g_v0) = loss_and_grads(
        batch, batch_sim, steps, weights,
        params=(batch.material_density, batch.gravity, batch.wind_velocity, batch.particle_v0))
    assert batch_sim.linear_solver.world_info.shape == (3, 3)
    for w, model in enumerate(singles):
        part = batch.world_slice(w)
        sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(**solve))
        params = [model.material_density, model.gravity, model.particle_v0]
        if model.wind_velocity is not None:
            params.append(model.wind_velocity)
        xs, grads = loss_and_grads(model, sim, steps, weights[part], params=params)
        # on CUDA the batch and the single world add their blocks with atomics in different orders: in float64
        # their gradients differed by up to 1.5e-8 relatively on an H100 (2026-11-27)
        same = equal_on(device, rtol=1e-7)
        same(x[part], xs)
        same(g_density[w], grads[0][0])
        same(g_gravity[w], grads[1][0])
        same(g_v0[part], grads[2])
        if model.wind_velocity is not None:
            same(g_wind[w], grads[3][0])
        else:
            assert np.all(np.isfinite(g_wind[w]))  # a windless world: density and drag 0, the wind does nothing
        assert np.abs(grads[0]).max() > 0.0


def draped_builder():
    """A 6x6 cloth dropped onto a sphere: contact (projection, repulsion and friction) within a few steps."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    b.add_cloth_grid((6, 6), (0.4, 0.4), material=wc.preset("gray-interlock", thicken=2), pos=(-0.2, -0.2, 0.01),
                     vel=(0.0, 0.0, -1.0))
    b.add_obstacle_sphere(0.12, name="ball", pos=(0.0, 0.0, -0.12))
    return b


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("solve", [SSOR, TILED, MULTIGRID, TILED_MULTIGRID],
                         ids=["sequential", "tiled", "multigrid", "tiled-multigrid"])
def test_worlds_with_contact_equal_single_runs_states_and_gradients(solve, device):
    """A cloth dropped on a sphere (projection, repulsion, friction) replicated with a different push per world:
    states and the gradients of every parameter (forces, density, stretching, bending, x0, v0, the sphere's
    placement) equal single-world runs (float64), bitwise on the CPU (the material, which the worlds share, to
    rounding: the sum of theirs; single-world gradients are checked against central differences in
    tests/test_contact_gradient_matrix.py): each world's contacts are projected by their own thread block, a world
    without new contacts in a round keeps its solution, and one without contacts in a step passes its gradient on
    exactly, so steps where only some worlds touch the sphere (13 here) match too. On CUDA to rounding (the
    assembly's atomic additions; not yet run there)."""
    base, steps, worlds = draped_builder(), 30, 3
    rng = np.random.default_rng(2)
    pushed = [0, 6, 42, 48]
    pushes = [rng.normal(0.0, 0.05, (len(pushed), 3)) for _ in range(worlds)]
    composed = wc.ModelBuilder()
    composed.replicate(base, worlds)
    batch = composed.finalize(device, requires_grad=True, dtype=wp.float64)
    same = equal_on(device, rtol=1e-6)
    weights = rng.standard_normal((batch.particle_count, 3))
    options = wc.SolverOptions(**solve)

    def run(model, forces, w):
        x, grads, sim = pushed_gradients(model, forces, w, dt=0.01, steps=steps, options=options)
        assert sim.collision.fail_safe_steps == 0 and sim.collision.start_gap_steps == 0
        return x, grads, sim

    forces = np.zeros((batch.particle_count, 3))
    for w in range(worlds):
        forces[batch.world_slice(w)][pushed] = pushes[w]
    x, grad, sim = run(batch, forces, weights)
    pairs, material_sum = 0, {}
    for w in range(worlds):
        model = base.finalize(device, requires_grad=True, dtype=wp.float64)
        single = np.zeros((model.particle_count, 3))
        single[pushed] = pushes[w]
        part = batch.world_slice(w)
        xs, gs, alone = run(model, single, weights[part])
        pairs += alone.proximity.last_count
        same(x[part], xs)
        for k in (0, 1, 2):  # forces, x0, v0: per particle
            same(grad[k][part], gs[k])
        same(grad[3][w], gs[3][0])  # the world's sphere
        for k in (4, 5, 6):  # the worlds share one material: its gradient is the sum of theirs
            material_sum[k] = material_sum.get(k, 0.0) + gs[k]
        assert all(np.abs(g).max() > 0.0 for g in gs)
    for k, total in material_sum.items():  # summed in another order: to rounding
        np.testing.assert_allclose(grad[k], total, rtol=1e-12, atol=1e-12 * np.abs(total).max())
    assert sim.proximity.last_count == pairs > 0  # the cloths rest on their spheres, each world's pairs its own


@pytest.mark.parametrize("device", DEVICES)
def test_the_multigrid_asked_for_runs_several_large_worlds_on_every_device(device):
    # worlds over linear.TILED_MAX_PARTICLES: on CUDA "auto" would give them warp.optim's CG, whose multigrid takes one
    # world, so they get the tiled CG (a V-cycle on each world's block); on the CPU the sequential CG
    many = wc.ModelBuilder(gravity=(0.0, 0.0, -2.0))
    many.replicate(hanging_builder(res=32), 2)
    model = many.finalize(device)
    assert model.particle_count // 2 > wc.solver.linear.TILED_MAX_PARTICLES
    sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(preconditioner="multigrid", cg_tol=1e-6))
    solver = sim.linear_solver
    assert solver.preconditioner == "multigrid"
    assert solver.backend == ("sequential" if wp.get_device(device).is_cpu else "tiled")
    x = wc.rollout(sim, model.state(), steps=2)[-1].particle_x.numpy()
    assert solver.info().converged and np.all(np.isfinite(x))
    np.testing.assert_allclose(x[model.world_slice(0)], x[model.world_slice(1)], atol=1e-5)


@pytest.mark.parametrize("solver", ["device", "numpy"])
def test_second_try_and_fail_safe_act_on_their_worlds_alone(solver):
    """Worlds whose steps need the collision stage's second try (a sheet between two planes) or its fail-safe (a
    cloth dropped on a sphere with a tight projection-strain limit), next to a world that needs neither: each world
    goes through its own tries, so states and the gradients of forces, x0, v0, the obstacles' placement and each
    world's material equal single-world runs, bitwise. With either projection solver: each names the worlds whose
    projection failed."""
    from test_collision_gradients import SANDWICH_THICKNESS, sandwich_builder

    pushed = [0, 6, 42, 48]
    worlds = [(sandwich_builder(), None), (draped_builder(), (0.0, 0.0, 3.0)),  # pushed up: no fail-safe
              (draped_builder(), (0.0, 0.0, -0.3)), (draped_builder(), (0.5, 0.0, -0.5))]
    for builder, _ in worlds[1:]:  # the worlds of a model share their collision settings
        builder.set_collision(thickness=SANDWICH_THICKNESS, repulsion_stiffness=0.0)
    options = wc.SolverOptions(**SSOR, collision=wc.CollisionOptions(max_projection_strain=0.02, solver=solver))
    steps = 12

    def run(model, forces, weights):
        return pushed_gradients(model, forces, weights, dt=0.005, steps=steps, options=options)

    composed = wc.ModelBuilder()
    for builder, _ in worlds:
        composed.add_world(builder)
    batch = composed.finalize("cpu", requires_grad=True, dtype=wp.float64)
    forces = np.zeros((batch.particle_count, 3))
    weights = np.random.default_rng(4).standard_normal((batch.particle_count, 3))
    for w, (_, push) in enumerate(worlds):
        if push is not None:
            forces[np.arange(batch.particle_count)[batch.world_slice(w)][pushed]] = push
    x, grads, sim = run(batch, forces, weights)
    tries = []
    for w, (builder, _) in enumerate(worlds):
        model = builder.finalize("cpu", requires_grad=True, dtype=wp.float64)
        part = batch.world_slice(w)
        xs, gs, alone = run(model, forces[part], weights[part])
        tries.append((alone.collision.start_gap_steps, alone.collision.fail_safe_steps))
        np.testing.assert_array_equal(x[part], xs)
        for k in (0, 1, 2):  # forces, x0, v0: per particle
            np.testing.assert_array_equal(grads[k][part], gs[k])
        np.testing.assert_array_equal(grads[3][batch.obstacle_world == w], gs[3])  # the world's obstacles
        for k in (4, 5, 6):  # density, stretching, bending: each world's cloth its own material
            np.testing.assert_array_equal(grads[k][w], gs[k][0])
        assert np.abs(gs[1]).max() > 0.0
    assert tries[0][0] >= 1 and tries[0][1] == 0  # the sandwich: resolved by the second try
    assert tries[1] == (0, 0)  # pushed up: neither
    assert tries[2][1] >= 1 and tries[3][1] >= 1  # dropped fast: the fail-safe
    assert sim.collision.fail_safe_steps >= 1 and sim.collision.start_gap_steps >= 1


def test_overlapping_worlds_do_not_collide():
    """Two worlds in the same place with self-collision: a cloth falling through the place where the other world's
    cloth is pinned falls as it does alone (it would land on it if worlds collided)."""
    def falling():
        b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
        b.add_cloth_grid((4, 4), (0.4, 0.4), material=wc.preset("gray-interlock", thicken=2), pos=(0.0, 0.0, 0.1))
        b.set_collision(self_collision=True)
        return b

    def resting():
        b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
        b.add_cloth_grid((4, 4), (0.4, 0.4), material=wc.preset("gray-interlock", thicken=2), pos=(-0.05, -0.05, 0.0))
        for p in range(25):
            b.add_pin(p)
        b.set_collision(self_collision=True)
        return b

    composed = wc.ModelBuilder()
    composed.add_world(falling())
    composed.add_world(resting())
    batch = composed.finalize("cpu", dtype=wp.float64)
    options = wc.SolverOptions(**SSOR)
    steps = 25
    x = wc.rollout(wc.Simulator(batch, 0.01, options=options), batch.state(), steps=steps)[-1].particle_x.numpy()
    alone = falling().finalize("cpu", dtype=wp.float64)
    xs = wc.rollout(wc.Simulator(alone, 0.01, options=options), alone.state(), steps=steps)[-1].particle_x.numpy()
    np.testing.assert_array_equal(x[batch.world_slice(0)], xs)
    assert x[batch.world_slice(0)][:, 2].max() < -0.1  # fell through the pinned cloth's place at z = 0
    # the same two cloths in one world collide: the falling one stops on the pinned one
    both = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    mat = wc.preset("gray-interlock", thicken=2)
    both.add_cloth_grid((4, 4), (0.4, 0.4), material=mat, pos=(0.0, 0.0, 0.1))
    first = both.add_cloth_grid((4, 4), (0.4, 0.4), material=mat, pos=(-0.05, -0.05, 0.0))
    for p in range(25):
        both.add_pin(first + p)
    both.set_collision(self_collision=True)
    one = both.finalize("cpu", dtype=wp.float64)
    x1 = wc.rollout(wc.Simulator(one, 0.01, options=options), one.state(), steps=steps)[-1].particle_x.numpy()
    assert x1[:25, 2].min() > -0.01


def test_failing_world_is_named():
    """A world whose cloth starts far too fast trips the divergence guard; the error names its world."""
    composed = wc.ModelBuilder()
    composed.add_world(hanging_builder())
    fast = wc.ModelBuilder(gravity=(0.0, 0.0, -2.0))
    fast.add_cloth_grid((2, 2), (0.2, 0.2), material=wc.preset("gray-interlock", thicken=2), vel=(0.0, 0.0, -1.0e4))
    composed.add_world(fast)
    model = composed.finalize("cpu")
    sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(preconditioner="block_ssor"))
    with pytest.raises(wc.SimulationError, match=r"step 1 .*world 1, its particle \d") as err:
        sim.step(model.state(), model.empty_state())
    assert err.value.worlds == [1]


def test_replicate_scene_with_obstacles_and_handles():
    """replicate copies cloths, handles, pins and obstacles (renamed per world) with their motions; per-world views
    are views."""
    base = hanging_builder(moving_pin=True)
    base.add_obstacle_sphere(0.1, name="ball", pos=(0.0, 0.3, -0.3),
                             motion=[(0.0, (0.0, 0.0, 0.0), (0, 0, 0, 1)), (1.0, (0.0, 0.1, 0.0), (0, 0, 0, 1))])
    composed = wc.ModelBuilder()
    assert list(composed.replicate(base, 3)) == [0, 1, 2]
    model = composed.finalize("cpu")
    n = base.particle_count
    assert model.world_count == 3 and model.particle_count == 3 * n
    assert model.world_particle_start.tolist() == [0, n, 2 * n, 3 * n]
    assert model.particle_world.numpy().tolist() == [0] * n + [1] * n + [2] * n
    assert model.obstacle_names == ["ball_0", "ball_1", "ball_2"]
    assert model.obstacle_world.tolist() == [0, 1, 2]
    assert all(m is not None for m in model.obstacle_motion)
    single = base.finalize("cpu")
    handles = single.handle_particle.numpy()
    assert model.handle_particle.numpy().tolist() == [p + w * n for w in range(3) for p in handles]
    assert model.pin_particle.numpy().tolist() == [p + w * n for w in range(3) for p in single.pin_particle.numpy()]
    assert model.pin_motion[2] is single.pin_motion[0] or np.array_equal(model.pin_motion[2].offsets,
                                                                           single.pin_motion[0].offsets)
    state = model.state()
    view = model.world_state(state, 1)
    view.particle_x.fill_(0.0)
    x = state.particle_x.numpy()
    assert np.all(x[n:2 * n] == 0.0) and np.any(x[:n] != 0.0)
    assert model.world_of(2 * n) == 2 and model.particle_name(n + 1) == f"particle {n + 1} (world 1, its particle 1)"


def test_replicated_worlds_share_the_builders_materials_unless_asked_for_their_own():
    base = hanging_builder()
    shared, own = wc.ModelBuilder(), wc.ModelBuilder()
    shared.replicate(base, 3)
    own.replicate(base, 3, own_materials=True)
    assert shared.finalize("cpu").material_count == 1
    model = own.finalize("cpu")
    assert model.material_count == 3
    assert model.tri_material.numpy().reshape(3, -1).tolist() == [[w] * base.finalize("cpu").tri_count
                                                                   for w in range(3)]
    np.testing.assert_array_equal(model.material_stretching.numpy()[2], model.material_stretching.numpy()[0])


def test_world_errors():
    base = hanging_builder()
    own = hanging_builder()
    with pytest.raises(ValueError, match="has a cloth of its own"):
        own.add_world(base)
    composed = wc.ModelBuilder()
    composed.add_world(base)
    with pytest.raises(ValueError, match="add_handle: this builder holds worlds"):
        composed.add_handle(0)
    with pytest.raises(ValueError, match="set_wind: this builder holds worlds"):
        composed.set_wind((1.0, 0.0, 0.0))
    damped = hanging_builder()
    damped.set_damping(mass=0.5)
    with pytest.raises(ValueError, match=r"world 1 differs from world 0 .*damping mass 0.5 \(world 0: 0.0\)"):
        composed.add_world(damped)
    with pytest.raises(ValueError, match="count must be a positive integer"):
        composed.replicate(base, 0)
    with pytest.raises(ValueError, match="world 3 out of range"):
        composed.finalize("cpu").world_slice(3)
    composed.add_world(base)
    with pytest.raises(ValueError, match="'multigrid' with the warp CG backend takes a model of one world"):
        wc.Simulator(composed.finalize("cpu"), 0.01, options=wc.SolverOptions(preconditioner="multigrid",
                                                                              cg_backend="warp"))
    # "auto" on the CPU: a multigrid hierarchy per world, each world's V-cycle on its own thread
    solver = wc.Simulator(composed.finalize("cpu"), 0.01).linear_solver
    assert solver.preconditioner == "multigrid" and solver.multigrid_levels[0] == 2 * base.particle_count
    pinned = wc.ModelBuilder()
    pinned.add_cloth_grid((2, 2), (0.2, 0.2), material=wc.preset("gray-interlock"))
    for p in range(pinned.particle_count):
        pinned.add_pin(p)
    composed.add_world(pinned)  # a world with nothing to coarsen: block SSOR for all
    assert wc.Simulator(composed.finalize("cpu"), 0.01).linear_solver.preconditioner == "block_ssor"
    with pytest.raises(ValueError, match="world 2: the multigrid preconditioner needs at least one particle"):
        wc.Simulator(composed.finalize("cpu"), 0.01, options=wc.SolverOptions(preconditioner="multigrid"))


# -- the control task's batches ---------------------------------------------------------------------------------------
def draped_task(steps=30, **kw):
    """Pushes on the corners of the cloth dropped on a sphere (contact from step 1) towards a centre of mass."""
    from warpcloth.tasks.control import ControlTask

    model = draped_builder().finalize("cpu", requires_grad=True, dtype=wp.float64)
    return ControlTask(model, 0.01, particles=(0, 6, 42, 48), interval_steps=10, intervals=2, steps=steps,
                       target_com=(0.05, 0.0, -0.05), options=wc.SolverOptions(**SSOR), template=draped_builder(),
                       **kw)


def test_control_batches_equal_single_evaluations_with_contact():
    """evaluate_many runs its requests as one batch of worlds (a cloth dropped on a sphere, projection, repulsion and
    friction); every loss, gradient and final position equals the single evaluation's, bitwise, for the loss and
    for each centre-of-mass coordinate (the Gauss-Newton Jacobian's rows)."""
    task = draped_task()
    rng = np.random.default_rng(3)
    params = [rng.normal(0.0, 4.0, task.n_params) for _ in range(4)]
    requests = [(params[1], 0), (params[1], 2), (params[2], 1)]
    mixed = [(p, None) for p in params]
    for batch in (requests, mixed):
        before = task.simulations
        out = task.evaluate_many(batch)
        assert task.simulations - before == len(batch) and task.batch_retries == 0
        for (p, k), e in zip(batch, out):
            alone = task.evaluate(p, component=k)
            assert e.loss == alone.loss
            np.testing.assert_array_equal(e.grad, alone.grad)
            np.testing.assert_array_equal(e.positions, alone.positions)
    stage = task.worlds(4).sim.collision
    assert stage.phase_seconds["projection"] > 0 and task.worlds(4).model.world_count == 4  # contact, batched


def test_jacobian_rows_from_one_recording_equal_single_evaluations_with_contact():
    """jacobian_worlds: one forward pass and three reverse passes give each centre-of-mass row that a forward +
    backward simulation of its own gives, bitwise (the cloth on its sphere: contact throughout), for one world and a
    batch; evaluate_many serves a point's three rows that way."""
    task = draped_task()
    rng = np.random.default_rng(5)
    params = [rng.normal(0.0, 4.0, task.n_params) for _ in range(3)]
    single = task.jacobian_worlds(params[:1])[0]
    assert task.simulations == 1 and task.reverse_passes == 3
    batched = task.worlds(3).jacobian_worlds(params)
    requests = [(p, c) for p in params[1:] for c in range(3)]
    served = task.evaluate_many(requests)
    assert task.batch_retries == 0 and task.reverse_passes == 3 + 6
    for p, rows, many in ((params[0], single, None), *zip(params[1:], batched[1:], (served[:3], served[3:]))):
        for c in range(3):
            alone = task.evaluate(p, component=c)
            for e in (rows[c], None if many is None else many[c]):
                if e is None:
                    continue
                assert e.loss == alone.loss
                np.testing.assert_array_equal(e.grad, alone.grad)
                np.testing.assert_array_equal(e.positions, alone.positions)
    np.testing.assert_array_equal(batched[0][1].grad, single[1].grad)


def test_jacobian_rows_of_points_no_better_than_their_thresholds_skip_the_reverse_passes():
    task = draped_task()
    rng = np.random.default_rng(6)
    params = [rng.normal(0.0, 4.0, task.n_params) for _ in range(2)]
    coms = [task.evaluate(p).com - task.target_com for p in params]
    losses = [0.5 * float(r @ r) for r in coms]  # as the open loop computes a point's loss (no regulariser here)
    for worse_than, skipped in (([losses[0], losses[1]], True), ([losses[0], np.nextafter(losses[1], np.inf)], False)):
        before = task.reverse_passes
        out = task.evaluate_many([(p, c, t) for p, t in zip(params, worse_than) for c in range(3)])
        assert task.reverse_passes - before == (0 if skipped else 6)
        for p, rows in zip(params, (out[:3], out[3:])):
            alone = task.evaluate(p, component=1)
            assert rows[1].loss == alone.loss and np.array_equal(rows[1].positions, alone.positions)
            assert (rows[1].grad is None) if skipped else np.array_equal(rows[1].grad, alone.grad)


def throw_task(steps=60, **kw):
    from warpcloth.tasks import scenes as S
    from warpcloth.tasks.throw import ThrowTask

    return ThrowTask(S.basket_scene("cpu", dtype=wp.float64), steps=steps, **kw)


def test_a_failing_request_in_a_batch_is_returned_and_the_others_kept():
    """A request whose simulation raises (pushes far past the speed limit) gets its exception in its place; the
    batch is run again request by request, so the others still equal their single evaluations."""
    task = throw_task(steps=40)
    good = np.full(task.n_params, 1.0)
    out = task.evaluate_many([(good, None), (np.full(task.n_params, 1e9), None)])
    assert isinstance(out[1], wc.SimulationError) and task.batch_retries == 1
    assert out[0].loss == task.evaluate(good).loss


@pytest.mark.parametrize("optimizer", ["gauss-newton", "lbfgs"])
def test_batched_open_loop_optimisation_gives_the_sequential_result(optimizer):
    """The open loop with its Jacobian rows in one batch, and three starts in lockstep, end where the one-at-a-time
    runs end (the cloth on its sphere: contact throughout): the same pushes and the same history, bitwise."""
    from warpcloth.tasks.controllers import optimize_open_loop, optimize_open_loop_starts

    task = draped_task()
    rng = np.random.default_rng(4)
    starts = [None, rng.normal(0.0, 5.0, task.n_params), rng.normal(0.0, 5.0, task.n_params)]
    alone = [optimize_open_loop(task, start=s, iters=7, optimizer=optimizer, batch=False) for s in starts]
    batched = optimize_open_loop(task, start=starts[1], iters=7, optimizer=optimizer)
    before = task.batches
    lockstep = optimize_open_loop_starts(task, starts, iters=7, optimizer=optimizer)
    assert task.batches > before
    for a, b in zip(alone + [alone[1]], lockstep + [batched]):
        assert a.losses == b.losses and a.simulations == b.simulations and a.failed_trials == b.failed_trials
        np.testing.assert_array_equal(a.params, b.params)
    assert min(r.error_pct for r in alone) < 100.0


def test_a_control_task_refuses_worlds_of_different_sizes():
    from warpcloth.tasks.control import ControlTask

    composed = wc.ModelBuilder()
    composed.add_world(draped_builder())
    small = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    small.add_cloth_grid((2, 2), (0.4, 0.4), material=wc.preset("gray-interlock"))
    composed.add_world(small)
    model = composed.finalize("cpu", requires_grad=True)
    with pytest.raises(ValueError, match="particle counts differ"):
        ControlTask(model, 0.01, particles=(0,), interval_steps=1, intervals=1, steps=2, target_com=(0, 0, 0))


def test_add_world_refuses_a_builder_with_obstacles_or_settings_of_its_own():
    """What the outer builder would otherwise lose or mis-assign: an obstacle of no world, settings no world uses."""
    with_obstacle = wc.ModelBuilder()
    with_obstacle.add_obstacle_sphere(0.1, name="ball")
    damped = wc.ModelBuilder()
    damped.set_damping(mass=0.5)
    for outer, what in ((with_obstacle, "obstacles"), (damped, "damping")):
        with pytest.raises(ValueError, match=f"add_world: this builder has .*{what}"):
            outer.add_world(draped_builder())


def test_a_tasks_replayed_simulations_equal_its_first_uncaptured_ones():
    """A control task captures its rollouts at their second use (ControlTask._captured): the losses, gradients,
    Jacobian rows and final positions of the uncaptured first call and of the replays are the same, bitwise, in
    contact (the cloth on its sphere) and out of it (the throw in free flight)."""
    rng = np.random.default_rng(9)
    for make in (lambda: draped_task(steps=20), lambda: throw_task(steps=30)):
        task = make()
        p = rng.normal(0.0, 2.0, task.n_params)
        evaluations = [task.evaluate(p) for _ in range(3)]
        losses = [task.losses_worlds([p])[0] for _ in range(3)]
        rows = [make().jacobian_worlds([p])[0]] + [task.jacobian_worlds([p])[0] for _ in range(2)]
        for e in evaluations[1:] + losses:
            assert e.loss == evaluations[0].loss
            np.testing.assert_array_equal(e.positions, evaluations[0].positions)
        for e in evaluations[1:]:
            np.testing.assert_array_equal(e.grad, evaluations[0].grad)
        for r in rows[1:]:
            for c in range(3):
                assert r[c].loss == rows[0][c].loss
                np.testing.assert_array_equal(r[c].grad, rows[0][c].grad)
        assert np.any(evaluations[0].grad) and np.any(rows[0][2].grad)
    assert task.rerun_steps == []  # the throw's 30 steps are free flight


def test_a_checkpointed_tasks_replayed_evaluations_equal_its_first_uncaptured_one(monkeypatch):
    """A task whose rollouts are checkpointed (segment_steps < steps: wc.checkpointed_backward, uncaptured) replays
    them in segments from its second evaluation on (wc.CapturedRollout's segment_steps): the losses, gradients and
    final positions are the uncaptured first evaluation's, bitwise."""
    rng = np.random.default_rng(4)
    uncaptured = wc.checkpointed_backward
    for make in (lambda: draped_task(steps=20, segment_steps=6), lambda: throw_task(steps=30, segment_steps=7)):
        monkeypatch.setattr(wc, "checkpointed_backward", uncaptured)
        task = make()
        p = rng.normal(0.0, 2.0, task.n_params)
        evaluations = [task.evaluate(p) for _ in range(2)]  # the first uncaptured, the second captures

        def refused(*args, **kwargs):
            raise AssertionError("a captured task ran its rollout uncaptured")

        monkeypatch.setattr(wc, "checkpointed_backward", refused)
        evaluations += [task.evaluate(p) for _ in range(2)]
        for e in evaluations[1:]:
            assert e.loss == evaluations[0].loss
            np.testing.assert_array_equal(e.positions, evaluations[0].positions)
            np.testing.assert_array_equal(e.grad, evaluations[0].grad)
        assert np.any(evaluations[0].grad)


def test_a_checkpointed_task_past_the_captured_segments_budget_runs_uncaptured(monkeypatch):
    """The replay in segments keeps every State: a task of more particle-steps than
    gradients.CAPTURED_SEGMENTS_PARTICLE_STEPS stays with wc.checkpointed_backward at every evaluation."""
    from warpcloth.solver import gradients

    task = draped_task(steps=20, segment_steps=6)
    monkeypatch.setattr(gradients, "CAPTURED_SEGMENTS_PARTICLE_STEPS", task.model.particle_count * 20 - 1)
    calls = []
    uncaptured = wc.checkpointed_backward
    monkeypatch.setattr(wc, "checkpointed_backward", lambda *a, **k: calls.append(1) or uncaptured(*a, **k))
    p = np.random.default_rng(4).normal(0.0, 2.0, task.n_params)
    evaluations = [task.evaluate(p) for _ in range(3)]
    assert len(calls) == 3
    assert evaluations[2].loss == evaluations[0].loss


def test_a_task_captures_again_where_the_models_default_placements_changed():
    """The captured controls hold the model's default targets and placements (host arrays a user may edit): moved
    in place after the capture, the next evaluation is the moved scene's, bitwise what a new task gives."""
    task, fresh = draped_task(steps=10), draped_task(steps=10)
    p = np.random.default_rng(3).normal(0.0, 1.0, task.n_params)
    for _ in range(3):
        before = task.evaluate(p)
    for t in (task, fresh):
        t.model.obstacle_rest_transform[0, 2] += 0.004  # the sphere 4 mm higher
    moved, expected = task.evaluate(p), fresh.evaluate(p)
    assert moved.loss != before.loss
    assert moved.loss == expected.loss
    np.testing.assert_array_equal(moved.grad, expected.grad)
