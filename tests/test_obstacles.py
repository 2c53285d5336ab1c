"""Rigid obstacles: shapes, keyframed motion, world points (kernel, gradients), builder, scenes and USD output."""


import numpy as np
import pytest
import warp as wp
import warp.autograd
from conftest import seed_data

import warpcloth as wc
from warpcloth.geometry.primitives import contact_edges, unique_edges
from warpcloth.geometry.transforms import quat_from_matrix, quat_to_matrix
from warpcloth.kernels.obstacle import obstacle_kernels
from warpcloth.mesh_io import load_obj
from warpcloth.scene import load_scene, scene_from_toml
from warpcloth.usd import write_usd

MATERIAL = wc.preset("gray-interlock")


def _quat(axis, angle):
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([np.sin(angle / 2.0) * axis, [np.cos(angle / 2.0)]])


def _signed_volume(v, f):
    return np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0


def _normals(v, f):
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def _builder(res=(3, 2)):
    b = wc.ModelBuilder()
    b.add_cloth_grid(res, (0.3, 0.2), material=MATERIAL)
    return b


# -- shapes ------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("subdivisions", [0, 1, 3])
def test_sphere_mesh_is_a_closed_outward_icosphere(subdivisions):
    v, f = wc.sphere_mesh(0.7, subdivisions)
    assert f.dtype == np.int32 and v.dtype == np.float64
    assert len(f) == 20 * 4**subdivisions and len(v) == 10 * 4**subdivisions + 2
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 0.7, rtol=1e-12)
    n = _normals(v, f)
    centroid = v[f].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", n, centroid) > 0.0)  # every face points away from the centre
    vol = _signed_volume(v, f)
    assert 0.0 < vol < 4.0 / 3.0 * np.pi * 0.7**3
    edges = unique_edges(f)
    assert len(v) - len(edges) + len(f) == 2  # closed genus-0 surface


def test_box_and_plane_meshes():
    v, f = wc.box_mesh((0.1, 0.2, 0.3))
    assert v.shape == (8, 3) and f.shape == (12, 3)
    assert _signed_volume(v, f) == pytest.approx(0.2 * 0.4 * 0.6)
    n = _normals(v, f)
    assert np.all(np.einsum("ij,ij->i", n, v[f].mean(axis=1)) > 0.0)
    assert len(unique_edges(f)) == 18
    # the edges contacts use: the box's 12 (each along one axis), not its face diagonals; every edge of a sphere
    edges = unique_edges(f)
    along_one_axis = np.count_nonzero(v[edges[:, 0]] != v[edges[:, 1]], axis=1) == 1
    np.testing.assert_array_equal(contact_edges(v, f), edges[along_one_axis])
    sv, sf = wc.sphere_mesh(0.3, 2)
    np.testing.assert_array_equal(contact_edges(sv, sf), unique_edges(sf))

    v, f = wc.plane_mesh((2.0, 1.0), (4, 3))
    assert v.shape == (20, 3) and f.shape == (24, 3)
    np.testing.assert_allclose(v.min(axis=0), [-1.0, -0.5, 0.0])
    np.testing.assert_allclose(v.max(axis=0), [1.0, 0.5, 0.0])
    boundary = contact_edges(v, f)  # a flat plane: only its outline, 2 (4 + 3) edges
    ends = v[boundary]  # (edges, 2, 3)
    on_side = np.isclose(np.abs(ends[:, :, 0]), 1.0).all(axis=1) | np.isclose(np.abs(ends[:, :, 1]), 0.5).all(axis=1)
    assert len(boundary) == 14 and on_side.all()
    n = _normals(v, f)
    assert np.all(n[:, 2] > 0.0) and np.allclose(n[:, :2], 0.0)


def test_funnel_mesh_reproduces_contain_obj():
    v, f = wc.funnel_mesh()
    ref = load_obj(seed_data("meshes/contain.obj"), validate=False)
    np.testing.assert_array_equal(v, ref.positions)
    np.testing.assert_array_equal(f, ref.triangles)
    # The faces look up into the cavity, towards the funnel's axis (x = y = 0.5).
    n = _normals(v, f)
    to_axis = np.array([0.5, 0.5, 0.0]) - v[f].mean(axis=1)
    to_axis[:, 2] = 0.0
    assert np.all(n[:, 2] > 0.0) and np.all(np.einsum("ij,ij->i", n, to_axis) > 0.0)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: wc.sphere_mesh(0.0), "sphere radius must be finite and > 0"),
        (lambda: wc.sphere_mesh(1.0, -1), "sphere subdivisions must be an integer >= 0"),
        (lambda: wc.sphere_mesh(1.0, 9), "sphere subdivisions must be <= 8"),
        (lambda: wc.box_mesh((1.0, 0.0, 1.0)), "box half_extents must be finite and > 0"),
        (lambda: wc.box_mesh((1.0, 1.0)), "box half_extents must have 3 components"),
        (lambda: wc.plane_mesh((1.0, np.nan)), "plane size must be finite and > 0"),
        (lambda: wc.plane_mesh((1.0, 1.0), (0, 1)), r"plane res\[0\] must be an integer >= 1"),
    ],
)
def test_shape_parameter_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_quaternion_matrix_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        q = q if q[3] >= 0 else -q
        np.testing.assert_allclose(quat_from_matrix(quat_to_matrix(q)), q, atol=1e-12)
    with pytest.raises(ValueError, match="reflection"):
        quat_from_matrix(np.diag([1.0, 1.0, -1.0]))


# -- RigidMotion -------------------------------------------------------------------------------------------------------


def test_rigid_motion_interpolates_and_holds():
    q90 = _quat([0, 0, 1], np.pi / 2)
    m = wc.RigidMotion.from_keyframes([(1.0, (0, 0, 0), (0, 0, 0, 1)), (3.0, (2.0, -4.0, 1.0), q90)])
    tr, q = m.at(2.0)
    np.testing.assert_allclose(tr, [1.0, -2.0, 0.5])
    np.testing.assert_allclose(q, _quat([0, 0, 1], np.pi / 4), atol=1e-15)
    tr, q = m.at(1.5)
    np.testing.assert_allclose(tr, [0.5, -1.0, 0.25])
    np.testing.assert_allclose(q, _quat([0, 0, 1], np.pi / 8), atol=1e-15)
    for t, k in ((-5.0, 0), (1.0, 0), (3.0, 1), (10.0, 1)):
        tr, q = m.at(t)
        np.testing.assert_array_equal(tr, m.translations[k])
        np.testing.assert_array_equal(q, m.rotations[k])
    # Shortest arc: -q is the same rotation, and slerp must not go the long way round.
    m2 = wc.RigidMotion([1.0, 3.0], m.translations, [[0, 0, 0, 1], -q90])
    _, q = m2.at(2.0)
    np.testing.assert_allclose(quat_to_matrix(q), quat_to_matrix(_quat([0, 0, 1], np.pi / 4)), atol=1e-15)
    single = wc.RigidMotion([0.0], [[1, 2, 3]], [[0, 0, 0, 1]])
    np.testing.assert_array_equal(single.at(7.0)[0], [1, 2, 3])


@pytest.mark.parametrize(
    "keys, match",
    [
        ([], "at least one"),
        ([(0.0, (0, 0, 0), (0, 0, 0, 1)), (0.0, (0, 0, 0), (0, 0, 0, 1))], "keyframe 1: key times must be strictly"),
        ([(0.0, (0, 0, 0), (0, 0, 0, 1)), (1.0, (0, 0, 0), (0, 0, 0.1, 1))], "keyframe 1: rotation: quaternion"),
        ([(np.nan, (0, 0, 0), (0, 0, 0, 1))], "keyframe 0: time is not finite"),
        ([(0.0, (0, np.inf, 0), (0, 0, 0, 1))], "keyframe 0: translation is not finite"),
        ([(0.0, (0, 0), (0, 0, 0, 1))], "keyframe 0: translation needs 3 components"),
        ([(0.0, (0, 0, 0), (0, 0, 1))], r"keyframe 0: rotation needs 4 components"),
        ([(0.0, (0, 0, 0))], "keyframe 0: expected"),
    ],
)
def test_rigid_motion_errors(keys, match):
    with pytest.raises(ValueError, match=match):
        wc.RigidMotion.from_keyframes(keys)


# -- world points ------------------------------------------------------------------------------------------------------


def _obstacle_model(dtype, requires_grad=False):
    b = _builder()
    b.add_obstacle_box((0.1, 0.2, 0.05), pos=(0.3, -0.2, 0.5), rot=_quat([1, 2, 3], 0.7), name="crate")
    v, f = wc.sphere_mesh(0.15, 1)
    b.add_obstacle_mesh(
        v + [0.01, 0.02, 0.0],  # off-centre in its own frame
        f,
        pos=(-0.4, 0.1, 0.2),
        rot=quat_to_matrix(_quat([0, 1, 1], -0.4)),
        motion=[
            (0.0, (0.0, 0.0, 0.0), (0, 0, 0, 1)),
            (0.5, (0.1, 0.0, -0.2), _quat([0, 0, 1], 0.8)),
            (1.0, (0.3, 0.2, -0.1), _quat([1, 0, 0], 0.5)),
        ],
    )
    return b.finalize("cpu", requires_grad=requires_grad, dtype=dtype)


@pytest.mark.parametrize("dtype", [wp.float32, wp.float64])
def test_world_points_kernel_matches_numpy(dtype):
    m = _obstacle_model(dtype)
    c = m.control()
    assert c.obstacle_transform.dtype == (wp.transformd if dtype == wp.float64 else wp.transformf)
    box_v, box_f = wc.box_mesh((0.1, 0.2, 0.05))
    sph_v, sph_f = wc.sphere_mesh(0.15, 1)
    tol = 1e-6 if dtype == wp.float32 else 1e-13
    for t in (0.0, 0.3, 0.75, 2.0):
        x = wc.obstacle_points(m, c, t).numpy()
        ref = wc.obstacle_points_numpy(m, t)
        np.testing.assert_allclose(x, ref, atol=tol)
        # Independent reference: x = R_m (R_b u + p_b) + p_m.
        tr, qm = m.obstacle_motion[1].at(t)
        Rb = quat_to_matrix(_quat([0, 1, 1], -0.4))
        expect = ((sph_v + [0.01, 0.02, 0.0]) @ Rb.T + [-0.4, 0.1, 0.2]) @ quat_to_matrix(qm).T + tr
        np.testing.assert_allclose(ref[8:], expect, atol=tol)  # float32 models store float32 vertices
        expect_box = box_v @ quat_to_matrix(_quat([1, 2, 3], 0.7)).T + [0.3, -0.2, 0.5]
        np.testing.assert_allclose(ref[:8], expect_box, atol=tol)
    # A moved base placement (as an optimiser would set it) is followed by both.
    tf = m.obstacle_rest_transform.copy()
    tf[0, :3] += [0.05, 0.0, -0.1]
    c.obstacle_transform.assign(tf)
    np.testing.assert_allclose(wc.obstacle_points(m, c, 0.4).numpy(), wc.obstacle_points_numpy(m, 0.4, tf), atol=tol)
    # Concatenation bookkeeping.
    assert m.obstacle_names == ["crate", "obstacle1"]
    np.testing.assert_array_equal(m.obstacle_vertex_start, [0, 8, 8 + len(sph_v)])
    np.testing.assert_array_equal(m.obstacle_tri_start, [0, 12, 12 + len(sph_f)])
    np.testing.assert_array_equal(m.obstacle_vertex_body.numpy(), [0] * 8 + [1] * len(sph_v))
    np.testing.assert_array_equal(m.obstacle_tri_indices.numpy(), np.concatenate([box_f, sph_f + 8]))
    assert m.obstacle_edge_count == 12 + len(unique_edges(sph_f))  # the box's face diagonals are flat: no contacts


def test_obstacle_points_gradient_matches_finite_differences():
    m = _obstacle_model(wp.float64, requires_grad=True)
    c = m.control()
    t = 0.3
    rng = np.random.default_rng(2)
    w = rng.standard_normal((m.obstacle_vertex_count, 3))

    def loss(tf=None, local=None):
        if tf is not None:
            c.obstacle_transform.assign(tf)
        if local is not None:
            m.obstacle_vertex_local.assign(local)
        return float(np.sum(w * wc.obstacle_points(m, c, t).numpy()))

    tape = wp.Tape()
    with tape:
        x = wc.obstacle_points(m, c, t)
    tape.backward(grads={x: wp.array(w, dtype=wp.vec3d, device="cpu")})
    g_tf = c.obstacle_transform.grad.numpy().copy()
    g_local = m.obstacle_vertex_local.grad.numpy().copy()
    assert np.any(g_tf[:, 3:] != 0.0)

    tf0 = c.obstacle_transform.numpy().copy()
    eps = 1e-6
    fd = np.zeros_like(tf0)
    for b in range(tf0.shape[0]):
        for k in range(7):  # position and all four quaternion components, taken as given (not renormalised)
            tp, tm = tf0.copy(), tf0.copy()
            tp[b, k] += eps
            tm[b, k] -= eps
            fd[b, k] = (loss(tf=tp) - loss(tf=tm)) / (2 * eps)
    c.obstacle_transform.assign(tf0)
    np.testing.assert_allclose(g_tf, fd, rtol=1e-7, atol=1e-8)

    local0 = m.obstacle_vertex_local.numpy().copy()
    d = rng.standard_normal(local0.shape)
    fd_dir = (loss(local=local0 + eps * d) - loss(local=local0 - eps * d)) / (2 * eps)
    assert np.sum(g_local * d) == pytest.approx(fd_dir, rel=1e-7)


def test_world_points_kernel_gradcheck():
    rng = np.random.default_rng(3)
    q = rng.standard_normal((2, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    local = wp.array(rng.standard_normal((5, 3)), dtype=wp.vec3d, device="cpu", requires_grad=True)
    body = wp.array([0, 1, 1, 0, 1], dtype=wp.int32, device="cpu")
    base = wp.array(np.concatenate([rng.standard_normal((2, 3)), q], 1), dtype=wp.transformd, device="cpu",
                    requires_grad=True)
    motion = wp.array(np.tile([0.1, 0.2, 0.3, *_quat([1, 1, 0], 0.3)], (2, 1)), dtype=wp.transformd, device="cpu")
    out = wp.zeros(5, dtype=wp.vec3d, device="cpu", requires_grad=True)
    assert warp.autograd.gradcheck(
        obstacle_kernels(wp.float64).world_points, dim=5, inputs=[local, body, base, motion], outputs=[out],
        eps=1e-6, atol=1e-7, rtol=1e-6, show_summary=False, device="cpu",
        input_output_mask=[("vertex_local", "world"), ("base_transform", "world")],
    )


def test_obstacle_points_errors():
    m = _builder().finalize("cpu")
    with pytest.raises(ValueError, match="obstacle_points: the model has no obstacles"):
        wc.obstacle_points(m, m.control(), 0.0)
    m = _obstacle_model(wp.float32)
    with pytest.raises(ValueError, match="control.obstacle_transform must be"):
        wc.obstacle_points(m, wc.Control(None, None, None), 0.0)
    with pytest.raises(ValueError, match="out must be"):
        wc.obstacle_points(m, m.control(), 0.0, out=wp.zeros(3, dtype=wp.vec3, device="cpu"))


# -- builder -----------------------------------------------------------------------------------------------------------


def test_cloth_edges_are_unique_and_sorted():
    m = _builder(res=(4, 3)).finalize("cpu")
    v, f = 5 * 4, 4 * 3 * 2
    assert m.edge_count == v + f - 1  # Euler characteristic of a disc
    e = m.edge_indices.numpy()
    assert e.shape == (m.edge_count, 2) and e.dtype == np.int32
    assert np.all(e[:, 0] < e[:, 1])
    assert len(np.unique(e, axis=0)) == len(e)
    assert np.all(np.diff(e[:, 0].astype(np.int64) * v + e[:, 1]) > 0)  # rows sorted
    # Every triangle side is an edge.
    tri = m.triangles_np
    sides = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    np.testing.assert_array_equal(np.unique(sides, axis=0), e)


def test_collision_settings():
    m = _builder().finalize("cpu")
    assert m.collision is None and m.obstacle_count == 0
    assert m.obstacle_vertex_local is None and m.obstacle_tri_indices is None and m.obstacle_edge_indices is None
    assert m.control().obstacle_transform is None

    b = _builder()
    b.set_collision(self_collision=True, thickness=1e-3)
    m = b.finalize("cpu")
    assert m.collision == wc.CollisionSettings(obstacles=False, self_collision=True, thickness=1e-3)

    b = _builder()
    b.add_obstacle_plane((1.0, 1.0), pos=(0, 0, -1))
    m = b.finalize("cpu", requires_grad=True)
    assert m.collision == wc.CollisionSettings(obstacles=True, self_collision=False, thickness=5e-4)
    c = m.control()
    assert c.obstacle_transform.shape == (1,) and c.obstacle_transform.requires_grad
    assert m.obstacle_vertex_local.requires_grad

    for bad in (0.0, -1e-3, np.nan, np.inf):
        with pytest.raises(ValueError, match="thickness"):
            _builder().set_collision(thickness=bad)
    with pytest.raises(ValueError, match="thickness"):
        wc.CollisionSettings(obstacles=True, self_collision=False, thickness=0.0)
    with pytest.raises(ValueError, match="self_collision must be a boolean"):
        _builder().set_collision(self_collision="yes")


def test_obstacle_names_and_placement():
    b = _builder()
    assert b.add_obstacle_sphere(0.1, 0) == 0
    assert b.add_obstacle_box((0.1, 0.1, 0.1), name="obstacle2") == 1
    assert b.add_obstacle_funnel() == 2  # "obstacle2" is taken: the next free default name
    assert [o.name for o in b.obstacles] == ["obstacle0", "obstacle2", "obstacle3"]
    with pytest.raises(ValueError, match="obstacle name 'obstacle2' is used twice"):
        b.add_obstacle_plane(name="obstacle2")
    with pytest.raises(ValueError, match="'2nd' is not a valid identifier"):
        b.add_obstacle_plane(name="2nd")
    with pytest.raises(ValueError, match="'a b' is not a valid identifier"):
        b.add_obstacle_plane(name="a b")
    # A rotation matrix and the equivalent quaternion give the same placement.
    q = _quat([1, -1, 2], 1.1)
    b.add_obstacle_box((0.1, 0.2, 0.3), name="by_quat", rot=q, pos=(1, 2, 3))
    b.add_obstacle_box((0.1, 0.2, 0.3), name="by_matrix", rot=quat_to_matrix(q), pos=(1, 2, 3))
    tf = {o.name: o.transform for o in b.obstacles}
    np.testing.assert_allclose(tf["by_quat"], tf["by_matrix"], atol=1e-14)
    with pytest.raises(ValueError, match="obstacle 'bad_rot': rot must be a rotation matrix"):
        b.add_obstacle_box((0.1, 0.1, 0.1), name="bad_rot", rot=2.0 * np.eye(3))
    with pytest.raises(ValueError, match="obstacle 'bad_q': rot: quaternion .* norm 2"):
        b.add_obstacle_box((0.1, 0.1, 0.1), name="bad_q", rot=(0, 0, 0, 2))
    with pytest.raises(ValueError, match="obstacle 'bad_motion': motion keyframe 1: key times"):
        b.add_obstacle_box((0.1, 0.1, 0.1), name="bad_motion",
                           motion=[(1.0, (0, 0, 0), (0, 0, 0, 1)), (0.5, (0, 0, 0), (0, 0, 0, 1))])
    assert b.obstacle_count == 5  # failed calls add nothing


def test_obstacle_mesh_errors():
    b = _builder()
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], dtype=float)
    with pytest.raises(ValueError, match=r"obstacle 'wall': triangle 1 \[0, 1, 3\] is degenerate"):
        b.add_obstacle_mesh(v, [[0, 1, 2], [0, 1, 3]], name="wall")
    with pytest.raises(ValueError, match=r"triangle 0 \[0, 0, 2\] is degenerate"):
        b.add_obstacle_mesh(v, [[0, 0, 2]])
    with pytest.raises(ValueError, match=r"triangle 0 \[0, 1, 4\] has an index out of range \[0, 4\)"):
        b.add_obstacle_mesh(v, [[0, 1, 4]])
    with pytest.raises(ValueError, match="vertex 2 is not finite"):
        b.add_obstacle_mesh(np.where(np.arange(4)[:, None] == 2, np.nan, v), [[0, 1, 3]])
    with pytest.raises(ValueError, match=r"triangles must have shape \(T, 3\) with T > 0"):
        b.add_obstacle_mesh(v, np.zeros((0, 3), dtype=int))
    with pytest.raises(ValueError, match="triangles must hold integers"):
        b.add_obstacle_mesh(v, [[0.0, 1.0, 2.0]])
    # Open, non-manifold meshes are fine: three triangles on one edge.
    v5 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], dtype=float)
    b.add_obstacle_mesh(v5, [[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    assert b.finalize("cpu").obstacle_edge_count == 7


def test_obstacle_from_obj_and_usd(tmp_path):
    obj = tmp_path / "quad.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3 4/4\n")
    b = _builder()
    b.add_obstacle_obj(obj, scale=2.0, name="quad", pos=(0, 0, -1))
    usd = tmp_path / "ball.usda"
    sv, sf = wc.sphere_mesh(0.25, 1)
    g = wc.grid_mesh(1, 1, 1.0, 1.0)
    write_usd(usd, triangles=g.triangles, frames=[g.positions], fps=10.0, obstacles=[("ball", sv, sf)])
    b.add_obstacle_usd(usd, prim_path="/World/Obstacles/ball", scale=2.0, name="ball")
    m = b.finalize("cpu")
    np.testing.assert_array_equal(m.obstacle_triangles_np[:2], [[0, 1, 2], [0, 2, 3]])  # fan-triangulated quad
    x = wc.obstacle_points_numpy(m, 0.0)
    np.testing.assert_allclose(x[:4], [[0, 0, -1], [2, 0, -1], [2, 2, -1], [0, 2, -1]])
    np.testing.assert_allclose(x[4:], 2.0 * sv, atol=1e-6)  # USD stores float32 points
    with pytest.raises(ValueError, match="scale must be a finite number > 0"):
        b.add_obstacle_usd(usd, scale=0.0)


# -- scenes ------------------------------------------------------------------------------------------------------------

_SCENE = """
name = "obstacle-test"
[sim]
dt = 0.01
steps = 2
[cloth]
grid = { res = [2, 2], size = [0.2, 0.2] }
material = "gray-interlock"
"""


def test_scene_obstacles_and_collision(tmp_path):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    text = _SCENE + """
[[obstacles]]
shape = "sphere"
radius = 0.3
subdivisions = 1
name = "ball"
pos = [0.0, 0.0, -1.0]
rot_deg = [0.0, 0.0, 90.0]
motion = [[0.0, [0, 0, 0], [0, 0, 0, 1]], [1.0, [0, 0, 0.5], [0, 0, 0.7071067811865476, 0.7071067811865476]]]

[[obstacles]]
shape = "funnel"
pos = [-0.5, -1.0, -0.55]

[[obstacles]]
shape = "box"
half_extents = [0.1, 0.2, 0.3]

[[obstacles]]
shape = "plane"
size = [2.0, 3.0]
res = [2, 1]

[[obstacles]]
mesh = { path = "tri.obj", scale = 2.0 }

[collision]
self_collision = true
thickness = 1e-3
"""
    scene = scene_from_toml(text, base_dir=tmp_path)
    m = scene.model_builder.finalize("cpu")
    assert m.obstacle_names == ["ball", "obstacle1", "obstacle2", "obstacle3", "obstacle4"]
    assert m.collision == wc.CollisionSettings(obstacles=True, self_collision=True, thickness=1e-3)
    np.testing.assert_allclose(m.obstacle_rest_transform[0], [0, 0, -1, 0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    np.testing.assert_allclose(m.obstacle_rest_transform[1], [-0.5, -1.0, -0.55, 0, 0, 0, 1])
    assert m.obstacle_motion[0].key_count == 2 and m.obstacle_motion[1] is None
    ts = m.obstacle_tri_start
    assert list(np.diff(ts)) == [80, 4, 12, 4, 1]
    np.testing.assert_allclose(wc.obstacle_points_numpy(m, 0.0)[-3:], [[0, 0, 0], [2, 0, 0], [0, 2, 0]])


@pytest.mark.parametrize(
    "extra, match",
    [
        ("[[obstacles]]\nshape = 'sphere'\nradius = 1.0\ncolour = 'red'\n", r"obstacles\[0\].colour: unknown key"),
        ("[[obstacles]]\nshape = 'cone'\n", r"obstacles\[0\].shape: unknown shape 'cone'"),
        ("[[obstacles]]\nshape = 'box'\nradius = 1.0\n", r"obstacles\[0\].radius: not a parameter of shape 'box'"),
        ("[[obstacles]]\nshape = 'box'\n", r"obstacles\[0\].half_extents: missing required key"),
        ("[[obstacles]]\nshape = 'sphere'\nradius = -1.0\n", r"obstacles\[0\].radius: must be > 0"),
        ("[[obstacles]]\nshape = 'sphere'\nradius = 1.0\nsubdivisions = 1.5\n",
         r"obstacles\[0\].subdivisions: expected an integer"),
        ("[[obstacles]]\nradius = 1.0\n", r"obstacles\[0\]: give exactly one of 'shape' and 'mesh'"),
        ("[[obstacles]]\nmesh = 'missing.obj'\n", r"obstacles\[0\].mesh: file not found"),
        ("[[obstacles]]\nmesh = { path = 'x.obj', prim = '/a' }\n", r"obstacles\[0\].mesh.prim: unknown key"),
        ("[[obstacles]]\nshape = 'funnel'\nmotion = [[0.0, [0, 0, 0], [0, 0, 1, 1]]]\n",
         r"obstacles\[0\].motion\[0\]\[2\]: must be a unit quaternion"),
        ("[[obstacles]]\nshape = 'funnel'\nmotion = [[0.0, [0, 0, 0]]]\n", r"obstacles\[0\].motion\[0\]: expected"),
        ("[[obstacles]]\nshape = 'funnel'\nname = 'x'\n[[obstacles]]\nshape = 'funnel'\nname = 'x'\n",
         r"obstacles\[1\]: obstacle name 'x' is used twice"),
        ("[[obstacles]]\nshape = 'funnel'\nname = '1x'\n", r"obstacles\[0\]: obstacle name '1x' is not a valid"),
        ("obstacles = 3\n", r"obstacles: expected an array of tables"),
        ("[collision]\nthickness = 0.0\n", r"collision.thickness: must be > 0.0"),
        ("[collision]\nself_collision = 1\n", r"collision.self_collision: expected a boolean"),
        ("[collision]\nradius = 1.0\n", r"collision.radius: unknown key"),
    ],
)
def test_scene_obstacle_errors(extra, match, tmp_path):
    # Top-level keys must come before any table in TOML, so an "obstacles = 3" line goes first.
    text = extra + _SCENE if extra.startswith("obstacles =") else _SCENE + extra
    with pytest.raises(ValueError, match=match):
        scene_from_toml(text, source="t.toml", base_dir=tmp_path)


def test_embedded_drape_sphere_scene():
    scene = load_scene("drape-sphere")
    m = scene.model_builder.finalize("cpu")
    assert m.obstacle_names == ["ball"] and m.collision.obstacles and not m.collision.self_collision
    # The cloth starts above the sphere, not inside it.
    assert m.particle_x0.numpy()[:, 2].min() > np.linalg.norm(wc.obstacle_points_numpy(m, 0.0), axis=1).max()


# -- USD ---------------------------------------------------------------------------------------------------------------


def test_usd_time_sampled_obstacles(tmp_path):
    from pxr import Usd, UsdGeom

    m = _obstacle_model(wp.float64)
    frames_t = [0.0, 0.25, 0.5, 0.75]
    cloth = [m.particle_x0.numpy()] * len(frames_t)
    obstacles = wc.obstacle_meshes_numpy(m, frames_t)
    assert obstacles[0][1].ndim == 2 and obstacles[1][1].shape[0] == len(frames_t)  # static box, moving sphere
    path = tmp_path / "out.usda"
    write_usd(path, triangles=m.triangles_np, frames=cloth, fps=4.0, obstacles=obstacles)

    stage = Usd.Stage.Open(str(path))
    box = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Obstacles/crate"))
    assert box.GetPointsAttr().GetNumTimeSamples() == 0
    np.testing.assert_allclose(np.array(box.GetPointsAttr().Get()), wc.obstacle_points_numpy(m, 0.0)[:8], atol=1e-6)
    ball = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Obstacles/obstacle1"))
    attr = ball.GetPointsAttr()
    assert list(attr.GetTimeSamples()) == [0.0, 1.0, 2.0, 3.0]
    for k, t in enumerate(frames_t):
        pts = np.array(attr.Get(Usd.TimeCode(k)))
        np.testing.assert_allclose(pts, wc.obstacle_points_numpy(m, t)[8:], atol=1e-6)
        extent = np.array(ball.GetExtentAttr().Get(Usd.TimeCode(k)))
        np.testing.assert_allclose(extent, [pts.min(axis=0), pts.max(axis=0)])
    np.testing.assert_array_equal(
        np.array(ball.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), m.obstacle_triangles_np[12:] - 8
    )

    with pytest.raises(ValueError, match="obstacle 'obstacle1' has 4 frames of vertices, the cloth has 2"):
        write_usd(path, triangles=m.triangles_np, frames=cloth[:2], fps=4.0, obstacles=obstacles)


def test_cli_writes_scene_obstacles(tmp_path):
    from pxr import Usd, UsdGeom

    from warpcloth.cli import main

    scene = tmp_path / "scene.toml"
    scene.write_text(_SCENE + """
[[obstacles]]
shape = "plane"
name = "floor"
pos = [0.0, 0.0, -5.0]

[[obstacles]]
shape = "box"
half_extents = [0.1, 0.1, 0.1]
pos = [0.0, 0.0, -3.0]
motion = [[0.0, [0, 0, 0], [0, 0, 0, 1]], [1.0, [1.0, 0, 0], [0, 0, 0, 1]]]
""")
    out = tmp_path / "out.usda"
    assert main(["simulate", str(scene), "--usd", str(out), "--device", "cpu"]) == 0
    stage = Usd.Stage.Open(str(out))
    floor = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Obstacles/floor")).GetPointsAttr()
    assert floor.GetNumTimeSamples() == 0
    np.testing.assert_allclose(np.array(floor.Get())[:, 2], -5.0)
    box = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Obstacles/obstacle1")).GetPointsAttr()
    assert list(box.GetTimeSamples()) == [0.0, 1.0, 2.0]
    # The box slides 1 m/s along x: 0.01 m per 0.01 s step.
    shift = np.array(box.Get(Usd.TimeCode(2)))[:, 0] - np.array(box.Get(Usd.TimeCode(0)))[:, 0]
    np.testing.assert_allclose(shift, 0.02, atol=1e-6)
