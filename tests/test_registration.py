"""Registration of a template cloth to a recorded point cloud (warpcloth.registration): a rigidly moved grid seen
from one side, an analytically bent grid (an isometric arch), stray points, and bad input."""

import math

import numpy as np
import pytest

from warpcloth import grid_mesh
from warpcloth.recordings import look_at, sample_surface, visible
from warpcloth.registration import (
    SmoothDeformation,
    register_nonrigid,
    register_rigid,
    start_from_points,
)

N = 16
GRID = grid_mesh(N, N, 0.5, 0.5)
X, TRIS = GRID.positions, GRID.triangles


def _symmetries():
    # the square grid's eight vertex permutations that map it onto itself: points alone cannot tell them apart
    idx = np.arange((N + 1) ** 2).reshape(N + 1, N + 1)
    return [b.ravel() for a in (idx, idx.T) for b in (a, a[::-1], a[:, ::-1], a[::-1, ::-1])]


def vertex_rms(found, truth):
    """RMS vertex distance [m], in the grid's symmetric numbering that fits best."""
    return min(math.sqrt(float(np.mean(np.sum((found[p] - truth) ** 2, axis=1)))) for p in _symmetries())


def rotation(axis, angle):
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def seen_cloud(y, eye, rng, count=2000, noise=0.002, outliers=0.0):
    """count points a camera at eye sees of the cloth y, with noise [m] and a share of stray points."""
    cam = look_at(eye, y.mean(axis=0), fov=50.0)
    pts = sample_surface(y, TRIS, 4 * count, rng)[0]
    pts = pts[visible(pts, y, TRIS, cam)][:count]
    assert len(pts) == count
    pts = pts + rng.normal(0.0, noise, pts.shape)
    k = int(outliers * count)
    if k:
        lo, hi = y.min(axis=0) - 0.1, y.max(axis=0) + 0.1
        pts[rng.choice(count, k, replace=False)] = rng.uniform(lo, hi, (k, 3))
    return pts


def arch(x, radius=0.2):
    """The grid bent over a cylinder along y (no stretch: an isometry), turned by 72 degrees at each end."""
    phi = (x[:, 0] - 0.25) / radius
    return np.stack([radius * np.sin(phi), x[:, 1], radius * np.cos(phi)], axis=1) + [0.1, -0.2, 0.5]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_rigidly_moved_grid_seen_from_one_side_is_placed_within_a_few_mm(seed):
    rng = np.random.default_rng(seed)
    R, t = rotation(rng.normal(size=3), math.radians(rng.uniform(30, 150))), rng.normal(0.0, 0.3, 3)
    y = X @ R.T + t
    pts = seen_cloud(y, y.mean(axis=0) + 1.5 * R[:, 2] + 0.3 * R[:, 0], rng)
    Rf, tf, rms = register_rigid(X, TRIS, pts)
    assert np.allclose(Rf.T @ Rf, np.eye(3), atol=1e-9) and np.linalg.det(Rf) > 0
    assert rms < 0.003  # the noise is 2 mm along each axis
    assert vertex_rms(X @ Rf.T + tf, y) < 0.007


def test_a_given_start_is_refined_in_place():
    rng = np.random.default_rng(7)
    R, t = rotation([0.3, -1.0, 0.5], math.radians(120)), np.array([0.2, -0.1, 0.4])
    y = X @ R.T + t
    pts = seen_cloud(y, y.mean(axis=0) + 1.5 * R[:, 2], rng)
    Rf, tf, rms = register_rigid(X, TRIS, pts, init=(rotation([1, 0, 0], 0.05) @ R, t + 0.01))
    assert rms < 0.003 and np.sqrt(np.mean(np.sum((X @ Rf.T + tf - y) ** 2, axis=1))) < 0.007


def test_an_arch_is_recovered_by_the_nonrigid_step_with_its_edge_lengths():
    rng = np.random.default_rng(3)
    y = arch(X)
    pts = seen_cloud(y, y.mean(axis=0) + [0.2, -0.3, 1.2], rng)
    rigid = register_rigid(X, TRIS, pts)
    fit = register_nonrigid(X, TRIS, pts, rigid=rigid)
    placed = X @ rigid[0].T + rigid[1]
    assert vertex_rms(placed, y) > 0.05  # the flat template, rigidly placed, is far from the arch
    assert fit.rms < 0.003  # the noise is 2 mm along each axis
    assert vertex_rms(fit.positions, y) < 0.010
    assert np.mean(np.abs(fit.strain)) < 0.01 and np.max(np.abs(fit.strain)) < 0.05
    smooth = register_nonrigid(X, TRIS, pts, rigid=rigid, polish=0)  # the low-dimensional fit alone
    assert vertex_rms(smooth.positions, y) < 0.020
    assert smooth.coefficients.shape == (smooth.deformation.modes, 3)
    assert np.allclose(smooth.positions, placed + smooth.deformation.displacements(smooth.coefficients))


def curl(x, radius=0.3):
    """The grid hanging from its top edge (y = 0.5) and curled about it on a cylinder (an isometry): the top edge
    stays, the bottom swings 0.3 m out of the plane."""
    s = 0.5 - x[:, 1]
    return np.stack([x[:, 0], 0.5 - radius * np.sin(s / radius), -radius * (1.0 - np.cos(s / radius))], axis=1)


def test_a_held_cloth_keeps_its_held_vertices_and_the_rest_fits_the_points():
    """A cloth held at its top corners and swung: the held vertices stay exactly where the template has them (no
    rigid step moves them), the rest lands on the curled cloth; registered freely, the held vertices move."""
    rng = np.random.default_rng(8)
    held = [int(np.argmin(np.sum((X - [0.0, 0.5, 0.0]) ** 2, axis=1))),
            int(np.argmin(np.sum((X - [0.5, 0.5, 0.0]) ** 2, axis=1)))]
    y = curl(X)
    pts = seen_cloud(y, y.mean(axis=0) + [0.3, -0.2, 1.5], rng)
    fit = register_nonrigid(X, TRIS, pts, fixed=held, both_ways=True, polish=30)
    np.testing.assert_array_equal(fit.positions[held], X[held])
    assert fit.rms < 0.004  # the noise is 2 mm along each axis
    assert np.sqrt(np.mean(np.sum((fit.positions - y) ** 2, axis=1))) < 0.01
    assert vertex_rms(X, y) > 0.1  # the template is far from it
    free = register_nonrigid(X, TRIS, pts)
    assert np.linalg.norm(free.positions[held] - X[held], axis=1).max() > 0.01
    modes = SmoothDeformation(X, TRIS, 8, fixed=held)
    assert np.all(modes.basis[held] == 0.0) and np.allclose(modes.basis.T @ (modes.mass[:, None] * modes.basis),
                                                            np.eye(8), atol=1e-8)


def test_a_second_frame_is_registered_from_the_first():
    """initial: the deformation starts from the given positions (a frame's registration), not from the template."""
    rng = np.random.default_rng(9)
    held = [int(np.argmin(np.sum((X - [0.0, 0.5, 0.0]) ** 2, axis=1))),
            int(np.argmin(np.sum((X - [0.5, 0.5, 0.0]) ** 2, axis=1)))]
    y0, y1 = curl(X, 0.3), curl(X, 0.28)
    first = register_nonrigid(X, TRIS, seen_cloud(y0, y0.mean(axis=0) + [0.3, -0.2, 1.5], rng), fixed=held,
                              both_ways=True)
    pts = seen_cloud(y1, y1.mean(axis=0) + [0.3, -0.2, 1.5], rng)
    second = register_nonrigid(X, TRIS, pts, fixed=held, both_ways=True, initial=first.positions)
    assert np.sqrt(np.mean(np.sum((second.positions - y1) ** 2, axis=1))) < 0.015
    np.testing.assert_array_equal(second.positions[held], first.positions[held])


def test_five_percent_stray_points_do_not_break_it():
    rng = np.random.default_rng(4)
    y = arch(X)
    pts = seen_cloud(y, y.mean(axis=0) + [0.2, -0.3, 1.2], rng, outliers=0.05)
    fit = register_nonrigid(X, TRIS, pts)
    assert vertex_rms(fit.positions, y) < 0.015 and np.max(np.abs(fit.strain)) < 0.10


def test_start_from_points_takes_a_model_or_a_mesh():
    from warpcloth import ModelBuilder, preset

    builder = ModelBuilder()
    builder.add_cloth_mesh(GRID, material=preset("gray-interlock"))
    model = builder.finalize()
    rng = np.random.default_rng(5)
    y = X @ rotation([1, 2, 3], 1.0).T + [0.1, 0.2, 0.3]
    pts = seen_cloud(y, y.mean(axis=0) + [0.0, 0.0, 1.5], rng)
    positions = start_from_points(model, pts)
    assert positions.shape == X.shape and vertex_rms(positions, y) < 0.01
    assert vertex_rms(start_from_points(GRID, pts), y) < 0.01


def test_smooth_deformation_is_mass_orthonormal_and_starts_with_translation():
    d = SmoothDeformation(X, TRIS, 10)
    assert d.basis.shape == (len(X), 10) and d.modes == 10
    assert np.allclose(d.basis.T @ (d.mass[:, None] * d.basis), np.eye(10), atol=1e-8)
    assert np.ptp(d.basis[:, 0]) < 1e-8 and abs(d.eigenvalues[0]) < 1e-8
    assert np.all(np.diff(d.eigenvalues) >= -1e-9)
    c = np.zeros((10, 3))
    c[0] = [1.0, 0.0, 0.0]
    assert np.allclose(d.displacements(c)[:, 1:], 0.0)
    with pytest.raises(ValueError, match="coefficients"):
        d.displacements(np.zeros((9, 3)))


def _pts():
    return sample_surface(X, TRIS, 100, np.random.default_rng(0))[0]


@pytest.mark.parametrize("call, match", [
    (lambda: register_rigid(X[:, :2], TRIS, _pts()), "template_positions"),
    (lambda: register_rigid(X, TRIS[:, :2], _pts()), "template_triangles"),
    (lambda: register_rigid(X, TRIS + 1000, _pts()), "template_triangles row 0"),
    (lambda: register_rigid(X, np.zeros((1, 3), dtype=int), _pts()), "no area"),
    (lambda: register_rigid(X, TRIS, _pts()[:5]), "points holds 5 rows"),
    (lambda: register_rigid(X, TRIS, np.where(np.arange(100)[:, None] == 7, np.nan, _pts())), "points row 7"),
    (lambda: register_rigid(X, TRIS, _pts(), trim=0.0), "trim"),
    (lambda: register_rigid(X, TRIS, _pts(), init=(np.ones((3, 3)), np.zeros(3))), "init"),
    (lambda: register_rigid(X, TRIS, _pts(), iterations=0), "iterations"),
    (lambda: register_nonrigid(X, TRIS, _pts(), modes=10_000), "modes"),
    (lambda: register_nonrigid(X, TRIS, _pts(), rigid=(np.eye(3), np.zeros(2))), "rigid"),
    (lambda: register_nonrigid(X, TRIS, _pts(), preserve_lengths=-1.0), "preserve_lengths"),
    (lambda: register_nonrigid(X, TRIS, _pts(), smoothness=math.nan), "smoothness"),
    (lambda: register_nonrigid(X, TRIS, _pts(), polish=-1), "polish"),
    (lambda: register_nonrigid(X, TRIS, _pts(), fixed=[3, len(X)]), "fixed entry 1"),
    (lambda: register_nonrigid(X, TRIS, _pts(), fixed=[0.5]), "fixed must hold vertex indices"),
    (lambda: register_nonrigid(X, TRIS, _pts(), initial=X[:-1]), "initial has shape"),
    (lambda: register_nonrigid(X, TRIS, _pts(), initial=X, rigid=(np.eye(3), np.zeros(3))), "initial positions"),
    (lambda: SmoothDeformation(X, TRIS, len(X) - 1, fixed=[0, 1]), "modes"),
    (lambda: start_from_points("cloth", _pts()), "model_or_template"),
])
def test_bad_input_is_refused_naming_the_argument(call, match):
    with pytest.raises(ValueError, match=match):
        call()
