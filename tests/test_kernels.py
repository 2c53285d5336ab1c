"""Element physics: forces are minus energy gradients, Hessian blocks are force Jacobians, and the kernels agree
with an independent NumPy transcription of SPEC.md §1.2-1.3 (tests/reference.py)."""

import importlib

import numpy as np
import pytest
import reference
import warp as wp
import warp.autograd

import warpcloth as wc
from warpcloth.kernels.implicit import implicit_kernels
from warpcloth.mesh_io import TriangleMesh

DT = 0.01

# Two triangles sharing the edge 0-1 (one hinge); material square of side 0.1 m.
UV = np.array([[0.0, 0.0], [0.1, 0.0], [0.1, 0.1], [0.0, 0.1]])
TRIS = np.array([[0, 1, 2], [0, 2, 3]])


def hinge_model(material, positions=None):
    tri_uv = UV[TRIS]
    pos = np.c_[UV, np.zeros(4)] if positions is None else positions
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_cloth_mesh(TriangleMesh(pos, TRIS, tri_uv), material=material)
    model = b.finalize("cpu", dtype=wp.float64)
    sim = wc.Simulator(model, DT, options=wc.SolverOptions(cg_tol=1e-12))
    return model, sim


def forces_and_stiffness(sim, model, x):
    """With v = 0 and no gravity: b = dt f and A = M + dt^2 H."""
    state = model.state()
    state.particle_x.assign(x)
    state.particle_v.zero_()
    A, b = sim.dense_system(state)
    M = np.kron(np.diag(model.particle_mass()), np.eye(3))
    return b / DT, (A - M) / DT**2


def elastic_energy(sim, model, x):
    state = model.state()
    state.particle_x.assign(x)
    state.particle_v.zero_()
    e = sim.energy(state)
    return e["stretching"] + e["bending"]


def random_bent_positions(rng, scale=0.02):
    x = np.c_[UV, np.zeros(4)] * [1.1, 0.95, 1.0]
    return x + scale * rng.standard_normal(x.shape)


ISOTROPIC = wc.Material.isotropic(density=0.2, stretch_stiffness=50.0, shear_stiffness=20.0,
                                  poisson_coupling=5.0, bend_stiffness=1e-4)


def test_force_is_minus_energy_gradient():
    rng = np.random.default_rng(0)
    model, sim = hinge_model(ISOTROPIC)
    x = random_bent_positions(rng)
    f, _ = forces_and_stiffness(sim, model, x)
    h = 1e-7
    grad = np.zeros(12)
    for i in range(12):
        xp, xm = x.copy().reshape(-1), x.copy().reshape(-1)
        xp[i] += h
        xm[i] -= h
        e_plus, e_minus = elastic_energy(sim, model, xp.reshape(4, 3)), elastic_energy(sim, model, xm.reshape(4, 3))
        grad[i] = (e_plus - e_minus) / (2 * h)
    assert np.abs(f).max() > 1e-3
    np.testing.assert_allclose(f, -grad, rtol=1e-5, atol=1e-6 * np.abs(f).max())


def test_hessian_blocks_are_force_jacobians_where_exact():
    # ARCSim's H drops G01 (Du'Dv + Dv'Du), clamps G to max(G, 0) and is Gauss-Newton for bending: it is the exact
    # Jacobian for stretches along the material axes (G01 = 0, G >= 0) of a flat sheet (theta = rest angle).
    rng = np.random.default_rng(1)
    model, sim = hinge_model(ISOTROPIC)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    x = (np.c_[UV, np.zeros(4)] * [1.15, 1.05, 1.0]) @ q.T
    _, H = forces_and_stiffness(sim, model, x)
    h = 1e-7
    J = np.zeros((12, 12))
    for i in range(12):
        xp, xm = x.copy().reshape(-1), x.copy().reshape(-1)
        xp[i] += h
        xm[i] -= h
        J[:, i] = (forces_and_stiffness(sim, model, xp.reshape(4, 3))[0]
                   - forces_and_stiffness(sim, model, xm.reshape(4, 3))[0]) / (2 * h)
    np.testing.assert_allclose(H, -J, atol=1e-5 * np.abs(H).max())


def test_hessian_is_symmetric_psd_when_bent_and_sheared():
    rng = np.random.default_rng(2)
    model, sim = hinge_model(wc.preset("gray-interlock", thicken=2))
    for _ in range(5):
        _, H = forces_and_stiffness(sim, model, random_bent_positions(rng, 0.03))
        np.testing.assert_allclose(H, H.T, atol=1e-9 * np.abs(H).max())
        assert np.linalg.eigvalsh(H).min() > -1e-8 * np.abs(H).max()


@pytest.fixture(scope="module")
def gray_samples():
    return reference.stretching_samples(wc.preset("gray-interlock").stretching)


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_stretching_matches_numpy_reference(gray_samples, seed):
    rng = np.random.default_rng(seed)
    gray = wc.preset("gray-interlock", thicken=2)
    no_bending = wc.Material(density=gray.density, stretching=gray.stretching, bending=np.zeros((3, 5)),
                             thicken=2.0)
    model, sim = hinge_model(no_bending)
    # strains spread over the table, including shear and compression
    x = np.c_[UV, np.zeros(4)] @ np.array([[1.2, 0.1, 0.0], [0.15, 0.9, 0.05], [0.0, 0.0, 1.0]])
    x = x + 0.01 * rng.standard_normal(x.shape)
    f, _ = forces_and_stiffness(sim, model, x)
    expected = np.zeros((4, 3))
    for tri in TRIS:
        expected[tri] += reference.stretching_force(x[tri], UV[tri], gray_samples, 2.0)
    assert np.abs(expected).max() > 1e-3
    np.testing.assert_allclose(f.reshape(4, 3), expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())


@pytest.mark.parametrize("seed", [6, 7])
def test_bending_matches_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    gray = wc.preset("gray-interlock", thicken=2)
    no_stretching = wc.Material(density=gray.density, stretching=np.zeros((6, 4)), bending=gray.bending,
                                thicken=2.0)
    # rotate the material frame so the edge direction samples between table rows
    rot = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    uv = UV @ rot.T
    tri_uv = uv[TRIS]
    x = np.c_[UV, np.zeros(4)]
    x[2, 2] = 0.03 + 0.01 * rng.random()  # fold face 0 (x2) up, varying the curvature sample
    x[3, 2] = -0.01 * rng.random()
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_cloth_mesh(TriangleMesh(x, TRIS, tri_uv), material=no_stretching)
    model = b.finalize("cpu", dtype=wp.float64)
    sim = wc.Simulator(model, DT)
    f, _ = forces_and_stiffness(sim, model, x)
    hinge = model.hinge_indices.numpy()[0]
    area_sum = 2 * 0.5 * 0.1 * 0.1
    directions = [reference_direction(uv[hinge[1]] - uv[hinge[0]])] * 2
    expected = np.zeros((4, 3))
    expected[hinge] = reference.bending_force(x[hinge], 0.1 * np.sqrt(2), area_sum, directions, gray.bending, 2.0)
    assert np.abs(expected).max() > 1e-6
    np.testing.assert_allclose(f.reshape(4, 3), expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())


def reference_direction(du):
    a = abs(np.degrees(np.arctan2(du[1], du[0]))) % 180.0  # direction of an undirected edge in [0, 180)
    a = 180.0 - a if a > 90.0 else a  # the table is symmetric about 90 degrees (reflection padding)
    return a / 45.0


def test_dihedral_angle_sign_and_gradient():
    # theta grows when the hinge folds towards face 0's normal, and dtheta matches finite differences
    model, sim = hinge_model(ISOTROPIC)
    bd = __import__("warpcloth.kernels.bending", fromlist=["bending_funcs"]).bending_funcs(wp.float64)
    vec3 = wp.vec3d

    @wp.kernel
    def angle_and_grad(x: wp.array(dtype=vec3), out: wp.array(dtype=wp.float64), g: wp.array(dtype=vec3)):
        th = bd.dihedral_angle(x[0], x[1], x[2], x[3])
        g0, g1, g2, g3 = bd.angle_gradient(x[0], x[1], x[2], x[3])
        out[0] = th
        g[0] = g0
        g[1] = g1
        g[2] = g2
        g[3] = g3

    hinge = model.hinge_indices.numpy()[0]
    rng = np.random.default_rng(8)
    x = random_bent_positions(rng, 0.02)[hinge]

    def evaluate(xx):
        out = wp.zeros(1, dtype=wp.float64)
        g = wp.zeros(4, dtype=vec3)
        wp.launch(angle_and_grad, 1, inputs=[wp.array(xx, dtype=vec3)], outputs=[out, g])
        return out.numpy()[0], g.numpy()

    theta, grad = evaluate(x)
    assert np.isclose(theta, reference.dihedral(*x)[0])
    fd = np.zeros((4, 3))
    for i in range(4):
        for c in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, c] += 1e-7
            xm[i, c] -= 1e-7
            fd[i, c] = (evaluate(xp)[0] - evaluate(xm)[0]) / 2e-7
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_wind_and_handle_kernels_gradcheck():
    k = implicit_kernels(wp.float64)
    rng = np.random.default_rng(9)
    vec3 = wp.vec3d
    x = wp.array(random_bent_positions(rng), dtype=vec3, requires_grad=True)
    v = wp.array(rng.standard_normal((4, 3)), dtype=vec3, requires_grad=True)
    tris = wp.array(TRIS, dtype=wp.int32)
    area = wp.array([0.005, 0.005], dtype=wp.float64, requires_grad=True)
    free = wp.full(4, -1, dtype=wp.int32)
    world = wp.zeros(4, dtype=wp.int32)
    wind = wp.array([[3.0, -1.0, 2.0]], dtype=vec3, requires_grad=True)
    rho = wp.array([1.2], dtype=wp.float64, requires_grad=True)
    drag = wp.array([0.3], dtype=wp.float64, requires_grad=True)
    rhs = wp.zeros(4, dtype=vec3, requires_grad=True)
    assert warp.autograd.gradcheck(
        k.wind, dim=2, inputs=[tris, area, free, world, wind, rho, drag, x, v, wp.float64(DT)], outputs=[rhs],
        eps=1e-7, atol=1e-6, rtol=1e-5, raise_exception=False, show_summary=False)


FACTORIES = {"implicit": "implicit_kernels", "block_matrix": "block_matrix_kernels",
             "cg_sequential": "sequential_cg_kernels", "cg_tiled": "tiled_cg_kernels", "cg_warp": "warp_cg_kernels",
             "multigrid": "multigrid_kernels", "collision": "collision_kernels",
             "contact": "contact_kernels", "failsafe": "failsafe_kernels", "losses": "loss_kernels",
             "obstacle": "obstacle_kernels", "projection": "device_round_kernels", "proximity": "proximity_kernels"}


@pytest.mark.parametrize("scalar", [wp.float32, wp.float64], ids=["float32", "float64"])
def test_no_two_kernels_of_one_precision_share_a_name(scalar):
    # Warp 1.19's CPU graphs look each launched kernel up by its module and name, so two kernels of one name in one
    # graph replay one's code for both: a taped step and its backward pass captured together (the assembly and its
    # adjoint's "potential", once both "faces") read out of bounds (benchmarks/gpu/capture_probe.py, one_graph)
    seen = {}
    for module, factory in FACTORIES.items():
        namespace = getattr(importlib.import_module(f"warpcloth.kernels.{module}"), factory)(scalar)
        for attr, kernel in vars(namespace).items():
            if isinstance(kernel, wp.Kernel):
                other = seen.setdefault((kernel.module.name, kernel.key), (attr, kernel))
                assert other[1] is kernel, f"{module}.{factory}: {attr} and {other[0]} share the name {kernel.key}"
    assert len(seen) > 70  # every factory was walked
