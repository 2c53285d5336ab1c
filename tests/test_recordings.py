"""Synthetic recordings (warpcloth.recordings): uniform surface sampling, a camera's visibility with self-occlusion,
noise, dropped frames, hidden markers, and point-cloud and marker files on disk with their refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from warpcloth.mesh_io import grid_mesh
from warpcloth.preview import Camera
from warpcloth.recordings import (
    check_markers,
    look_at,
    marker_recording,
    point_cloud_recording,
    read_markers,
    read_point_clouds,
    sample_surface,
    visible,
    write_markers,
    write_point_clouds,
)


def sheet(res=16, size=1.0):
    m = grid_mesh(res, res, size, size)
    return m.positions, m.triangles


def folded(res=16, gap=0.02):
    """A unit sheet folded along x = 0.5: the half x > 0.5 laid back over the half x < 0.5, gap [m] above it."""
    x, tris = sheet(res)
    x = x.copy()
    over = x[:, 0] > 0.5 + 1e-9
    x[over, 0] = 1.0 - x[over, 0]
    x[over, 2] = gap
    return x, tris, over


def above(height=5.0, fov=30.0):
    return look_at((0.5, 0.5, height), (0.5, 0.5, 0.0), fov=fov)


def below(height=5.0, fov=30.0):
    return look_at((0.5, 0.5, -height), (0.5, 0.5, 0.0), fov=fov)


# sampling


def test_samples_are_uniform_over_a_unit_square():
    x, tris = sheet(8)
    points, face, bary = sample_surface(x, tris, 40_000, np.random.default_rng(1))
    assert points.shape == (40_000, 3) and face.shape == (40_000,) and bary.shape == (40_000, 3)
    sigma = np.sqrt(1.0 / 12.0 / 40_000)  # of the mean of a uniform variable on [0, 1]
    assert np.all(np.abs(points[:, :2].mean(axis=0) - 0.5) < 4.0 * sigma)
    assert np.all(np.abs(points[:, :2].std(axis=0) - np.sqrt(1.0 / 12.0)) < 0.01)
    assert np.allclose(np.einsum("pk,pkc->pc", bary, x[tris[face]]), points)
    assert np.all(bary >= 0.0) and np.allclose(bary.sum(axis=1), 1.0)
    assert np.allclose(bary.mean(axis=0), 1.0 / 3.0, atol=0.01)  # uniform inside each triangle


def test_counts_per_triangle_are_proportional_to_area():
    x, tris = sheet(6)
    x = x.copy()
    x[:, 0] = x[:, 0] ** 2  # triangles of unequal areas, 0.0007 to 0.025 m^2
    x[:, 2] = 0.3 * x[:, 1] ** 2  # not flat either
    count = 60_000
    _, face, _ = sample_surface(x, tris, count, np.random.default_rng(2))
    area = 0.5 * np.linalg.norm(np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]]), axis=1)
    expected = count * area / area.sum()
    counts = np.bincount(face, minlength=len(tris))
    assert area.max() / area.min() > 10.0
    assert np.all(np.abs(counts - expected) < 4.5 * np.sqrt(expected)), np.max(np.abs(counts - expected)
                                                                            / np.sqrt(expected))
    chi2 = float(np.sum((counts - expected) ** 2 / expected))
    assert chi2 < len(tris) + 5.0 * np.sqrt(2.0 * len(tris))


def test_a_zero_area_triangle_is_never_sampled():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], dtype=float)
    tris = np.array([[0, 1, 2], [0, 1, 3]])  # the second lies on a line
    _, face, _ = sample_surface(x, tris, 5000, np.random.default_rng(3))
    assert np.all(face == 0)


# visibility


def test_a_flat_sheet_seen_from_above_or_below_is_all_visible():
    x, tris = sheet()
    points = sample_surface(x, tris, 2000, np.random.default_rng(4))[0]
    assert visible(points, x, tris, above()).all()
    assert visible(points, x, tris, below()).all()  # its back is a surface too


def test_points_outside_the_picture_or_behind_the_camera_are_not_seen():
    x, tris = sheet()
    points = sample_surface(x, tris, 2000, np.random.default_rng(5))[0]
    narrow = look_at((0.5, 0.5, 1.0), (0.5, 0.5, 0.0), fov=20.0, width=100, height=100)  # a 0.35 m square
    seen = visible(points, x, tris, narrow)
    assert np.array_equal(seen, np.all(np.abs(points[:, :2] - 0.5) < np.tan(np.radians(10.0)), axis=1))
    assert not visible(points, x, tris, look_at((0.5, 0.5, 1.0), (0.5, 0.5, 2.0))).any()


def test_the_lower_of_two_parallel_sheets_is_hidden_where_the_upper_covers_it():
    lower, tris = sheet()
    upper = lower.copy()
    upper[:, 0] *= 0.5  # over x in [0, 0.5]
    upper[:, 2] = 0.01
    both = np.concatenate([lower, upper])
    both_tris = np.concatenate([tris, tris + len(lower)])
    rng = np.random.default_rng(6)
    low_points = sample_surface(lower, tris, 3000, rng)[0]
    up_points = sample_surface(upper, tris, 1000, rng)[0]
    camera = above(height=20.0, fov=5.0)  # the covered strip's edge moves by 0.01 * 0.5 / 20 m at most
    seen = visible(np.concatenate([low_points, up_points]), both, both_tris, camera)
    low_seen, up_seen = seen[:3000], seen[3000:]
    assert up_seen.all()
    assert not low_seen[low_points[:, 0] < 0.499].any()
    assert low_seen[low_points[:, 0] > 0.501].all()
    # from below the upper sheet is the hidden one
    assert not visible(up_points, both, both_tris, below(height=20.0, fov=5.0)).any()


def test_a_folded_sheet_hides_its_lower_layer_from_above_and_its_upper_layer_from_below():
    x, tris, over = folded()
    points, face, _ = sample_surface(x, tris, 4000, np.random.default_rng(7))
    top = over[tris[face]].all(axis=1)  # on the folded-back half
    bottom = (~over[tris[face]]).all(axis=1)
    inner = points[:, 0] < 0.5 - 1.0 / 16.0 - 0.01  # clear of the crease's triangles
    camera_up, camera_down = above(height=20.0, fov=5.0), below(height=20.0, fov=5.0)
    from_above, from_below = visible(points, x, tris, camera_up), visible(points, x, tris, camera_down)
    assert from_above[top].all() and not from_above[bottom & inner].any()
    assert from_below[bottom].all() and not from_below[top & inner].any()


def test_an_obstacle_occludes_the_cloth():
    x, tris = sheet()
    plate = np.array([[-0.1, -0.1, 0.2], [0.5, -0.1, 0.2], [0.5, 1.1, 0.2], [-0.1, 1.1, 0.2]])
    plate_tris = np.array([[0, 1, 2], [0, 2, 3]])
    points = sample_surface(x, tris, 2000, np.random.default_rng(8))[0]
    seen = visible(points, x, tris, above(height=20.0, fov=5.0), obstacles=[("plate", plate, plate_tris)])
    assert not seen[points[:, 0] < 0.49].any() and seen[points[:, 0] > 0.51].all()



def test_a_moving_obstacle_occludes_in_each_frame_where_it_is():
    x, tris = sheet()
    plate = np.array([[-0.1, -0.1, 0.2], [0.5, -0.1, 0.2], [0.5, 1.1, 0.2], [-0.1, 1.1, 0.2]])
    moving = np.stack([plate, plate + [0.6, 0.0, 0.0]])  # over the left half, then over the right
    clouds = point_cloud_recording(np.stack([x, x]), tris, points=1000, noise=0.0, drop=0.0,
                                   camera=above(height=20.0, fov=5.0), rng=np.random.default_rng(16),
                                   obstacles=[("plate", moving, np.array([[0, 1, 2], [0, 2, 3]]))])
    assert clouds[0][:, 0].min() > 0.49 and clouds[1][:, 0].max() < 0.51


# recordings


def trajectory(frames=25, res=16):
    x, tris = sheet(res)
    t = np.linspace(0.0, 1.0, frames)[:, None, None]
    wave = 0.05 * np.sin(2.0 * np.pi * (x[None, :, 0:1] + t))
    return x[None] + np.concatenate([np.zeros_like(wave), np.zeros_like(wave), wave], axis=2), tris


def test_point_cloud_noise_has_the_standard_deviation_asked():
    x, tris = sheet()
    frames = np.stack([x, x, x])  # flat at z = 0: a point's z is its noise
    clouds = point_cloud_recording(frames, tris, points=20_000, noise=0.002, drop=0.0,
                                   rng=np.random.default_rng(9))
    z = np.concatenate([c[:, 2] for c in clouds])
    assert abs(z.std() / 0.002 - 1.0) < 0.03 and abs(z.mean()) < 1e-4
    exact = point_cloud_recording(frames, tris, points=100, noise=0.0, drop=0.0, rng=np.random.default_rng(9))
    assert all(np.all(c[:, 2] == 0.0) for c in exact)


def test_dropped_frames_are_none_and_never_the_first():
    frames, tris = trajectory()
    for seed in range(5):
        clouds = point_cloud_recording(frames, tris, points=50, drop=0.1, rng=np.random.default_rng(seed))
        assert len(clouds) == 25 and sum(c is None for c in clouds) == 3  # round(2.5) up
        assert clouds[0] is not None and all(c.shape == (50, 3) for c in clouds if c is not None)
    assert all(c is not None for c in point_cloud_recording(frames, tris, points=10, drop=0.0,
                                                            rng=np.random.default_rng(0)))
    with pytest.raises(ValueError, match="drop 0.99 of 25 frames drops 25; at most 24"):
        point_cloud_recording(frames, tris, drop=0.99, rng=np.random.default_rng(0))


def test_a_camera_recording_holds_the_points_asked_all_on_the_seen_side():
    x, tris, over = folded()
    frames = np.stack([x, x])
    clouds = point_cloud_recording(frames, tris, points=2000, noise=0.0, drop=0.0,
                                   camera=above(height=20.0, fov=5.0), rng=np.random.default_rng(10))
    for cloud in clouds:
        assert cloud.shape == (2000, 3)
        inner = cloud[:, 0] < 0.5 - 1.0 / 16.0 - 0.01
        assert np.allclose(cloud[inner, 2], 0.02)  # only the upper layer where the fold covers the lower
    with pytest.raises(ValueError, match="the camera sees none of the cloth in frame 0"):
        point_cloud_recording(frames, tris, camera=look_at((0.5, 0.5, 1.0), (0.5, 0.5, 2.0)),
                              rng=np.random.default_rng(0))


def test_same_seed_same_recording():
    frames, tris = trajectory(frames=6)
    camera = look_at((2.0, -1.0, 1.5), (0.5, 0.5, 0.0))

    def record(seed):
        rng = np.random.default_rng(seed)
        return (point_cloud_recording(frames, tris, points=300, camera=camera, drop=0.2, rng=rng),
                marker_recording(frames, tris, noise=0.001, rng=rng))

    (a, ma), (b, mb), (c, _) = record(11), record(11), record(12)
    assert all((p is None and q is None) or np.array_equal(p, q) for p, q in zip(a, b))
    assert all(np.array_equal(p, q, equal_nan=True) for p, q in zip(ma, mb))
    assert not all(p is not None and q is not None and np.array_equal(p, q) for p, q in zip(a, c))


def test_markers_are_spread_followed_and_hidden_in_the_share_asked():
    frames, tris = trajectory()
    rec = marker_recording(frames, tris, markers=12, hidden=0.2, rng=np.random.default_rng(13))
    assert rec.triangles.shape == (12,) and rec.barycentric.shape == (12, 3) and rec.positions.shape == (25, 12, 3)
    nan = np.isnan(rec.positions)
    assert np.array_equal(nan.all(axis=2), nan.any(axis=2))  # hidden on every axis or none
    assert np.all(nan[..., 0].sum(axis=1) == 2)  # 0.2 of 12, rounded, in each frame
    assert len({tuple(np.flatnonzero(row)) for row in nan[..., 0]}) > 1  # not the same markers in every frame
    truth = np.einsum("mk,fmkc->fmc", rec.barycentric, frames[:, tris[rec.triangles]])
    assert np.allclose(rec.positions[~nan], truth[~nan])
    start = truth[0]
    gaps = np.linalg.norm(start[:, None] - start[None], axis=2) + np.eye(12)
    assert gaps.min() > 0.2  # farthest-point sampling: 12 markers on a unit square keep apart
    fifth = marker_recording(frames, tris, markers=13, hidden=0.2, rng=np.random.default_rng(13))
    assert np.all(np.isnan(fifth.positions[..., 0]).sum(axis=1) == 3)  # 2.6 rounds to 3
    noisy = marker_recording(frames, tris, markers=12, hidden=0.0, noise=0.003, rng=np.random.default_rng(13))
    assert not np.isnan(noisy.positions).any()
    assert abs((noisy.positions - truth).std() / 0.003 - 1.0) < 0.1  # 2,700 draws


# files


def test_point_clouds_round_trip_through_ply_and_npy(tmp_path):
    frames, tris = trajectory(frames=12)
    clouds = point_cloud_recording(frames, tris, points=64, drop=0.25, rng=np.random.default_rng(14))
    kept = [i for i, c in enumerate(clouds) if c is not None]
    for kind in (".ply", ".npy"):
        paths = write_point_clouds(tmp_path / kind[1:], clouds, kind=kind)
        assert [p.name for p in paths] == [f"frame_{i:04d}{kind}" for i in kept]
        indices, back = read_point_clouds(tmp_path / kind[1:])
        assert indices.tolist() == kept and indices.dtype == np.int64
        assert all(np.array_equal(b, clouds[i]) for i, b in zip(kept, back))


def test_files_are_in_natural_order_and_any_ply_vertex_layout_reads(tmp_path):
    for name in ("c10.npy", "c2.npy", "c9.npy", "notes.txt"):
        if name.endswith(".npy"):
            np.save(tmp_path / name, np.full((3, 3), float(name[1:-4])))
        else:
            (tmp_path / name).write_text("ignored")
    indices, clouds = read_point_clouds(tmp_path)
    assert indices.tolist() == [2, 9, 10] and [c[0, 0] for c in clouds] == [2.0, 9.0, 10.0]
    # a mesh PLY of float32 vertices with other properties and a face element, in ASCII: its x, y, z are read
    vertex = np.array([(0, 0, 0, 1, 255), (1, 0, 0, 1, 0), (0, 1, 0.5, 1, 7)],
                      dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("nz", "f4"), ("red", "u1")])
    face = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))])
    (tmp_path / "ply").mkdir()
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")],
            text=True).write(str(tmp_path / "ply" / "scan_3.ply"))
    indices, clouds = read_point_clouds(tmp_path / "ply")
    assert indices.tolist() == [3] and np.array_equal(clouds[0], [[0, 0, 0], [1, 0, 0], [0, 1, 0.5]])


def test_markers_round_trip_through_json_and_npz(tmp_path):
    frames, tris = trajectory(frames=5)
    rec = marker_recording(frames, tris, markers=6, hidden=0.3, rng=np.random.default_rng(15))
    for suffix in (".json", ".npz"):
        path = write_markers(tmp_path / f"markers{suffix}", *rec)
        back = read_markers(path, triangle_count=len(tris))
        assert back.triangles.dtype == np.int64
        assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(rec, back))
    data = json.loads((tmp_path / "markers.json").read_text())
    assert data["markers"][0] == {"triangle": int(rec.triangles[0]), "barycentric": rec.barycentric[0].tolist()}
    assert sum(p is None for row in data["positions"] for p in row) == np.isnan(rec.positions[..., 0]).sum()


def test_a_hand_written_marker_file_reads(tmp_path):
    path = tmp_path / "markers.json"
    path.write_text('{"markers": [{"triangle": 3, "barycentric": [1, 0, 0]},\n'
                    '             {"triangle": 0, "barycentric": [0.25, 0.25, 0.5]}],\n'
                    ' "positions": [[[0, 0, 1], null], [[0, 0, 1.5], [1, 2, 3]]]}')
    rec = read_markers(path)
    assert rec.triangles.tolist() == [3, 0] and rec.positions.shape == (2, 2, 3)
    assert np.isnan(rec.positions[0, 1]).all() and rec.positions[1, 1].tolist() == [1, 2, 3]


# refusals


def _write_npy(directory, name, array):
    directory.mkdir(exist_ok=True)
    np.save(directory / name, np.asarray(array))


@pytest.mark.parametrize("files, message", [
    ({}, "holds no .ply or .npy point clouds"),
    ({"a_1.npy": np.zeros((2, 3)), "a_2.ply": None}, "mixes .npy and .ply files"),
    ({"0001.obj": None}, r"holds no .ply or .npy point clouds \(.obj frames are a vertex recording"),
    ({"f_1.npy": [[0, 0, 0], [0, np.nan, 0]]}, r"f_1.npy: point 1 is not finite: \[0.0, nan, 0.0\]"),
    ({"f_1.npy": [[0, 0, 0], [0, 0, 0], [np.inf, 0, 0]]}, "f_1.npy: point 2 is not finite"),
    ({"f_1.npy": np.zeros((4, 2))}, r"f_1.npy: a point cloud must have shape \(P, 3\), P >= 1, got \(4, 2\)"),
    ({"f_1.npy": np.zeros((0, 3))}, r"f_1.npy: a point cloud must have shape .*got \(0, 3\)"),
    ({"f_1.npy": np.array(["a", "b", "c"])}, "f_1.npy: the array must hold numbers"),
    ({"first.npy": np.zeros((2, 3))}, "first.npy: a point-cloud file's name must hold its frame index"),
    ({"f_7.npy": np.zeros((2, 3)), "f_007.npy": np.zeros((2, 3))}, "name frames 7 and 7; each file needs its own"),
    ({"f_1.npy": "garbage"}, "f_1.npy: not a readable .npy array"),
    ({"f_1.ply": "garbage"}, "f_1.ply: not a readable PLY file"),
    ({"f_1.ply": "no z"}, "f_1.ply: a point-cloud PLY needs a vertex element with x, y and z, lacks z"),
    ({"f_1.ply": "inf"}, r"f_1.ply: point 1 is not finite: \[inf, 0.0, 0.0\]"),
])
def test_a_bad_point_cloud_directory_is_refused_naming_the_file(tmp_path, files, message):
    d = tmp_path / "rec"
    d.mkdir()
    for name, content in files.items():
        if name.endswith(".npy") and isinstance(content, str):
            (d / name).write_text(content)
        elif name.endswith(".npy"):
            _write_npy(d, name, content)
        elif content == "no z":
            vertex = np.zeros(2, dtype=[("x", "f4"), ("y", "f4")])
            PlyData([PlyElement.describe(vertex, "vertex")]).write(str(d / name))
        elif content == "inf":
            PlyData([PlyElement.describe(np.array([(0, 0, 0), (np.inf, 0, 0)], dtype=[(c, "f8") for c in "xyz"]),
                                         "vertex")]).write(str(d / name))
        else:
            (d / name).write_text("garbage" if content is None or content == "garbage" else content)
    with pytest.raises(ValueError, match=message):
        read_point_clouds(d)


def test_writing_point_clouds_refuses_what_it_cannot_read_back(tmp_path):
    with pytest.raises(ValueError, match="kind must be one of"):
        write_point_clouds(tmp_path / "a", [np.zeros((2, 3))], kind=".obj")
    with pytest.raises(ValueError, match="no frame to write"):
        write_point_clouds(tmp_path / "a", [None, None])
    with pytest.raises(ValueError, match=r"frame 1: point 0 is not finite"):
        write_point_clouds(tmp_path / "a", [np.zeros((2, 3)), np.full((1, 3), np.nan)])
    write_point_clouds(tmp_path / "b", [np.zeros((2, 3))], kind=".npy")
    with pytest.raises(ValueError, match="already holds recording files"):
        write_point_clouds(tmp_path / "b", [np.zeros((2, 3))])
    with pytest.raises(ValueError, match="is not a directory"):
        read_point_clouds(tmp_path / "missing")


@pytest.mark.parametrize("change, message", [
    (dict(triangles=[0, 600]), "marker 1 is on triangle 600, which the mesh lacks"),
    (dict(triangles=[0, -1]), "marker 1 has a negative triangle -1"),
    (dict(triangles=[0.0, 1.0]), "triangles must be integers of shape"),
    (dict(barycentric=[[1, 0, 0], [0.5, 0.4, 0.2]]), r"marker 1 has barycentric coordinates \[0.5, 0.4, 0.2\]"),
    (dict(barycentric=[[1.5, -0.5, 0], [1, 0, 0]]), "marker 0 has barycentric .* must be >= 0 and sum to one"),
    (dict(barycentric=[[1, 0, 0]]), r"barycentric must have shape \(2, 3\)"),
    (dict(positions=np.zeros((3, 2, 2))), r"positions must have shape \(F, 2, 3\)"),
    (dict(positions=[[[0, 0, 0], [0, 0, 0]], [[0, 0, 0], [np.nan, 0, 0]]]), "frame 1 marker 1 has position"),
    (dict(positions=[[[0, 0, np.inf], [0, 0, 0]]]), "frame 0 marker 0 has position"),
])
def test_bad_markers_are_refused_naming_the_marker(change, message):
    markers = dict(triangles=[0, 5], barycentric=[[1, 0, 0], [0.2, 0.3, 0.5]], positions=np.zeros((2, 2, 3)))
    markers.update(change)
    with pytest.raises(ValueError, match=message):
        check_markers(**markers, triangle_count=512)


@pytest.mark.parametrize("text, message", [
    ("{", "markers.json: not valid JSON"),
    ('{"markers": []}', 'markers.json: must be an object with lists "markers" and "positions"'),
    ('{"markers": [{"triangle": 1, "barycentric": [1, 0]}], "positions": []}', "markers.json: marker 0 must be"),
    ('{"markers": [{"triangle": 1, "barycentric": [1, 0, 0]}], "positions": [[[0, 0, 0]], [[0, 0]]]}',
     r"markers.json: frame 1 marker 0 must be \[x, y, z\] or null"),
    ('{"markers": [{"triangle": 1, "barycentric": [1, 0, 0]}], "positions": [[]]}',
     "markers.json: frame 0 of positions must list 1 entries"),
    ('{"markers": [{"triangle": 1, "barycentric": [0.5, 0, 0]}], "positions": [[null]]}',
     "markers.json: marker 0 has barycentric coordinates"),
    ('{"markers": [{"triangle": 9, "barycentric": [1, 0, 0]}], "positions": [[null]]}',
     r"markers.json: marker 0 is on triangle 9, which the mesh lacks \(8 triangles\)"),
])
def test_a_bad_marker_file_is_refused_naming_the_file(tmp_path, text, message):
    path = tmp_path / "markers.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_markers(path, triangle_count=8)


def test_marker_files_of_other_kinds_are_refused(tmp_path):
    with pytest.raises(ValueError, match="is not a file"):
        read_markers(tmp_path / "missing.json")
    (tmp_path / "m.csv").write_text("1,2,3")
    with pytest.raises(ValueError, match="must end in .json or .npz"):
        read_markers(tmp_path / "m.csv")
    np.savez(tmp_path / "m.npz", triangles=np.zeros(2, dtype=int))
    with pytest.raises(ValueError, match="m.npz: not an .npz of triangles, barycentric, positions"):
        read_markers(tmp_path / "m.npz")
    with pytest.raises(ValueError, match="must end in .json or .npz"):
        write_markers(tmp_path / "m.txt", [0], [[1, 0, 0]], np.zeros((1, 1, 3)))


def test_bad_arguments_are_refused_naming_them():
    x, tris = sheet(2)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="sample_surface: rng must be a numpy.random.Generator"):
        sample_surface(x, tris, 10, 0)
    with pytest.raises(ValueError, match="sample_surface: count must be an integer >= 1"):
        sample_surface(x, tris, 0, rng)
    with pytest.raises(ValueError, match="sample_surface: the surface has no area"):
        sample_surface(np.zeros_like(x), tris, 10, rng)
    with pytest.raises(ValueError, match="visible: camera must be a warpcloth.preview.Camera"):
        visible(x, x, tris, (0, 0, 1))
    with pytest.raises(ValueError, match="visible: point 1 is not finite"):
        visible([[0, 0, 0], [np.nan, 0, 0]], x, tris, above())
    with pytest.raises(ValueError, match="visible: tolerance must be > 0"):
        visible(x, x, tris, above(), tolerance=0.0)
    with pytest.raises(ValueError, match="point_cloud_recording: noise must be a finite number >= 0"):
        point_cloud_recording([x], tris, noise=-1.0, rng=rng)
    with pytest.raises(ValueError, match=r"point_cloud_recording: frame 1 vertex 0 is not finite"):
        point_cloud_recording([x, np.full_like(x, np.nan)], tris, rng=rng)
    with pytest.raises(ValueError, match=r"marker_recording: hidden must be a finite number in \[0.0, 1.0\)"):
        marker_recording([x], tris, hidden=1.0, rng=rng)
    with pytest.raises(ValueError, match="look_at: up .* is along the view direction"):
        look_at((0, 0, 0), (1, 0, 0), up=(2, 0, 0))
    assert isinstance(look_at((0, 0, 0), (0, 0, -1)), Camera)  # straight down: +y is up in the picture
