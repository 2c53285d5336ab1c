"""Rigid obstacles: triangle meshes with a base placement and an optional keyframed rigid motion.

Frames and conventions:

- An obstacle's ``vertices`` are given in its **body frame** [m].
- Its **base placement** ``transform = (px, py, pz, qx, qy, qz, qw)`` (position [m], unit quaternion in Warp's
  (x, y, z, w) order) takes body coordinates to world coordinates: ``base * u = R(q) u + p``. On a device it is
  ``Control.obstacle_transform``, which carries gradients.
- A scripted :class:`RigidMotion` ``M(t)`` is applied **on top of** the placement, in world coordinates:
  ``x(t) = M(t) * (base * u) = R_m(t) (R_b u + p_b) + p_m(t)``. Its rotation therefore turns about the **world
  origin**, not about the obstacle. To spin an obstacle about its own centre, give it ``pos = (0, 0, 0)`` (keep
  ``rot`` if wanted) and put its position into the motion's translations instead. Motion keyframes get no gradient.

Built-in shapes (:func:`plane_mesh`, :func:`box_mesh`, :func:`sphere_mesh`, :func:`funnel_mesh`) return
``(vertices, triangles)`` in the body frame, with triangles counter-clockwise seen from the side the cloth is meant to
be on (outside a closed shape). Obstacle meshes need not be closed or manifold.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from warpcloth.mesh_io import DEGENERATE_AREA_FRACTION, grid_mesh

if TYPE_CHECKING:  # pragma: no cover
    from warpcloth.model import Control, Model

__all__ = [
    "IDENTITY_TRANSFORM",
    "Obstacle",
    "RigidMotion",
    "box_mesh",
    "funnel_mesh",
    "obstacle_meshes_numpy",
    "obstacle_motion_numpy",
    "obstacle_points",
    "obstacle_points_numpy",
    "plane_mesh",
    "quat_from_matrix",
    "quat_to_matrix",
    "sphere_mesh",
    "unique_edges",
]

QUAT_UNIT_TOL = 1.0e-6
"""Largest accepted | |q| - 1 | of a rotation quaternion; beyond it a quaternion is an error, not renormalised."""

IDENTITY_TRANSFORM = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
"""The identity placement (px, py, pz, qx, qy, qz, qw)."""

_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_MAX_SPHERE_SUBDIVISIONS = 8  # 1,310,720 triangles; more is almost surely a typo


# ----------------------------------------------------------------------------------------------------------------------
# Quaternions (x, y, z, w), host side.


def _check_quat(what: str, q) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (4,):
        raise ValueError(f"{what}: a quaternion needs 4 components (x, y, z, w), got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError(f"{what}: quaternion has a non-finite component: {q.tolist()}")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_UNIT_TOL:
        raise ValueError(
            f"{what}: quaternion {q.tolist()} has norm {norm:.9g}; it must be a unit quaternion (x, y, z, w) "
            f"within {QUAT_UNIT_TOL:g}"
        )
    return q


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(q, dtype=np.float64)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_matrix(R) -> np.ndarray:
    """Unit quaternion (x, y, z, w) with ``w >= 0`` of a rotation matrix (3, 3).

    Raises:
        ValueError: when ``R`` is not a 3x3 rotation (orthonormal within 1e-6, determinant +1).
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"a rotation matrix must have shape (3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError("rotation matrix has a non-finite entry")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0.0:
        raise ValueError("rot must be a rotation matrix (orthonormal within 1e-6, determinant +1, no reflection)")
    # Shepperd's method: branch on the largest of (trace, diagonal) for a well-conditioned square root.
    tr = np.trace(R)
    d = np.diag(R)
    k = int(np.argmax([tr, d[0], d[1], d[2]]))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + d[0] - d[1] - d[2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + d[1] - d[0] - d[2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + d[2] - d[0] - d[1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0.0 else q


def _slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Spherical linear interpolation along the shorter arc (q and -q are the same rotation)."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 1.0 - 1e-12:  # (nearly) the same rotation: the slerp weights are 0/0
        q = (1.0 - s) * q0 + s * q1
    else:
        theta = math.acos(min(dot, 1.0))
        sin_theta = math.sin(theta)
        q = (math.sin((1.0 - s) * theta) * q0 + math.sin(s * theta) * q1) / sin_theta
    return q / np.linalg.norm(q)


def _placement(what: str, pos, rot) -> np.ndarray:
    """(7,) transform from a position [m] and a rotation (None, a 3x3 matrix or a quaternion (x, y, z, w))."""
    p = np.asarray(pos, dtype=np.float64)
    if p.shape != (3,):
        raise ValueError(f"{what}: pos must have 3 components, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{what}: pos has a non-finite component: {p.tolist()}")
    if rot is None:
        q = np.array([0.0, 0.0, 0.0, 1.0])
    else:
        r = np.asarray(rot, dtype=np.float64)
        if r.shape == (3, 3):
            try:
                q = quat_from_matrix(r)
            except ValueError as exc:
                raise ValueError(f"{what}: {exc}") from None
        elif r.shape == (4,):
            q = _check_quat(f"{what}: rot", r)
            q = q / np.linalg.norm(q)  # within QUAT_UNIT_TOL already: remove the rounding, not an error
        else:
            raise ValueError(
                f"{what}: rot must be a 3x3 rotation matrix or a quaternion (x, y, z, w), got shape {r.shape}"
            )
    return np.concatenate([p, q])


def _transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ quat_to_matrix(transform[3:]).T + transform[:3]


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Transform ``a * b`` (apply b, then a) as (7,)."""
    Ra = quat_to_matrix(a[3:])
    ax, ay, az, aw = a[3:]
    bx, by, bz, bw = b[3:]
    q = np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )
    return np.concatenate([Ra @ b[:3] + a[:3], q])


# ----------------------------------------------------------------------------------------------------------------------


@dataclass
class RigidMotion:
    """Keyframed rigid motion: piecewise-linear translation, slerp rotation, held constant outside the keys.

    Built from arrays (converted to float64 and validated on construction) or with :meth:`from_keyframes`.
    """

    times: np.ndarray
    """Key times [s], strictly increasing, shape (K,), K >= 1."""
    translations: np.ndarray
    """Translation at each key [m], shape (K, 3)."""
    rotations: np.ndarray
    """Rotation at each key as a unit quaternion (x, y, z, w), shape (K, 4); not renormalised."""

    def __post_init__(self):
        self.times = np.asarray(self.times, dtype=np.float64)
        self.translations = np.asarray(self.translations, dtype=np.float64)
        self.rotations = np.asarray(self.rotations, dtype=np.float64)
        k = self.times.shape[0] if self.times.ndim == 1 else -1
        if k < 1:
            raise ValueError(f"motion: times must have shape (K,) with K >= 1 keyframes, got {self.times.shape}")
        if self.translations.shape != (k, 3):
            raise ValueError(f"motion: translations must have shape ({k}, 3), got {self.translations.shape}")
        if self.rotations.shape != (k, 4):
            raise ValueError(f"motion: rotations must have shape ({k}, 4), got {self.rotations.shape}")
        for i in range(k):
            if not math.isfinite(self.times[i]):
                raise ValueError(f"motion keyframe {i}: time is not finite: {self.times[i]}")
            if i and self.times[i] <= self.times[i - 1]:
                raise ValueError(
                    f"motion keyframe {i}: key times must be strictly increasing, got {self.times[i]} after "
                    f"{self.times[i - 1]}"
                )
            if not np.all(np.isfinite(self.translations[i])):
                raise ValueError(f"motion keyframe {i}: translation is not finite: {self.translations[i].tolist()}")
            _check_quat(f"motion keyframe {i}: rotation", self.rotations[i])

    @classmethod
    def from_keyframes(cls, keyframes) -> RigidMotion:
        """Builds a motion from ``[(time [s], (tx, ty, tz) [m], (qx, qy, qz, qw)), ...]``.

        Raises:
            ValueError: naming the keyframe for a malformed, non-finite, out-of-order or non-unit entry.
        """
        keys = list(keyframes)
        if not keys:
            raise ValueError("motion needs at least one (time, translation, quaternion) keyframe")
        times, trans, rots = [], [], []
        for i, key in enumerate(keys):
            if isinstance(key, (str, bytes)) or len(key) != 3:
                raise ValueError(f"motion keyframe {i}: expected (time, (tx, ty, tz), (qx, qy, qz, qw)), got {key!r}")
            t, tr, q = key
            tr, q = np.asarray(tr, dtype=np.float64), np.asarray(q, dtype=np.float64)
            if tr.shape != (3,):
                raise ValueError(f"motion keyframe {i}: translation needs 3 components, got shape {tr.shape}")
            if q.shape != (4,):
                raise ValueError(f"motion keyframe {i}: rotation needs 4 components (x, y, z, w), got shape {q.shape}")
            times.append(float(t))
            trans.append(tr)
            rots.append(q)
        return cls(np.array(times), np.array(trans), np.array(rots))

    @property
    def key_count(self) -> int:
        """Number of keyframes K."""
        return int(self.times.shape[0])

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Translation (3,) [m] and unit quaternion (4,) (x, y, z, w) at time ``t`` [s].

        Before the first key and after the last one the motion holds that key's value. Between keys the translation
        is linear and the rotation a slerp along the shorter arc (renormalised against rounding).
        """
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"motion: time must be finite, got {t}")
        if t <= self.times[0]:
            return self.translations[0].copy(), self.rotations[0].copy()
        if t >= self.times[-1]:
            return self.translations[-1].copy(), self.rotations[-1].copy()
        i = int(np.searchsorted(self.times, t, side="right")) - 1
        s = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        tr = (1.0 - s) * self.translations[i] + s * self.translations[i + 1]
        return tr, _slerp(self.rotations[i], self.rotations[i + 1], s)

    def transform_at(self, t: float) -> np.ndarray:
        """The motion at time ``t`` as a (7,) transform (tx, ty, tz, qx, qy, qz, qw)."""
        tr, q = self.at(t)
        return np.concatenate([tr, q])


@dataclass
class Obstacle:
    """A rigid triangle mesh (validated and converted on construction).

    Raises on construction:
        ValueError: for an invalid name, a wrong shape, a non-finite vertex (naming it), a triangle index out of
            range or a degenerate (zero-area) triangle (naming the triangle), or a bad transform.
    """

    name: str
    """Obstacle name; a valid USD identifier (letters, digits and underscores, not starting with a digit)."""
    vertices: np.ndarray
    """Vertex positions in the obstacle's body frame [m], shape (V, 3), float64."""
    triangles: np.ndarray
    """Vertex indices, shape (T, 3), int32, T >= 1; counter-clockwise seen from the side the cloth is on."""
    transform: np.ndarray
    """Base placement (px, py, pz [m], qx, qy, qz, qw), shape (7,), float64: world = R(q) body + p."""
    motion: RigidMotion | None = None
    """Scripted motion applied on top of the placement (see the module docstring), or None for a static obstacle."""

    def __post_init__(self):
        if not isinstance(self.name, str) or not _IDENTIFIER.match(self.name):
            raise ValueError(
                f"obstacle name {self.name!r} is not a valid identifier (letters, digits and underscores, "
                "not starting with a digit)"
            )
        what = f"obstacle {self.name!r}"
        v = np.asarray(self.vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
            raise ValueError(f"{what}: vertices must have shape (V, 3) with V > 0, got {v.shape}")
        bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
        if bad.size:
            raise ValueError(f"{what}: vertex {int(bad[0])} is not finite: {v[bad[0]].tolist()}")
        tri = np.asarray(self.triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0:
            raise ValueError(f"{what}: triangles must have shape (T, 3) with T > 0, got {tri.shape}")
        if not np.issubdtype(tri.dtype, np.integer):
            raise ValueError(f"{what}: triangles must hold integers, got dtype {tri.dtype}")
        bad = np.argwhere((tri < 0) | (tri >= len(v)))
        if len(bad):
            t = int(bad[0][0])
            raise ValueError(f"{what}: triangle {t} {tri[t].tolist()} has an index out of range [0, {len(v)})")
        tri = tri.astype(np.int32)
        area = 0.5 * np.linalg.norm(np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]]), axis=1)
        threshold = DEGENERATE_AREA_FRACTION * float(np.mean(area))
        bad = np.flatnonzero(area <= threshold)
        if bad.size:
            t = int(bad[0])
            raise ValueError(
                f"{what}: triangle {t} {tri[t].tolist()} is degenerate (area {area[t]:.6g} m^2); "
                "obstacle triangles need a non-zero area"
            )
        tf = np.asarray(self.transform, dtype=np.float64)
        if tf.shape != (7,):
            raise ValueError(f"{what}: transform must be (px, py, pz, qx, qy, qz, qw), got shape {tf.shape}")
        if not np.all(np.isfinite(tf[:3])):
            raise ValueError(f"{what}: transform position is not finite: {tf[:3].tolist()}")
        _check_quat(f"{what}: transform", tf[3:])
        if self.motion is not None and not isinstance(self.motion, RigidMotion):
            raise ValueError(f"{what}: motion must be a RigidMotion or None, got {type(self.motion).__name__}")
        self.vertices, self.triangles, self.transform = v, tri, tf

    @property
    def vertex_count(self) -> int:
        """Number of vertices V."""
        return int(self.vertices.shape[0])

    @property
    def triangle_count(self) -> int:
        """Number of triangles T."""
        return int(self.triangles.shape[0])

    def world_vertices(self, t: float = 0.0) -> np.ndarray:
        """Vertex positions in the world at time ``t`` [s] with the base placement, shape (V, 3) [m]."""
        tf = self.transform if self.motion is None else _compose(self.motion.transform_at(t), self.transform)
        return _transform_points(tf, self.vertices)


# ----------------------------------------------------------------------------------------------------------------------
# Built-in shapes.


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
    """A rectangle in the body XY plane, centred on the origin, facing +z.

    Args:
        size: (width along x, height along y) [m], > 0.
        res: cells along x and y (>= 1); ``res[0] * res[1] * 2`` triangles.

    Returns:
        ``(vertices (V, 3) float64, triangles (T, 3) int32)``, triangles counter-clockwise seen from +z.
    """
    sx, sy = _positive("plane size", size, 2)
    if isinstance(res, (str, bytes)) or len(res) != 2:
        raise ValueError(f"plane res must be two cell counts, got {res!r}")
    rx, ry = (_count(f"plane res[{i}]", r, 1) for i, r in enumerate(res))
    mesh = grid_mesh(rx, ry, float(sx), float(sy))
    return mesh.positions - np.array([0.5 * sx, 0.5 * sy, 0.0]), mesh.triangles.astype(np.int32)


def box_mesh(half_extents: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box centred on the origin: 8 vertices, 12 triangles facing outwards.

    Args:
        half_extents: half sizes (hx, hy, hz) [m], > 0.

    Returns:
        ``(vertices (8, 3) float64, triangles (12, 3) int32)``; vertex ``i + 2 j + 4 k`` is at
        ``((2i - 1) hx, (2j - 1) hy, (2k - 1) hz)``.
    """
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
    """An icosphere: an icosahedron whose faces are split in four ``subdivisions`` times, projected on the sphere.

    Args:
        radius: sphere radius [m], > 0. Every vertex lies exactly on the sphere (the faces inside it).
        subdivisions: 0 (the icosahedron, 20 triangles) to 8; ``20 * 4**subdivisions`` triangles and
            ``10 * 4**subdivisions + 2`` vertices (3: 1280 triangles, 642 vertices).

    Returns:
        ``(vertices (V, 3) float64, triangles (T, 3) int32)``, triangles facing outwards.
    """
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
    """The seed's funnel (``meshes/contain.obj`` of Liang et al. 2019): an inverted square pyramid without a lid.

    The 1 m x 1 m square opening spans [0, 1] x [0, 1] at z = 0 (two corners at z = 1e-6, as in the file) and the apex
    is at (0.5, 0.5, -0.666539). The seed's collision demo places it with ``pos = (-0.5, -1, -0.55)``. The four
    triangles are the file's, in its winding: they face up into the cavity, where the cloth falls.

    Returns:
        ``(vertices (5, 3) float64, triangles (4, 3) int32)``.
    """
    return _FUNNEL_VERTICES.copy(), _FUNNEL_TRIANGLES.copy()


# ----------------------------------------------------------------------------------------------------------------------


def unique_edges(triangles: np.ndarray) -> np.ndarray:
    """Unique undirected edges of a triangle mesh: shape (E, 2) int32, each row (lo, hi) with lo < hi, rows sorted."""
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(tri) == 0:
        return np.zeros((0, 2), dtype=np.int32)
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    edges.sort(axis=1)
    return np.unique(edges, axis=0).astype(np.int32)


def _require_obstacles(model: Model, what: str) -> None:
    if model.obstacle_count == 0:
        raise ValueError(f"{what}: the model has no obstacles")


def obstacle_motion_numpy(model: Model, t: float) -> np.ndarray:
    """The scripted motion of every obstacle at time ``t`` [s] as transforms, shape (obstacle_count, 7).

    Static obstacles get the identity (0, 0, 0, 0, 0, 0, 1).
    """
    out = np.tile(IDENTITY_TRANSFORM, (model.obstacle_count, 1))
    for b, motion in enumerate(model.obstacle_motion):
        if motion is not None:
            out[b] = motion.transform_at(t)
    return out


def _check_transforms(model: Model, transforms) -> np.ndarray:
    tf = np.asarray(transforms, dtype=np.float64)
    if tf.shape != (model.obstacle_count, 7):
        raise ValueError(f"transforms must have shape ({model.obstacle_count}, 7), got {tf.shape}")
    return tf


def obstacle_points_numpy(model: Model, t: float, transforms=None) -> np.ndarray:
    """World positions of all obstacle vertices at time ``t`` [s], on the host (float64).

    Args:
        model: a model with obstacles.
        t: time [s] at which the scripted motions are evaluated.
        transforms: base placements, shape (obstacle_count, 7); default ``model.obstacle_rest_transform``
            (pass ``control.obstacle_transform.numpy()`` to follow an optimised placement).

    Returns:
        Positions [m], shape (obstacle_vertex_count, 3), in the model's concatenated vertex order.
    """
    _require_obstacles(model, "obstacle_points_numpy")
    base = model.obstacle_rest_transform if transforms is None else _check_transforms(model, transforms)
    motion = obstacle_motion_numpy(model, t)
    local = model.obstacle_vertex_local.numpy().astype(np.float64)
    out = np.empty_like(local)
    for b in range(model.obstacle_count):
        lo, hi = model.obstacle_vertex_start[b], model.obstacle_vertex_start[b + 1]
        out[lo:hi] = _transform_points(_compose(motion[b], base[b]), local[lo:hi])
    return out


def obstacle_meshes_numpy(model: Model, times: Sequence[float], transforms=None) -> list:
    """Obstacles as ``(name, vertices, triangles)`` for :func:`warpcloth.usd.write_usd`.

    A static obstacle's vertices are (M, 3) (at ``times[0]``); a moving one's are (F, M, 3), one per entry of
    ``times`` [s]. Triangles (K, 3) index the obstacle's own vertices. ``transforms`` as in
    :func:`obstacle_points_numpy`. A model without obstacles gives an empty list.
    """
    if model.obstacle_count == 0:
        return []
    times = [float(t) for t in times]
    if not times:
        raise ValueError("obstacle_meshes_numpy: times is empty")
    moving = any(m is not None for m in model.obstacle_motion)
    frames = [obstacle_points_numpy(model, t, transforms) for t in (times if moving else times[:1])]
    vs, ts = model.obstacle_vertex_start, model.obstacle_tri_start
    out = []
    for b, name in enumerate(model.obstacle_names):
        tris = model.obstacle_triangles_np[ts[b]: ts[b + 1]] - vs[b]
        if model.obstacle_motion[b] is None:
            verts = frames[0][vs[b]: vs[b + 1]]
        else:
            verts = np.stack([f[vs[b]: vs[b + 1]] for f in frames])
        out.append((name, verts, tris))
    return out


def obstacle_points(model: Model, control: Control, t: float, out: wp.array | None = None) -> wp.array:
    """World positions of all obstacle vertices at time ``t`` [s], computed on the model's device.

    ``x = motion(t) * (control.obstacle_transform[body] * local)``. The launch is recorded on an active ``wp.Tape``
    like any other, so gradients flow to ``control.obstacle_transform`` (position and quaternion components) and
    to ``model.obstacle_vertex_local`` when they require them. The motions are evaluated on the host; they get no
    gradient.

    Args:
        model: a model with obstacles.
        control: supplies ``obstacle_transform``, the base placements.
        t: time [s] at which the scripted motions are evaluated.
        out: optional output array, (obstacle_vertex_count,) vec3 of the model's scalar type, on its device.
            A new array (with a gradient when the inputs have one) when None. Do not reuse one array for two
            times while a tape records.

    Returns:
        The positions [m], shape (obstacle_vertex_count,) vec3.

    Raises:
        ValueError: when the model has no obstacles, the control has no ``obstacle_transform`` of the right size, or
            ``out`` has the wrong shape, dtype or device.
    """
    from warpcloth.kernels.obstacle import obstacle_kernels

    _require_obstacles(model, "obstacle_points")
    t_ = model.types
    base = getattr(control, "obstacle_transform", None)
    if base is None or base.shape != (model.obstacle_count,) or base.dtype != t_.transform:
        got = "None" if base is None else f"shape {base.shape}, dtype {wp.types.type_repr(base.dtype)}"
        raise ValueError(
            f"obstacle_points: control.obstacle_transform must be ({model.obstacle_count},) "
            f"{wp.types.type_repr(t_.transform)}, got {got}; create the control with model.control()"
        )
    n = model.obstacle_vertex_count
    if out is None:
        rg = base.requires_grad or model.obstacle_vertex_local.requires_grad
        out = wp.empty(n, dtype=t_.vec3, device=model.device, requires_grad=rg)
    elif out.shape != (n,) or out.dtype != t_.vec3 or out.device != model.device:
        raise ValueError(
            f"obstacle_points: out must be ({n},) {wp.types.type_repr(t_.vec3)} on {model.device}, got shape "
            f"{out.shape}, dtype {wp.types.type_repr(out.dtype)} on {out.device}"
        )
    motion = wp.array(obstacle_motion_numpy(model, t), dtype=t_.transform, device=model.device)
    wp.launch(
        obstacle_kernels(model.scalar).world_points,
        dim=n,
        inputs=[model.obstacle_vertex_local, model.obstacle_vertex_body, base, motion],
        outputs=[out],
        device=model.device,
    )
    return out
