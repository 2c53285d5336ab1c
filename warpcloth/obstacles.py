"""Rigid obstacles: triangle meshes, closed or not, with a base placement and an optional keyframed motion. The
placement (on a device ``Control.obstacle_transform``) carries gradients; a :class:`RigidMotion` ``M(t)`` does not and
acts in world coordinates, ``x(t) = M(t) * (base * u)``, turning about the world origin: to spin an obstacle about its
centre, place it at the origin and put its position into the motion's translations."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from warpcloth.geometry.motion import RigidMotion
from warpcloth.geometry.transforms import IDENTITY_TRANSFORM, check_quat, compose, transform_points
from warpcloth.kernels.obstacle import obstacle_kernels
from warpcloth.mesh_io import DEGENERATE_AREA_FRACTION
from warpcloth.model import Control, Model

__all__ = [
    "Obstacle",
    "RigidMotion",
    "obstacle_meshes_numpy",
    "obstacle_motion_numpy",
    "obstacle_points",
    "obstacle_points_numpy",
]

_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


# ----------------------------------------------------------------------------------------------------------------------


@dataclass
class Obstacle:
    """A rigid triangle mesh, validated and converted on construction.

    Raises:
        ValueError: a bad name, shape or transform, a non-finite vertex, an index out of range, a zero-area triangle.
    """

    name: str
    """A USD identifier: letters, digits and underscores, not starting with a digit."""
    vertices: np.ndarray
    """Vertex positions in the obstacle's body frame [m], shape (V, 3), float64."""
    triangles: np.ndarray
    """Vertex indices, shape (T, 3), int32, T >= 1; counter-clockwise seen from the side the cloth is on."""
    transform: np.ndarray
    """Base placement (px, py, pz [m], qx, qy, qz, qw), shape (7,), float64: world = R(q) body + p."""
    motion: RigidMotion | None = None
    """Scripted motion on top of the placement, or None (static)."""

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
        check_quat(f"{what}: transform", tf[3:])
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
        tf = self.transform if self.motion is None else compose(self.motion.transform_at(t), self.transform)
        return transform_points(tf, self.vertices)


# ----------------------------------------------------------------------------------------------------------------------
# Model-level obstacle geometry.


def _require_obstacles(model: Model, what: str) -> None:
    if model.obstacle_count == 0:
        raise ValueError(f"{what}: the model has no obstacles")


def obstacle_motion_numpy(model: Model, t: float) -> np.ndarray:
    """Every obstacle's scripted motion at time ``t`` [s], (obstacle_count, 7); the identity for a static one."""
    out = np.tile(IDENTITY_TRANSFORM, (model.obstacle_count, 1))
    for b, motion in enumerate(model.obstacle_motion):
        if motion is not None:
            out[b] = motion.transform_at(t)
    return out


def obstacle_motion(model: Model, t: float) -> wp.array:
    """:func:`obstacle_motion_numpy` as a new array of transforms on the model's device."""
    return wp.array(obstacle_motion_numpy(model, t), dtype=model.types.transform, device=model.device)


def _check_transforms(model: Model, transforms) -> np.ndarray:
    tf = np.asarray(transforms, dtype=np.float64)
    if tf.shape != (model.obstacle_count, 7):
        raise ValueError(f"transforms must have shape ({model.obstacle_count}, 7), got {tf.shape}")
    return tf


def obstacle_points_numpy(model: Model, t: float, transforms=None) -> np.ndarray:
    """World positions [m] (obstacle_vertex_count, 3) float64 of every obstacle vertex at time ``t`` [s], on the
    host. ``transforms``: base placements (obstacle_count, 7), default ``model.obstacle_rest_transform``."""
    _require_obstacles(model, "obstacle_points_numpy")
    base = model.obstacle_rest_transform if transforms is None else _check_transforms(model, transforms)
    motion = obstacle_motion_numpy(model, t)
    local = model.obstacle_vertex_local.numpy().astype(np.float64)
    out = np.empty_like(local)
    for b in range(model.obstacle_count):
        lo, hi = model.obstacle_vertex_start[b], model.obstacle_vertex_start[b + 1]
        out[lo:hi] = transform_points(compose(motion[b], base[b]), local[lo:hi])
    return out


def obstacle_meshes_numpy(model: Model, times: Sequence[float], transforms=None) -> list:
    """``(name, vertices, triangles)`` per obstacle for :func:`warpcloth.usd.write_usd`: vertices (M, 3) at ``times[0]``
    if static, else (F, M, 3) at ``times`` [s], indexed locally; ``transforms`` as in :func:`obstacle_points_numpy`."""
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


def obstacle_points(model: Model, control: Control, t: float, out: wp.array | None = None, *,
                    motion: wp.array | None = None) -> wp.array:
    """World positions [m] (obstacle_vertex_count,) vec3 at time ``t`` [s] on the model's device,
    ``motion(t) * (control.obstacle_transform[body] * local)``, taped to both factors.

    Args:
        out: the output array, or None for a new one; not one array for two times on a tape.
        motion: :func:`obstacle_motion` at ``t`` (default: made now; a captured graph needs one made before).

    Raises:
        ValueError: no obstacles, no ``obstacle_transform`` of the right size, or a wrong ``out``.
    """
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
    if motion is None:
        motion = obstacle_motion(model, t)
    wp.launch(
        obstacle_kernels(model.scalar).world_points,
        dim=n,
        inputs=[model.obstacle_vertex_local, model.obstacle_vertex_body, base, motion],
        outputs=[out],
        device=model.device,
    )
    return out
