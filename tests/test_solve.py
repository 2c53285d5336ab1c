"""The linear solve: CG agrees with a dense solve, and its recorded adjoint agrees with the dense adjoint
(dL/db = A^-1 g, dL/dA_ij = -lam_i dv_j^T on the stored blocks; SPEC.md §4.1)."""

import numpy as np
import pytest
import warp as wp

import warpcloth as wc

ROT_XZ = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # grid XY plane -> vertical XZ plane


def hanging_sim(dtype=wp.float64, **options):
    b = wc.ModelBuilder()
    b.add_cloth_grid((5, 5), (0.5, 0.5), material=wc.preset("gray-interlock", thicken=2), rot=ROT_XZ)
    b.add_handle(30)
    b.add_pin(35)
    b.set_wind((0.0, 4.0, 1.0))
    model = b.finalize("cpu", requires_grad=True, dtype=dtype)
    return wc.Simulator(model, 0.02, options=wc.SolverOptions(**options))


def assembled(sim):
    """A state a few steps in (bent, moving) and the buffers of its system."""
    traj = wc.rollout(sim, sim.model.state(), steps=3)
    A, b = sim.dense_system(traj[-1])
    values, rhs, dv, _ = sim._buffers()
    return traj[-1], A, b, values, rhs, dv


@pytest.mark.parametrize("backend", ["sequential", "warp"])
@pytest.mark.parametrize("preconditioner", ["jacobi", "block_jacobi"])
def test_cg_matches_dense_solve(backend, preconditioner):
    sim = hanging_sim(cg_tol=1e-12, cg_atol=1e-30, cg_backend=backend, preconditioner=preconditioner)
    _, A, b, values, rhs, dv = assembled(sim)
    iters, residual = sim._cg(values, rhs, dv)
    assert 0 < iters < sim.options.cg_max_iters and residual <= 1e-12
    expected = np.linalg.solve(A, b)
    np.testing.assert_allclose(dv.numpy().reshape(-1), expected, rtol=1e-9, atol=1e-10 * np.abs(expected).max())


@pytest.mark.parametrize("backend", ["sequential", "warp"])
def test_solve_adjoint_matches_dense(backend):
    sim = hanging_sim(cg_tol=1e-12, cg_backend=backend)
    state = assembled(sim)[0]
    model = sim.model
    values = wp.zeros(model.bsr_nnz, dtype=model.types.mat33, requires_grad=True)
    rhs = wp.zeros(model.particle_count, dtype=model.types.vec3, requires_grad=True)
    dv = wp.zeros(model.particle_count, dtype=model.types.vec3, requires_grad=True)
    pin_dv = wp.zeros_like(dv)
    sim._assemble(state, model.control(requires_grad=False), state.time + sim.dt, values, rhs, pin_dv)
    A, b = sim.dense_system(state)
    tape = wp.Tape()
    with tape:
        sim._solve_recorded(values, rhs, dv)
    g = np.random.default_rng(0).standard_normal((model.particle_count, 3))
    tape.backward(grads={dv: wp.array(g, dtype=model.types.vec3)})

    lam = np.linalg.solve(A, g.reshape(-1))  # A is symmetric
    x = np.linalg.solve(A, b)
    np.testing.assert_allclose(rhs.grad.numpy().reshape(-1), lam, rtol=1e-8, atol=1e-10 * np.abs(lam).max())
    # dL/dA_ij = -lam_i x_j^T for every stored block, and only there
    offsets, columns = model.bsr_offsets.numpy(), model.bsr_columns.numpy()
    grads = values.grad.numpy()
    lam3, x3 = lam.reshape(-1, 3), x.reshape(-1, 3)
    for i in range(model.particle_count):
        for s in range(offsets[i], offsets[i + 1]):
            np.testing.assert_allclose(grads[s], -np.outer(lam3[i], x3[columns[s]]), rtol=1e-7,
                                       atol=1e-10 * np.abs(lam).max() * np.abs(x).max())


def test_system_is_symmetric_positive_definite_with_pins():
    sim = hanging_sim()
    _, A, _, _, _, _ = assembled(sim)
    np.testing.assert_allclose(A, A.T, atol=1e-12 * np.abs(A).max())
    assert np.linalg.eigvalsh(A).min() > 0.0
    # the pinned particle's row is the identity: its velocity change is prescribed
    p = sim.model.pin_particle.numpy()[0]
    np.testing.assert_array_equal(A[3 * p: 3 * p + 3], np.eye(3 * sim.model.particle_count)[3 * p: 3 * p + 3])
