"""The multigrid preconditioner: its aggregation hierarchy (every free particle in one aggregate, Galerkin blocks
equal to the dense P^T A P), its solves against dense ones, and that it is a stronger preconditioner than block
SSOR (fewer iterations on the same system)."""

import numpy as np
import pytest
import warp as wp
from conftest import DEVICES

import warpcloth as wc
from warpcloth.errors import SimulationError
from warpcloth.solver.multigrid import MAX_COARSEST, ParallelMultigrid, WorldHierarchies

ROT_XZ = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def hanging_builder(res, pins=(0,)):
    b = wc.ModelBuilder()
    b.add_cloth_grid((res, res), (0.5, 0.5), material=wc.preset("gray-interlock", thicken=2), rot=ROT_XZ)
    for p in pins:
        b.add_pin(p)
    b.add_handle(res)
    b.set_wind((0.0, 4.0, 1.0))
    return b


def hanging(res, dtype=wp.float64, pins=(0,), device="cpu"):
    return hanging_builder(res, pins).finalize(device, dtype=dtype)


def hierarchy_of(model):
    return WorldHierarchies.of_model(model)


def prolongations(h):
    """Dense piecewise-constant prolongations (3 n_l x 3 n_{l+1}) of each level, from the flat aggregate map."""
    start, agg = h.level_start, h.aggregate
    out = []
    for level in range(len(h.sizes) - 1):
        n, m = h.sizes[level], h.sizes[level + 1]
        P = np.zeros((n, m))
        for i in range(n):
            a = agg[start[level] + i]
            if a >= 0:
                P[i, a - start[level + 1]] = 1.0
        out.append(np.kron(P, np.eye(3)))
    return out


def test_every_free_particle_is_in_one_aggregate_and_pinned_ones_in_none():
    model = hanging(20, pins=(0, 5, 399))
    h = hierarchy_of(model)
    assert h.sizes[0] == model.particle_count and h.sizes[-1] <= MAX_COARSEST
    assert all(a > b for a, b in zip(h.sizes, h.sizes[1:])), h.sizes
    assert len(h.sizes) >= 3, "the test should reach a level coarsened from a Galerkin pattern"
    pinned = model.particle_pin.numpy() >= 0
    fine = h.aggregate[: h.sizes[0]]
    np.testing.assert_array_equal(fine < 0, pinned)
    # every aggregate of every level is used (no empty coarse node)
    for level in range(len(h.sizes) - 1):
        agg = h.aggregate[h.level_start[level]: h.level_start[level + 1]]
        used = np.unique(agg[agg >= 0])
        np.testing.assert_array_equal(used, np.arange(h.level_start[level + 1], h.level_start[level + 2]))


def test_galerkin_slot_maps_equal_the_dense_triple_product():
    model = hanging(20, pins=(0, 7))
    h = hierarchy_of(model)
    n = model.particle_count
    offsets, columns = model.bsr_offsets.numpy(), model.bsr_columns.numpy()
    rows = np.repeat(np.arange(n), np.diff(offsets))
    rng = np.random.default_rng(1)
    blocks = rng.standard_normal((len(columns), 3, 3))
    # the pattern of a pinned particle carries no coupling (its row is the identity, its column is eliminated)
    pinned = model.particle_pin.numpy() >= 0
    blocks[pinned[rows] | pinned[columns]] = 0.0

    def dense(level_blocks, level_offsets, level_columns, size, base):
        A = np.zeros((size, 3, size, 3))
        for i in range(size):
            for k in range(level_offsets[i], level_offsets[i + 1]):
                A[i, :, level_columns[k] - base, :] = level_blocks[k]
        return A.reshape(3 * size, 3 * size)

    coarse = np.zeros((len(h.columns), 3, 3))
    np.add.at(coarse, h.fine_slot[h.fine_slot >= 0], blocks[h.fine_slot >= 0])
    assert np.all(h.fine_slot[pinned[rows] | pinned[columns]] == -1)
    for k in range(len(h.columns)):  # level by level, in order, as the kernel does
        if h.coarse_slot[k] >= 0:
            coarse[h.coarse_slot[k]] += coarse[k]
    A = dense(blocks, offsets, columns, n, 0)
    n0 = h.sizes[0]
    for level, P in enumerate(prolongations(h)):
        A = P.T @ A @ P
        size, base = h.sizes[level + 1], h.level_start[level + 1]
        rows_of_level = slice(base - n0, base - n0 + size + 1)
        np.testing.assert_allclose(dense(coarse, h.offsets[rows_of_level], h.columns, size, base), A,
                                   atol=1e-12 * np.abs(A).max())
        diag = h.diag_slot[base - n0: base - n0 + size]
        np.testing.assert_array_equal(h.columns[diag], base + np.arange(size))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("backend", ["sequential", "warp", "tiled"])  # the Gauss-Seidel V-cycle, the parallel one
@pytest.mark.parametrize("dtype", [wp.float32, wp.float64])
def test_multigrid_solve_matches_dense(dtype, backend, device):
    model = hanging(8, dtype=dtype, pins=(0, 3), device=device)
    sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(cg_tol=1e-12 if dtype == wp.float64 else 1e-6,
                                                             cg_atol=1e-30, preconditioner="multigrid",
                                                             cg_backend=backend))
    assert sim.linear_solver.preconditioner == "multigrid" and len(sim.linear_solver.multigrid_levels) >= 2
    state = wc.rollout(sim, model.state(), steps=3)[-1]
    A, b = sim.dense_system(state)
    values, rhs, _ = sim.assemble(state)
    dv = wp.zeros_like(rhs)
    info = sim.linear_solver.solve(values, rhs, dv)
    assert info.converged
    expected = np.linalg.solve(A, b)
    tol = 1e-9 if dtype == wp.float64 else 2e-4
    np.testing.assert_allclose(dv.numpy().reshape(-1), expected, atol=tol * np.abs(expected).max())


def test_separate_pieces_coarsen_and_solve():
    # 30 separate two-triangle patches: once each is one node, they have no neighbours left to aggregate with
    b = wc.ModelBuilder()
    for k in range(30):
        b.add_cloth_grid((1, 1), (0.1, 0.1), material=wc.preset("gray-interlock"), pos=(0.2 * k, 0.0, 0.0))
    model = b.finalize("cpu", dtype=wp.float64)
    h = hierarchy_of(model)
    assert h.sizes[0] == 120 and h.sizes[-1] <= MAX_COARSEST
    sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(cg_tol=1e-12, cg_atol=1e-30))
    assert sim.linear_solver.preconditioner == "multigrid"
    A, rhs = sim.dense_system(model.state())
    values, b_arr, _ = sim.assemble(model.state())
    dv = wp.zeros_like(b_arr)
    assert sim.linear_solver.solve(values, b_arr, dv).converged
    np.testing.assert_allclose(dv.numpy().reshape(-1), np.linalg.solve(A, rhs), rtol=1e-9, atol=1e-14)


def test_multigrid_takes_fewer_iterations_than_block_ssor():
    model = hanging(32, dtype=wp.float32)
    sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(preconditioner="block_ssor"))
    state = wc.rollout(sim, model.state(), steps=5)[-1]
    values, rhs, _ = sim.assemble(state)
    iterations = {}
    for name in ("block_ssor", "multigrid"):
        solver = wc.LinearSolver(model, wc.SolverOptions(preconditioner=name, cg_tol=1e-5))
        dv = wp.zeros_like(rhs)
        info = solver.solve(values, rhs, dv)
        assert info.converged, name
        iterations[name] = info.iterations
    # measured: 15 against 50 (benchmarks/step_time.py has the 64x64 figures)
    assert iterations["multigrid"] < 0.5 * iterations["block_ssor"], iterations


def solve_negative_definite(backend):
    """The multigrid's solve of a negative definite system (-I on the diagonal, no coupling: the coarse level's
    first pivot is negative)."""
    model = hanging(6)
    solver = wc.LinearSolver(model, wc.SolverOptions(preconditioner="multigrid", cg_backend=backend))
    blocks = np.zeros((model.bsr_nnz, 3, 3))
    blocks[model.particle_diag_slot.numpy()] = -np.eye(3)
    values = wp.array(blocks, dtype=model.types.mat33)
    rhs = wp.array(np.ones((model.particle_count, 3)), dtype=model.types.vec3)
    return solver, solver.solve(values, rhs, wp.zeros_like(rhs))


def test_a_system_that_is_not_positive_definite_raises():
    solver, info = solve_negative_definite("sequential")
    assert not np.isfinite(info.residual)
    with pytest.raises(SimulationError, match="non-finite residual"):
        solver.check(info, "forward", 3)


def test_all_pinned_model_falls_back_and_explicit_multigrid_is_refused():
    b = wc.ModelBuilder()
    b.add_cloth_grid((1, 1), (0.1, 0.1), material=wc.preset("gray-interlock"))
    for p in range(4):
        b.add_pin(p)
    model = b.finalize("cpu")
    assert wc.LinearSolver(model, wc.SolverOptions()).preconditioner == "block_ssor"
    for backend in ("sequential", "tiled", "warp"):
        with pytest.raises(ValueError, match="not pinned; use preconditioner='block_ssor' .* or 'block_jacobi'"):
            wc.LinearSolver(model, wc.SolverOptions(preconditioner="multigrid", cg_backend=backend))


def test_block_ssor_has_no_parallel_form():
    for backend in ("tiled", "warp"):
        with pytest.raises(ValueError, match="'block_ssor' needs cg_backend 'sequential'.*'multigrid' \\(in parallel"):
            wc.LinearSolver(hanging(4), wc.SolverOptions(preconditioner="block_ssor", cg_backend=backend))


@pytest.mark.parametrize("device", DEVICES)
def test_the_parallel_multigrid_takes_about_the_sequential_ones_iterations(device):
    # the warp backend's V-cycle (damped Jacobi smoothing, what CUDA runs) against the sequential Gauss-Seidel one
    model = hanging(32, dtype=wp.float32, device=device)
    sim = wc.Simulator(model, 0.02)
    state = wc.rollout(sim, model.state(), steps=5)[-1]
    values, rhs, _ = sim.assemble(state)
    iterations = {}
    for backend, name in (("sequential", "multigrid"), ("warp", "multigrid"), ("warp", "block_jacobi"),
                          ("tiled", "multigrid")):
        solver = wc.LinearSolver(model, wc.SolverOptions(cg_backend=backend, preconditioner=name, cg_tol=1e-5))
        dv = wp.zeros_like(rhs)
        info = solver.solve(values, rhs, dv)
        assert info.converged, (backend, name)
        iterations[backend, name] = info.iterations
    # measured: 22 sequential, 22 parallel, 234 block Jacobi (issue 37's target: within 1.5x on the GPU)
    assert iterations["warp", "multigrid"] <= 1.5 * iterations["sequential", "multigrid"], iterations
    assert iterations["warp", "multigrid"] < 0.5 * iterations["warp", "block_jacobi"], iterations
    # the same V-cycle on the threads of one block, in the tiled CG: its rounding differs from warp.optim's CG
    assert abs(iterations["tiled", "multigrid"] - iterations["warp", "multigrid"]) <= 1, iterations


def test_the_parallel_multigrid_reports_a_system_that_is_not_positive_definite():
    _, info = solve_negative_definite("warp")
    assert not np.isfinite(info.residual)


@pytest.mark.parametrize("backend", ["sequential", "tiled"])  # a world's V-cycle on its thread, on its block
def test_worlds_of_different_meshes_each_solve_with_their_own_hierarchy(backend):
    # a 3x3 and a 14x14 sheet (hierarchies of different depths, pins in one): each world's steps and solves are
    # bitwise the ones its model alone gives, and the flat layout holds each world's levels where it says
    builders = [hanging_builder(3, (0,)), hanging_builder(14, (0, 5))]
    composed = wc.ModelBuilder()
    for b in builders:
        composed.add_world(b)
    batch = composed.finalize("cpu", dtype=wp.float64)
    h = hierarchy_of(batch)
    depths = [len(w.sizes) for w in h.worlds]
    assert depths[0] < depths[1], depths
    for w, world in enumerate(h.worlds):
        for level, size in enumerate(world.sizes):
            assert h.world_level_hi[w, level] - h.world_level_lo[w, level] == size
            assert h.level_start[level] <= h.world_level_lo[w, level] <= h.world_level_hi[w, level] \
                <= h.level_start[level + 1]
    options = wc.SolverOptions(cg_tol=1e-10, cg_backend=backend, preconditioner="multigrid")
    sim = wc.Simulator(batch, 0.02, options=options)
    assert sim.linear_solver.preconditioner == "multigrid"
    x = [s.particle_x.numpy() for s in wc.rollout(sim, batch.state(), steps=3)]
    iterations = sim.linear_solver.world_info[:, 0]
    for w, b in enumerate(builders):
        alone = wc.Simulator(b.finalize("cpu", dtype=wp.float64), 0.02, options=options)
        xs = [s.particle_x.numpy() for s in wc.rollout(alone, alone.model.state(), steps=3)]
        for k, (a, e) in enumerate(zip(x, xs)):
            np.testing.assert_array_equal(a[batch.world_slice(w)], e, err_msg=f"world {w}, state {k}")
        assert iterations[w] == alone.linear_solver.world_info[0, 0]


def dense_v_cycle(A: np.ndarray, prolongation: list[np.ndarray], b: np.ndarray, omega: float) -> np.ndarray:
    """One V-cycle of the parallel multigrid in dense NumPy: two damped block-Jacobi sweeps from zero down, the
    residual restricted by P^T, the next level's correction added, two sweeps up; the coarsest level solved."""
    if not prolongation:
        return np.linalg.solve(A, b)
    n = A.shape[0] // 3
    blocks = A.reshape(n, 3, n, 3)[np.arange(n), :, np.arange(n), :]
    dinv = np.linalg.inv(blocks)

    def smooth(x):
        return x + omega * np.einsum("nij,nj->ni", dinv, (b - A @ x).reshape(n, 3)).reshape(-1)

    x = smooth(smooth(np.zeros_like(b)))
    P = prolongation[0]
    x = x + P @ dense_v_cycle(P.T @ A @ P, prolongation[1:], P.T @ (b - A @ x), omega)
    return smooth(smooth(x))


@pytest.mark.parametrize("device", DEVICES)
def test_the_parallel_v_cycle_is_the_dense_one_whichever_levels_run_in_one_block(device, monkeypatch):
    # with one CG iteration from zero the solution is a multiple of M^-1 b, M^-1 the preconditioner's V-cycle; the
    # levels from ParallelMultigrid.BLOCK_NODES down run in one thread block, the others a launch a stage
    model = hanging(32, pins=(0, 7), device=device)
    sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(cg_backend="warp", preconditioner="multigrid"))
    state = wc.rollout(sim, model.state(), steps=3)[-1]
    A, b = sim.dense_system(state)
    values, rhs, _ = sim.assemble(state)
    h = hierarchy_of(model)
    assert len(h.sizes) >= 4, h.sizes  # two coarse levels and the coarsest: every split below is a different one
    expected = dense_v_cycle(A, prolongations(h), b, ParallelMultigrid.OMEGA)
    directions = []
    for block_nodes in (h.sizes[1], h.sizes[2], 0):  # the one block from level 1, from level 2, the coarsest only
        monkeypatch.setattr(ParallelMultigrid, "BLOCK_NODES", block_nodes)
        solver = wc.LinearSolver(model, wc.SolverOptions(cg_backend="warp", preconditioner="multigrid",
                                                         cg_max_iters=1))
        dv = wp.zeros_like(rhs)
        solver.solve(values, rhs, dv)
        got = dv.numpy().reshape(-1)
        directions.append(got)
        step = got @ expected / (expected @ expected)
        np.testing.assert_allclose(got, step * expected, atol=1e-9 * np.abs(step * expected).max(),
                                   err_msg=f"BLOCK_NODES {block_nodes}")
    for other in directions[1:]:  # the same arithmetic per node whatever runs in the block: bitwise
        np.testing.assert_array_equal(other, directions[0])
