"""What a camera or a marker set would record of a cloth trajectory (points on the surface with noise, what one
camera sees with the occlusion, dropped frames; markers, some hidden), drawn from a ``np.random.Generator`` (same
seed, same recording); and recordings on disk: a directory of ``.ply`` or ``.npy`` point clouds, one file a frame
(:func:`read_point_clouds`), and a ``.json`` or ``.npz`` marker file (:func:`read_markers`)."""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import warp as wp

from warpcloth.kernels.recordings import unoccluded
from warpcloth.mesh_io import natural_key
from warpcloth.outputs import check_frames, check_geometry, check_triangles
from warpcloth.preview import Camera

__all__ = ["MarkerRecording", "check_markers", "frame_stride_of", "look_at", "marker_recording",
           "point_cloud_recording", "read_markers", "read_point_clouds", "sample_surface", "visible", "write_markers",
           "write_point_clouds"]

POINT_CLOUD_SUFFIXES = (".ply", ".npy")
BARYCENTRIC_TOLERANCE = 1e-6
"""How far a marker's barycentric coordinates may sum from one, or fall below zero."""
_MAX_BATCH = 200_000  # points sampled at once while filling a camera's view


class MarkerRecording(NamedTuple):
    """Markers on a cloth's surface: ``triangles`` (M,) int64, the triangle each sits on; ``barycentric`` (M, 3), its
    coordinates on that triangle's corners in their order; ``positions`` (F, M, 3) [m], recorded, NaN where hidden."""

    triangles: np.ndarray
    barycentric: np.ndarray
    positions: np.ndarray


FRAME_RATE_TOLERANCE = 1e-6
"""How far (relative) a recording's frame period may fall from a whole number of steps."""


def frame_stride_of(frame_rate: float, dt: float) -> int:
    """The steps of ``dt`` [s] between frames of a recording made at ``frame_rate`` [1/s]: its frame period must be a
    whole number of steps (within :data:`FRAME_RATE_TOLERANCE`), since a fit compares a frame with the step it falls
    on; ValueError otherwise, or for a rate or step not finite and positive, naming the step that would fit."""
    for value, name in ((frame_rate, "frame_rate"), (dt, "dt")):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) or not 0.0 < value < math.inf:
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    steps = 1.0 / (float(frame_rate) * float(dt))
    stride = max(1, round(steps))
    if abs(steps - stride) > FRAME_RATE_TOLERANCE * stride:
        raise ValueError(f"a recording at {frame_rate:g} frames/s has a frame every {steps:.4g} steps of {dt:g} s; its "
                         f"frames must fall on steps: set dt to {1.0 / (frame_rate * stride):.6g} s (a frame every "
                         f"{stride} step{'s' if stride > 1 else ''}) or another 1 / ({frame_rate:g} k) s, or resample "
                         "the recording")
    return stride


def _rng(rng, what):
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"{what}: rng must be a numpy.random.Generator (np.random.default_rng(seed)), "
                         f"got {type(rng).__name__}")
    return rng


def _integer(value, name, what, minimum=1):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{what}: {name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _number(value, name, what, low, high=math.inf, high_open=True):
    ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
    if not ok or not math.isfinite(value) or value < low or value > high or (high_open and value == high):
        bound = f"in [{low}, {high})" if high_open and high < math.inf else f">= {low}"
        raise ValueError(f"{what}: {name} must be a finite number {bound}, got {value!r}")
    return float(value)


def _tolerance(value, what):
    value = _number(value, "tolerance", what, 0.0)
    if value == 0.0:
        raise ValueError(f"{what}: tolerance must be > 0 (a point on the surface would hide itself)")
    return value


def _points(points, what):
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{what}: points must have shape (P, 3), got {p.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(p), axis=1))
    if bad.size:
        raise ValueError(f"{what}: point {int(bad[0])} is not finite: {p[bad[0]].tolist()}")
    return p


def _cumulative_area(x, tris, what):
    areas = 0.5 * np.linalg.norm(np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]]), axis=1)
    total = np.cumsum(areas)
    if not (len(total) and total[-1] > 0.0):
        raise ValueError(f"{what}: the surface has no area ({len(tris)} triangles)")
    return total / total[-1]


def _sample(x, tris, cumulative, count, rng):
    # side="right" never picks a zero-area triangle: its cumulative interval is empty
    face = np.searchsorted(cumulative, rng.random(count), side="right").astype(np.int64)
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    bary = np.stack([1.0 - u - v, u, v], axis=1)
    return np.einsum("pk,pkc->pc", bary, x[tris[face]]), face, bary


def sample_surface(positions, triangles, count: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` points uniformly distributed by area over a mesh's surface: ``(points (count, 3) [m], triangle
    (count,) int64, barycentric (count, 3))``, ``points[k] = barycentric[k] @ positions[triangles[triangle[k]]]``.
    ValueError naming a bad position, triangle, ``count`` (an integer >= 1), ``rng`` or a surface of no area."""
    what = "sample_surface"
    x = check_frames([positions], what)[0]
    tris = check_triangles(triangles, len(x), what)
    count, rng = _integer(count, "count", what), _rng(rng, what)
    return _sample(x, tris, _cumulative_area(x, tris, what), count, rng)


def look_at(eye, target, *, fov: float = 40.0, up=None, width: int = 640, height: int = 480) -> Camera:
    """A pinhole :class:`warpcloth.preview.Camera` at ``eye`` [m] looking at ``target`` [m], ``fov`` [degrees] wide
    across its ``width`` x ``height`` image, ``up`` upwards in it (default +z, or +y when looking along z).
    ValueError for ``eye == target``, ``up`` along the view or ``fov`` outside (0, 180)."""
    what = "look_at"
    eye, target = np.asarray(eye, dtype=np.float64), np.asarray(target, dtype=np.float64)
    forward = target - eye
    if up is None:
        up = (0.0, 1.0, 0.0) if abs(forward[2]) > 0.999 * np.linalg.norm(forward) else (0.0, 0.0, 1.0)
    up = np.asarray(up, dtype=np.float64)
    if eye.shape != (3,) or target.shape != (3,) or up.shape != (3,) or not np.all(np.isfinite([eye, target, up])):
        raise ValueError(f"{what}: eye, target and up must be finite 3-vectors")
    fov = _number(fov, "fov", what, 0.0, 180.0)
    width, height = _integer(width, "width", what), _integer(height, "height", what)
    if fov == 0.0 or not np.any(forward):
        raise ValueError(f"{what}: needs fov in (0, 180) and eye != target, got fov {fov}, eye {eye.tolist()}")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) <= 1e-9 * np.linalg.norm(up):
        raise ValueError(f"{what}: up {up.tolist()} is along the view direction {forward.tolist()}")
    right /= np.linalg.norm(right)
    half = math.tan(math.radians(fov) / 2.0)
    window = (-half, half, -half * height / width, half * height / width)
    return Camera(eye, forward, right, np.cross(right, forward), window, width, height)


def _in_view(points, camera):
    depth = (points - camera.eye) @ camera.forward
    mask = depth > 0.0
    rc = camera.pixel(points[mask])
    mask[mask] = (rc[:, 0] >= 0) & (rc[:, 0] < camera.height) & (rc[:, 1] >= 0) & (rc[:, 1] < camera.width)
    return mask


class _Occluders:
    # a wp.Mesh of the cloth's and the obstacles' triangles, built anew for each frame (a tree built for the frame's
    # shape, not refit from another)

    def __init__(self, tris, vertex_count, obstacles, device):
        parts, offset = [tris], vertex_count
        for verts, otris in obstacles:
            parts.append(otris + offset)
            offset += verts.shape[-2]
        self.device, self.obstacles = wp.get_device(device), obstacles
        self.indices = wp.array(np.concatenate(parts).astype(np.int32).ravel(), dtype=wp.int32, device=self.device)
        self.frame = self.mesh = None

    def seen(self, cloth, i, points, camera, tolerance):
        if self.frame != i:
            verts = np.concatenate([cloth] + [v if v.ndim == 2 else v[i] for v, _ in self.obstacles])
            self.mesh = wp.Mesh(points=wp.array(verts.astype(np.float32), dtype=wp.vec3, device=self.device),
                                indices=self.indices)
            self.frame = i
        mask = _in_view(points, camera)
        index = np.flatnonzero(mask)
        if index.size:
            seen = wp.zeros(index.size, dtype=wp.int32, device=self.device)
            wp.launch(unoccluded, dim=index.size, device=self.device, record_tape=False,
                      inputs=[self.mesh.id, wp.vec3(camera.eye), wp.array(points[index].astype(np.float32),
                                                                          dtype=wp.vec3, device=self.device),
                              float(tolerance)], outputs=[seen])
            mask[index] = seen.numpy() == 1
        return mask


def _camera(camera, what):
    if not isinstance(camera, Camera):
        raise ValueError(f"{what}: camera must be a warpcloth.preview.Camera (e.g. warpcloth.recordings.look_at), "
                         f"got {type(camera).__name__}")
    return camera


def visible(points, positions, triangles, camera: Camera, *, obstacles=(), tolerance: float = 1e-4,
            device=None) -> np.ndarray:
    """Which points (P, 3) [m] the pinhole ``camera`` sees of a cloth at ``positions`` (N, 3) [m] with
    ``triangles`` (T, 3): in front of it, inside its image, and nothing of the cloth or of ``obstacles``
    (``(name, vertices (M, 3), triangles (K, 3))`` each) on the ray from the eye closer than the point less
    ``tolerance`` [m] (far below the cloth's thickness). Both sides of the cloth are surfaces: a point on the side
    facing away from the camera is seen when nothing covers it. Returns a bool mask (P,); ValueError naming a bad
    point, position, triangle, obstacle, camera or tolerance."""
    what = "visible"
    p = _points(points, what)
    tris, frames, checked = check_geometry(triangles, check_frames([positions], what), obstacles, what)
    if len(tris) == 0:
        raise ValueError(f"{what}: the cloth has no triangles")
    tolerance = _tolerance(tolerance, what)
    occluders = _Occluders(tris, len(frames[0]), checked, device)
    return occluders.seen(frames[0], 0, p, _camera(camera, what), tolerance)


def point_cloud_recording(trajectory_frames, triangles, *, points: int = 2000, noise: float = 0.002,
                          camera: Camera | None = None, drop: float = 0.1, obstacles=(), tolerance: float = 1e-4,
                          rng: np.random.Generator, device=None) -> list[np.ndarray | None]:
    """What a camera records of a cloth trajectory (F, N, 3) [m]: per frame, ``points`` points uniformly distributed
    by area over the surface it sees, moved by Gaussian noise of standard deviation ``noise`` [m] along each axis.
    ``camera`` None sees every side, nothing occluded; a camera (:func:`look_at`) sees what :func:`visible` keeps
    (obstacle vertices (M, 3) or (F, M, 3)), sampled until ``points`` are seen. ``round(drop * F)`` frames but
    frame 0 (the start is always recorded) are dropped. Returns F entries, (points, 3) float64 arrays or None
    (dropped). ValueError naming a bad frame, triangle, obstacle or argument, or a frame the camera sees none of."""
    what = "point_cloud_recording"
    tris, frames, checked = check_geometry(triangles, check_frames(trajectory_frames, what), obstacles, what)
    count, rng = _integer(points, "points", what), _rng(rng, what)
    noise, drop = _number(noise, "noise", what, 0.0), _number(drop, "drop", what, 0.0, 1.0)
    tolerance = _tolerance(tolerance, what)
    dropped_count = math.floor(drop * len(frames) + 0.5)
    if dropped_count > len(frames) - 1:
        raise ValueError(f"{what}: drop {drop} of {len(frames)} frames drops {dropped_count}; at most "
                         f"{len(frames) - 1} (every frame but the first) can be dropped")
    dropped = set((1 + rng.choice(len(frames) - 1, size=dropped_count, replace=False)).tolist())
    occluders = None if camera is None else _Occluders(tris, len(frames[0]), checked, device)
    camera = camera if camera is None else _camera(camera, what)
    out = []
    for i, x in enumerate(frames):
        if i in dropped:
            out.append(None)
            continue
        cumulative = _cumulative_area(x, tris, f"{what}: frame {i}")
        if occluders is None:
            cloud = _sample(x, tris, cumulative, count, rng)[0]
        else:
            kept, seen, tried, batch = [], 0, 0, count
            while seen < count:
                sample = _sample(x, tris, cumulative, batch, rng)[0]
                sample = sample[occluders.seen(x, i, sample, camera, tolerance)]
                kept.append(sample)
                seen, tried = seen + len(sample), tried + batch
                if seen == 0:
                    raise ValueError(f"{what}: the camera sees none of the cloth in frame {i} "
                                     f"({tried} points tried)")
                batch = min(math.ceil(1.1 * (count - seen) * tried / seen) + 16, _MAX_BATCH)
            cloud = np.concatenate(kept)[:count]
        out.append(cloud + rng.normal(0.0, noise, cloud.shape) if noise > 0.0 else cloud)
    return out


def marker_recording(trajectory_frames, triangles, *, markers: int = 12, hidden: float = 0.2, noise: float = 0.0,
                     rng: np.random.Generator) -> MarkerRecording:
    """What a motion-capture system records of a cloth trajectory (F, N, 3) [m]: ``markers`` points on the surface,
    spread by farthest-point sampling (in frame 0's shape) over surface points sampled uniformly by area, followed
    through every frame, moved by Gaussian noise of standard deviation ``noise`` [m] along each axis, and in each
    frame ``round(hidden * markers)`` of them, drawn at random, hidden (NaN). ValueError naming a bad frame,
    triangle or argument."""
    what = "marker_recording"
    frames = check_frames(trajectory_frames, what)
    tris = check_triangles(triangles, len(frames[0]), what)
    count, rng = _integer(markers, "markers", what), _rng(rng, what)
    hidden, noise = _number(hidden, "hidden", what, 0.0, 1.0), _number(noise, "noise", what, 0.0)
    candidates, face, bary = _sample(frames[0], tris, _cumulative_area(frames[0], tris, f"{what}: frame 0"),
                                     max(64 * count, 2048), rng)
    chosen = [int(rng.integers(len(candidates)))]
    distance = np.linalg.norm(candidates - candidates[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(candidates - candidates[chosen[-1]], axis=1))
    face, bary = face[chosen], bary[chosen]
    positions = np.einsum("mk,fmkc->fmc", bary, np.stack(frames)[:, tris[face]])
    if noise > 0.0:
        positions += rng.normal(0.0, noise, positions.shape)
    per_frame = math.floor(hidden * count + 0.5)  # round half up
    for k in range(positions.shape[0]):
        positions[k, rng.choice(count, size=per_frame, replace=False)] = np.nan
    return MarkerRecording(face, bary, positions)


def check_markers(triangles, barycentric, positions, *, triangle_count: int | None = None,
                  what: str = "markers") -> MarkerRecording:
    """The markers as a :class:`MarkerRecording`; ValueError naming ``what`` and the marker or (frame, marker) for:
    a triangle not an integer in ``[0, triangle_count)``, barycentric coordinates not (M, 3), below zero or not
    summing to one (within :data:`BARYCENTRIC_TOLERANCE`), positions not (F, M, 3), a position neither finite nor
    NaN on all three axes (NaN: hidden)."""
    tris = np.asarray(triangles)
    if tris.ndim != 1 or tris.size == 0 or not np.issubdtype(tris.dtype, np.integer):
        raise ValueError(f"{what}: triangles must be integers of shape (M,), M >= 1, got {tris.dtype} {tris.shape}")
    bad = np.flatnonzero((tris < 0) | (tris >= (triangle_count if triangle_count is not None else np.inf)))
    if bad.size:
        raise ValueError(f"{what}: marker {int(bad[0])} is on triangle {int(tris[bad[0]])}, which the mesh lacks "
                         f"({triangle_count} triangles)" if tris[bad[0]] >= 0 else
                         f"{what}: marker {int(bad[0])} has a negative triangle {int(tris[bad[0]])}")
    bary = np.asarray(barycentric, dtype=np.float64)
    if bary.shape != (len(tris), 3):
        raise ValueError(f"{what}: barycentric must have shape ({len(tris)}, 3), one row a marker, got {bary.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(bary), axis=1) | np.any(bary < -BARYCENTRIC_TOLERANCE, axis=1)
                         | (np.abs(bary.sum(axis=1) - 1.0) > BARYCENTRIC_TOLERANCE))
    if bad.size:
        raise ValueError(f"{what}: marker {int(bad[0])} has barycentric coordinates {bary[bad[0]].tolist()}; they "
                         "must be >= 0 and sum to one")
    x = np.asarray(positions, dtype=np.float64)
    if x.ndim != 3 or x.shape[1:] != (len(tris), 3) or x.shape[0] == 0:
        raise ValueError(f"{what}: positions must have shape (F, {len(tris)}, 3), F >= 1, got {x.shape}")
    finite, nan = np.isfinite(x), np.isnan(x)
    bad = np.argwhere(~(np.all(finite, axis=2) | np.all(nan, axis=2)))
    if bad.size:
        f, m = (int(k) for k in bad[0])
        raise ValueError(f"{what}: frame {f} marker {m} has position {x[f, m].tolist()}; a position is finite, or "
                         "NaN on every axis (hidden)")
    return MarkerRecording(tris.astype(np.int64), bary, x)


def write_markers(path: str | os.PathLike, triangles, barycentric, positions) -> Path:
    """Write markers (:func:`check_markers`) to ``path``: ``.json`` as :func:`read_markers` describes (a hidden
    marker: null) or ``.npz`` (arrays ``triangles``, ``barycentric``, ``positions``, NaN where hidden). Overwrites;
    returns the path. ValueError for another suffix or bad markers."""
    path = Path(path)
    markers = check_markers(triangles, barycentric, positions, what=f"write_markers {str(path)!r}")
    if path.suffix.lower() == ".npz":
        np.savez(path, **markers._asdict())
    elif path.suffix.lower() == ".json":
        rows = [[None if np.isnan(p[0]) else p.tolist() for p in frame] for frame in markers.positions]
        defs = [{"triangle": int(t), "barycentric": b.tolist()} for t, b in zip(markers.triangles,
                                                                               markers.barycentric)]
        text = ",\n    ".join(json.dumps(row) for row in rows)
        path.write_text('{\n  "markers": [\n    ' + ",\n    ".join(json.dumps(d) for d in defs)
                        + '\n  ],\n  "positions": [\n    ' + text + "\n  ]\n}\n")
    else:
        raise ValueError(f"write_markers: {str(path)!r} must end in .json or .npz")
    return path


def _json_markers(path):
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path.name}: not valid JSON: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("markers"), list) or not isinstance(
            data.get("positions"), list):
        raise ValueError(f"{path.name}: must be an object with lists \"markers\" and \"positions\"")
    tris, bary = [], []
    for m, entry in enumerate(data["markers"]):
        t, b = (entry.get("triangle"), entry.get("barycentric")) if isinstance(entry, dict) else (None, None)
        if isinstance(t, bool) or not isinstance(t, int) or not (isinstance(b, list) and len(b) == 3 and all(
                isinstance(c, (int, float)) and not isinstance(c, bool) for c in b)):
            raise ValueError(f"{path.name}: marker {m} must be {{\"triangle\": integer, \"barycentric\": "
                             f"[three numbers]}}, got {entry!r}")
        tris.append(t)
        bary.append(b)
    positions = np.full((len(data["positions"]), len(tris), 3), np.nan)
    for f, row in enumerate(data["positions"]):
        if not isinstance(row, list) or len(row) != len(tris):
            raise ValueError(f"{path.name}: frame {f} of positions must list {len(tris)} entries, one a marker")
        for m, p in enumerate(row):
            if p is None:
                continue
            if not (isinstance(p, list) and len(p) == 3 and all(
                    isinstance(c, (int, float)) and not isinstance(c, bool) for c in p)):
                raise ValueError(f"{path.name}: frame {f} marker {m} must be [x, y, z] or null (hidden), got {p!r}")
            positions[f, m] = p
    return np.array(tris, dtype=np.int64), np.array(bary, dtype=np.float64).reshape(-1, 3), positions


def read_markers(path: str | os.PathLike, *, triangle_count: int | None = None) -> MarkerRecording:
    """Read a marker recording: ``.npz`` as :func:`write_markers` writes it, or ``.json`` (easily written by hand)::

        {"markers": [{"triangle": 17, "barycentric": [0.2, 0.3, 0.5]}, ...],
         "positions": [[[x, y, z], null, ...], ...]}

    ``positions`` holds one list a frame, one ``[x, y, z]`` [m] a marker in the order of ``markers``, ``null``
    where it is hidden (NaN in the result). ValueError naming the file and the marker or frame for a missing file,
    another suffix, a bad entry or what :func:`check_markers` refuses (a triangle >= ``triangle_count``, the
    mesh's, when given)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"read_markers: {str(path)!r} is not a file")
    if path.suffix.lower() == ".json":
        arrays = _json_markers(path)
    elif path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = tuple(data[k] for k in MarkerRecording._fields)
        except (KeyError, ValueError, OSError) as exc:
            raise ValueError(f"{path.name}: not an .npz of {', '.join(MarkerRecording._fields)}: {exc}") from None
    else:
        raise ValueError(f"read_markers: {str(path)!r} must end in .json or .npz")
    return check_markers(*arrays, triangle_count=triangle_count, what=path.name)


def _frame_index(path):
    number = re.search(r"\d+", path.stem)
    if number is None:
        raise ValueError(f"{path.name}: a point-cloud file's name must hold its frame index (e.g. frame_0007"
                         f"{path.suffix}), this one holds no number")
    return int(number[0])


def _read_cloud(path):
    if path.suffix.lower() == ".npy":
        try:
            cloud = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise ValueError(f"{path.name}: not a readable .npy array: {exc}") from None
        if not (np.issubdtype(cloud.dtype, np.integer) or np.issubdtype(cloud.dtype, np.floating)):
            raise ValueError(f"{path.name}: the array must hold numbers, got dtype {cloud.dtype}")
    else:
        from plyfile import PlyData

        try:
            data = PlyData.read(str(path))
        except Exception as exc:  # noqa: BLE001 (plyfile's parse errors, and the OS's)
            raise ValueError(f"{path.name}: not a readable PLY file: {exc}") from None
        names = data["vertex"].data.dtype.names if "vertex" in data else ()
        lacking = [c for c in "xyz" if c not in names]
        if lacking:
            raise ValueError(f"{path.name}: a point-cloud PLY needs a vertex element with x, y and z, lacks "
                             f"{', '.join(lacking) if names else 'the vertex element'}")
        try:
            cloud = np.stack([np.asarray(data["vertex"][c], dtype=np.float64) for c in "xyz"], axis=1)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path.name}: the vertices' x, y and z must be numbers: {exc}") from None
    cloud = np.asarray(cloud, dtype=np.float64)
    if cloud.ndim != 2 or cloud.shape[1] != 3 or cloud.shape[0] == 0:
        raise ValueError(f"{path.name}: a point cloud must have shape (P, 3), P >= 1, got {cloud.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(cloud), axis=1))
    if bad.size:
        raise ValueError(f"{path.name}: point {int(bad[0])} is not finite: {cloud[bad[0]].tolist()}")
    return cloud


def _cloud_files(directory, what):
    d = Path(directory)
    if not d.is_dir():
        raise ValueError(f"{what}: {str(directory)!r} is not a directory")
    files = sorted((f for f in d.iterdir() if f.suffix.lower() in (*POINT_CLOUD_SUFFIXES, ".obj")),
                   key=lambda f: natural_key(f.name))
    return d, files


def holds_point_clouds(directory: str | os.PathLike) -> bool:
    """Whether ``directory`` holds ``.ply`` or ``.npy`` files (a point-cloud recording, not OBJ vertex frames)."""
    d = Path(directory)
    return d.is_dir() and any(f.suffix.lower() in POINT_CLOUD_SUFFIXES for f in d.iterdir())


def read_point_clouds(directory: str | os.PathLike) -> tuple[np.ndarray, list[np.ndarray]]:
    """Read a point-cloud recording: ``(indices (K,) int64, clouds)``, ``clouds[k]`` the (P_k, 3) float64 points [m]
    of frame ``indices[k]``, the first number in its file's name; files in natural order (``frame_2`` before
    ``frame_10``), indices increasing, a missing index a dropped frame. Other files than ``.ply``, ``.npy`` and
    ``.obj`` are ignored. ValueError naming the directory or the file (and point) for: no point-cloud files,
    several kinds, a name without a number, two files of one index, an unreadable file, a shape not (P, 3) with P
    >= 1, a non-finite point."""
    what = "read_point_clouds"
    d, files = _cloud_files(directory, what)
    kinds = sorted({f.suffix.lower() for f in files})
    if len(kinds) > 1:
        raise ValueError(f"{what}: {str(d)!r} mixes {' and '.join(kinds)} files; a recording is one kind")
    if not files or kinds == [".obj"]:
        extra = " (.obj frames are a vertex recording: warpcloth.load_obj_sequence)" if files else ""
        raise ValueError(f"{what}: {str(d)!r} holds no .ply or .npy point clouds{extra}")
    indices = [_frame_index(f) for f in files]
    for k in range(1, len(files)):
        if indices[k] <= indices[k - 1]:
            raise ValueError(f"{what}: {files[k - 1].name} and {files[k].name} name frames {indices[k - 1]} and "
                             f"{indices[k]}; each file needs its own frame index, increasing in name order")
    return np.array(indices, dtype=np.int64), [_read_cloud(f) for f in files]


def write_point_clouds(directory: str | os.PathLike, frames: Sequence[np.ndarray | None], *,
                       kind: str = ".ply") -> list[Path]:
    """Write a point-cloud recording (:func:`read_point_clouds` reads it back): frame ``i`` of ``frames`` ((P, 3)
    [m] arrays, None where dropped: no file) to ``frame_{i:04d}{kind}``, ``kind`` ``.ply`` (binary, float64
    ``x``, ``y``, ``z``) or ``.npy``, in ``directory`` (created). Returns the paths written. ValueError for another
    kind, a directory already holding recording files, no frame, or a frame with a bad shape or non-finite point."""
    what = "write_point_clouds"
    if kind not in POINT_CLOUD_SUFFIXES:
        raise ValueError(f"{what}: kind must be one of {POINT_CLOUD_SUFFIXES}, got {kind!r}")
    clouds = {i: _points(f, f"{what}: frame {i}") for i, f in enumerate(frames) if f is not None}
    if not clouds:
        raise ValueError(f"{what}: no frame to write (every one is None)")
    for i, c in clouds.items():
        if len(c) == 0:
            raise ValueError(f"{what}: frame {i} has no points")
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise ValueError(f"{what}: {str(d)!r} is not a directory")
    if d.is_dir() and _cloud_files(d, what)[1]:
        raise ValueError(f"{what}: {str(d)!r} already holds recording files; write into an empty or new directory")
    d.mkdir(parents=True, exist_ok=True)
    digits = max(4, len(str(len(frames) - 1)))
    paths = []
    for i, cloud in clouds.items():
        path = d / f"frame_{i:0{digits}d}{kind}"
        if kind == ".npy":
            np.save(path, cloud)
        else:
            from plyfile import PlyData, PlyElement

            vertex = np.empty(len(cloud), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
            vertex["x"], vertex["y"], vertex["z"] = cloud.T
            PlyData([PlyElement.describe(vertex, "vertex")], byte_order="<").write(str(path))
        paths.append(path)
    return paths
