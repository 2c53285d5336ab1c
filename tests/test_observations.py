"""Observation losses: vertices, markers and point clouds against NumPy references, their gradients through a short
rollout against central differences, one loss per world, depth back-projection, and bad input named."""

import numpy as np
import pytest
import warp as wp
from conftest import hanging_builder

import warpcloth as wc
from warpcloth.kernels.losses import loss_kernels
from warpcloth.observations import MarkerFrames, PointCloudFrames, VertexFrames, points_from_depth

STEPS = 4
DT = 0.02
FRAMES = list(range(1, STEPS + 1))  # compared: the states after each step


class Hanging:
    """A hanging 4x4 cloth (float64), ``worlds`` copies, each with its own perturbed start."""

    def __init__(self, worlds=1, seed=0):
        template = hanging_builder()
        if worlds == 1:
            builder = template
        else:
            builder = wc.ModelBuilder()
            builder.replicate(template, worlds)
        self.model = m = builder.finalize("cpu", requires_grad=True, dtype=wp.float64)
        self.sim = wc.Simulator(m, DT, options=wc.SolverOptions(cg_tol=1e-12, cg_max_iters=2000))
        rng = np.random.default_rng(seed)
        n = m.particle_count
        self.state = m.state()
        self.state.particle_x.assign(m.particle_x0.numpy() + 2e-3 * rng.standard_normal((n, 3)))
        self.state.particle_v.assign(0.1 * rng.standard_normal((n, 3)))
        self.tri = m.triangles_np[: m.tri_count // worlds]  # one world's triangles (world 0: local indices)
        self.n = n // worlds

    def positions(self):
        """Simulated positions of the compared frames, (STEPS, particle_count, 3)."""
        return np.stack([s.particle_x.numpy() for s in wc.rollout(self.sim, self.state, steps=STEPS)[1:]])

    def loss(self, bound, frames=FRAMES):
        traj = wc.rollout(self.sim, self.state, steps=STEPS)
        return bound([traj[k].particle_x for k in frames], frames).numpy().copy()

    def check_gradient(self, bound, name="v0", seed=1, rel_eps=1e-6, tol=1e-5):
        """Tape gradient of the sum of the worlds' losses along a random direction of the initial velocity (or
        positions) against central differences; returns the relative error."""
        a = self.state.particle_v if name == "v0" else self.state.particle_x
        a.grad.zero_()
        tape = wp.Tape()
        with tape:
            traj = wc.rollout(self.sim, self.state, steps=STEPS)
            loss = bound([traj[k].particle_x for k in FRAMES], FRAMES)
        tape.backward(grads={loss: wp.ones(self.model.world_count, dtype=wp.float64)})
        grad = a.grad.numpy().copy()
        tape.zero()
        rng = np.random.default_rng(seed)
        direction = rng.standard_normal(grad.shape)
        base = a.numpy().copy()
        eps = rel_eps * max(1.0, np.abs(base).max())
        try:
            a.assign(base + eps * direction)
            plus = self.loss(bound).sum()
            a.assign(base - eps * direction)
            minus = self.loss(bound).sum()
        finally:
            a.assign(base)
        fd = (plus - minus) / (2 * eps)
        analytic = float(np.sum(grad * direction))
        rel = abs(analytic - fd) / max(abs(fd), 1e-300)
        assert rel < tol, f"{name}: tape {analytic:.10e}, central differences {fd:.10e}, relative error {rel:.2e}"
        return rel


# -- NumPy references -------------------------------------------------------------------------------------------

def closest_on_segment(p, a, b):
    ab = b - a
    t = np.clip(np.einsum("...i,...i", p - a, ab) / np.einsum("...i,...i", ab, ab), 0.0, 1.0)
    return a + t[..., None] * ab


def closest_on_triangles(p, A, B, C):
    """Closest point to p (3,) on each triangle (T, 3): the plane's foot where inside, else the nearest edge point
    (another algorithm than the kernel's)."""
    n = np.cross(B - A, C - A)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    foot = p - np.einsum("ti,ti->t", p - A, n)[:, None] * n
    inside = np.ones(len(A), dtype=bool)
    for u, v in ((A, B), (B, C), (C, A)):
        inside &= np.einsum("ti,ti->t", np.cross(v - u, foot - u), n) >= 0.0
    edges = np.stack([closest_on_segment(p, u, v) for u, v in ((A, B), (B, C), (C, A))])  # (3, T, 3)
    best = edges[np.argmin(np.linalg.norm(edges - p, axis=2), axis=0), np.arange(len(A))]
    return np.where(inside[:, None], foot, best)


def surface_distances(points, x, tri):
    A, B, C = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    return np.array([np.linalg.norm(closest_on_triangles(p, A, B, C) - p, axis=1).min() for p in points])


def huber(d, delta):
    return np.where(d <= delta, 0.5 * d**2, delta * (d - 0.5 * delta))


def point_cloud_reference(x_frames, clouds, tri, robust=None, both_ways=False, both_ways_weight=1.0):
    terms = []
    for x, q in zip(x_frames, clouds):
        if q is None:
            continue
        d = surface_distances(q, x, tri)
        if robust is not None and robust[0] == "trimmed":  # the P - floor(fraction P) nearest
            term = (np.sort(d)[: len(d) - int(np.floor(robust[1] * len(d)))] ** 2).mean()
        else:
            term = (d**2 if robust is None else huber(d, robust[1])).mean()
        if both_ways:
            nearest = np.min(np.linalg.norm(x[:, None, :] - q[None, :, :], axis=2), axis=1)
            term += both_ways_weight * (nearest**2).mean()
        terms.append(term)
    return np.mean(terms)


def sample_surface(x, tri, count, rng, noise):
    t = rng.integers(0, len(tri), count)
    b = rng.dirichlet(np.ones(3), count)
    p = np.einsum("pk,pki->pi", b, x[tri[t]])
    return p + noise * rng.standard_normal((count, 3))


# -- vertices ---------------------------------------------------------------------------------------------------

def test_vertex_loss_is_the_trajectory_fits_arithmetic_bitwise_and_its_gradient_matches():
    h = Hanging()
    rng = np.random.default_rng(3)
    x = h.positions()
    frames = np.concatenate([h.model.particle_x0.numpy()[None], x + 0.01 * rng.standard_normal(x.shape)])
    bound = VertexFrames(frames).bind(h.model)
    traj = wc.rollout(h.sim, h.state, steps=STEPS)
    ours = bound([traj[k].particle_x for k in FRAMES], FRAMES).numpy()
    # TrajectoryFit's loss: the same kernel, scale and launch order
    m = h.model
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    scale = m.scalar(1.0 / (STEPS * m.particle_count))
    for k in FRAMES:
        wp.launch(loss_kernels(wp.float64).world_squared_distance, m.particle_count,
                  inputs=[traj[k].particle_x, wp.array(frames[k], dtype=wp.vec3d), m.particle_world,
                          wp.zeros(1, dtype=wp.int32), scale], outputs=[loss])
    assert ours.tobytes() == loss.numpy().tobytes()
    np.testing.assert_allclose(ours[0], np.mean(np.sum((x - frames[1:]) ** 2, axis=2)), rtol=1e-12)
    h.check_gradient(bound)


# -- markers ----------------------------------------------------------------------------------------------------

def marker_setup(h, rng, hidden=0.3):
    M = 7
    tri = rng.integers(0, len(h.tri), M)
    bary = rng.dirichlet(np.ones(3), M)
    bary[0] = (1.0, 0.0, 0.0)  # on a vertex
    x = h.positions()[:, : h.n]
    sim = np.einsum("mk,fmki->fmi", bary, x[:, h.tri[tri]])
    rec = np.concatenate([sim[:1] * 0.0, sim + 0.01 * rng.standard_normal(sim.shape)])  # frame 0: not compared
    rec[1:][rng.random((STEPS, M)) < hidden] = np.nan
    rec[2] = np.nan  # every marker hidden in frame 2
    return tri, bary, rec


def test_marker_loss_skips_hidden_markers_and_its_gradient_matches():
    h = Hanging()
    rng = np.random.default_rng(4)
    tri, bary, rec = marker_setup(h, rng)
    bound = MarkerFrames(tri, bary, rec).bind(h.model)
    x = h.positions()
    sim = np.einsum("mk,fmki->fmi", bary, x[:, h.tri[tri]])
    d2 = np.sum((sim - rec[1:]) ** 2, axis=2)
    expected = np.nanmean(d2)  # over the visible (frame, marker) pairs
    assert np.isnan(rec[1:]).any() and np.isfinite(d2).sum() > 0
    np.testing.assert_allclose(h.loss(bound), [expected], rtol=1e-12)
    rel_v = h.check_gradient(bound, "v0")
    rel_x = h.check_gradient(bound, "x0")
    print(f"marker loss gradient: relative error {rel_v:.1e} (velocity), {rel_x:.1e} (positions)")
    with pytest.raises(ValueError, match=r"no marker is visible in the compared frames \[2\]"):
        h.loss(bound, frames=[2])


def test_markers_capture_into_a_cpu_graph():
    h = Hanging()
    tri, bary, rec = marker_setup(h, np.random.default_rng(5))
    bound = MarkerFrames(tri, bary, rec).bind(h.model)
    assert bound.capturable
    captured = wc.CapturedRollout(h.sim, h.state, steps=STEPS,
                                  loss=lambda traj: bound([traj[k].particle_x for k in FRAMES], FRAMES))
    captured.run()
    np.testing.assert_array_equal(captured.loss.numpy(), h.loss(bound))


# -- point clouds -----------------------------------------------------------------------------------------------

def clouds_of(h, rng, sizes=(60, 45, None, 80), noise=0.01, outliers=3):
    x = h.positions()[:, : h.n]
    clouds = [None]  # frame 0: not compared
    for k, size in enumerate(sizes):
        if size is None:
            clouds.append(None)
            continue
        q = sample_surface(x[k], h.tri, size, rng, noise)
        q[:outliers] += rng.normal(0.0, 0.1, (outliers, 3))
        clouds.append(q)
    return x, clouds


@pytest.mark.parametrize("robust, both_ways", [(None, False), (("huber", 0.008), False), (("trimmed", 0.1), False),
                                               (None, True)], ids=["squared", "huber", "trimmed", "both-ways"])
def test_point_cloud_loss_matches_brute_force_and_its_gradient_matches(robust, both_ways):
    h = Hanging()
    rng = np.random.default_rng(6)
    x, clouds = clouds_of(h, rng)
    obs = PointCloudFrames(clouds, robust=robust, both_ways=both_ways, both_ways_weight=0.5)
    bound = obs.bind(h.model)
    assert not bound.capturable
    expected = point_cloud_reference(x, clouds[1:], h.tri, robust, both_ways, 0.5)
    np.testing.assert_allclose(h.loss(bound), [expected], rtol=1e-10)
    if robust is not None and robust[0] == "huber":  # both branches of the Huber loss are taken
        d = np.concatenate([surface_distances(q, xk, h.tri) for xk, q in zip(x, clouds[1:]) if q is not None])
        assert (d < 0.008).any() and (d > 0.008).any()
    rel = h.check_gradient(bound, tol=1e-5)
    print(f"point cloud loss {robust} both_ways={both_ways}: gradient relative error {rel:.1e}")
    if robust is not None and robust[0] == "trimmed":  # the kept set held fixed: a second step size agrees too
        h.check_gradient(bound, rel_eps=1e-5, tol=1e-5)


def test_huber_is_its_formula():
    """One point off a flat cloth by a known distance: the loss is 0.5 d^2 below delta, delta (d - delta/2) above."""
    h = Hanging()
    x0 = h.model.particle_x0.numpy()  # the cloth in the plane y = 0, x in [0, 0.5], z in [-0.5, 0]
    for d, delta in ((0.003, 0.01), (0.03, 0.01), (0.2, 0.05)):
        obs = PointCloudFrames([np.array([[0.21, d, -0.27]])], robust=("huber", delta))
        loss = obs.bind(h.model)([wp.array(x0, dtype=wp.vec3d)]).numpy()[0]
        np.testing.assert_allclose(loss, huber(d, delta), rtol=1e-12)
        plain = PointCloudFrames([np.array([[0.21, -d, -0.27]])]).bind(h.model)([wp.array(x0, dtype=wp.vec3d)])
        np.testing.assert_allclose(plain.numpy()[0], d * d, rtol=1e-12)


def test_trimming_leaves_out_the_outliers():
    """Points on the flat cloth and two 0.3 m off it: trimming a fifth of ten leaves the two out (the loss is the
    inliers' mean squared distance), and the kept set is chosen per world."""
    h = Hanging(worlds=2, seed=3)
    x0 = h.model.particle_x0.numpy()  # both worlds' cloths in the plane y = 0, x in [0, 0.5], z in [-0.5, 0]
    rng = np.random.default_rng(4)
    inliers = np.column_stack([rng.uniform(0.05, 0.45, 8), rng.uniform(-0.004, 0.004, 8), rng.uniform(-0.45, -0.05, 8)])
    cloud = np.vstack([inliers, [[0.2, 0.3, -0.2], [0.3, -0.3, -0.3]]])
    shifted = x0.copy()
    shifted[h.n:, 1] += 0.002  # world 1's cloth 2 mm off the plane
    loss = PointCloudFrames([cloud], robust=("trimmed", 0.2)).bind(h.model)([wp.array(shifted, dtype=wp.vec3d)])
    np.testing.assert_allclose(loss.numpy(), [np.mean(inliers[:, 1] ** 2), np.mean((inliers[:, 1] - 0.002) ** 2)],
                               rtol=1e-9)
    plain = PointCloudFrames([cloud]).bind(h.model)([wp.array(shifted, dtype=wp.vec3d)]).numpy()
    assert (plain > 100 * loss.numpy()).all()


def test_each_world_has_its_own_loss():
    h = Hanging(worlds=2, seed=7)
    rng = np.random.default_rng(8)
    x = h.positions()
    one = Hanging()
    x_one = one.positions()
    q_source = sample_surface(x_one[0, : one.n], one.tri, 40, rng, 0.01)
    clouds = [None, q_source, None, q_source + 0.01, q_source - 0.02]
    tri, bary, rec = marker_setup(one, rng)
    obs = [PointCloudFrames(clouds, robust=("huber", 0.01), both_ways=True),
           MarkerFrames(tri, bary, rec), VertexFrames(np.concatenate([x_one[:1] * 0, x_one])[:, : one.n])]
    for o in obs:
        got = h.loss(o.bind(h.model))
        for w in range(2):
            xw = x[:, w * h.n:(w + 1) * h.n]
            if isinstance(o, PointCloudFrames):
                ref = point_cloud_reference(xw, clouds[1:], h.tri, o.robust, True)
            elif isinstance(o, MarkerFrames):
                ref = np.nanmean(np.sum((np.einsum("mk,fmki->fmi", bary, xw[:, h.tri[tri]]) - rec[1:]) ** 2, axis=2))
            else:
                ref = np.mean(np.sum((xw - x_one[:, : one.n]) ** 2, axis=2))
            np.testing.assert_allclose(got[w], ref, rtol=1e-10, err_msg=f"{type(o).__name__}, world {w}")
    h.check_gradient(obs[0].bind(h.model))


# -- depth images -----------------------------------------------------------------------------------------------

def test_depth_of_a_plane_back_projects_onto_it():
    H, W, fx, fy, cx, cy = 24, 32, 40.0, 42.0, 15.5, 11.5
    # a camera at (0.1, -1, 0.2) looking along world +y (OpenCV: x right, y down, z forward)
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, (0.1, -1.0, 0.2)
    # the world plane y = 0.5 tilted: n . p = c with n = (0.2, 1, 0.1)/|.|, seen through each pixel's ray
    n = np.array([0.2, 1.0, 0.1])
    c = n @ np.array([0.0, 0.5, 0.0])
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u, dtype=float)], axis=-1)  # camera, z = 1
    z = (c - n @ T[:3, 3]) / (rays @ R.T @ n)
    depth = z.copy()
    depth[3, 4], depth[5, 6], depth[7, 8] = 0.0, np.nan, np.inf  # holes
    p = points_from_depth(depth, (fx, fy, cx, cy), T)
    assert p.shape == (H * W - 3, 3)
    np.testing.assert_allclose(p @ n, c, atol=1e-12)
    centre = points_from_depth(np.full((1, 1), 2.0), (fx, fy, 0.0, 0.0), T)  # the principal point's ray: +z
    np.testing.assert_allclose(centre[0], T[:3, 3] + 2.0 * R[:, 2], atol=1e-15)
    # pixel (u, v) = (31, 0): right of and above the principal point
    np.testing.assert_allclose(p[31], T[:3, 3] + R @ (z[0, 31] * rays[0, 31]), atol=1e-12)


# -- bad input --------------------------------------------------------------------------------------------------

def test_bad_input_names_the_offending_index():
    h = Hanging()
    m = h.model
    cloud = np.zeros((5, 3))
    with pytest.raises(ValueError, match=r"frame 1, point 3: not finite"):
        PointCloudFrames([cloud, np.where(np.arange(5)[:, None] == 3, np.nan, cloud)])
    with pytest.raises(ValueError, match=r"frame 0, point 2: not finite"):
        PointCloudFrames([np.where(np.arange(5)[:, None] == 2, np.inf, cloud)])
    with pytest.raises(ValueError, match=r"frame 1 must be \(P, 3\)"):
        PointCloudFrames([cloud, np.zeros((0, 3))])
    with pytest.raises(ValueError, match="every frame is dropped"):
        PointCloudFrames([None, None])
    with pytest.raises(ValueError, match="Huber delta must be positive"):
        PointCloudFrames([cloud], robust=("huber", -0.01))
    with pytest.raises(ValueError, match=r"robust must be None, \('huber', delta \[m\]\) or \('trimmed', fraction\)"):
        PointCloudFrames([cloud], robust=("median", 0.1))
    for fraction in (0.0, 1.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="the trimmed fraction must be in"):
            PointCloudFrames([cloud], robust=("trimmed", fraction))
    with pytest.raises(ValueError, match="both_ways_weight"):
        PointCloudFrames([cloud], both_ways=True, both_ways_weight=-1.0)
    with pytest.raises(ValueError, match="every compared frame"):
        PointCloudFrames([cloud, None]).bind(m)([m.particle_x0], [1])
    tri, bary = np.array([0, 1, 2]), np.array([[1.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.2, 0.2, 0.6]])
    pos = np.zeros((2, 3, 3))
    with pytest.raises(ValueError, match=r"marker 1's barycentric coordinates .* sum to 1"):
        MarkerFrames(tri, bary * [[1.0], [1.001], [1.0]], pos)
    with pytest.raises(ValueError, match=r"marker 2's barycentric coordinates"):
        MarkerFrames(tri, np.array([[1.0, 0.0, 0.0], [0.5, 0.5, 0.0], [1.2, 0.0, -0.2]]), pos)
    with pytest.raises(ValueError, match=r"marker 1's triangle 32 out of range"):
        MarkerFrames([0, len(h.tri), 2], bary, pos).bind(m)
    partly = pos.copy()
    partly[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"frame 1, marker 2: .* partly NaN"):
        MarkerFrames(tri, bary, partly)
    with pytest.raises(ValueError, match=r"positions must be \(F, 3, 3\)"):
        MarkerFrames(tri, bary, np.zeros((2, 4, 3)))
    bad = np.zeros((3, h.n, 3))
    bad[2, 7, 1] = np.nan
    with pytest.raises(ValueError, match=r"frame 2, vertex 7: not finite"):
        VertexFrames(bad)
    with pytest.raises(ValueError, match=r"the frames hold 24 vertices"):
        VertexFrames(np.zeros((3, 24, 3))).bind(m)
    bound = VertexFrames(np.zeros((3, h.n, 3))).bind(m)
    with pytest.raises(ValueError, match=r"compared frame 3 out of range"):
        bound([m.particle_x0], [3])
    with pytest.raises(ValueError, match=r"positions\[0\] \(frame 1\) must be"):
        bound([wp.zeros(h.n, dtype=wp.vec3f)], [1])
    a, c = wc.ModelBuilder(), wc.ModelBuilder()
    a.add_cloth_grid((2, 2), (1.0, 1.0), material=wc.preset("gray-interlock"))
    c.add_cloth_grid((3, 2), (1.0, 1.0), material=wc.preset("gray-interlock"))
    unequal = wc.ModelBuilder()
    unequal.add_world(a)
    unequal.add_world(c)
    with pytest.raises(ValueError, match=r"world 1's cloth differs from world 0's"):
        VertexFrames(np.zeros((2, 9, 3))).bind(unequal.finalize("cpu", dtype=wp.float64))
    with pytest.raises(ValueError, match=r"intrinsics"):
        points_from_depth(np.ones((2, 2)), (0.0, 1.0, 0.0, 0.0), np.eye(4))
    with pytest.raises(ValueError, match=r"rigid"):
        points_from_depth(np.ones((2, 2)), (1.0, 1.0, 0.0, 0.0), np.diag([2.0, 1.0, 1.0, 1.0]))
