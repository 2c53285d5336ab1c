
import numpy as np
import pytest
from conftest import seed_data

from warpcloth.mesh_io import TriangleMesh, grid_mesh, load_obj, load_usd_mesh, validate_triangles


def _signed_uv_areas(tri_uv):
    d1 = tri_uv[:, 1] - tri_uv[:, 0]
    d2 = tri_uv[:, 2] - tri_uv[:, 0]
    return 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])


QUAD_OBJ = """\
# two unit quads side by side, the second written with negative indices
o cloth
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vn 0 0 1
s off
f 1/1/1 2/2/1 3/3/1 4/4/1
v 2 0 0
v 2 1 0
vt 2 0
vt 2 1
f 2/2 -2/-2 -1/-1 3/3
"""


def test_obj_quads_vt_negative_indices(tmp_path):
    path = tmp_path / "quads.obj"
    path.write_text(QUAD_OBJ)
    mesh = load_obj(path)
    assert mesh.positions.shape == (6, 3) and mesh.positions.dtype == np.float64
    assert mesh.triangles.dtype == np.int32
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    assert mesh.tri_uv.shape == (4, 3, 2)
    np.testing.assert_array_equal(mesh.tri_uv[2], [[1, 0], [2, 0], [2, 1]])
    np.testing.assert_allclose(_signed_uv_areas(mesh.tri_uv), 0.5)
    assert mesh.velocities is None

    scaled = load_obj(path, scale=0.5)
    np.testing.assert_allclose(scaled.positions, 0.5 * mesh.positions)
    np.testing.assert_allclose(scaled.tri_uv, 0.5 * mesh.tri_uv)


def test_obj_vertex_normal_forms_and_no_vt(tmp_path):
    path = tmp_path / "plain.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 1\nvn 0 0 1\nf 1//1 2//1 3//1\nf 2 4 3\n")
    mesh = load_obj(path)
    assert mesh.tri_uv is None
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2], [1, 3, 2]])


def test_obj_round_trip_of_grid(tmp_path):
    grid = grid_mesh(3, 2, 1.5, 1.0)
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in grid.positions.tolist()]
    uv = grid.tri_uv.reshape(-1, 2)
    lines += [f"vt {u!r} {v!r}" for u, v in uv.tolist()]
    for t, tri in enumerate(grid.triangles):
        lines.append("f " + " ".join(f"{i + 1}/{3 * t + k + 1}" for k, i in enumerate(tri)))
    path = tmp_path / "grid.obj"
    path.write_text("\n".join(lines) + "\n")
    mesh = load_obj(path)
    np.testing.assert_array_equal(mesh.positions, grid.positions)
    np.testing.assert_array_equal(mesh.triangles, grid.triangles)
    np.testing.assert_array_equal(mesh.tri_uv, grid.tri_uv)


def test_obj_arcsim_velocity_lines(tmp_path):
    path = tmp_path / "arcsim.obj"
    path.write_text(
        "vt 0 0\nvt 1 0\nvt 0 1\nv 0 0 0\nny 0 0 0\nnv 0.1 0 0\nv 1 0 0\nny 1 0 0\nnv 0 0.2 0\n"
        "v 0 1 0\nny 0 1 0\nnv 0 0 0.3\nf 1/1 2/2 3/3\n"
    )
    mesh = load_obj(path)
    np.testing.assert_array_equal(mesh.velocities, np.diag([0.1, 0.2, 0.3]))


@pytest.mark.parametrize(
    "text, match",
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", r":4: vertex index 4 out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n", r":4: vertex index -4 out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r":4: vertex index 0 is not valid"),
        ("v 0 0\n", r":1: 'v' needs 3 to 4 numbers"),
        ("v 0 0 a\n", r":1: 'v' has a non-numeric value"),
        ("v 0 0 0\nv 1 0 0\nf 1 2\n", r":3: face needs at least 3 corners"),
        ("v 0 0 0\nl 1 2\n", r":2: unsupported OBJ directive 'l'"),
        ("vt 0 0 1\n", r":1: 3D material coordinate"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2 3\n", r":5: face has vt indices on some corners"),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\nf 2 4 3\n",
            r":9: face has no vt indices but the face on line 8 had",
        ),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nnv 0 0 0\nf 1 2 3\n", r"1 'nv' lines for 3 'v' lines"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 2\n", r"triangle 0 \[0, 1, 1\] repeats a vertex"),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/3 3/2\n",
            r"triangle 0 .*negative \(inverted winding\)",
        ),
    ],
)
def test_obj_errors_name_file_and_line(tmp_path, text, match):
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as info:
        load_obj(path)
    assert str(path) in str(info.value)


def test_validate_triangles_errors():
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1]], dtype=float)
    with pytest.raises(ValueError, match=r"triangle 1 \[1, 3, 7\]: index 7 out of range"):
        validate_triangles(pos, np.array([[0, 1, 2], [1, 3, 7]]))
    with pytest.raises(ValueError, match=r"triangle 0 \[-1, 1, 2\]: index -1"):
        validate_triangles(pos, np.array([[-1, 1, 2]]))
    with pytest.raises(ValueError, match=r"triangle 0 \[2, 1, 2\] repeats"):
        validate_triangles(pos, np.array([[2, 1, 2]]))
    bad = pos.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"vertex 3 has a non-finite position"):
        validate_triangles(bad, np.array([[0, 1, 2]]))
    # Edge (0, 1) shared by three triangles.
    tris = np.array([[0, 1, 2], [1, 0, 4], [0, 1, 3]])
    with pytest.raises(ValueError, match=r"non-manifold edge \(0, 1\) is shared by 3 triangles: \[0, 1, 2\]"):
        validate_triangles(pos, tris)
    uv = np.array([[[0, 0], [1, 0], [0, 1]], [[0, 0], [1, 0], [2, 0]]], dtype=float)
    with pytest.raises(ValueError, match=r"triangle 1 \[1, 3, 2\]: material-space area is zero"):
        validate_triangles(pos, np.array([[0, 1, 2], [1, 3, 2]]), uv)
    uv_nan = uv.copy()
    uv_nan[0, 1, 0] = np.inf
    with pytest.raises(ValueError, match=r"triangle 0: non-finite material"):
        validate_triangles(pos, np.array([[0, 1, 2], [1, 3, 2]]), uv_nan)
    with pytest.raises(ValueError, match=r"tri_uv must have shape \(2, 3, 2\)"):
        validate_triangles(pos, np.array([[0, 1, 2], [1, 3, 2]]), uv[:1])


@pytest.mark.parametrize("res_x, res_y", [(1, 1), (3, 2), (16, 16)])
def test_grid_counts_orientation_and_areas(res_x, res_y):
    g = grid_mesh(res_x, res_y, 2.0, 1.0)
    assert g.positions.shape == ((res_x + 1) * (res_y + 1), 3)
    assert g.triangles.shape == (2 * res_x * res_y, 3) and g.triangles.dtype == np.int32
    np.testing.assert_array_equal(g.positions[:, 2], 0.0)
    # Row-major, x fastest.
    np.testing.assert_allclose(g.positions[1, :2], [2.0 / res_x, 0.0])
    np.testing.assert_allclose(g.positions[res_x + 1, :2], [0.0, 1.0 / res_y])
    np.testing.assert_allclose(g.tri_uv, g.positions[g.triangles][:, :, :2])
    areas = _signed_uv_areas(g.tri_uv)
    np.testing.assert_allclose(areas, 1.0 / (res_x * res_y))  # every triangle counterclockwise from +z
    assert areas.sum() == pytest.approx(2.0)
    validate_triangles(g.positions, g.triangles, g.tri_uv)


def test_grid_alternates_diagonals():
    g = grid_mesh(2, 1, 2.0, 1.0)
    # Cell (0, 0) is split along 0-4, cell (1, 0) along 2-4.
    edges = {tuple(sorted(e)) for t in g.triangles.tolist() for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    assert (0, 4) in edges and (2, 4) in edges and (1, 3) not in edges and (1, 5) not in edges


@pytest.mark.parametrize(
    "args, match", [((0, 1, 1.0, 1.0), "res_x"), ((1, 1, 1.0, -1.0), "size_y"), ((1.5, 1, 1.0, 1.0), "res_x")]
)
def test_grid_errors(args, match):
    with pytest.raises(ValueError, match=match):
        grid_mesh(*args)


def _write_usd_mesh(path, *, interpolation, left_handed=False, indexed=False):
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Xform.Define(stage, "/Root")
    xform = UsdGeom.Xform.Define(stage, "/Root/Parent")
    xform.AddTranslateOp().Set(Gf.Vec3d(1.0, 2.0, 3.0))
    stage.DefinePrim("/Root/Parent/NotAMesh", "Xform")
    mesh = UsdGeom.Mesh.Define(stage, "/Root/Parent/Cloth")
    mesh.AddScaleOp().Set(Gf.Vec3f(2.0, 2.0, 2.0))
    points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0)]
    mesh.CreatePointsAttr(points)
    mesh.CreateFaceVertexCountsAttr([4, 3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 1, 4, 2])
    if left_handed:
        mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    uv = [(p[0], p[1]) for p in points]
    pv_api = UsdGeom.PrimvarsAPI(mesh)
    if interpolation == "vertex":
        pv = pv_api.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
        pv.Set(Vt.Vec2fArray(uv))
    else:
        fv = [uv[i] for i in [0, 1, 2, 3, 1, 4, 2]]
        pv = pv_api.CreatePrimvar("uv", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
        if indexed:
            pv.Set(Vt.Vec2fArray(uv))
            pv.SetIndices(Vt.IntArray([0, 1, 2, 3, 1, 4, 2]))
        else:
            pv.Set(Vt.Vec2fArray(fv))
    stage.GetRootLayer().Save()


@pytest.mark.parametrize("interpolation, indexed", [("vertex", False), ("faceVarying", False), ("faceVarying", True)])
def test_usd_mesh_round_trip(tmp_path, interpolation, indexed):
    path = tmp_path / "mesh.usda"
    _write_usd_mesh(path, interpolation=interpolation, indexed=indexed)
    mesh = load_usd_mesh(path)
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    # Local scale 2, then the parent's translation (1, 2, 3).
    np.testing.assert_allclose(mesh.positions[4], [5.0, 2.0, 3.0])
    np.testing.assert_allclose(mesh.positions[2], [3.0, 4.0, 3.0])
    np.testing.assert_allclose(mesh.tri_uv[2], [[1, 0], [2, 0], [1, 1]])
    np.testing.assert_allclose(_signed_uv_areas(mesh.tri_uv), 0.5)
    assert mesh.positions.dtype == np.float64


def test_usd_mesh_left_handed_and_prim_errors(tmp_path):
    path = tmp_path / "mesh.usda"
    _write_usd_mesh(path, interpolation="faceVarying", left_handed=True)
    # Reversed to counterclockwise; a leftHanded mesh with counterclockwise uvs is then inverted -> error.
    with pytest.raises(ValueError, match="inverted"):
        load_usd_mesh(path)
    mesh = load_usd_mesh(path, validate=False)
    np.testing.assert_array_equal(mesh.triangles, [[0, 2, 1], [0, 3, 2], [1, 2, 4]])
    with pytest.raises(ValueError, match="no prim at '/Nope'"):
        load_usd_mesh(path, prim_path="/Nope")
    with pytest.raises(ValueError, match="not a Mesh"):
        load_usd_mesh(path, prim_path="/Root/Parent/NotAMesh")
    empty = tmp_path / "empty.usda"
    from pxr import Usd

    empty_stage = Usd.Stage.CreateNew(str(empty))
    empty_stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match="no UsdGeom.Mesh"):
        load_usd_mesh(empty)


def test_triangle_mesh_counts():
    g = grid_mesh(2, 3, 1.0, 1.0)
    assert isinstance(g, TriangleMesh) and g.vertex_count == 12 and g.triangle_count == 12


def test_demo_wind_mesh():
    mesh = load_obj(seed_data("meshes/demo_wind.obj"))
    assert mesh.positions.shape == (289, 3)
    assert mesh.triangles.shape == (512, 3)
    assert mesh.tri_uv.shape == (512, 3, 2)
    assert mesh.velocities.shape == (289, 3)
    # A 1 m square in material space, every triangle counterclockwise.
    areas = _signed_uv_areas(mesh.tri_uv)
    assert np.all(areas > 0) and areas.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(mesh.tri_uv.reshape(-1, 2).min(axis=0), [0, 0])
    np.testing.assert_allclose(mesh.tri_uv.reshape(-1, 2).max(axis=0), [1, 1])
