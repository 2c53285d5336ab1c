"""The preview shows what happened: each pixel the nearest surface along its ray (warpcloth.preview's ray cast), so a
cloth resting on a sphere hides the sphere's top, and a trajectory's frames are framed by one camera."""

import numpy as np
import pytest
from PIL import Image

import warpcloth as wc
from warpcloth.preview import CLOTH_BACK_COLOR, CLOTH_COLOR, Camera, render_frame

RADIUS = 0.3


def _cloth_on_sphere(height: float = RADIUS + 0.005):
    """A flat 1 m sheet (normals +z) whose centre rests just above a sphere of radius RADIUS at the origin."""
    mesh = wc.grid_mesh(16, 16, 1.0, 1.0)
    sphere = wc.sphere_mesh(RADIUS, 3)
    return mesh.triangles, mesh.positions + np.array([-0.5, -0.5, height]), [("ball", *sphere)]


def _hue_mask(rgb: np.ndarray, color) -> np.ndarray:
    """Pixels of some shade of ``color`` (the lighting scales it)."""
    rgb = rgb[..., :3].astype(np.float64) / 255.0
    scale = rgb.max(axis=-1, keepdims=True)
    hue = np.divide(rgb, scale, out=np.zeros_like(rgb), where=scale > 0.1)
    return np.all(np.abs(hue - np.array(color) / max(color)) < 0.12, axis=-1)


def test_cloth_resting_on_a_sphere_shows_cloth_at_the_spheres_top():
    triangles, positions, obstacles = _cloth_on_sphere()
    points = np.concatenate([positions, obstacles[0][1]])
    camera = Camera.framing(points, 160, 120, view=(20.0, -60.0))
    rgb, ids = render_frame(triangles, positions, obstacles, camera=camera, device="cpu")
    assert rgb.shape == (120, 160, 3) and ids.shape == (120, 160)
    top = camera.pixel([0.0, 0.0, RADIUS]).astype(int)
    assert ids[tuple(top)] == 0  # the cloth, not the sphere's cap
    assert _hue_mask(rgb[tuple(top)], CLOTH_COLOR)  # its front, the side its normals face
    # the sphere's side facing the camera, below the sheet's edge, shows the sphere
    toward = camera.eye[:2] / np.linalg.norm(camera.eye[:2])
    side = np.r_[np.sqrt(RADIUS**2 - 0.2**2) * toward, -0.2]
    assert ids[tuple(camera.pixel(side).astype(int))] == 1
    assert ids[0, 0] == -1 and np.all(rgb[0, 0] > 200)  # background


def test_render_frame_from_below_shows_the_cloths_back():
    triangles, positions, obstacles = _cloth_on_sphere()
    rgb, ids = render_frame(triangles, positions, width=80, height=60, view=(-30.0, 30.0), device="cpu")
    cloth = ids == 0
    assert cloth.sum() > 500 and np.all(_hue_mask(rgb[cloth], CLOTH_BACK_COLOR))
    assert not np.any(_hue_mask(rgb[cloth], CLOTH_COLOR))


def test_open_obstacles_are_translucent_closed_ones_opaque():
    # seen from above, a sheet under a plate (an open surface) shows through it; under a box (closed) it does not
    triangles, positions, _ = _cloth_on_sphere(height=0.0)
    box = wc.box_mesh((0.3, 0.3, 0.05))
    plate = (box[0], box[1][[i for i, t in enumerate(box[1]) if np.all(box[0][t, 2] > 0)]])  # the box's top only
    colors = {}
    for name, (verts, tris) in {"plate": plate, "box": box}.items():
        rgb, ids = render_frame(triangles, positions, [(name, verts + [0.0, 0.0, 0.2], tris)], width=60, height=60,
                                view=(90.0, 0.0), device="cpu")
        assert ids[30, 30] == 1, name  # the obstacle is the nearest surface
        colors[name] = rgb[30, 30].astype(int)
    assert colors["plate"][0] > colors["plate"][2] and colors["box"][0] < colors["box"][2], colors


def test_camera_frames_every_point():
    rng = np.random.default_rng(0)
    points = rng.uniform(-1.0, 1.0, (200, 3)) * [3.0, 0.5, 1.0] + [10.0, -2.0, 5.0]
    for view in ((20.0, -60.0), (60.0, 10.0), (90.0, 0.0), (-10.0, 200.0)):
        camera = Camera.framing(points, 200, 100, view=view, margin=0.05)
        rows, cols = camera.pixel(points).T
        assert rows.min() >= 4.9 and rows.max() <= 95.1 and cols.min() >= 9.9 and cols.max() <= 190.1, view
        assert min(rows.min(), 100 - rows.max()) < 5.1 or min(cols.min(), 200 - cols.max()) < 10.1  # tight


def test_render_frame_bad_input():
    triangles, positions, obstacles = _cloth_on_sphere()
    with pytest.raises(ValueError, match="samples must be an integer >= 1"):
        render_frame(triangles, positions, samples=0)
    with pytest.raises(ValueError, match=r"obstacle 'ball' vertices must have shape \(M, 3\)"):
        render_frame(triangles, positions, [("ball", np.zeros((2, 4, 3)), [[0, 1, 2]])])


def test_drape_preview_draws_no_sphere_through_the_cloth(tmp_path):
    """``warpcloth simulate drape-sphere --steps 20 --preview``'s last frame: the cloth rests on the sphere, so down
    the picture's middle column, which crosses the sphere's top, every pixel between the cloth's first and last is
    cloth (a painter's algorithm draws some of the sphere's cap over it)."""
    scene = wc.load_scene("drape-sphere")
    model, sim = scene.build(device="cpu")
    state, nxt, control = model.state(), model.empty_state(), model.control()
    for _ in range(20):
        sim.step(state, nxt, control)
        state, nxt = nxt, state
    x = state.particle_x.numpy()
    assert x[:, 2].max() > RADIUS  # resting on top, not through
    obstacles = wc.obstacle_meshes_numpy(model, [state.time])
    wc.write_preview(tmp_path / "drape.png", triangles=model.tri_indices.numpy(), frames=[x], fps=100.0,
                     obstacles=obstacles, size=3.0)
    with Image.open(tmp_path / "drape.png") as im:
        rgb = np.asarray(im.convert("RGB"))
    column = _hue_mask(rgb[:, rgb.shape[1] // 2], CLOTH_COLOR)
    cloth = np.flatnonzero(column)
    assert len(cloth) > 20
    span = column[cloth[0]: cloth[-1] + 1]
    assert span.mean() > 0.97, f"{np.sum(~span)} of {len(span)} pixels from the cloth's top to its bottom are not cloth"


def test_a_preview_draws_recorded_points_over_the_cloth(tmp_path):
    """Points on a flat sheet are drawn as dots of POINT_COLOUR over it; points far off fall outside the picture (the
    camera frames the cloth); without points there are none; points of another frame count or not finite are
    refused, naming the frame and point."""
    from warpcloth.preview import POINT_COLOUR

    builder = wc.ModelBuilder()
    builder.add_cloth_grid((4, 4), (0.5, 0.5), material=wc.preset("gray-interlock"))
    model = builder.finalize("cpu")
    x, tris = model.particle_x0.numpy(), model.tri_indices.numpy()
    lo, hi = x.min(axis=0), x.max(axis=0)
    beside = lo + np.linspace(0.1, 0.9, 20)[:, None] * (hi - lo)  # along the sheet's diagonal, on it
    far = beside + 100.0

    def red_pixels(points):
        wc.write_preview(tmp_path / "p.png", triangles=tris, frames=[x], fps=50.0, points=points, size=2.0)
        with Image.open(tmp_path / "p.png") as im:
            rgb = np.asarray(im.convert("RGB")).astype(int)
        return int(np.sum(np.all(rgb == POINT_COLOUR, axis=-1)))

    assert red_pixels([beside]) >= 20 and red_pixels(None) == 0 and red_pixels([None]) == 0
    assert red_pixels([far]) == 0 and red_pixels([2.0 * x.mean(axis=0) - far]) == 0  # far ahead, far behind
    with pytest.raises(ValueError, match="points has 2 frames, the cloth 1"):
        wc.write_preview(tmp_path / "p.png", triangles=tris, frames=[x], fps=50.0, points=[beside, beside])
    with pytest.raises(ValueError, match="points of frame 0, point 3: not finite"):
        wc.write_preview(tmp_path / "p.png", triangles=tris, frames=[x], fps=50.0,
                         points=[np.where(np.arange(20)[:, None] == 3, np.nan, beside)])
