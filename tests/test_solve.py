"""The linear solve: CG agrees with a dense solve, and its recorded adjoint agrees with the dense adjoint
(dL/db = A^-1 g, dL/dA_ij = -lam_i dv_j^T on the stored blocks; SPEC.md §4.1)."""

import numpy as np
import pytest
import warp as wp
from conftest import DEVICES

import warpcloth as wc

ROT_XZ = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # grid XY plane -> vertical XZ plane


def hanging_sim(dtype=wp.float64, device="cpu", **options):
    b = wc.ModelBuilder()
    b.add_cloth_grid((5, 5), (0.5, 0.5), material=wc.preset("gray-interlock", thicken=2), rot=ROT_XZ)
    b.add_handle(30)
    b.add_pin(35)
    b.set_wind((0.0, 4.0, 1.0))
    model = b.finalize(device, requires_grad=True, dtype=dtype)
    return wc.Simulator(model, 0.02, options=wc.SolverOptions(**options))


def assembled(sim):
    """A state a few steps in (bent, moving), its dense system, its blocks and a solution buffer."""
    traj = wc.rollout(sim, sim.model.state(), steps=3)
    A, b = sim.dense_system(traj[-1])
    values, rhs, _ = sim.assemble(traj[-1])
    dv = wp.zeros_like(rhs)
    return traj[-1], A, b, values, rhs, dv


@pytest.mark.parametrize("backend, preconditioner", [
    ("sequential", "jacobi"), ("sequential", "block_jacobi"), ("sequential", "block_ssor"), ("sequential", "multigrid"),
    ("warp", "jacobi"), ("warp", "block_jacobi"), ("warp", "multigrid"), ("tiled", "jacobi"), ("tiled", "block_jacobi"),
    ("tiled", "multigrid"),
])
@pytest.mark.parametrize("device", DEVICES)
def test_cg_matches_dense_solve(backend, preconditioner, device):
    sim = hanging_sim(device=device, cg_tol=1e-12, cg_atol=1e-30, cg_backend=backend, preconditioner=preconditioner)
    _, A, b, values, rhs, dv = assembled(sim)
    iters, residual, converged = sim.linear_solver.solve(values, rhs, dv)
    assert converged and 0 < iters < sim.options.cg_max_iters and residual <= 1e-12
    expected = np.linalg.solve(A, b)
    np.testing.assert_allclose(dv.numpy().reshape(-1), expected, rtol=1e-9, atol=1e-10 * np.abs(expected).max())


@pytest.mark.parametrize("backend, preconditioner", [("sequential", "block_ssor"), ("sequential", "block_jacobi"),
                                                    ("sequential", "multigrid"),
                                                    ("warp", "block_jacobi"), ("warp", "multigrid"),
                                                    ("tiled", "block_jacobi"), ("tiled", "multigrid")])
@pytest.mark.parametrize("device", DEVICES)
def test_solve_adjoint_matches_dense(backend, preconditioner, device):
    sim = hanging_sim(device=device, cg_tol=1e-12, cg_backend=backend, preconditioner=preconditioner)
    _, A, b, values, rhs, _ = assembled(sim)
    model = sim.model
    values, rhs = wp.clone(values, requires_grad=True), wp.clone(rhs, requires_grad=True)
    dv = wp.zeros(model.particle_count, dtype=model.types.vec3, requires_grad=True, device=model.device)
    tape = wp.Tape()
    with tape:
        sim.linear_solver.solve_recorded(values, rhs, dv)
    g = np.random.default_rng(0).standard_normal((model.particle_count, 3))
    tape.backward(grads={dv: wp.array(g, dtype=model.types.vec3, device=model.device)})

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


@wp.kernel
def _weighted_sum(x: wp.array(dtype=wp.vec3d), v: wp.array(dtype=wp.vec3d), wx: wp.array(dtype=wp.vec3d),
                  wv: wp.array(dtype=wp.vec3d), loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(x[i], wx[i]) + wp.dot(v[i], wv[i]) + wp.float64(0.5) * wp.dot(x[i], x[i]))


def rollout_gradients(element_adjoint):
    """Gradients of a loss on a damped, pinned, wind-blown rollout w.r.t. every differentiable input."""
    b = wc.ModelBuilder()
    b.add_cloth_grid((5, 5), (0.5, 0.5), material=wc.preset("tango-red-jet-set", thicken=2), rot=ROT_XZ)
    b.add_handle(30)
    b.add_pin(35, motion=[(0.0, (0.0, 0.0, 0.0)), (0.1, (0.01, 0.03, 0.02))])
    b.set_wind((0.5, 4.0, 1.0), drag=0.2)
    b.set_damping(mass=0.3, stiffness=0.002)
    model = b.finalize("cpu", requires_grad=True, dtype=wp.float64)
    sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(cg_tol=1e-13, cg_atol=1e-30))
    sim.assembler.element_adjoint = element_adjoint
    state = model.state()
    control = model.control(particle_force=True)
    rng = np.random.default_rng(3)
    weights = [wp.array(rng.standard_normal((model.particle_count, 3)), dtype=wp.vec3d) for _ in range(2)]
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    tape = wp.Tape()
    with tape:
        traj = wc.rollout(sim, state, control, steps=6)
        wp.launch(_weighted_sum, model.particle_count, inputs=[traj[-1].particle_x, traj[-1].particle_v, *weights],
                  outputs=[loss])
    tape.backward(loss)
    arrays = [state.particle_x, state.particle_v, model.material_density, model.material_stretching,
              model.material_bending, model.gravity, model.wind_velocity, model.handle_stiffness,
              model.damping_mass, model.damping_stiffness, control.particle_force, control.handle_target,
              control.pin_target]
    return [a.grad.numpy().copy() for a in arrays]


def test_contracted_element_adjoint_equals_warp_autodiff():
    # the custom adjoint of the stretching/bending assembly against Warp's autodiff of the same kernels
    contracted = rollout_gradients("contracted")
    autodiff = rollout_gradients("autodiff")
    for c, a in zip(contracted, autodiff):
        assert np.abs(a).max() > 0.0
        np.testing.assert_allclose(c, a, rtol=1e-8, atol=1e-10 * np.abs(a).max())


def test_ssor_warm_start_from_the_solution_takes_no_iterations():
    sim = hanging_sim(cg_tol=1e-10, preconditioner="block_ssor")
    _, A, b, values, rhs, dv = assembled(sim)
    x = wp.array(np.linalg.solve(A, b).reshape(-1, 3), dtype=sim.model.types.vec3)
    iters, residual, converged = sim.linear_solver.solve(values, rhs, x, guess=x)
    assert converged and iters == 0 and residual <= 1e-10
    cold = wp.zeros_like(x)
    assert sim.linear_solver.solve(values, rhs, cold).iterations > 5
