"""Triangle meshes for cloth and obstacles: OBJ and USD loading, validation, flat grids."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["TriangleMesh", "grid_mesh", "load_obj", "load_obj_sequence", "load_usd_mesh", "obj_sequence_files",
           "validate_triangles"]

# Triangles whose material area is below this fraction of the mean |area| count as degenerate (round-off).
DEGENERATE_AREA_FRACTION = 1e-12


@dataclass(eq=False)
class TriangleMesh:
    """A triangle mesh with optional material-space coordinates.

    Attributes:
        positions: World positions [m], shape (N, 3), float64.
        triangles: Vertex indices, shape (T, 3), int32, counterclockwise when seen from the front.
        tri_uv: Material-space coordinates [m] per triangle corner (seams may split them), (T, 3, 2) float64, or None.
        velocities: Initial vertex velocities [m/s], shape (N, 3), float64, or None (ARCSim's ``nv`` OBJ lines).
    """

    positions: np.ndarray
    triangles: np.ndarray
    tri_uv: np.ndarray | None = None
    velocities: np.ndarray | None = None

    @property
    def vertex_count(self) -> int:
        """Number of vertices N."""
        return int(self.positions.shape[0])

    @property
    def triangle_count(self) -> int:
        """Number of triangles T."""
        return int(self.triangles.shape[0])


def _tri_uv_areas(tri_uv: np.ndarray) -> np.ndarray:
    d1 = tri_uv[:, 1] - tri_uv[:, 0]
    d2 = tri_uv[:, 2] - tri_uv[:, 0]
    return 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])


def validate_triangles(positions: np.ndarray, triangles: np.ndarray, tri_uv: np.ndarray | None = None) -> None:
    """Check a mesh for what the simulator cannot handle; every triangle's material-space area, in its own winding,
    must be positive (ARCSim's ``det(Dm) > 0``).

    Raises:
        ValueError: naming the vertex, triangle or edge: a wrong shape or dtype, a non-finite position, an index out of
            range or repeated in a triangle, a triangle listed twice (either winding), a non-finite, degenerate or
            inverted material triangle, an edge of more than two triangles.
    """
    positions = np.asarray(positions)
    triangles = np.asarray(triangles)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions must have shape (N, 3), got {positions.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"triangles must have shape (T, 3), got {triangles.shape}")
    if triangles.size and not np.issubdtype(triangles.dtype, np.integer):
        raise ValueError(f"triangles must hold integers, got dtype {triangles.dtype}")
    bad = np.flatnonzero(~np.all(np.isfinite(positions), axis=1))
    if len(bad):
        v = int(bad[0])
        raise ValueError(f"vertex {v} has a non-finite position {positions[v].tolist()}")
    n = positions.shape[0]
    bad = np.argwhere((triangles < 0) | (triangles >= n))
    if len(bad):
        t, k = (int(i) for i in bad[0])
        raise ValueError(f"triangle {t} {triangles[t].tolist()}: index {int(triangles[t, k])} out of range [0, {n})")
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    repeated = (a == b) | (b == c) | (a == c)
    bad = np.flatnonzero(repeated)
    if len(bad):
        t = int(bad[0])
        raise ValueError(f"triangle {t} {triangles[t].tolist()} repeats a vertex index")

    if tri_uv is not None:
        tri_uv = np.asarray(tri_uv)
        if tri_uv.shape != (triangles.shape[0], 3, 2):
            raise ValueError(f"tri_uv must have shape ({triangles.shape[0]}, 3, 2), got {tri_uv.shape}")
        bad = np.flatnonzero(~np.all(np.isfinite(tri_uv), axis=(1, 2)))
        if len(bad):
            t = int(bad[0])
            raise ValueError(f"triangle {t}: non-finite material coordinates {tri_uv[t].tolist()}")
        if len(tri_uv):
            areas = _tri_uv_areas(tri_uv.astype(np.float64))
            threshold = DEGENERATE_AREA_FRACTION * float(np.mean(np.abs(areas)))
            bad = np.flatnonzero(areas <= threshold)
            if len(bad):
                t = int(bad[0])
                kind = "negative (inverted winding)" if areas[t] < -threshold else "zero (degenerate)"
                raise ValueError(
                    f"triangle {t} {triangles[t].tolist()}: material-space area is {kind}: {areas[t]:.6g} m^2; "
                    "material coordinates must be counterclockwise in the triangle's vertex order"
                )

    if len(triangles):
        # the same three vertices twice (either winding): double mass, and hinges between coincident faces
        corners = np.sort(triangles.astype(np.int64), axis=1)
        _, first, inverse = np.unique(corners, axis=0, return_index=True, return_inverse=True)
        repeats = np.flatnonzero(first[inverse.reshape(-1)] != np.arange(len(triangles)))
        if len(repeats):
            t = int(repeats[0])
            t0 = int(first[inverse.reshape(-1)[t]])
            raise ValueError(f"triangle {t} {triangles[t].tolist()} repeats triangle {t0} {triangles[t0].tolist()} "
                             "(the same vertices, in either winding)")
        # Undirected edges: sort each edge's two vertices, then count how many triangles hold it.
        edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]).astype(np.int64)
        edges.sort(axis=1)
        uniq, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
        bad = np.flatnonzero(counts > 2)
        if len(bad):
            e = int(bad[0])
            tris = sorted({int(i) % len(triangles) for i in np.flatnonzero(inverse.reshape(-1) == e)})
            a, b = (int(i) for i in uniq[e])
            raise ValueError(f"non-manifold edge ({a}, {b}) is shared by {len(tris)} triangles: {tris}")


def _resolve_obj_index(token: str, count: int, what: str, where: str) -> int:
    try:
        i = int(token)
    except ValueError:
        raise ValueError(f"{where}: bad {what} index {token!r}") from None
    if i > 0:
        j = i - 1
    elif i < 0:
        j = count + i  # negative indices count back from the last element defined so far
    else:
        raise ValueError(f"{where}: {what} index 0 is not valid (OBJ indices start at 1)")
    if not 0 <= j < count:
        raise ValueError(f"{where}: {what} index {i} out of range ({count} defined so far)")
    return j


def _parse_floats(tokens: list[str], n_min: int, n_max: int, what: str, where: str) -> list[float]:
    if not n_min <= len(tokens) <= n_max:
        expected = str(n_min) if n_min == n_max else f"{n_min} to {n_max}"
        raise ValueError(f"{where}: '{what}' needs {expected} numbers, got {len(tokens)}")
    try:
        return [float(t) for t in tokens]
    except ValueError:
        raise ValueError(f"{where}: '{what}' has a non-numeric value in {' '.join(tokens)!r}") from None


# OBJ directives that carry nothing the simulator uses: normals are recomputed, groups/materials are cosmetic.
_OBJ_IGNORED = {"vn", "o", "g", "s", "usemtl", "mtllib"}


def load_obj(path: str | os.PathLike, *, scale: float = 1.0, validate: bool = True) -> TriangleMesh:
    """Loads a triangle mesh from a Wavefront OBJ file, positions and material coordinates times ``scale``: ``v``,
    ``vt`` (into ``tri_uv``), ``f`` (any corner form, negative indices; polygons fan-triangulated) and ARCSim's ``nv``
    velocities, ignoring ``vn``, ``o``, ``g``, ``s``, ``usemtl``, ``mtllib``, ``ny`` and comments. ``validate`` runs
    :func:`validate_triangles` (off for non-manifold obstacles).

    Raises:
        ValueError: naming the file and line: a malformed line or unsupported directive, an index out of range,
            ``vt`` on some faces only, an ``nv`` count other than the ``v`` count; and as :func:`validate_triangles`.
    """
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"load_obj: scale must be a finite number > 0, got {scale!r}")
    positions: list[list[float]] = []
    uvs: list[list[float]] = []
    velocities: list[list[float]] = []
    triangles: list[tuple[int, int, int]] = []
    tri_uv_idx: list[tuple[int, int, int]] = []
    first_face_has_vt: tuple[bool, int] | None = None  # (has vt, line number) of the first face
    with open(path, encoding="utf-8") as f:
        for lineno, raw in enumerate(f, start=1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            where = f"{path}:{lineno}"
            key, *tokens = line.split()
            if key == "v":
                # x y z and an optional homogeneous w, which must be 1.
                xyz = _parse_floats(tokens, 3, 4, "v", where)
                if len(xyz) == 4 and xyz[3] != 1.0:
                    raise ValueError(f"{where}: homogeneous w = {xyz[3]} != 1 is not supported")
                positions.append(xyz[:3])
            elif key == "vt":
                uvw = _parse_floats(tokens, 2, 3, "vt", where)
                if len(uvw) == 3 and uvw[2] != 0.0:
                    raise ValueError(f"{where}: 3D material coordinate w = {uvw[2]} != 0 is not supported")
                uvs.append(uvw[:2])
            elif key == "nv":
                velocities.append(_parse_floats(tokens, 3, 3, "nv", where))
            elif key == "ny":
                _parse_floats(tokens, 3, 3, "ny", where)
            elif key == "f":
                if len(tokens) < 3:
                    raise ValueError(f"{where}: face needs at least 3 corners, got {len(tokens)}")
                vidx, tidx = [], []
                for corner in tokens:
                    parts = corner.split("/")
                    if len(parts) > 3:
                        raise ValueError(f"{where}: bad face corner {corner!r}")
                    vidx.append(_resolve_obj_index(parts[0], len(positions), "vertex", where))
                    has_vt = len(parts) >= 2 and parts[1] != ""
                    tidx.append(_resolve_obj_index(parts[1], len(uvs), "texture", where) if has_vt else None)
                has = [t is not None for t in tidx]
                if any(has) and not all(has):
                    raise ValueError(f"{where}: face has vt indices on some corners but not on others")
                if first_face_has_vt is None:
                    first_face_has_vt = (has[0], lineno)
                elif first_face_has_vt[0] != has[0]:
                    state = "has" if has[0] else "has no"
                    other = "had" if first_face_has_vt[0] else "had none"
                    raise ValueError(
                        f"{where}: face {state} vt indices but the face on line {first_face_has_vt[1]} {other}; "
                        "material coordinates must be given for all faces or none"
                    )
                for i in range(1, len(vidx) - 1):
                    triangles.append((vidx[0], vidx[i], vidx[i + 1]))
                    if has[0]:
                        tri_uv_idx.append((tidx[0], tidx[i], tidx[i + 1]))
            elif key in _OBJ_IGNORED:
                continue
            else:
                raise ValueError(f"{where}: unsupported OBJ directive {key!r}")

    pos = np.array(positions, dtype=np.float64).reshape(-1, 3) * scale
    tris = np.array(triangles, dtype=np.int32).reshape(-1, 3)
    tri_uv = None
    if first_face_has_vt is not None and first_face_has_vt[0]:
        tri_uv = np.array(uvs, dtype=np.float64).reshape(-1, 2)[np.array(tri_uv_idx, dtype=np.int64)] * scale
    vel = None
    if velocities:
        if len(velocities) != len(positions):
            raise ValueError(
                f"{path}: {len(velocities)} 'nv' lines for {len(positions)} 'v' lines; need one per vertex"
            )
        vel = np.array(velocities, dtype=np.float64)
    if validate:
        try:
            validate_triangles(pos, tris, tri_uv)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    return TriangleMesh(positions=pos, triangles=tris, tri_uv=tri_uv, velocities=vel)


def load_usd_mesh(
    path: str | os.PathLike,
    *,
    prim_path: str | None = None,
    time_code: float | None = None,
    validate: bool = True,
) -> TriangleMesh:
    """Loads a triangle mesh from a ``UsdGeom.Mesh`` (``prim_path``, None: the first) in world coordinates,
    counterclockwise, polygons fan-triangulated; material coordinates from an ``st`` or ``uv`` primvar (``faceVarying``
    or ``vertex``); ``time_code`` None reads the default value, else the earliest time sample.

    Raises:
        ImportError: when ``pxr`` (package ``usd-core``) is missing.
        ValueError: naming the file and prim when there is no mesh, the prim is not a mesh, it has holes, its
            topology is inconsistent, or its material-coordinate primvar has an unsupported interpolation or width.
    """
    try:
        from pxr import Usd, UsdGeom
    except ImportError as exc:  # pragma: no cover - usd-core is a dependency
        raise ImportError("load_usd_mesh needs the 'usd-core' package (pip install usd-core)") from exc

    stage = Usd.Stage.Open(os.fspath(path))
    if stage is None:
        raise ValueError(f"{path}: cannot open as a USD stage")
    if prim_path is None:
        prim = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)), None)
        if prim is None:
            raise ValueError(f"{path}: no UsdGeom.Mesh prim found")
    else:
        prim = stage.GetPrimAtPath(prim_path)
        if not prim.IsValid():
            raise ValueError(f"{path}: no prim at {prim_path!r}")
        if not prim.IsA(UsdGeom.Mesh):
            raise ValueError(f"{path}: prim {prim_path!r} is a {prim.GetTypeName() or 'typeless prim'}, not a Mesh")
    where = f"{path}: mesh {prim.GetPath()}"
    mesh = UsdGeom.Mesh(prim)

    points_attr = mesh.GetPointsAttr()
    if time_code is None:
        time = Usd.TimeCode.Default()
        if points_attr.Get(time) is None and points_attr.GetNumTimeSamples() > 0:
            time = Usd.TimeCode(points_attr.GetTimeSamples()[0])
    else:
        time = Usd.TimeCode(time_code)
    points = points_attr.Get(time)
    if points is None:
        raise ValueError(f"{where}: has no points")
    points = np.array(points, dtype=np.float64).reshape(-1, 3)
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    indices = np.array(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    holes = mesh.GetHoleIndicesAttr().Get(time)
    if holes is not None and len(holes):
        raise ValueError(f"{where}: holeIndices are not supported ({len(holes)} holes)")
    if np.any(counts < 3):
        f = int(np.flatnonzero(counts < 3)[0])
        raise ValueError(f"{where}: face {f} has {counts[f]} vertices; need at least 3")
    if counts.sum() != len(indices):
        raise ValueError(
            f"{where}: faceVertexCounts sum to {counts.sum()} but there are {len(indices)} faceVertexIndices"
        )

    # Fan triangulation, kept as face-vertex (corner) numbers so faceVarying primvars can be gathered the same way.
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    corners = [
        (s, s + i, s + i + 1) for s, c in zip(starts.tolist(), counts.tolist()) for i in range(1, c - 1)
    ]
    corners = np.array(corners, dtype=np.int64).reshape(-1, 3)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        corners = corners[:, [0, 2, 1]]
    tris = indices[corners] if len(corners) else np.zeros((0, 3), dtype=np.int64)

    xform = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), dtype=np.float64)
    # USD matrices act on row vectors: p' = [p, 1] @ M.
    positions = points @ xform[:3, :3] + xform[3, :3]

    tri_uv = None
    primvars = UsdGeom.PrimvarsAPI(prim)
    for name in ("st", "uv"):
        pv = primvars.GetPrimvar(name)
        if not pv or not pv.HasValue():
            continue
        values = pv.ComputeFlattened(time)
        values = np.array(values, dtype=np.float64)
        if values.ndim != 2 or values.shape[1] != 2:
            raise ValueError(f"{where}: primvar {name!r} must hold 2-component values, got shape {values.shape}")
        interp = pv.GetInterpolation()
        if interp == UsdGeom.Tokens.faceVarying:
            if len(values) != len(indices):
                raise ValueError(
                    f"{where}: faceVarying primvar {name!r} has {len(values)} values for {len(indices)} face vertices"
                )
            tri_uv = values[corners]
        elif interp in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
            if len(values) != len(points):
                raise ValueError(
                    f"{where}: {interp} primvar {name!r} has {len(values)} values for {len(points)} points"
                )
            tri_uv = values[tris]
        else:
            raise ValueError(
                f"{where}: primvar {name!r} has unsupported interpolation {interp!r} (need faceVarying or vertex)"
            )
        break

    if np.any(tris > np.iinfo(np.int32).max):
        raise ValueError(f"{where}: vertex index exceeds int32")
    tris = tris.astype(np.int32)
    if validate:
        try:
            validate_triangles(positions, tris, tri_uv)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
    return TriangleMesh(positions=positions, triangles=tris, tri_uv=tri_uv)


def grid_mesh(res_x: int, res_y: int, size_x: float, size_y: float) -> TriangleMesh:
    """A flat cloth of ``res_x`` by ``res_y`` cells (>= 1) in the XY plane (z = 0) over [0, size_x] x [0, size_y] [m],
    its own rest shape; vertex ``(i, j)`` is ``j * (res_x + 1) + i``, cell diagonals alternate in a checkerboard,
    triangles are counterclockwise from +z. ValueError naming an argument out of range."""
    for pname, value in (("res_x", res_x), ("res_y", res_y)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"grid_mesh: {pname} must be an integer >= 1, got {value!r}")
    for pname, value in (("size_x", size_x), ("size_y", size_y)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) or not (
            np.isfinite(value) and value > 0
        ):
            raise ValueError(f"grid_mesh: {pname} must be a finite number > 0, got {value!r}")
    nx, ny = int(res_x) + 1, int(res_y) + 1
    xs = np.linspace(0.0, float(size_x), nx)
    ys = np.linspace(0.0, float(size_y), ny)
    gx, gy = np.meshgrid(xs, ys)  # shape (ny, nx): row j, column i -> x fastest when flattened
    positions = np.stack([gx.ravel(), gy.ravel(), np.zeros(nx * ny)], axis=1)

    i, j = np.meshgrid(np.arange(res_x), np.arange(res_y))
    i, j = i.ravel(), j.ravel()
    v00 = j * nx + i
    v10 = v00 + 1
    v01 = v00 + nx
    v11 = v01 + 1
    even = (i + j) % 2 == 0
    # Even cells: diagonal v00-v11; odd cells: diagonal v10-v01. All counterclockwise from +z.
    t0 = np.where(even[:, None], np.stack([v00, v10, v11], 1), np.stack([v00, v10, v01], 1))
    t1 = np.where(even[:, None], np.stack([v00, v11, v01], 1), np.stack([v10, v11, v01], 1))
    triangles = np.stack([t0, t1], axis=1).reshape(-1, 3).astype(np.int32)
    tri_uv = positions[triangles][:, :, :2].copy()
    return TriangleMesh(positions=positions, triangles=triangles, tri_uv=tri_uv)


def natural_key(name: str) -> list:
    """The sort key of a frame file's name: digit runs compared as numbers (``2.obj`` before ``10.obj``)."""
    return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name)]


def obj_sequence_files(directory: str | os.PathLike) -> list[Path]:
    """The .obj files of a sequence (one frame per file) in frame order: names with digit runs compared as numbers
    (2.obj before 10.obj). ValueError for a missing directory or fewer than two files."""
    if not Path(directory).is_dir():
        raise ValueError(f"sequence directory {str(directory)!r} does not exist")
    files = sorted(Path(directory).glob("*.obj"), key=lambda f: natural_key(f.name))
    if len(files) < 2:
        raise ValueError(f"sequence directory {str(directory)!r} holds {len(files)} .obj files; need >= 2")
    return files


def load_obj_sequence(files: Sequence[str | os.PathLike]) -> list[np.ndarray]:
    """Vertex positions (n, 3) [m] of each frame file; ValueError for a frame of another size or non-finite."""
    frames = [load_obj(f, validate=False).positions for f in files]
    for f, x in zip(files, frames):
        if x.shape != frames[0].shape:
            raise ValueError(f"frame {Path(f).name} has {len(x)} vertices, frame 0 has {len(frames[0])}")
        bad = np.flatnonzero(~np.all(np.isfinite(x), axis=1))
        if bad.size:
            raise ValueError(f"frame {Path(f).name}: vertex {int(bad[0])} has a non-finite position "
                             f"{x[bad[0]].tolist()}")
    return frames
