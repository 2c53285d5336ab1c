"""Goals on the final state: coverage's measure against shapes whose covered area is known exactly, its surrogate's
relation to the measure and its order, each goal's add() gradient against central differences (on positions and
through a short fall onto a table), one value per world, and bad input named."""

import math

import numpy as np
import pytest
import warp as wp

import warpcloth as wc
from warpcloth.goals import Coverage, TargetPoints, TargetPositions

RES, SIZE = 8, 0.4
TOL = 0.02


def table_builder(*, res=RES, size=SIZE, z=0.0, table_height=0.0, moving_table=False) -> wc.ModelBuilder:
    """A res x res cloth of size x size [m] centred over the origin at height z, a 2 m table with its top at
    table_height."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    b.add_cloth_grid((res, res), (size, size), material=wc.preset("gray-interlock"), pos=(-size / 2, -size / 2, z))
    still = (0.0, 0.0, 0.0, 1.0)
    motion = [(0.0, (0.0, 0.0, 0.0), still), (1.0, (0.1, 0.0, 0.0), still)] if moving_table else None
    b.add_obstacle_plane((2.0, 2.0), name="table", pos=(0.0, 0.0, table_height), motion=motion)
    return b


def table_model(worlds=1, **kwargs) -> wc.Model:
    b = table_builder(**kwargs)
    if worlds > 1:
        template, b = b, wc.ModelBuilder()
        b.replicate(template, worlds)
    return b.finalize("cpu", requires_grad=True, dtype=wp.float64)


def grid(res=RES, size=SIZE) -> np.ndarray:
    """The flat cloth on the table (z = 0): vertex (i, j) = j (res + 1) + i at (-size/2 + i h, -size/2 + j h)."""
    j, i = np.divmod(np.arange((res + 1) ** 2), res + 1)
    h = size / res
    return np.stack([-size / 2 + i * h, -size / 2 + j * h, np.zeros_like(i, dtype=float)], axis=1)


def fold(x, width, gap=0.006, axis=1):
    """The strip beyond ``width`` (a share of the side) from the +axis edge folded back over the cloth, ``gap``
    above the table."""
    x = x.copy()
    line = SIZE / 2 - width * SIZE
    over = x[:, axis] > line + 1e-12
    x[over, axis] = 2 * line - x[over, axis]
    x[over, 2] = gap
    return x


def lift(x, width, axis=1):
    """The strip beyond ``width`` from the +axis edge turned up to stand vertically above its edge line."""
    x = x.copy()
    line = SIZE / 2 - width * SIZE
    over = x[:, axis] > line + 1e-12
    x[over, 2] = x[over, axis] - line
    x[over, axis] = line
    return x


def rotate(x, degrees, shift=(0.0, 0.0)):
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    out = x.copy()
    out[:, 0], out[:, 1] = c * x[:, 0] - s * x[:, 1] + shift[0], s * x[:, 0] + c * x[:, 1] + shift[1]
    return out


# -- coverage's measure ------------------------------------------------------------------------------------------

def test_coverage_measures_shapes_whose_union_is_known_exactly():
    cov = Coverage(table_model(), table_height=0.0, flat_tolerance=TOL)
    flat = grid()
    # (shape, exact share, tolerance): axis-aligned edges are exact; slanted ones within the row spacing's bound
    cases = {
        "flat": (flat, 1.0, 1e-12),
        "flat, stretched 1.1x along x (the share is of the rest area)": (flat * [1.1, 1.0, 1.0], 1.1, 1e-12),
        "rotated 30 degrees, moved": (rotate(flat, 30.0, (0.2, -0.1)), 1.0, 1e-5),
        "folded in half along x": (fold(flat, 0.5, axis=1), 0.5, 1e-12),
        "folded in half along y": (fold(flat, 0.5, axis=0), 0.5, 1e-12),
        "folded in half, rotated 17 degrees": (rotate(fold(flat, 0.5), 17.0), 0.5, 1e-5),
        "a quarter folded": (fold(flat, 0.25), 0.75, 1e-12),
        "half of it standing up off the table": (lift(flat, 0.5), 0.5, 1e-12),
        "floating 5 cm above the table": (flat + [0.0, 0.0, 0.05], 0.0, 0.0),
    }
    for name, (x, exact, tol) in cases.items():
        got = cov.measure(x)
        print(f"{name}: measure {got:.9f}, exact {exact:.9f}, error {got - exact:.1e}")
        assert abs(got - exact) <= tol, f"{name}: measure {got!r}, exact {exact!r}, error {got - exact:.2e}"


def test_coverage_of_two_overlapping_layers_is_their_union():
    """Two square sheets, the second slid by (s, -t) over the first: union 2 L^2 - (L - s)(L - t) of rest 2 L^2;
    the union's inner edges lie between rows, within the rows' bound h / L per edge."""
    b = table_builder()
    b.add_cloth_grid((RES, RES), (SIZE, SIZE), material=wc.preset("gray-interlock"), pos=(-SIZE / 2, -SIZE / 2, 0.0))
    cov = Coverage(b.finalize("cpu", requires_grad=True, dtype=wp.float64), table_height=0.0, flat_tolerance=TOL)
    L = SIZE
    for s, t in ((0.07, 0.03), (0.1, 0.0), (0.0, 0.2), (0.123456, 0.0654321)):
        x = np.concatenate([grid(), grid() + [s, -t, 0.006]])
        exact = (2 * L * L - (L - s) * (L - t)) / (2 * L * L)
        got = cov.measure(x)
        print(f"two layers slid by ({s}, {-t}): measure {got:.9f}, exact {exact:.9f}, error {got - exact:.1e}")
        assert abs(got - exact) <= 2.0 / cov.resolution, f"({s}, {-t}): measure {got!r}, exact {exact!r}"
        np.testing.assert_allclose(cov.measure(rotate(x, 33.0)), got, atol=2.0 / cov.resolution)


def test_coverage_counts_a_triangle_only_when_all_its_vertices_are_within_the_tolerance():
    cov = Coverage(table_model(), table_height=0.0, flat_tolerance=TOL)
    x = grid()
    x[RES * (RES + 1) + RES, 2] = 1.5 * TOL  # one corner vertex lifted: its one or two corner triangles drop out
    lost = (~cov.flat(x)).sum()
    assert 1 <= lost <= 2
    # the lost triangle's edge along the rows: within half a row (h = SIZE / resolution) times its length
    bound = 0.5 * (SIZE / cov.resolution) * (SIZE / RES) / SIZE**2
    np.testing.assert_allclose(cov.measure(x), 1.0 - lost * 0.5 / RES**2, atol=bound)
    np.testing.assert_allclose(cov.measure(rotate(x, 10.0)), 1.0 - lost * 0.5 / RES**2, atol=bound)
    x[RES * (RES + 1) + RES, 2] = 0.9 * TOL
    assert cov.flat(x).all() and abs(cov.measure(x) - 1.0) < 1e-12


def test_coverage_follows_up_and_the_table_height():
    """The same shape on a wall (up = +y, the table's face at y = 0.3)."""
    b = wc.ModelBuilder(gravity=(0.0, -9.8, 0.0))
    b.add_cloth_grid((RES, RES), (SIZE, SIZE), material=wc.preset("gray-interlock"))
    b.add_obstacle_box((1.0, 0.1, 1.0), name="wall", pos=(0.0, 0.2, 0.0))
    model = b.finalize("cpu", requires_grad=True, dtype=wp.float64)
    cov = Coverage(model, table_height=0.3, up=(0.0, 2.0, 0.0), flat_tolerance=TOL)
    x = fold(grid(), 0.25)[:, [0, 2, 1]] + [0.0, 0.3, 0.0]  # z -> y
    np.testing.assert_allclose(cov.measure(x), 0.75, atol=1e-12)


# -- coverage's surrogate ----------------------------------------------------------------------------------------

def test_the_surrogate_is_the_measure_without_overlap_and_lower_by_a_folded_layer():
    model = table_model()
    cov = Coverage(model, table_height=0.0, flat_tolerance=TOL)
    out = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    for width in (0.0, 0.125, 0.25, 0.375, 0.5):
        for shape, lifted in ((fold(grid(), width), False), (lift(grid(), width), True)):
            for x in (shape, rotate(shape, 40.0), rotate(shape, 180.0) * [1.0, -1.0, 1.0]):  # the last: upside down
                out.zero_()
                cov.add(_state(model, x), out)
                S = 1.0 - out.numpy()[0]
                np.testing.assert_allclose(S, cov.surrogate(x), atol=1e-12)
                expected = cov.measure(x) - (0.0 if lifted else width)  # the folded layer: width; rows: 1e-7
                assert abs(S - expected) < 1e-6, f"width {width}, lifted {lifted}: S {S}, expected {expected}"


def _state(model, x):
    state = model.state()
    state.particle_x.assign(np.asarray(x, dtype=np.float64))
    return state


def test_the_surrogate_orders_shapes_as_the_measure_does():
    """Landing shapes of a fling: folds and standing strips of growing width, a crumple of growing amplitude, a
    cloth raised off the table; where the measure strictly drops, the surrogate drops too."""
    cov = Coverage(table_model(), table_height=0.0, flat_tolerance=TOL)
    rng = np.random.default_rng(3)
    noise = rng.standard_normal((RES + 1) ** 2)
    families = {
        "folds": [fold(grid(), w) for w in (0.0, 0.125, 0.25, 0.375, 0.5)],
        "standing strips": [lift(grid(), w) for w in (0.0, 0.125, 0.25, 0.5, 0.75)],
        "crumples": [grid() + np.outer(noise, [0.0, 0.0, a]) for a in (0.0, 0.5 * TOL, TOL, 2 * TOL, 4 * TOL)],
        "raised": [grid() + [0.0, 0.0, h] for h in (0.0, 0.5 * TOL, 2 * TOL, 5 * TOL, 20 * TOL)],
        "folds then raised": [fold(grid(), 0.25), fold(grid(), 0.25) + [0.0, 0.0, 3 * TOL]],
    }
    for name, shapes in families.items():
        m = [cov.measure(x) for x in shapes]
        S = [cov.surrogate(x) for x in shapes]
        print(f"{name}: measure {np.round(m, 4).tolist()}, surrogate {np.round(S, 4).tolist()}")
        for k in range(len(shapes) - 1):
            assert m[k] >= m[k + 1] and S[k] >= S[k + 1], f"{name} {k}: measure {m}, surrogate {S}"
            if m[k] > m[k + 1]:
                assert S[k] > S[k + 1], f"{name}, shapes {k} and {k + 1}: measure {m}, surrogate {S}"


# -- gradients ---------------------------------------------------------------------------------------------------

def check_gradient(run, a: wp.array, what: str, *, seed=1, rel_eps=1e-6, tol=1e-6) -> float:
    """The tape's gradient of sum(run()) (run: a goal's add into a new out, every launch on the tape) with respect
    to ``a`` along a random direction, against central differences; returns the relative error."""
    a.grad.zero_()
    tape = wp.Tape()
    with tape:
        out = run()
    tape.backward(grads={out: wp.ones(out.shape[0], dtype=wp.float64)})
    grad = a.grad.numpy().copy()
    tape.zero()
    direction = np.random.default_rng(seed).standard_normal(grad.shape)
    base = a.numpy().copy()
    eps = rel_eps * max(1.0, np.abs(base).max())
    try:
        a.assign(base + eps * direction)
        plus = run().numpy().sum()
        a.assign(base - eps * direction)
        minus = run().numpy().sum()
    finally:
        a.assign(base)
    fd = (plus - minus) / (2 * eps)
    analytic = float(np.sum(grad * direction))
    rel = abs(analytic - fd) / max(abs(fd), 1e-300)
    assert abs(fd) > 1e-8, f"{what}: the loss does not change along the direction ({fd:.3e}): a test that cannot fail"
    assert rel < tol, f"{what}: tape {analytic:.10e}, central differences {fd:.10e}, relative error {rel:.2e}"
    print(f"{what}: gradient relative error {rel:.1e}")
    return rel


def goals_of(model, final: np.ndarray, tol=0.008):
    """One of each goal for a cloth that falls towards the table: coverage, points on the table under the cloth
    (both ways and Huber too), the flat grid as vertex targets."""
    n = model.world_particle_start[1]
    rng = np.random.default_rng(5)
    points = final[rng.choice(n, 12, replace=False)] * [1.0, 1.0, 0.0] + [0.01, -0.02, 0.004]
    return {
        "coverage": Coverage(model, table_height=0.0, flat_tolerance=tol),
        "target points": TargetPoints(model, points),
        "target points, both ways, huber": TargetPoints(model, points, both_ways=True, huber=0.012),
        "target positions": TargetPositions(model, final * [1.0, 1.0, 0.0]),
    }


def adder(goal, model, state_of):
    def run():
        out = wp.zeros(model.world_count, dtype=wp.float64, requires_grad=True)
        goal.add(state_of(), out, 0.7)
        return out

    return run


def test_each_goals_gradient_on_positions_matches_central_differences():
    model = table_model(res=4, size=0.2)
    rng = np.random.default_rng(2)
    x0 = grid(4, 0.2) + rng.normal(0.0, 0.003, ((5 * 5), 3))
    x0[:, 2] = rng.uniform(0.0, 0.03, 25)  # within the tolerance, near it and beyond
    state = _state(model, x0)
    for name, goal in goals_of(model, x0).items():
        check_gradient(adder(goal, model, lambda: state), state.particle_x, f"{name}, on positions")



def test_the_coverage_gradient_of_a_cloth_face_down_matches_central_differences():
    # the sum of signed areas is negative here: the adjoint of its absolute value must see the sum's sign
    model = table_model(res=4, size=0.2)
    rng = np.random.default_rng(3)
    x0 = grid(4, 0.2) * [1.0, -1.0, 1.0] + rng.normal(0.0, 0.003, (25, 3))
    x0[:, 2] = rng.uniform(0.0, 0.03, 25)
    state = _state(model, x0)
    goal = Coverage(model, table_height=0.0, flat_tolerance=0.008)
    assert goal.surrogate(x0) > 0.01
    check_gradient(adder(goal, model, lambda: state), state.particle_x, "coverage, face down")

def test_each_goals_gradient_through_a_fall_towards_the_table_matches_central_differences():
    model = table_model(res=4, size=0.2, z=0.028)
    sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(cg_tol=1e-12, cg_max_iters=2000))
    rng = np.random.default_rng(4)
    start = model.state()
    start.particle_x.assign(model.particle_x0.numpy() + rng.normal(0.0, 0.004, (25, 3)))
    start.particle_v.assign(rng.normal(0.0, 0.1, (25, 3)))
    final = wc.rollout(sim, start, steps=3)[-1].particle_x.numpy()
    assert final[:, 2].min() > 0.01, "the cloth reached the table's repulsion: not the smooth test meant here"
    for name, goal in goals_of(model, final).items():
        run = adder(goal, model, lambda: wc.rollout(sim, start, steps=3)[-1])
        check_gradient(run, start.particle_v, f"{name}, after 3 steps", tol=1e-5)


# -- worlds ------------------------------------------------------------------------------------------------------

def test_every_world_gets_its_own_value():
    one, two = table_model(), table_model(worlds=2)
    shapes = [fold(grid(), 0.25) + [0.0, 0.0, 0.004], rotate(lift(grid(), 0.125), 20.0)]
    state = _state(two, np.concatenate(shapes))
    for name in goals_of(one, shapes[0], TOL):
        goal_two = goals_of(two, shapes[0], TOL)[name]
        out = wp.zeros(2, dtype=wp.float64, requires_grad=True)
        goal_two.add(state, out)
        for w, x in enumerate(shapes):
            goal_one = goals_of(one, shapes[0], TOL)[name]
            single = wp.zeros(1, dtype=wp.float64, requires_grad=True)
            goal_one.add(_state(one, x), single)
            np.testing.assert_allclose(out.numpy()[w], single.numpy()[0], rtol=1e-12, err_msg=f"{name}, world {w}")
            assert goal_two.measure(x, world=w) == goal_one.measure(x), f"{name}, world {w}"
        check_gradient(adder(goal_two, two, lambda: state), state.particle_x, f"{name}, two worlds")
    assert Coverage(two, table_height=0.0, table="table").measure(shapes[1], world=1) == pytest.approx(0.875, abs=1e-6)


# -- bad input ---------------------------------------------------------------------------------------------------

def test_a_coverage_goal_without_a_table_is_an_error():
    b = wc.ModelBuilder()
    b.add_cloth_grid((2, 2), (0.2, 0.2), material=wc.preset("gray-interlock"))
    bare = b.finalize("cpu", requires_grad=True, dtype=wp.float64)
    model = table_model(table_height=0.1)
    for make, message in [
        (lambda: Coverage(bare, table_height=0.0), "no obstacle, so no table"),
        (lambda: Coverage(model, table_height=None), "needs a table"),
        (lambda: Coverage(model, table_height=0.0), r"no table at height 0.0 m .*upward faces at \[0.1\] m"),
        (lambda: Coverage(model, table_height=0.1, up=(0.0, 0.0, -1.0)), "no table at height"),
        (lambda: Coverage(model, table_height=0.1, table="bench"), "no obstacle named 'bench'"),
        (lambda: Coverage(table_model(moving_table=True), table_height=0.0), "no static obstacle"),
    ]:
        with pytest.raises(ValueError, match=message):
            make()
    assert Coverage(model, table_height=0.1, table="table").measure(grid() + [0, 0, 0.1]) == pytest.approx(1.0)


@pytest.mark.parametrize("kwargs, message", [
    (dict(flat_tolerance=0.004), "must exceed the repulsion thickness"),
    (dict(flat_tolerance=-1.0), "flat_tolerance must be finite and > 0"),
    (dict(flat_tolerance=float("nan")), "flat_tolerance must be finite"),
    (dict(up=(0.0, 0.0, 0.0)), "up must be a finite non-zero 3-vector"),
    (dict(up=(0.0, 1.0)), "up must be"),
    (dict(table_height=float("nan")), "table_height must be finite"),
    (dict(resolution=0), "resolution must be a positive integer"),
])
def test_bad_coverage_arguments_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Coverage(table_model(), **{"table_height": 0.0, **kwargs})


def test_bad_targets_are_named():
    model = table_model()
    n = (RES + 1) ** 2
    nan_point = np.zeros((4, 3))
    nan_point[2, 1] = np.nan
    nan_particle = grid()
    nan_particle[7] = np.inf
    for make, message in [
        (lambda: TargetPoints(model, np.zeros((0, 3))), r"points must be \(P, 3\) with P >= 1, got shape \(0, 3\)"),
        (lambda: TargetPoints(model, []), "points must be"),
        (lambda: TargetPoints(model, np.zeros((4, 2))), r"got shape \(4, 2\)"),
        (lambda: TargetPoints(model, nan_point), "point 2 is not finite"),
        (lambda: TargetPoints(model, np.zeros((4, 3)), huber=0.0), "huber must be finite and > 0"),
        (lambda: TargetPoints(model, np.zeros((4, 3)), both_ways=1), "both_ways must be a bool"),
        (lambda: TargetPositions(model, np.zeros((n - 1, 3))), rf"must be \({n}, 3\)"),
        (lambda: TargetPositions(model, nan_particle), "particle 7 is not finite"),
    ]:
        with pytest.raises(ValueError, match=message):
            make()


def test_bad_add_and_measure_arguments_are_named():
    model = table_model()
    goal = Coverage(model, table_height=0.0, flat_tolerance=TOL)
    state, out = model.state(), wp.zeros(1, dtype=wp.float64, requires_grad=True)
    single = table_builder().finalize("cpu", requires_grad=True)  # float32
    nan = grid()
    nan[3, 2] = np.nan
    for call, message in [
        (lambda: goal.add(state, wp.zeros(2, dtype=wp.float64)), r"out must be a \(1,\) array of float64"),
        (lambda: goal.add(state, wp.zeros(1, dtype=wp.float32)), "out must be"),
        (lambda: goal.add(single.state(), out), "state.particle_x must be"),
        (lambda: goal.add(state, out, float("nan")), "weight must be finite"),
        (lambda: goal.measure(grid()[:-1]), r"positions must be one world's \(81, 3\)"),
        (lambda: goal.measure(nan), "particle 3 is not finite"),
        (lambda: goal.measure(grid(), world=1), r"world 1 out of range \[0, 1\)"),
    ]:
        with pytest.raises(ValueError, match=message):
            call()


def test_target_measures_are_known_distances():
    """Points at known distances from the flat cloth (above its inside, beside an edge, off a corner); vertex
    targets all moved by a known offset."""
    model = table_model()
    x = grid() + [0.0, 0.0, 0.004]
    h = SIZE / 2
    points = np.array([[0.01, 0.02, 0.054], [h + 0.03, 0.05, 0.004], [h + 0.03, h + 0.04, 0.004], [-0.1, 0.1, 0.004]])
    d = np.array([0.05, 0.03, 0.05, 0.0])
    state = _state(model, x)
    for huber in (None, 0.04):
        goal = TargetPoints(model, points, huber=huber)
        assert goal.measure(x) == pytest.approx(math.sqrt(np.mean(d**2)), rel=1e-12)
        out = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        goal.add(state, out, 2.0)
        rho = d**2 if huber is None else np.where(d <= huber, 0.5 * d**2, huber * (d - 0.5 * huber))
        assert out.numpy()[0] == pytest.approx(2.0 * rho.mean(), rel=1e-10)
    # both ways: the vertices' RMS distance to their nearest point is the larger here
    both = TargetPoints(model, points, both_ways=True)
    nearest = np.min(np.linalg.norm(x[:, None] - points[None], axis=2), axis=1)
    assert both.measure(x) == pytest.approx(max(math.sqrt(np.mean(d**2)), math.sqrt(np.mean(nearest**2))), rel=1e-12)
    assert math.sqrt(np.mean(nearest**2)) > math.sqrt(np.mean(d**2))
    offset = np.array([0.03, -0.04, 0.0])
    goal = TargetPositions(model, x + offset)
    assert goal.measure(x) == pytest.approx(0.05, rel=1e-12)
    out = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    goal.add(state, out)
    assert out.numpy()[0] == pytest.approx(0.5 * 0.05**2, rel=1e-12)


def test_a_single_precision_model_adds_what_the_host_computes():
    model = table_builder().finalize("cpu", requires_grad=True)  # float32
    x = rotate(fold(grid(), 0.25) + [0.0, 0.0, 0.004], 25.0)
    state = model.state()
    state.particle_x.assign(x.astype(np.float32))
    for goal, host in [(Coverage(model, table_height=0.0, flat_tolerance=TOL), None),
                       (TargetPositions(model, grid()), 0.5 * np.mean(np.sum((x - grid()) ** 2, axis=1)))]:
        out = wp.zeros(1, dtype=wp.float32, requires_grad=True)
        goal.add(state, out)
        expected = 1.0 - goal.surrogate(x) if host is None else host
        assert abs(out.numpy()[0] - expected) < 1e-5, f"{goal.name}: {out.numpy()[0]} against {expected}"


def test_coverage_and_target_positions_capture_into_a_cpu_graph():
    model = table_model(res=4, size=0.2, z=0.028)
    sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(cg_tol=1e-12, cg_max_iters=2000))
    start = model.state()
    final = wc.rollout(sim, start, steps=3)[-1]
    for goal in (Coverage(model, table_height=0.0, flat_tolerance=0.008), TargetPositions(model, grid(4, 0.2))):
        assert goal.capturable

        def loss(trajectory, goal=goal):
            out = wp.zeros(1, dtype=wp.float64, requires_grad=True)
            goal.add(trajectory[-1], out)
            return out

        captured = wc.CapturedRollout(sim, start, steps=3, loss=loss)
        captured.run()
        np.testing.assert_array_equal(captured.loss.numpy(), loss([final]).numpy(), err_msg=goal.name)
    assert not TargetPoints(model, grid(4, 0.2)).capturable
