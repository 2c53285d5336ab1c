"""A rollout captured as a graph and replayed gives the uncaptured rollout's trajectory and gradients, and a step
that never reads the device back still reports its failures, naming the step."""

import numpy as np
import pytest
import warp as wp
from conftest import DEVICES, hanging_builder

import warpcloth as wc

STEPS = 6


@wp.kernel
def height_loss(x: wp.array(dtype=wp.vec3), loss: wp.array(dtype=float)):
    wp.atomic_add(loss, 0, x[wp.tid()][2] * float(1 + wp.tid() % 3))


def loss_of(trajectory):
    loss = wp.zeros(1, dtype=float, requires_grad=True)
    wp.launch(height_loss, trajectory[-1].particle_x.shape[0], inputs=[trajectory[-1].particle_x], outputs=[loss])
    return loss


def gradient_arrays(model, state, control):
    """Every array a user can optimise here: the start state, the materials, gravity, wind, forces, handle and pin
    targets."""
    return {"particle_x": state.particle_x, "particle_v": state.particle_v, "density": model.material_density,
            "stretching": model.material_stretching, "bending": model.material_bending, "gravity": model.gravity,
            "wind": model.wind_velocity, "force": control.particle_force, "handle_target": control.handle_target,
            "pin_target": control.pin_target}


def scene(device, **options):
    b = hanging_builder(res=5)
    b.add_pin(3)  # a hard pin as well, so its target is a parameter
    model = b.finalize(device, requires_grad=True)
    sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(cg_tol=1e-7, **options))
    return model, sim, model.state(requires_grad=True), model.control(requires_grad=True, particle_force=True)


def exact_or_close(device):
    """Bitwise on the CPU (the same kernels in the same order); on CUDA the warp backend's reductions may reorder."""
    if wp.get_device(device).is_cpu:
        return lambda a, b: np.testing.assert_array_equal(a, b)
    return lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * max(np.abs(b).max(), 1e-12))


@pytest.mark.parametrize("device", DEVICES)
def test_captured_forward_equals_uncaptured(device):
    model, sim, state, control = scene(device)
    expected = [s.particle_x.numpy().copy() for s in wc.rollout(sim, state, control, steps=STEPS)]
    captured = wc.CapturedRollout(sim, state, control, steps=STEPS)
    for s in captured.trajectory[1:]:
        s.particle_x.zero_()  # what a replay writes, not what capturing left
    same = exact_or_close(device)
    for got, want in zip(captured.run(), expected):
        same(got.particle_x.numpy(), want)
    assert sim.stats["steps"] == 3 * STEPS  # the rollout, the capture's ordinary run, the replay (not the capture)


@pytest.mark.parametrize("device", DEVICES)
def test_captured_gradients_equal_uncaptured_for_every_parameter(device):
    model, sim, state, control = scene(device)
    arrays = gradient_arrays(model, state, control)
    tape = wp.Tape()
    with wp.ScopedDevice(device), tape:
        loss = loss_of(wc.rollout(sim, state, control, steps=STEPS))
    tape.backward(loss)
    expected = {name: a.grad.numpy().copy() for name, a in arrays.items()}
    tape.zero()
    assert all(not np.any(a.grad.numpy()) for a in arrays.values()), "tape.zero() left a gradient"
    assert all(np.abs(g).max() > 0 for g in expected.values()), {k: np.abs(g).max() for k, g in expected.items()}

    if wp.get_device(device).is_cuda:  # not captured there yet (Warp 1.19): run afresh each time, and say so
        with pytest.warns(RuntimeWarning, match="not captured on CUDA"):
            captured = wc.CapturedRollout(sim, state, control, steps=STEPS, loss=loss_of)
    else:
        captured = wc.CapturedRollout(sim, state, control, steps=STEPS, loss=loss_of)
        assert len(captured.graphs) == 3
    same = exact_or_close(device)
    for _ in range(2):  # a second replay starts from zeroed gradients: it does not add to the first
        captured.run()
        np.testing.assert_allclose(captured.loss.numpy(), loss.numpy(), rtol=1e-6)
        for name, a in arrays.items():
            same(a.grad.numpy(), expected[name])


@pytest.mark.parametrize("device", DEVICES)
def test_a_replay_reads_inputs_changed_in_place(device):
    model, sim, state, control = scene(device)
    captured = wc.CapturedRollout(sim, state, control, steps=STEPS)
    model.wind_velocity.assign(np.array([[0.0, -3.0, 1.0]], dtype=np.float32))
    control.handle_target.assign(control.handle_target.numpy() + 0.05)
    expected = wc.rollout(sim, state, control, steps=STEPS)[-1].particle_x.numpy()
    exact_or_close(device)(captured.run()[-1].particle_x.numpy(), expected)


@pytest.mark.parametrize("device", DEVICES)
def test_failures_are_reported_after_the_replay_naming_the_step(device):
    model, sim, state, control = scene(device)
    captured = wc.CapturedRollout(sim, state, control, steps=STEPS)
    state.particle_v.assign(np.full((model.particle_count, 3), 2e3, dtype=np.float32))  # over max_speed (1e3)
    with pytest.raises(wc.SimulationError, match=r"diverged at step 1 \(t = 0.02 s\): particle \d+ moves at"):
        captured.run()


@pytest.mark.parametrize("device", DEVICES)
def test_deferred_checks_name_the_failing_step(device):
    messages = []
    for every in (1, 0, 4):
        model, sim, state, control = scene(device, max_speed=0.6, sync_every=every)
        with pytest.raises(wc.SimulationError, match=r"diverged at step \d+ ") as err:
            wc.rollout(sim, state, control, steps=40)
        messages.append(str(err.value).split(":")[0])
    assert messages[0] == messages[1] == messages[2], messages  # the same step, whenever it is read


def test_capture_refuses_a_scene_with_contact():
    b = wc.ModelBuilder()
    b.add_cloth_grid((3, 3), (0.3, 0.3), material=wc.preset("gray-interlock"), pos=(-0.15, -0.15, 0.2))
    b.add_obstacle_sphere(0.1, 2)
    model = b.finalize("cpu")
    sim = wc.Simulator(model, 0.01)
    with pytest.raises(ValueError, match="collision stage or proximity forces"):
        wc.CapturedRollout(sim, model.state(), steps=2)


def test_capture_refuses_the_warp_backend_on_the_cpu():
    model = hanging_builder(res=3).finalize("cpu")
    sim = wc.Simulator(model, 0.02, options=wc.SolverOptions(cg_backend="warp"))
    with pytest.raises(ValueError, match="tests its convergence on the host"):
        wc.CapturedRollout(sim, model.state(), steps=2)


def test_an_untaped_step_allocates_nothing():
    model = hanging_builder(res=5).finalize("cpu")
    sim = wc.Simulator(model, 0.02)
    a, b = model.state(), model.empty_state()
    sim.step(a, b)
    sim.step(b, a)  # both States now hold the solve's first guess
    made = []
    original = wp.array.__init__

    def counting(self, *args, **kwargs):
        if kwargs.get("ptr") is None:  # not a view of existing memory
            made.append(kwargs.get("shape", args[:1]))
        original(self, *args, **kwargs)

    wp.array.__init__ = counting
    try:
        for _ in range(3):
            sim.step(a, b)
            sim.step(b, a)
    finally:
        wp.array.__init__ = original
    assert not made, f"{len(made)} arrays made in 6 untaped steps: {made}"


@pytest.mark.parametrize("device", DEVICES)
def test_scripted_motions_replay_their_targets(device):
    # a moving pin's targets are made on the host per step time: a replay must read the ones of its own steps
    model = hanging_builder(res=4, moving_pin=True).finalize(device)
    sim = wc.Simulator(model, 0.02)
    expected = wc.rollout(sim, model.state(), steps=STEPS)[-1].particle_x.numpy()
    captured = wc.CapturedRollout(sim, model.state(), steps=STEPS)
    captured.trajectory[-1].particle_x.zero_()
    exact_or_close(device)(captured.run()[-1].particle_x.numpy(), expected)


def test_a_replay_refuses_options_or_arrays_replaced_since_the_capture():
    model, sim, state, control = scene("cpu")
    captured = wc.CapturedRollout(sim, state, control, steps=2)
    sim.options = wc.SolverOptions(cg_tol=1e-6)  # kernel arguments the graph baked in
    with pytest.raises(ValueError, match="options changed since the capture"):
        captured.run()
    captured = wc.CapturedRollout(sim, state, control, steps=2)
    model.material_density = wp.array(model.material_density.numpy() * 1.1, dtype=model.scalar,
                                      requires_grad=True)  # a new array: the graph reads the old one
    with pytest.raises(ValueError, match="rebound since the capture"):
        captured.run()
