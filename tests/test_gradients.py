"""Rollout gradients (wp.Tape through the implicit steps and the CG adjoint) against central finite differences.

Scene (conftest.hanging_builder): a 4x4 gray-interlock cloth (bending table x30, so bending matters: the loss
differs by ~14% from the x1 table's and a 1% change of the table moves it by ~1e-3 relative) hanging in the XZ
plane from two soft handles (or a moving hard pin and a handle), wind across the plane so it billows and bends, a
little gravity; 10 steps of dt = 0.02 s, CG tolerance 1e-12. The initial state is jittered off the flat rest
state: at exactly zero shear (|G01| in the stretching lookup) and zero dihedral angle (the curvature clamp) the
model has kinks where a one-sided autodiff derivative and a central difference legitimately disagree.

Every test runs on each device the suite reaches (conftest.DEVICES: CUDA too where there is one), the finite
differences on the same device.

Loss: a random linear functional of the final positions and velocities plus the squared distance of the final
positions to a random target. Each test compares grad . d from the tape with (L(p + eps d) - L(p - eps d)) / 2 eps
for a random direction d, eps = 1e-6 x the parameter's largest entry.
"""

import zlib

import numpy as np
import pytest
import warp as wp
from conftest import DEVICES, hanging_builder

import warpcloth as wc

STEPS = 10
DT = 0.02
REL_EPS = 1.0e-6
TOL64 = 1.0e-4


class Problem:
    """A hanging-cloth rollout with a scalar loss, its tape gradient and its finite differences."""

    def __init__(self, dtype=wp.float64, *, moving_pin=False, cg_tol=1.0e-12, seed=0, integrator="euler",
                 device="cpu"):
        # stiffer bending: see the module docstring
        material = wc.preset("gray-interlock", thicken=2).scaled(bending=30.0)
        builder = hanging_builder(material=material, moving_pin=moving_pin)
        self.model = m = builder.finalize(device, requires_grad=True, dtype=dtype)
        self.sim = wc.Simulator(m, DT, options=wc.SolverOptions(cg_tol=cg_tol, cg_max_iters=2000,
                                                                integrator=integrator))
        rng = np.random.default_rng(seed)
        n = m.particle_count
        x0 = m.particle_x0.numpy().astype(np.float64)
        self.state = m.state()
        self.state.particle_x.assign(x0 + 2.0e-3 * rng.standard_normal((n, 3)))
        self.state.particle_v.assign(0.05 * rng.standard_normal((n, 3)))
        self.control = m.control(particle_force=True)
        self.control.particle_force.assign(1.0e-3 * rng.standard_normal((n, 3)))
        self.w_x = rng.standard_normal((n, 3))
        self.w_v = 0.1 * rng.standard_normal((n, 3))
        self.target = x0 + 0.1 * rng.standard_normal((n, 3))

    def arrays(self) -> dict:
        m, s, c = self.model, self.state, self.control
        arrays = {
            "x0": s.particle_x, "v0": s.particle_v, "density": m.material_density,
            "stretching": m.material_stretching, "bending": m.material_bending, "wind": m.wind_velocity,
            "gravity": m.gravity, "force": c.particle_force, "handle_target": c.handle_target,
            "handle_stiffness": m.handle_stiffness, "wind_density": m.wind_density, "wind_drag": m.wind_drag,
        }
        if m.pin_count:
            arrays["pin_target"] = c.pin_target
        return arrays

    def _loss(self, x, v):
        x, v = x.astype(np.float64), v.astype(np.float64)
        loss = np.sum(self.w_x * x) + np.sum(self.w_v * v) + np.sum((x - self.target) ** 2)
        return loss, self.w_x + 2.0 * (x - self.target), self.w_v

    def loss(self) -> float:
        final = wc.rollout(self.sim, self.state, self.control, steps=STEPS)[-1]
        return self._loss(*final.numpy())[0]

    def gradient(self, name) -> np.ndarray:
        arrays = self.arrays()
        for a in arrays.values():
            a.grad.zero_()
        tape = wp.Tape()
        with wp.ScopedDevice(self.model.device), tape:
            final = wc.rollout(self.sim, self.state, self.control, steps=STEPS)[-1]
        _, gx, gv = self._loss(*final.numpy())
        vec3, device = self.model.types.vec3, self.model.device
        tape.backward(grads={final.particle_x: wp.array(gx, dtype=vec3, device=device),
                             final.particle_v: wp.array(gv, dtype=vec3, device=device)})
        grad = arrays[name].grad.numpy().astype(np.float64).copy()
        tape.zero()
        return grad

    def finite_difference(self, name, direction, eps) -> float:
        a = self.arrays()[name]
        base = a.numpy().astype(np.float64).copy()
        try:
            a.assign(base + eps * direction)
            plus = self.loss()
            a.assign(base - eps * direction)
            minus = self.loss()
        finally:
            a.assign(base)
        return (plus - minus) / (2.0 * eps)

    def direction(self, name) -> np.ndarray:
        shape = self.arrays()[name].numpy().shape
        d = np.random.default_rng(zlib.crc32(name.encode())).standard_normal(shape)  # same d in every run
        return d / np.max(np.abs(d))


def check_directional(problem, name, tol=TOL64, reference=None):
    """Asserts grad . d matches the central difference; returns (tape value, FD value, relative error)."""
    d = problem.direction(name)
    scale = float(np.max(np.abs(problem.arrays()[name].numpy())))
    eps = REL_EPS * (scale if scale > 0.0 else 1.0)  # relative to the entries' scale (1 m for the pin at the origin)
    ref = reference if reference is not None else problem
    fd = ref.finite_difference(name, d, eps)
    grad = problem.gradient(name)
    tape_value = float(np.sum(grad * d))
    loss = abs(ref.loss())
    # The central difference must stand well clear of round-off and CG noise (~1e-12 |L| per evaluation), or a
    # wrong or zero gradient could pass: require a loss change over 2 eps of at least 1e-8 |L|.
    assert abs(fd) * 2.0 * eps > 1.0e-8 * loss, f"{name}: FD {fd:.3e} is lost in noise (loss {loss:.3e})"
    assert np.any(grad != 0.0), f"{name}: tape gradient is identically zero"
    err = abs(tape_value - fd) / abs(fd)
    assert err < tol, f"{name}: tape {tape_value:.10e} vs FD {fd:.10e}, relative error {err:.2e} >= {tol:g}"
    return tape_value, fd, err


def fd_along(problem, name, direction):
    return problem.finite_difference(name, direction, 1.0e-6)


@pytest.fixture(scope="module", params=DEVICES)
def handles64(request):
    return Problem(wp.float64, device=request.param)


@pytest.mark.parametrize(
    "name", ["x0", "v0", "density", "stretching", "wind", "gravity", "force", "handle_target", "handle_stiffness",
             "wind_density", "wind_drag"]
)
def test_gradient_float64(handles64, name):
    check_directional(handles64, name)


@pytest.fixture(scope="module", params=DEVICES)
def bdf2_problem(request):
    return Problem(wp.float64, integrator="bdf2", moving_pin=True, device=request.param)


@pytest.mark.parametrize("name", ["x0", "v0", "density", "stretching", "bending", "wind", "pin_target"])
def test_gradient_bdf2_float64(bdf2_problem, name):
    # BDF2 (SolverOptions.integrator): the blend of two states is a taped kernel and its step the same assembly and
    # implicit adjoint, so the tape differentiates it like backward Euler; a moving pin checks its targets too
    check_directional(bdf2_problem, name)


def test_gradient_bending_float64(handles64):
    check_directional(handles64, "bending")
    # The bending term must matter, else a wrong bending gradient could hide: scaling the whole bending table by
    # (1 + 1e-2) must change the loss by a visible amount (observed 9e-4 relative).
    table = handles64.model.material_bending.numpy()
    relative_effect = abs(fd_along(handles64, "bending", table)) * 1.0e-2 / abs(handles64.loss())
    assert relative_effect > 1.0e-4, f"bending barely affects the loss ({relative_effect:.2e})"


@pytest.mark.parametrize("device", DEVICES)
def test_gradient_moving_pin_float64(device):
    problem = Problem(wp.float64, moving_pin=True, device=device)
    check_directional(problem, "pin_target")
    # the rest of the scene's gradients still hold with a hard pin in the system
    check_directional(problem, "x0")
    check_directional(problem, "stretching")


# float32: the tape runs in float32 (CG tol 1e-6); the reference is the float64 central difference of the same
# scene (a float32 finite difference would be mostly round-off). Observed relative errors of the float32 tape
# gradient: density 1.9e-5, x0 7.8e-6 (stretching 8.3e-6, bending 9.4e-6, v0 1.5e-6, handle targets 1.5e-6, wind
# 1.4e-6, forces 1.0e-7, gravity 6.7e-8), against 1e-9 to 6e-8 in float64 (moving pin 6e-7; the forward CG's warm
# start makes the FD runs' round-off differ slightly). Tolerance 1e-3: a 50x margin.
TOL32 = 1.0e-3


@pytest.mark.parametrize("name", ["density", "x0"])
def test_gradient_float32(handles64, name):
    problem = Problem(wp.float32, cg_tol=1.0e-6, device=handles64.model.device)
    check_directional(problem, name, tol=TOL32, reference=handles64)
