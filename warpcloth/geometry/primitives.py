"""Meshes of simple shapes in their body frame, ``(vertices [m] (V, 3), triangles (T, 3) int32)``, counter-clockwise
seen from the side the cloth is meant to be on (outside a closed shape); the edges of a triangle mesh."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from warpcloth.mesh_io import grid_mesh

__all__ = ["box_mesh", "contact_edges", "funnel_mesh", "plane_mesh", "sphere_mesh", "unique_edges"]

_MAX_SPHERE_SUBDIVISIONS = 8  # 1,310,720 triangles; more is almost surely a typo


def _positive(what: str, value, n: int) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64).reshape(-1) if np.ndim(value) else np.full(1, float(value))
    if a.shape != (n,):
        raise ValueError(f"{what} must have {n} component{'s' if n > 1 else ''}, got {np.shape(value)}")
    if not np.all(np.isfinite(a)) or np.any(a <= 0.0):
        raise ValueError(f"{what} must be finite and > 0, got {a.tolist()}")
    return a


def _count(what: str, value, min_value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < min_value:
        raise ValueError(f"{what} must be an integer >= {min_value}, got {value!r}")
    return int(value)


def plane_mesh(size: Sequence[float] = (1.0, 1.0), res: Sequence[int] = (1, 1)) -> tuple[np.ndarray, np.ndarray]:
    """A rectangle in the body XY plane, centred on the origin, facing +z: ``size`` (x, y) [m] > 0, ``res`` cells
    along x and y (>= 1), ``2 * res[0] * res[1]`` triangles."""
    sx, sy = _positive("plane size", size, 2)
    if isinstance(res, (str, bytes)) or len(res) != 2:
        raise ValueError(f"plane res must be two cell counts, got {res!r}")
    rx, ry = (_count(f"plane res[{i}]", r, 1) for i, r in enumerate(res))
    mesh = grid_mesh(rx, ry, float(sx), float(sy))
    return mesh.positions - np.array([0.5 * sx, 0.5 * sy, 0.0]), mesh.triangles.astype(np.int32)


def box_mesh(half_extents: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box centred on the origin, ``half_extents`` (hx, hy, hz) [m] > 0: 8 vertices (vertex
    ``i + 2 j + 4 k`` at ``((2i - 1) hx, (2j - 1) hy, (2k - 1) hz)``), 12 triangles facing outwards."""
    h = _positive("box half_extents", half_extents, 3)
    i, j, k = np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")
    corner = np.stack([i.ravel("F"), j.ravel("F"), k.ravel("F")], axis=1)  # row i + 2j + 4k
    vertices = (2.0 * corner - 1.0) * h
    triangles = np.array(
        [
            [0, 2, 1], [1, 2, 3],  # -z
            [4, 5, 7], [4, 7, 6],  # +z
            [0, 1, 5], [0, 5, 4],  # -y
            [2, 7, 3], [2, 6, 7],  # +y
            [0, 4, 6], [0, 6, 2],  # -x
            [1, 3, 7], [1, 7, 5],  # +x
        ],
        dtype=np.int32,
    )
    return vertices, triangles


def sphere_mesh(radius: float, subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere of ``radius`` [m] > 0, its vertices on the sphere, triangles facing outwards: an icosahedron
    whose faces are split in four ``subdivisions`` (0 to 8) times, ``20 * 4**subdivisions`` triangles."""
    r = float(_positive("sphere radius", radius, 1)[0])
    n = _count("sphere subdivisions", subdivisions, 0)
    if n > _MAX_SPHERE_SUBDIVISIONS:
        raise ValueError(
            f"sphere subdivisions must be <= {_MAX_SPHERE_SUBDIVISIONS} ({20 * 4**_MAX_SPHERE_SUBDIVISIONS} "
            f"triangles), got {n}"
        )
    g = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array(
        [
            [-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0],
            [0, -1, g], [0, 1, g], [0, -1, -g], [0, 1, -g],
            [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1],
        ],
        dtype=np.float64,
    )
    f = np.array(
        [
            [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
            [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
            [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
            [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
        ],
        dtype=np.int64,
    )
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(n):
        # One new vertex per unique edge, at the edge's midpoint pushed out to the sphere.
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        edges.sort(axis=1)
        uniq, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = 0.5 * (v[uniq[:, 0]] + v[uniq[:, 1]])
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = (len(v) + inverse.reshape(-1)).reshape(3, -1).T  # columns: midpoints of edges 01, 12, 20
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        ab, bc, ca = m[:, 0], m[:, 1], m[:, 2]
        f = np.stack(
            [np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1), np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1)],
            axis=1,
        ).reshape(-1, 3)
        v = np.concatenate([v, mid])
    return v * r, f.astype(np.int32)


_FUNNEL_VERTICES = np.array(
    [[0.0, 1.0, 0.000001], [0.0, 0.0, 0.0], [0.5, 0.5, -0.666539], [1.0, 0.0, 0.0], [1.0, 1.0, 0.000001]]
)
_FUNNEL_TRIANGLES = np.array([[0, 1, 2], [2, 3, 4], [3, 2, 1], [4, 0, 2]], dtype=np.int32)


def funnel_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The seed's funnel (``meshes/contain.obj`` of Liang et al. 2019), an inverted square pyramid without a lid:
    the opening spans [0, 1] x [0, 1] at z = 0 (two corners at z = 1e-6, as in the file), the apex is at
    (0.5, 0.5, -0.666539); the file's four triangles face up into the cavity."""
    return _FUNNEL_VERTICES.copy(), _FUNNEL_TRIANGLES.copy()



FLAT_EDGE_COS = 1.0 - 1.0e-12
"""Two faces whose unit normals' dot product reaches this are coplanar (about 1.4e-6 rad apart at most)."""


def contact_edges(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """:func:`unique_edges` without the flat ones, between exactly two coplanar, consistently oriented faces. Why:
    docs/decisions.md, "No contacts on flat obstacle edges"."""
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    edges = unique_edges(tri)
    if len(tri) == 0:
        return edges
    v = np.asarray(vertices, dtype=np.float64)
    normal = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1.0e-300)
    sides = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    face = np.tile(np.arange(len(tri)), 3)
    order = np.lexsort((sides[:, 1], sides[:, 0]))
    sides, face = sides[order], face[order]
    row = np.searchsorted(edges[:, 0].astype(np.int64) * (len(v) + 1) + edges[:, 1],
                          sides[:, 0] * (len(v) + 1) + sides[:, 1])
    count = np.bincount(row, minlength=len(edges))
    first = np.searchsorted(row, np.arange(len(edges)))
    flat = np.zeros(len(edges), dtype=bool)
    two = np.flatnonzero(count == 2)
    flat[two] = np.einsum("ij,ij->i", normal[face[first[two]]], normal[face[first[two] + 1]]) >= FLAT_EDGE_COS
    return edges[~flat]


def unique_edges(triangles: np.ndarray) -> np.ndarray:
    """Unique undirected edges of a triangle mesh: shape (E, 2) int32, each row (lo, hi) with lo < hi, rows sorted."""
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(tri) == 0:
        return np.zeros((0, 2), dtype=np.int32)
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    edges.sort(axis=1)
    return np.unique(edges, axis=0).astype(np.int32)
