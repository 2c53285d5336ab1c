"""The same code on every device: a recorded rollout and its gradients agree with the CPU's."""

import numpy as np
import pytest
import warp as wp
from conftest import DEVICES, hanging_builder

import warpcloth as wc


@wp.kernel
def height_loss(x: wp.array(dtype=wp.vec3), loss: wp.array(dtype=float)):
    wp.atomic_add(loss, 0, x[wp.tid()][2])


def run(device):
    model = hanging_builder(res=6).finalize(device, requires_grad=True)
    sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(cg_tol=1e-7))
    tape = wp.Tape()
    with wp.ScopedDevice(device), tape:
        traj = wc.rollout(sim, model.state(), model.control(), steps=8)
        loss = wp.zeros(1, dtype=float, requires_grad=True)
        wp.launch(height_loss, model.particle_count, inputs=[traj[-1].particle_x], outputs=[loss])
    tape.backward(loss)
    return traj[-1].particle_x.numpy(), model.material_density.grad.numpy(), model.wind_velocity.grad.numpy()


@pytest.mark.parametrize("device", DEVICES)
def test_rollout_and_gradients_match_cpu(device):
    x_cpu, dens_cpu, wind_cpu = run("cpu")
    x, dens, wind = run(device)
    assert np.all(np.isfinite(x)) and np.abs(dens).max() > 0 and np.abs(wind).max() > 0
    np.testing.assert_allclose(x, x_cpu, atol=1e-5)
    np.testing.assert_allclose(dens, dens_cpu, rtol=1e-3)
    np.testing.assert_allclose(wind, wind_cpu, rtol=1e-3, atol=1e-3 * np.abs(wind_cpu).max())


@pytest.mark.parametrize("device", DEVICES)
def test_both_cg_backends_agree(device):
    results = []
    for backend in ("sequential", "warp"):
        model = hanging_builder(res=6).finalize(device)
        sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(cg_tol=1e-7, cg_backend=backend))
        results.append(wc.rollout(sim, model.state(), steps=5)[-1].particle_x.numpy())
    np.testing.assert_allclose(results[0], results[1], atol=1e-5)
