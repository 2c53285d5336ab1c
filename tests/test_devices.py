"""The same code on every device: a recorded rollout and its gradients agree with the CPU's."""

import numpy as np
import pytest
import warp as wp
from conftest import DEVICES, gpu_devices, hanging_builder

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


@pytest.mark.parametrize("device", gpu_devices())
def test_rollout_and_gradients_match_cpu(device):
    x_cpu, dens_cpu, wind_cpu = run("cpu")
    x, dens, wind = run(device)
    assert np.all(np.isfinite(x)) and np.abs(dens).max() > 0 and np.abs(wind).max() > 0
    np.testing.assert_allclose(x, x_cpu, atol=1e-5)
    np.testing.assert_allclose(dens, dens_cpu, rtol=1e-3)
    np.testing.assert_allclose(wind, wind_cpu, rtol=1e-3, atol=1e-3 * np.abs(wind_cpu).max())


@pytest.mark.parametrize("device", DEVICES)
def test_every_cg_backend_agrees(device):
    results = []
    for backend, preconditioner in (("sequential", "auto"), ("warp", "block_jacobi"), ("warp", "multigrid"),
                                    ("tiled", "auto"), ("tiled", "multigrid")):
        model = hanging_builder(res=6).finalize(device)
        sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(cg_tol=1e-7, cg_backend=backend,
                                                                 preconditioner=preconditioner))
        results.append(wc.rollout(sim, model.state(), steps=5)[-1].particle_x.numpy())
    for other in results[1:]:
        np.testing.assert_allclose(other, results[0], atol=1e-5)


def sphere_contact_model(device, **collision) -> wc.Model:
    """A 6x6 cloth falling onto a sphere, float64. Its centre is off the sphere's pole: centred over it (as it was),
    the closest triangle of the pole's vertex flips on a difference at rounding's scale, so a 1e-15 m perturbation of
    the start grew to 2.4e-3 m after 15 steps (an H100's run ended 2.4 mm from the CPU's), against 5.8e-12 m here."""
    b = wc.ModelBuilder()
    b.add_cloth_grid((6, 6), (0.4, 0.4), material=wc.preset("gray-interlock"), pos=(-0.1863, -0.1939, 0.16))
    b.add_obstacle_sphere(0.15, 2)
    if collision:
        b.set_collision(**collision)
    return b.finalize(device, requires_grad=True, dtype=wp.float64)


@pytest.mark.parametrize("repulsion", [True, False])
def test_the_sphere_scene_is_not_chaotic(repulsion):
    # what the device comparisons below rely on: a perturbation of the start at rounding's scale stays there
    def final(eps):
        model = sphere_contact_model("cpu", **({} if repulsion else {"repulsion_stiffness": 0.0}))
        sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(cg_tol=1e-10, cg_backend="warp"))
        state = model.state()
        state.particle_x.assign(state.particle_x.numpy()
                                + eps * np.random.default_rng(0).standard_normal((model.particle_count, 3)))
        return wc.rollout(sim, state, steps=15)[-1].particle_x.numpy()

    assert np.abs(final(1e-15) - final(0.0)).max() < 1e-9


@pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device here: the GPU path of contact is not tested")
def test_contact_on_cuda_matches_cpu():
    # repulsion and friction through the warp CG backend's matrix-free pair term, and their adjoints
    def run_contact(device):
        model = sphere_contact_model(device)
        sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(cg_tol=1e-10, cg_backend="warp"))
        control = model.control(requires_grad=True)
        tape = wp.Tape()
        with wp.ScopedDevice(device), tape:
            final = wc.rollout(sim, model.state(), control, steps=15)[-1]
        tape.backward(grads={final.particle_x: wp.array(np.ones((model.particle_count, 3)), dtype=wp.vec3d,
                                                        device=device)})
        assert sim.proximity.last_count > 0  # repulsion and friction act
        return (final.particle_x.numpy(), model.material_density.grad.numpy(),
                control.obstacle_transform.grad.numpy())

    for a, b in zip(run_contact("cpu"), run_contact("cuda:0")):
        np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-9 * max(np.abs(a).max(), 1.0))


@pytest.mark.parametrize("device", DEVICES)
def test_every_cg_backend_agrees_with_repulsion_pairs(device):
    # the pairs' cross blocks, applied matrix-free by each backend (a thread per pair), and their adjoints
    def run_backend(backend, preconditioner):
        model = sphere_contact_model(device)
        sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(cg_tol=1e-11, cg_backend=backend,
                                                                 preconditioner=preconditioner))
        tape = wp.Tape()
        with wp.ScopedDevice(device), tape:
            final = wc.rollout(sim, model.state(), steps=15)[-1]
        tape.backward(grads={final.particle_x: wp.array(np.ones((model.particle_count, 3)), dtype=wp.vec3d,
                                                        device=device)})
        assert sim.proximity.last_count > 0  # repulsion and friction act
        return final.particle_x.numpy(), model.material_density.grad.numpy()

    x_ref, g_ref = run_backend("sequential", "block_jacobi")
    for backend in ("tiled", "warp"):
        x, g = run_backend(backend, "block_jacobi")
        np.testing.assert_allclose(x, x_ref, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(g, g_ref, rtol=1e-6, atol=1e-9 * np.abs(g_ref).max())
