"""warpcloth.torch.simulate against wc.rollout on a plain wp.Tape, torch's gradcheck, chaining and bad inputs.

Scene: the 3x3 hanging cloth of conftest.hanging_builder in float64 (bending table x30 so bending matters, wind so
the cloth bends), its initial state jittered off the flat rest state (see test_gradients.py: kinks at zero shear),
CG tolerance 1e-12. The reference for every gradient is the same loss differentiated by a wp.Tape over wc.rollout
with Warp arrays, on a Simulator of its own.
"""

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
import warp as wp
from conftest import hanging_builder

import warpcloth as wc

torch = pytest.importorskip("torch")
wct = pytest.importorskip("warpcloth.torch")
GradcheckError = sys.modules["torch.autograd.gradcheck"].GradcheckError

DT = 0.02
STEPS = 4
MATERIAL = wc.preset("gray-interlock", thicken=2).scaled(bending=30.0)
OPTIONS = wc.SolverOptions(cg_tol=1.0e-12, cg_max_iters=2000)


def build_model(dtype=wp.float64, requires_grad=True):
    return hanging_builder(res=3, material=MATERIAL).finalize("cpu", requires_grad=requires_grad, dtype=dtype)


class Problem:
    """Inputs (NumPy), loss weights and the reference gradients of one rollout."""

    def __init__(self, steps=STEPS, seed=0):
        self.model = m = build_model()
        self.steps = steps
        rng = np.random.default_rng(seed)
        n = self.n = m.particle_count
        self.x0 = m.particle_x0.numpy() + 2.0e-3 * rng.standard_normal((n, 3))
        self.v0 = 0.05 * rng.standard_normal((n, 3))
        self.force_steps = 1.0e-3 * rng.standard_normal((steps, n, 3))
        self.force_shared = 1.0e-3 * rng.standard_normal((n, 3))
        # materials a little off the model's, so that simulate must write them for the results to agree
        self.density = m.material_density.numpy() * 1.1
        self.stretching = m.material_stretching.numpy() * (1.0 + 0.1 * rng.random(m.material_stretching.shape))
        self.bending = m.material_bending.numpy() * (1.0 + 0.1 * rng.random(m.material_bending.shape))
        # loss: weighted first, intermediate and final positions, intermediate and final velocities, and a square
        self.w_x = np.zeros((steps + 1, n, 3))
        self.w_v = np.zeros((steps + 1, n, 3))
        for frame, scale in ((0, 0.3), (steps // 2, 0.5), (steps, 1.0)):
            self.w_x[frame] = scale * rng.standard_normal((n, 3))
        for frame in (1, steps):
            self.w_v[frame] = 0.1 * rng.standard_normal((n, 3))
        self.target = self.x0 + 0.1 * rng.standard_normal((n, 3))

    def tensor(self, a, requires_grad=True):
        return torch.tensor(a, dtype=torch.float64, requires_grad=requires_grad)

    def loss_torch(self, x, v):
        w_x, w_v, target = (torch.from_numpy(a) for a in (self.w_x, self.w_v, self.target))
        return (w_x * x).sum() + (w_v * v).sum() + ((x[-1] - target) ** 2).sum()

    def loss_grads(self, x, v):
        """dL/dx and dL/dv of loss_torch, per frame (NumPy)."""
        gx = self.w_x.copy()
        gx[-1] += 2.0 * (x[-1] - self.target)
        return gx, self.w_v

    def set_materials(self, model):
        model.material_density.assign(self.density)
        model.material_stretching.assign(self.stretching)
        model.material_bending.assign(self.bending)

    def reference(self, force_form):
        """Gradients of the loss from a wp.Tape over wc.rollout; a shared force is one array per step, summed."""
        m = self.model
        vec3 = m.types.vec3
        self.set_materials(m)
        sim = wc.Simulator(m, DT, options=OPTIONS)
        state = wc.State(wp.array(self.x0, dtype=vec3, requires_grad=True),
                         wp.array(self.v0, dtype=vec3, requires_grad=True))
        forces = self.force_steps if force_form == "steps" else [self.force_shared] * self.steps
        controls = []
        for f in forces:
            c = m.control(particle_force=True)
            c.particle_force.assign(f)
            controls.append(c)
        for a in (m.material_density, m.material_stretching, m.material_bending):
            a.grad.zero_()
        tape = wp.Tape()
        with tape:
            traj = wc.rollout(sim, state, controls, steps=self.steps)
        x = np.stack([s.particle_x.numpy() for s in traj])
        v = np.stack([s.particle_v.numpy() for s in traj])
        gx, gv = self.loss_grads(x, v)
        grads = {}
        for k, s in enumerate(traj):
            grads[s.particle_x] = wp.array(gx[k], dtype=vec3)
            grads[s.particle_v] = wp.array(gv[k], dtype=vec3)
        tape.backward(grads=grads)
        force_grad = np.stack([c.particle_force.grad.numpy() for c in controls])
        if force_form == "shared":
            force_grad = force_grad.sum(axis=0)
        return x, v, {
            "x0": state.particle_x.grad.numpy(), "v0": state.particle_v.grad.numpy(), "particle_force": force_grad,
            "density": m.material_density.grad.numpy().copy(), "stretching": m.material_stretching.grad.numpy().copy(),
            "bending": m.material_bending.grad.numpy().copy(),
        }

    def torch_inputs(self, force_form, requires_grad=True):
        force = self.force_steps if force_form == "steps" else self.force_shared
        return {
            "x0": self.tensor(self.x0, requires_grad), "v0": self.tensor(self.v0, requires_grad),
            "particle_force": self.tensor(force, requires_grad), "density": self.tensor(self.density, requires_grad),
            "stretching": self.tensor(self.stretching, requires_grad),
            "bending": self.tensor(self.bending, requires_grad),
        }


@pytest.fixture(scope="module")
def problem():
    return Problem()


def assert_close(name, got, ref, rtol=1.0e-8):
    """Max-norm relative error against a reference that must not vanish."""
    got, ref = np.asarray(got), np.asarray(ref)
    assert got.shape == ref.shape, f"{name}: shape {got.shape} vs {ref.shape}"
    scale = np.max(np.abs(ref))
    assert scale > 0.0, f"{name}: reference gradient is identically zero"
    err = np.max(np.abs(got - ref)) / scale
    assert err < rtol, f"{name}: relative error {err:.2e} >= {rtol:g}"


# -- 1. forward ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("grad", [True, False])
def test_forward_equals_rollout(problem, grad):
    """Positions and velocities bit for bit; the trajectory really moves; the materials land in the model."""
    m = problem.model
    x_ref, v_ref, _ = problem.reference("steps")  # fresh simulator, recorded on a tape
    m.material_stretching.assign(m.material_stretching.numpy() * 0.5)  # simulate must write the given table back
    inputs = problem.torch_inputs("steps", requires_grad=grad)
    x, v = wct.simulate(wc.Simulator(m, DT, options=OPTIONS), steps=STEPS, **inputs)
    assert x.shape == v.shape == (STEPS + 1, problem.n, 3)
    assert x.dtype == v.dtype == torch.float64
    assert x.requires_grad == v.requires_grad == grad
    np.testing.assert_array_equal(x.detach().numpy(), x_ref)
    np.testing.assert_array_equal(v.detach().numpy(), v_ref)
    assert np.max(np.abs(x_ref[-1] - x_ref[0])) > 1.0e-3  # the steps did something
    np.testing.assert_array_equal(m.material_stretching.numpy(), problem.stretching)


# -- 2. gradients against the tape ------------------------------------------------------------------------------------


@pytest.mark.parametrize("force_form", ["steps", "shared"])
def test_gradients_equal_tape(problem, force_form):
    _, _, ref = problem.reference(force_form)
    inputs = problem.torch_inputs(force_form)
    sim = wc.Simulator(problem.model, DT, options=OPTIONS)
    x, v = wct.simulate(sim, steps=STEPS, **inputs)
    problem.loss_torch(x, v).backward()
    for name, t in inputs.items():
        assert t.grad is not None, f"{name} got no gradient"
        assert_close(name, t.grad.numpy(), ref[name])
    assert x.grad_fn.rec.tape is None  # released after a backward without retain_graph


def test_gradients_only_where_asked(problem):
    """Inputs that do not require grad get None; the rest still match the tape."""
    _, _, ref = problem.reference("steps")
    inputs = problem.torch_inputs("steps", requires_grad=False)
    inputs["v0"].requires_grad_()
    inputs["bending"].requires_grad_()
    x, v = wct.simulate(wc.Simulator(problem.model, DT, options=OPTIONS), steps=STEPS, **inputs)
    problem.loss_torch(x, v).backward()
    assert_close("v0", inputs["v0"].grad.numpy(), ref["v0"])
    assert_close("bending", inputs["bending"].grad.numpy(), ref["bending"])
    assert all(inputs[k].grad is None for k in ("x0", "particle_force", "density", "stretching"))


# -- 3. gradcheck -----------------------------------------------------------------------------------------------------

GRADCHECK = dict(eps=1.0e-6, atol=1.0e-5, rtol=1.0e-4, nondet_tol=0.0)


class _ScaleGrad(torch.autograd.Function):
    """Identity whose backward scales the gradient: a deliberately wrong gradient for gradcheck to catch."""

    @staticmethod
    def forward(ctx, t, scale):
        ctx.scale = scale
        return t.view_as(t)

    @staticmethod
    def backward(ctx, g):
        return g * ctx.scale, None


@pytest.fixture(scope="module")
def small():
    return Problem(steps=2, seed=1)


def rollout_fn(small, sim, density_scale=1.0):
    x0, bending = small.tensor(small.x0, False), small.tensor(small.bending, False)

    def fn(v0, density, force):
        x, v = wct.simulate(sim, x0, v0, steps=2, particle_force=force,
                            density=_ScaleGrad.apply(density, density_scale), bending=bending)
        return x[1:], v[-1]

    return fn


def test_gradcheck(small):
    sim = wc.Simulator(small.model, DT, options=OPTIONS)
    inputs = (small.tensor(small.v0), small.tensor(small.density), small.tensor(small.force_shared))
    assert torch.autograd.gradcheck(rollout_fn(small, sim), inputs, **GRADCHECK)
    # the check has teeth: a density gradient 0.1% off fails it
    with pytest.raises(GradcheckError):
        only_density = (inputs[0].detach(), inputs[1], inputs[2].detach())
        torch.autograd.gradcheck(rollout_fn(small, sim, density_scale=1.001), only_density, **GRADCHECK)


def test_gradcheck_positions_and_stiffness_tables(small):
    # x0, stretching and bending against central differences too, not only against the Warp tape of the same
    # simulator (the bridge's own gradients: test_gradients_equal_tape)
    sim = wc.Simulator(small.model, DT, options=OPTIONS)
    v0, density = small.tensor(small.v0, False), small.tensor(small.density, False)

    def fn(x0, stretching, bending):
        x, v = wct.simulate(sim, x0, v0, steps=2, density=density, stretching=stretching, bending=bending)
        return x[1:], v[-1]

    inputs = (small.tensor(small.x0), small.tensor(small.stretching), small.tensor(small.bending))
    assert torch.autograd.gradcheck(fn, inputs, **GRADCHECK)


def test_bdf2_through_the_bridge(small):
    # the bridge's preallocated States carry BDF2's history like wc.rollout's, and its gradients hold
    sim = wc.Simulator(small.model, DT, options=dataclasses.replace(OPTIONS, integrator="bdf2"))
    x0, v0 = small.tensor(small.x0, False), small.tensor(small.v0, False)
    x, _ = wct.simulate(sim, x0, v0, steps=3)
    start = wc.State(wp.array(small.x0, dtype=wp.vec3d), wp.array(small.v0, dtype=wp.vec3d))
    traj = wc.rollout(sim, start, steps=3)
    np.testing.assert_allclose(x[-1].numpy(), traj[-1].particle_x.numpy(), rtol=0, atol=1e-12)
    euler = wc.rollout(wc.Simulator(small.model, DT, options=OPTIONS), start, steps=3)[-1].particle_x.numpy()
    assert np.abs(euler - traj[-1].particle_x.numpy()).max() > 1e-6  # a different integrator was used

    def fn(v0, density):
        x, v = wct.simulate(sim, x0, v0, steps=3, density=density)
        return x[1:], v[-1]

    assert torch.autograd.gradcheck(fn, (small.tensor(small.v0), small.tensor(small.density)), **GRADCHECK)


# -- 4. chained calls, releasing the tape -----------------------------------------------------------------------------


def test_closed_loop_jacobian_rows_from_one_recording_match_finite_differences(small):
    # what the MLP's Gauss-Newton training does: a network maps the state at the start of each interval to a force,
    # and the three rows of d com_T / d weights come from three reverse passes through one recorded closed loop
    m = small.model
    sim = wc.Simulator(m, DT, options=OPTIONS)
    n = m.particle_count
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(6 * n, 8), torch.nn.Tanh(), torch.nn.Linear(8, 3)).double()
    weights = list(net.parameters())
    x0, v0 = small.tensor(small.x0, False), small.tensor(small.v0, False)

    def com_at_horizon():
        x, v = x0, v0
        for interval in range(2):
            push = 1.0e-2 * net(torch.cat([x.reshape(-1), v.reshape(-1)]))  # the force depends on the state
            force = torch.zeros((n, 3), dtype=torch.float64).index_put((torch.tensor([0, n - 1]),), push)
            xs, vs = wct.simulate(sim, x, v, steps=2, particle_force=force, time=2 * interval * DT)
            x, v = xs[-1], vs[-1]
        return x.mean(dim=0)

    com = com_at_horizon()
    rows = [torch.cat([g.reshape(-1) for g in torch.autograd.grad(com[c], weights, retain_graph=c < 2)])
            for c in range(3)]
    theta = torch.nn.utils.parameters_to_vector(weights).detach().clone()
    eps = 1.0e-3  # the forces are small: com_T is nearly linear in a weight, and smaller steps lose digits
    for k in np.random.default_rng(2).choice(theta.numel(), size=6, replace=False).tolist() + [theta.numel() - 1]:
        coms = []
        for sign in (1.0, -1.0):
            shifted = theta.clone()
            shifted[k] += sign * eps
            torch.nn.utils.vector_to_parameters(shifted, weights)
            with torch.no_grad():
                coms.append(com_at_horizon().numpy())
        fd = (coms[0] - coms[1]) / (2 * eps)
        tape = np.array([float(r[k]) for r in rows])
        assert np.abs(fd).max() > 1e-9, k
        np.testing.assert_allclose(tape, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max(), err_msg=f"weight {k}")
    torch.nn.utils.vector_to_parameters(theta, weights)


def test_chained_calls_equal_one_tape(problem):
    """Two calls with different stretching tables, then one backward: the full tape's gradients.

    The reference runs the halves on two models (one per table) on one tape; simulate runs both on one model, whose
    stretching array holds the second table when the first call's backward runs, so that backward must restore it.
    """
    half = 2
    s1 = problem.stretching
    s2 = problem.stretching * 1.5
    # reference: one tape over two rollouts
    models = [build_model(), build_model()]
    vec3 = models[0].types.vec3
    for mod, table in zip(models, (s1, s2)):
        mod.material_stretching.assign(table)
    state = wc.State(wp.array(problem.x0, dtype=vec3, requires_grad=True),
                     wp.array(problem.v0, dtype=vec3, requires_grad=True))
    tape = wp.Tape()
    with tape:
        first = wc.rollout(wc.Simulator(models[0], DT, options=OPTIONS), state, steps=half)
        second = wc.rollout(wc.Simulator(models[1], DT, options=OPTIONS), first[-1], steps=half)
    traj = first + second[1:]
    x = np.stack([s.particle_x.numpy() for s in traj])
    v = np.stack([s.particle_v.numpy() for s in traj])
    gx, gv = problem.loss_grads(x, v)
    grads = {}
    for k, s in enumerate(traj):
        grads[s.particle_x] = wp.array(gx[k], dtype=vec3)
        grads[s.particle_v] = wp.array(gv[k], dtype=vec3)
    tape.backward(grads=grads)

    # torch: two simulate calls on one model and simulator
    m = build_model()
    sim = wc.Simulator(m, DT, options=OPTIONS)
    x0, v0 = problem.tensor(problem.x0), problem.tensor(problem.v0)
    t1, t2 = problem.tensor(s1), problem.tensor(s2)
    xa, va = wct.simulate(sim, x0, v0, steps=half, stretching=t1)
    xb, vb = wct.simulate(sim, xa[-1], va[-1], steps=half, stretching=t2, time=half * DT)
    xt, vt = torch.cat([xa, xb[1:]]), torch.cat([va, vb[1:]])
    np.testing.assert_allclose(xt.detach().numpy(), x, rtol=0.0, atol=1.0e-12)
    loss = problem.loss_torch(xt, vt)
    loss.backward(retain_graph=True)
    assert_close("x0", x0.grad.numpy(), state.particle_x.grad.numpy())
    assert_close("v0", v0.grad.numpy(), state.particle_v.grad.numpy())
    assert_close("stretching (first call)", t1.grad.numpy(), models[0].material_stretching.grad.numpy())
    assert_close("stretching (second call)", t2.grad.numpy(), models[1].material_stretching.grad.numpy())
    # the backward left the model's arrays as the last forward wrote them
    np.testing.assert_array_equal(m.material_stretching.numpy(), s2)

    # retain_graph kept the tapes: a second backward gives the same gradients, bit for bit
    assert xa.grad_fn.rec.tape is not None
    first_grads = [t.grad.clone() for t in (x0, v0, t1, t2)]
    for t in (x0, v0, t1, t2):
        t.grad = None
    loss.backward()
    for a, t in zip(first_grads, (x0, v0, t1, t2)):
        assert torch.equal(a, t.grad)
    assert xa.grad_fn.rec.tape is None and xb.grad_fn.rec.tape is None  # released

    with pytest.raises(RuntimeError, match="second time"):
        loss.backward()


def test_tape_released_when_graph_dropped(small):
    sim = wc.Simulator(small.model, DT, options=OPTIONS)
    x, _ = wct.simulate(sim, small.tensor(small.x0), small.tensor(small.v0), steps=1)
    rec = x.grad_fn.rec
    assert rec.tape is not None
    del x, _
    assert rec.tape is None


# -- 5. captured calls -----------------------------------------------------------------------------------------------


@pytest.fixture
def launches(monkeypatch):
    """Counts the kernels launched from Python (a replayed graph launches none)."""
    count = [0]
    launch = wp.launch

    def counting(*args, **kwargs):
        count[0] += 1
        return launch(*args, **kwargs)

    monkeypatch.setattr(wp, "launch", counting)
    return count


def simulate_and_differentiate(problem, sim, inputs, capture, force_form="steps"):
    """One call of simulate and the loss's backward: (x, v, the six inputs' gradients) as NumPy."""
    t = problem.torch_inputs(force_form) if inputs is None else inputs()
    x, v = wct.simulate(sim, t["x0"], t["v0"], steps=problem.steps, particle_force=t["particle_force"],
                        density=t["density"], stretching=t["stretching"], bending=t["bending"], capture=capture)
    problem.loss_torch(x, v).backward()
    return x.detach().numpy(), v.detach().numpy(), {k: a.grad.numpy() for k, a in t.items()}


def assert_same_call(got, expected):
    np.testing.assert_array_equal(got[0], expected[0], err_msg="x")
    np.testing.assert_array_equal(got[1], expected[1], err_msg="v")
    for name, g in expected[2].items():
        assert np.any(g), name
        np.testing.assert_array_equal(got[2][name], g, err_msg=name)


@pytest.mark.parametrize("force_form", ["steps", "shared"])
def test_captured_calls_equal_uncaptured_ones_for_every_input(problem, force_form, launches):
    # two sets of inputs in turn: the first call of each runs, the second records the graphs, later ones replay them
    # (no launch from Python), each with its own inputs' trajectory and gradients, bitwise
    other = Problem(seed=3)
    expected = [simulate_and_differentiate(p, wc.Simulator(p.model, DT, options=OPTIONS), None, False, force_form)
                for p in (problem, other)]
    sim = wc.Simulator(build_model(), DT, options=OPTIONS)
    for call in range(6):
        p = (problem, other)[call % 2]
        before = launches[0]
        got = simulate_and_differentiate(p, sim, lambda p=p: p.torch_inputs(force_form), True, force_form)
        assert_same_call(got, expected[call % 2])
        assert (launches[0] == before) == (call >= 2), f"call {call}: {launches[0] - before} launches"


def test_two_captured_calls_waiting_for_their_backward_passes(problem):
    # the second call of one graph overwrites the first's trajectory in the graph's arrays: the first's backward
    # replays its forward again, and both gradients are the uncaptured calls' (as is a second backward pass)
    other = Problem(seed=3)

    def two_calls(sim, capture):
        inputs = [p.torch_inputs("steps") for p in (problem, other)]
        xs = [wct.simulate(sim, t["x0"], t["v0"], steps=problem.steps, particle_force=t["particle_force"],
                           density=t["density"], capture=capture) for t in inputs]
        loss = problem.loss_torch(*xs[0]) + other.loss_torch(*xs[1])
        loss.backward(retain_graph=True)
        first = [{k: t[k].grad.clone().numpy() for k in ("x0", "v0", "particle_force", "density")} for t in inputs]
        for t in inputs:
            for a in t.values():
                a.grad = None
        (2.0 * loss).backward()
        second = [{k: t[k].grad.numpy() for k in ("x0", "v0", "particle_force", "density")} for t in inputs]
        return [x.detach().numpy() for x, _ in xs], first, second

    expected = two_calls(wc.Simulator(build_model(), DT, options=OPTIONS), False)
    sim = wc.Simulator(build_model(), DT, options=OPTIONS)
    two_calls(sim, True)  # seen, then recorded
    got = two_calls(sim, True)  # replayed
    for a, b in zip(got[0], expected[0]):
        np.testing.assert_array_equal(a, b)
    for which in (1, 2):
        for g, e in zip(got[which], expected[which]):
            for name in e:
                np.testing.assert_array_equal(g[name], e[name], err_msg=name)
    for name in expected[1][0]:  # the seed doubled (not bitwise: the adjoint solves stop on an absolute tolerance too)
        np.testing.assert_allclose(got[2][0][name], 2.0 * got[1][0][name], rtol=1e-9)


def test_a_simulator_keeps_its_most_recent_captured_calls(problem, monkeypatch, launches):
    monkeypatch.setattr(wct, "MAX_CAPTURES", 1)
    sim = wc.Simulator(build_model(), DT, options=OPTIONS)
    expected = simulate_and_differentiate(problem, wc.Simulator(build_model(), DT, options=OPTIONS), None, False,
                                          "shared")

    def call(steps):  # a call of `steps` steps; whether it replayed
        before = launches[0]
        t = problem.torch_inputs("shared")
        x, v = wct.simulate(sim, t["x0"], t["v0"], steps=steps, particle_force=t["particle_force"],
                            density=t["density"], stretching=t["stretching"], bending=t["bending"], capture=True)
        if steps == problem.steps:
            np.testing.assert_array_equal(x.detach().numpy(), expected[0])
        return launches[0] == before

    steps, other = problem.steps, problem.steps - 1
    assert [call(steps), call(steps), call(steps)] == [False, False, True]
    assert [call(other), call(other), call(other)] == [False, False, True]  # dropped the first one's graphs
    assert [call(steps), call(steps), call(steps)] == [False, False, True]


def test_captured_contact_calls_equal_uncaptured_ones(device):
    # a sheet falling onto a sphere: captured one speculative graph a step, the steps in contact run again
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    mesh = wc.grid_mesh(4, 4, 0.3, 0.3)
    mesh.positions = mesh.positions + np.random.default_rng(5).uniform(-2e-3, 2e-3, mesh.positions.shape)
    mesh.positions = mesh.positions + [-0.15, -0.14, 0.13]
    b.add_cloth_mesh(mesh, material=wc.preset("gray-interlock", thicken=2))
    b.add_obstacle_sphere(0.1, 2)
    b.set_collision(friction=0.3, obstacle_friction=0.3)
    steps, n, rng = 14, len(mesh.positions), np.random.default_rng(2)
    force = rng.normal(0.0, 1e-3, (steps, n, 3))
    weights = rng.standard_normal((steps + 1, n, 3))

    def run(sim, capture):
        model = sim.model
        dtype, dev = wct.torch_dtype(model), wct.torch_device(model)
        t = [torch.tensor(a, dtype=dtype, device=dev, requires_grad=True)
             for a in (model.particle_x0.numpy(), np.zeros((n, 3)), force, model.material_density.numpy())]
        x, v = wct.simulate(sim, t[0], t[1], steps=steps, particle_force=t[2], density=t[3], capture=capture)
        (x * torch.tensor(weights, dtype=dtype, device=dev)).sum().backward()
        return [x.detach().cpu().numpy()] + [a.grad.cpu().numpy() for a in t]

    def simulator():
        return wc.Simulator(b.finalize(device, requires_grad=True), 0.01, options=wc.SolverOptions(cg_tol=1e-7))

    expected = run(simulator(), False)
    distance = np.linalg.norm(expected[0][-1], axis=1)  # from the sphere's centre: it landed on the sphere
    assert distance.min() < 0.11 and expected[0][0, :, 2].min() > 0.12, (distance.min(), expected[0][0, :, 2].min())
    sim = simulator()
    same = np.testing.assert_array_equal if sim.device.is_cpu else (
        lambda a, b: np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-5 * np.abs(b).max()))
    for _ in range(3):
        for name, a, e in zip(("x", "x0", "v0", "force", "density"), run(sim, True), expected):
            assert np.any(e), name
            same(a, e)


def test_capture_is_refused_where_the_steps_cannot_be_captured():
    # the warp CG backend tests its convergence on the host on the CPU
    model = hanging_builder(res=3, material=MATERIAL).finalize("cpu", requires_grad=True, dtype=wp.float64)
    sim = wc.Simulator(model, DT, options=wc.SolverOptions(cg_backend="warp"))
    x0 = torch.tensor(model.particle_x0.numpy())
    with pytest.raises(ValueError, match="capture=True, but the warp CG backend tests its convergence on the host"):
        wct.simulate(sim, x0, torch.zeros_like(x0), steps=2, capture=True)


# -- 6. errors --------------------------------------------------------------------------------------------------------


def test_bad_inputs_name_the_argument(small):
    sim = wc.Simulator(small.model, DT, options=OPTIONS)
    n = small.n
    ok = {"x0": small.tensor(small.x0), "v0": small.tensor(small.v0)}

    def call(**changes):
        kw = dict(ok)
        kw.update(changes)
        return wct.simulate(sim, kw.pop("x0"), kw.pop("v0"), steps=2, **kw)

    f64 = torch.float64
    cases = [
        ({"x0": torch.zeros(n, 3, dtype=torch.float32)}, r"x0 must have the model's dtype torch\.float64.*float32"),
        ({"v0": torch.zeros(n + 1, 3, dtype=f64)}, rf"v0 must have shape \({n}, 3\).*\({n + 1}, 3\)"),
        ({"particle_force": torch.zeros(3, n, 3, dtype=f64)}, r"particle_force must have shape .*\(2, \d+, 3\)"),
        ({"density": torch.zeros(1, dtype=torch.float32)}, r"density must have the model's dtype"),
        ({"stretching": torch.zeros(1, 4, 6, dtype=f64)}, r"stretching must have shape \(1, 6, 4\)"),
        ({"bending": torch.zeros(3, 5, dtype=f64)}, r"bending must have shape \(1, 3, 5\)"),
        ({"x0": torch.zeros(n, 3, dtype=f64, device="meta")}, r"x0 must be on the model's device cpu.*meta"),
        ({"particle_force": torch.zeros(n, 3, dtype=f64, device="meta")}, r"particle_force must be on .*device meta"),
    ]
    for changes, pattern in cases:
        with pytest.raises(ValueError, match=pattern):
            call(**changes)
    # values no material may hold, named; the model keeps the materials it had
    before = {k: getattr(small.model, f"material_{k}").numpy().copy() for k in ("density", "stretching", "bending")}
    stretching_nan = small.stretching.copy()
    stretching_nan[0, 2, 1] = np.nan
    stretching_negative = small.stretching.copy()
    stretching_negative[0, 4, 2] = -1.0
    bad_values = [
        ({"density": torch.zeros(1, dtype=f64)}, r"simulate: density\[0\] must be > 0, got 0.0"),
        ({"density": -small.tensor(small.density)}, r"density\[0\] must be > 0"),
        ({"stretching": small.tensor(stretching_nan)}, r"stretching\[0, 2, 1\] is not finite"),
        ({"stretching": small.tensor(stretching_negative)}, r"stretching\[0, 4, 2\] \(weft stretch k2\) must be >= 0"),
        ({"bending": -small.tensor(small.bending)}, r"bending\[0, 0, 0\] must be >= 0"),
    ]
    for changes, pattern in bad_values:
        with pytest.raises(ValueError, match=pattern):
            call(**changes)
    for k, value in before.items():
        np.testing.assert_array_equal(getattr(small.model, f"material_{k}").numpy(), value)
    with pytest.raises(ValueError, match="steps"):
        wct.simulate(sim, ok["x0"], ok["v0"], steps=-1)
    no_grad_model = build_model(requires_grad=False)
    with pytest.raises(ValueError, match="requires_grad=True"):
        wct.simulate(wc.Simulator(no_grad_model, DT), ok["x0"], ok["v0"], steps=1)


def test_torch_is_optional():
    """import warpcloth leaves torch alone; warpcloth.torch without torch says how to install it."""
    code = (
        "import sys, warpcloth\n"
        "assert 'torch' not in sys.modules, 'import warpcloth imported torch'\n"
        "sys.modules['torch'] = None\n"
        "try:\n"
        "    import warpcloth.torch\n"
        "except ImportError as e:\n"
        "    print('IMPORTERROR', e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "IMPORTERROR" in out.stdout and "pip install warpcloth[torch]" in out.stdout, out.stdout


def test_batch_dimension_equals_single_worlds():
    """A model of 3 worlds (one material each) takes (W, m, 3) tensors and returns (W, steps+1, m, 3): each world's
    trajectory and its gradients (x0, v0, per-step forces, its material's density) equal a one-world model's."""
    options = dataclasses.replace(OPTIONS, preconditioner="block_ssor")
    materials = [MATERIAL, wc.preset("11oz-black-denim", thicken=2), wc.preset("tango-red-jet-set", thicken=2)]
    composed = wc.ModelBuilder()
    for mat in materials:
        composed.add_world(hanging_builder(res=3, material=mat))
    batch = composed.finalize("cpu", requires_grad=True, dtype=wp.float64)
    W, m = batch.world_count, batch.particle_count // batch.world_count
    rng = np.random.default_rng(5)
    x0 = batch.particle_x0.numpy().reshape(W, m, 3) + 2.0e-3 * rng.standard_normal((W, m, 3))
    v0 = 0.05 * rng.standard_normal((W, m, 3))
    force = 1.0e-3 * rng.standard_normal((W, STEPS, m, 3))
    weights = torch.tensor(rng.standard_normal((W, STEPS + 1, m, 3)))

    def run(sim, x0, v0, force, density, w):
        t = [torch.tensor(a, dtype=torch.float64, requires_grad=True) for a in (x0, v0, force, density)]
        x, v = wct.simulate(sim, t[0], t[1], steps=STEPS, particle_force=t[2], density=t[3])
        (x * w).sum().backward()
        return x.detach().numpy(), [a.grad.numpy() for a in t]

    x, grads = run(wc.Simulator(batch, DT, options=options), x0, v0, force, batch.material_density.numpy(), weights)
    assert x.shape == (W, STEPS + 1, m, 3)
    for w, mat in enumerate(materials):
        model = hanging_builder(res=3, material=mat).finalize("cpu", requires_grad=True, dtype=wp.float64)
        xs, gs = run(wc.Simulator(model, DT, options=options), x0[w], v0[w], force[w],
                     model.material_density.numpy(), weights[w])
        np.testing.assert_allclose(x[w], xs, rtol=0, atol=1e-14)
        for name, g, g1 in zip(("x0", "v0", "force"), grads[:3], gs[:3]):
            np.testing.assert_allclose(g[w], g1, rtol=1e-10, atol=1e-14, err_msg=name)
        np.testing.assert_allclose(grads[3][w], gs[3][0], rtol=1e-10)
    with pytest.raises(ValueError, match=r"particle_force must have shape \(3, 16, 3\) or \(3, 4, 16, 3\)"):
        wct.simulate(wc.Simulator(batch, DT, options=options), torch.tensor(x0), torch.tensor(v0), steps=STEPS,
                     particle_force=torch.zeros(STEPS, W * m, 3, dtype=torch.float64))
