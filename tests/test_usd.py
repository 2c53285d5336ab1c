import numpy as np
import pytest

from warpcloth.mesh_io import grid_mesh, load_usd_mesh
from warpcloth.usd import read_usd_points, write_usd


def _frames(n_frames=5):
    g = grid_mesh(4, 3, 1.0, 0.75)
    rng = np.random.default_rng(0)
    frames = np.stack([g.positions + rng.normal(scale=0.1, size=g.positions.shape) for _ in range(n_frames)])
    return g, frames


@pytest.mark.parametrize("suffix", [".usda", ".usdc", ".usd"])
def test_write_read_round_trip(tmp_path, suffix):
    from pxr import Usd, UsdGeom

    g, frames = _frames()
    obstacle = grid_mesh(1, 1, 2.0, 2.0)
    path = tmp_path / f"out{suffix}"
    floor = ("floor", obstacle.positions, obstacle.triangles)
    write_usd(path, triangles=g.triangles, frames=list(frames), fps=25.0, obstacles=[floor])

    back = read_usd_points(path)
    assert back.shape == frames.shape
    np.testing.assert_array_equal(back, frames.astype(np.float32).astype(np.float64))

    stage = Usd.Stage.Open(str(path))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == len(frames) - 1
    assert stage.GetTimeCodesPerSecond() == 25.0 and stage.GetFramesPerSecond() == 25.0
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Cloth"))
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [3] * len(g.triangles)
    np.testing.assert_array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), g.triangles)
    extent = np.array(mesh.GetExtentAttr().Get(Usd.TimeCode(3)))
    np.testing.assert_allclose(extent, [frames[3].min(axis=0), frames[3].max(axis=0)], rtol=1e-6)
    floor_points = read_usd_points(path, prim="/World/Obstacles/floor")
    np.testing.assert_array_equal(floor_points[0], obstacle.positions)

    # The cloth prim reads back as a mesh (first time sample).
    m = load_usd_mesh(path, prim_path="/World/Cloth")
    np.testing.assert_allclose(m.positions, frames[0], atol=1e-6)


def test_overwrite_while_open(tmp_path):
    g, frames = _frames()
    path = tmp_path / "out.usda"
    write_usd(path, triangles=g.triangles, frames=frames, fps=50.0)
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))  # keep the layer open while rewriting
    write_usd(path, triangles=g.triangles, frames=frames[:2] + 1.0, fps=50.0)
    np.testing.assert_allclose(read_usd_points(path), frames[:2] + 1.0, atol=1e-6)
    del stage


def test_write_usd_errors(tmp_path):
    g, frames = _frames()
    path = tmp_path / "x.usda"
    with pytest.raises(ValueError, match="frames is empty"):
        write_usd(path, triangles=g.triangles, frames=[], fps=50.0)
    bad = frames.copy()
    bad[2, 7, 1] = np.nan
    with pytest.raises(ValueError, match="frame 2 vertex 7 is not finite"):
        write_usd(path, triangles=g.triangles, frames=bad, fps=50.0)
    with pytest.raises(ValueError, match="frame 1 has shape"):
        write_usd(path, triangles=g.triangles, frames=[frames[0], frames[1][:-1]], fps=50.0)
    with pytest.raises(ValueError, match="fps"):
        write_usd(path, triangles=g.triangles, frames=frames, fps=0.0)
    with pytest.raises(ValueError, match="up_axis"):
        write_usd(path, triangles=g.triangles, frames=frames, fps=50.0, up_axis="X")
    tris = g.triangles.copy()
    tris[3, 2] = 99
    with pytest.raises(ValueError, match="triangle 3"):
        write_usd(path, triangles=tris, frames=frames, fps=50.0)
    with pytest.raises(ValueError, match="'my box'"):
        bad_name = ("my box", g.positions, g.triangles)
        write_usd(path, triangles=g.triangles, frames=frames, fps=50.0, obstacles=[bad_name])
    with pytest.raises(ValueError, match="used twice"):
        write_usd(
            path,
            triangles=g.triangles,
            frames=frames,
            fps=50.0,
            obstacles=[("a", g.positions, g.triangles), ("a", g.positions, g.triangles)],
        )
    assert not path.exists()
