"""What a recording observes of the cloth, each as a loss on the device over a trajectory's compared frames.

An observation (:class:`VertexFrames`, :class:`MarkerFrames`, :class:`PointCloudFrames`) holds the recorded frames;
``observation.bind(model)`` checks them against the model and allocates the buffers its losses reuse, and returns an
:class:`ObservationLoss`, called with the simulated positions of the compared frames. The loss is differentiable
with Warp's tape with respect to those positions (and so to everything upstream of them). A model of several equal
worlds (``ModelBuilder.replicate``) gets one loss per world: every world is compared with the same recording.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import warp as wp

from warpcloth.kernels.losses import loss_kernels
from warpcloth.kernels.observations import observation_kernels


def _integer(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _finite_rows(name: str, rows, what: str) -> None:
    bad = ~np.isfinite(rows).all(axis=-1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name}, {what} {i}: not finite ({rows[i].tolist()})")


def _world_layout(model, what: str) -> tuple[int, np.ndarray]:
    """(particles of a world, one world's triangles in its own particle indices (T, 3) int32), checking that the
    model's worlds are equal cloths."""
    starts = np.asarray(model.world_particle_start, dtype=np.int64)
    counts = np.diff(starts)
    tris = np.asarray(model.triangles_np, dtype=np.int64)
    tri_world = np.searchsorted(starts, tris[:, 0], side="right") - 1
    local0 = None
    for w in range(model.world_count):
        local = tris[tri_world == w] - starts[w]
        if local0 is None:
            local0 = local
        elif counts[w] != counts[0] or not np.array_equal(local, local0):
            raise ValueError(f"{what}: world {w}'s cloth differs from world 0's; an observation compares equal worlds "
                             "(ModelBuilder.replicate) with one recording")
    return int(counts[0]), local0.astype(np.int32)


class ObservationLoss:
    """An observation bound to a model: ``loss(positions, frames)`` -> each world's loss, (world_count,).

    Call with ``positions[j]`` the simulated particle positions (``state.particle_x``, (particle_count,) vec3 of the
    model's precision) compared with recorded frame ``frames[j]`` (default ``range(len(positions))``). The loss is
    added, times ``weight``, into ``out`` (zeroed by the caller) or into a new zeroed array with ``requires_grad``.
    Evaluations share buffers: back-propagate one before the next. :attr:`capturable` says whether the launches
    can be recorded into a CPU graph (``wc.CapturedRollout``'s loss).

    Raises:
        ValueError: frames out of range or repeated, positions of another shape, type or device, no observed frame
            among those compared."""

    capturable = True

    def __init__(self, observation, model):
        self.observation, self.model = observation, model
        self.particles, self.triangles_np = _world_layout(model, type(observation).__name__)
        self._first = wp.array(np.asarray(model.world_particle_start[:-1], dtype=np.int32), dtype=wp.int32,
                               device=model.device)
        self._scalar = model.scalar

    def __call__(self, positions: Sequence[wp.array], frames: Sequence[int] | None = None, *,
                 out: wp.array | None = None, weight: float = 1.0) -> wp.array:
        model = self.model
        positions = list(positions)
        frames = list(range(len(positions)) if frames is None else frames)
        if len(frames) != len(positions) or not frames:
            raise ValueError(f"{len(positions)} position arrays for {len(frames)} frames; give one per frame, at "
                             "least one")
        count = self.observation.frame_count
        for j, k in enumerate(frames):
            if not _integer(k) or not 0 <= k < count:
                raise ValueError(f"compared frame {k!r} out of range: the recording has {count} frames")
            x = positions[j]
            if (not isinstance(x, wp.array) or x.shape != (model.particle_count,)
                    or not wp.types.types_equal(x.dtype, model.types.vec3) or x.device != model.device):
                raise ValueError(f"positions[{j}] (frame {k}) must be a ({model.particle_count},) array of "
                                 f"vec3 of {model.scalar.__name__} on {model.device}, got {x!r}")
        if len(set(frames)) != len(frames):
            raise ValueError(f"a frame is compared twice in {frames}")
        if not np.isfinite(weight):
            raise ValueError(f"weight must be finite, got {weight!r}")
        if out is None:
            out = wp.zeros(model.world_count, dtype=model.scalar, device=model.device, requires_grad=True)
        elif out.shape != (model.world_count,) or out.dtype != model.scalar:
            raise ValueError(f"out must be a ({model.world_count},) array of the model's scalar, got {out!r}")
        self._launch([int(k) for k in frames], positions, out, float(weight))
        return out


class _VertexLoss(ObservationLoss):
    def __init__(self, observation, model):
        super().__init__(observation, model)
        frames = observation.frames
        n = frames.shape[1]
        if n == self.particles:
            first = self._first  # one recording of a world, for every world
        elif n == model.particle_count:
            first = wp.zeros(model.world_count, dtype=wp.int32, device=model.device)  # every world its own
        else:
            raise ValueError(f"VertexFrames: the frames hold {n} vertices, the model's worlds {self.particles} "
                             f"each ({model.particle_count} in all)")
        self._offsets = first
        self._targets = [wp.array(f, dtype=model.types.vec3, device=model.device) for f in frames]
        self._kernel = loss_kernels(model.scalar).world_squared_distance

    def _launch(self, frames, positions, out, weight):
        model = self.model
        scale = self._scalar(weight * (1.0 / (len(frames) * self.particles)))  # weight 1: TrajectoryFit's, bitwise
        for k, x in zip(frames, positions):
            wp.launch(self._kernel, model.particle_count, inputs=[x, self._targets[k], model.particle_world,
                                                                  self._offsets, scale], outputs=[out])


class VertexFrames:
    """Every vertex of the cloth recorded in every frame, in the mesh's order: ``frames`` (F, n, 3) [m], n the
    particles of a world (one recording for every world) or of the whole model (each world its own).

    Loss: the mean over compared frames of the mean over a world's vertices of |x_sim - x_rec|^2 [m^2].
    ValueError: a shape other than (F, n, 3), a value not finite (naming frame and vertex)."""

    capturable = True

    def __init__(self, frames):
        frames = np.asarray(frames, dtype=np.float64)
        if frames.ndim != 3 or frames.shape[2] != 3 or frames.shape[0] < 1 or frames.shape[1] < 1:
            raise ValueError(f"VertexFrames: frames must be (F, n, 3) with F, n >= 1, got shape {frames.shape}")
        for k, f in enumerate(frames):
            _finite_rows(f"VertexFrames: frame {k}", f, "vertex")
        self.frames, self.frame_count = frames, frames.shape[0]

    def bind(self, model) -> ObservationLoss:
        return _VertexLoss(self, model)


class _MarkerLoss(ObservationLoss):
    def __init__(self, observation, model):
        super().__init__(observation, model)
        obs, device, vec3 = observation, model.device, model.types.vec3
        tri_count = len(self.triangles_np)
        for m, t in enumerate(obs.triangles):
            if not 0 <= t < tri_count:
                raise ValueError(f"MarkerFrames: marker {m}'s triangle {int(t)} out of range: the cloth (a world) "
                                 f"has {tri_count} triangles")
        self._tri = wp.array(self.triangles_np, dtype=wp.int32, device=device)
        self._marker_tri = wp.array(obs.triangles.astype(np.int32), dtype=wp.int32, device=device)
        self._bary = wp.array(obs.barycentric, dtype=vec3, device=device)
        visible = ~np.isnan(obs.positions[..., 0])  # (F, M)
        self._count = visible.sum(axis=1)
        self._offset = np.concatenate([[0], np.cumsum(self._count)[:-1]])
        f_idx, m_idx = np.nonzero(visible)  # row-major: frame by frame
        self._visible = wp.array(m_idx.astype(np.int32), dtype=wp.int32, device=device)
        self._target = wp.array(obs.positions[f_idx, m_idx].reshape(-1, 3), dtype=vec3, device=device)
        self._kernel = observation_kernels(model.scalar).marker_loss

    def _launch(self, frames, positions, out, weight):
        seen = int(sum(self._count[k] for k in frames))
        if seen == 0:
            raise ValueError(f"MarkerFrames: no marker is visible in the compared frames {frames}")
        scale, W = self._scalar(weight / seen), self.model.world_count
        for k, x in zip(frames, positions):
            n = int(self._count[k])
            if n:
                wp.launch(self._kernel, W * n, inputs=[x, self._tri, self._marker_tri, self._bary, self._visible,
                                                       self._target, int(self._offset[k]), n, self._first, scale],
                          outputs=[out])


class MarkerFrames:
    """M markers fixed on the cloth's surface: marker m at ``sum_k barycentric[m, k] x[tri[k]]``, ``tri`` triangle
    ``triangles[m]`` of the model's (of one world's) triangles; ``positions`` (F, M, 3) [m], all three NaN where a
    marker is hidden in a frame.

    Loss: the mean over the visible (frame, marker) pairs of the compared frames of |p_sim - p_rec|^2 [m^2]; a hidden
    marker is skipped by design, a frame with every marker hidden contributes nothing.
    ValueError: shapes; a coordinate < 0 or a sum off 1 by more than 1e-6 (naming the marker); a position partly
    NaN or infinite (naming frame and marker); at ``bind``, a triangle out of range (naming the marker)."""

    capturable = True

    def __init__(self, triangles, barycentric, positions):
        triangles = np.asarray(triangles)
        barycentric = np.asarray(barycentric, dtype=np.float64)
        positions = np.asarray(positions, dtype=np.float64)
        if triangles.ndim != 1 or triangles.size < 1 or not np.issubdtype(triangles.dtype, np.integer):
            raise ValueError(f"MarkerFrames: triangles must be (M,) integers, M >= 1, got {triangles.dtype} "
                             f"{triangles.shape}")
        M = triangles.size
        if barycentric.shape != (M, 3):
            raise ValueError(f"MarkerFrames: barycentric must be ({M}, 3), got {barycentric.shape}")
        if positions.ndim != 3 or positions.shape[1:] != (M, 3) or positions.shape[0] < 1:
            raise ValueError(f"MarkerFrames: positions must be (F, {M}, 3) with F >= 1, got {positions.shape}")
        for m, b in enumerate(barycentric):
            if not np.isfinite(b).all() or (b < 0.0).any() or abs(b.sum() - 1.0) > 1e-6:
                raise ValueError(f"MarkerFrames: marker {m}'s barycentric coordinates {b.tolist()} must be >= 0 and "
                                 "sum to 1 (within 1e-6)")
        nan = np.isnan(positions)
        partly = nan.any(axis=2) & ~nan.all(axis=2)
        if partly.any():
            k, m = np.argwhere(partly)[0]
            raise ValueError(f"MarkerFrames: frame {k}, marker {m}: position {positions[k, m].tolist()} is partly "
                             "NaN (a hidden marker has all three NaN)")
        inf = np.isinf(positions).any(axis=2)
        if inf.any():
            k, m = np.argwhere(inf)[0]
            raise ValueError(f"MarkerFrames: frame {k}, marker {m}: position {positions[k, m].tolist()} is infinite")
        self.triangles, self.barycentric, self.positions = triangles.astype(np.int64), barycentric, positions
        self.frame_count = positions.shape[0]

    def bind(self, model) -> ObservationLoss:
        return _MarkerLoss(self, model)


class _PointCloudLoss(ObservationLoss):
    capturable = False  # wp.Mesh.refit is not recorded by Warp's CPU graph capture (a Bvh's refit is)

    def __init__(self, observation, model):
        super().__init__(observation, model)
        obs, device, vec3 = observation, model.device, model.types.vec3
        W, n = model.world_count, self.particles
        self._kernels = observation_kernels(model.scalar)
        self._tri = wp.array(self.triangles_np, dtype=wp.int32, device=device)
        # one query mesh per world over its own slice of a single-precision copy of the positions
        self._mesh_points = wp.zeros(model.particle_count, dtype=wp.vec3f, device=device)
        # the trees are built on the initial positions, then refitted to each frame's
        wp.launch(self._kernels.to_mesh_points, model.particle_count, inputs=[model.particle_x0],
                  outputs=[self._mesh_points], record_tape=False)
        indices = wp.array(self.triangles_np.reshape(-1), dtype=wp.int32, device=device)
        self._meshes = [wp.Mesh(points=self._mesh_points[w * n:(w + 1) * n], indices=indices) for w in range(W)]
        self._mesh_ids = wp.array([m.id for m in self._meshes], dtype=wp.uint64, device=device)
        sizes = np.array([0 if p is None else len(p) for p in obs.points], dtype=np.int64)
        self._size, self._offset = sizes, np.concatenate([[0], np.cumsum(sizes)[:-1]])
        seen = [p for p in obs.points if p is not None]
        self._q = wp.array(np.concatenate(seen), dtype=vec3, device=device)
        # per-frame query results, allocated once: (face, bary) per world and recorded point; nearest per particle
        total = int(sizes.sum())
        self._face = wp.zeros(W * total, dtype=wp.int32, device=device)
        self._bary = wp.zeros(W * total, dtype=vec3, device=device)
        self._slot = np.cumsum(sizes > 0) - 1  # each observed frame's row of the nearest-point buffer
        self._nearest = (wp.zeros(len(seen) * model.particle_count, dtype=wp.int32, device=device)
                         if obs.both_ways else None)
        huber = obs.robust is not None and obs.robust[0] == "huber"
        self._delta = model.scalar(obs.robust[1] if huber else 0.0)
        self._trim = obs.robust[1] if obs.robust is not None and obs.robust[0] == "trimmed" else None
        # trimmed: each frame's kept points (1) by world, chosen on the host from their distances; else empty: all
        self._keep = wp.zeros(W * total if self._trim else 0, dtype=wp.int32, device=device)
        self._d2 = wp.zeros(W * int(sizes.max()) if self._trim else 0, dtype=model.scalar, device=device)

    def _launch(self, frames, positions, out, weight):
        model, K = self.model, self._kernels
        seen = [k for k in frames if self._size[k]]
        if not seen:
            raise ValueError(f"PointCloudFrames: every compared frame {frames} is dropped (None)")
        W, N = model.world_count, model.particle_count
        for k, x in zip(frames, positions):
            P, offset = int(self._size[k]), int(self._offset[k])
            if not P:
                continue
            base = W * offset
            wp.launch(K.to_mesh_points, N, inputs=[x], outputs=[self._mesh_points], record_tape=False)
            for mesh in self._meshes:
                mesh.refit()
            wp.launch(K.closest_on_surface, W * P, inputs=[self._mesh_ids, x, self._tri, self._first, self._q,
                                                           offset, P, base], outputs=[self._face, self._bary],
                      record_tape=False)
            kept = P
            if self._trim is not None:  # keep each world's P - floor(trim P) nearest points
                kept = P - int(math.floor(self._trim * P))
                wp.launch(K.surface_distance2, W * P, inputs=[x, self._tri, self._first, self._q, offset, P, base,
                                                              self._face, self._bary], outputs=[self._d2],
                          record_tape=False)
                d2 = self._d2.numpy()[: W * P].reshape(W, P)
                mask = np.zeros((W, P), dtype=np.int32)
                np.put_along_axis(mask, np.argpartition(d2, kept - 1, axis=1)[:, :kept], 1, axis=1)
                self._keep[base:base + W * P].assign(mask.ravel())
            scale = self._scalar(weight / (len(seen) * kept))
            wp.launch(K.surface_loss, W * P, inputs=[x, self._tri, self._first, self._q, offset, P, base,
                                                     self._face, self._bary, self._delta, self._keep, scale],
                      outputs=[out])
            if self._nearest is not None:
                row = int(self._slot[k]) * N
                wp.launch(K.nearest_point, N, inputs=[x, self._q, offset, P, row], outputs=[self._nearest],
                          record_tape=False)
                scale = self._scalar(weight * self.observation.both_ways_weight / (len(seen) * self.particles))
                wp.launch(K.nearest_loss, N, inputs=[x, self._q, self._nearest, row, model.particle_world, scale],
                          outputs=[out])


class PointCloudFrames:
    """A point set per frame, ``points[k]`` (P_k, 3) [m] of any size and order, or None for a dropped frame,
    compared by the distance d_i from each recorded point to the simulated cloth's surface (closest points on a
    ``wp.Mesh`` of the frame's positions, held fixed on the tape: the exact gradient where the closest point is
    unique).

    Loss: per observed compared frame, the mean over its points of rho(d_i), rho(d) = d^2, or with
    ``robust=("huber", delta)`` (delta > 0 [m]) d^2 / 2 up to delta and delta (d - delta / 2) beyond, or with
    ``robust=("trimmed", fraction)`` (0 < fraction < 1) d^2 over the P - floor(fraction P) points nearest the
    surface, the rest left out (chosen per frame and world on the host: a read-back a frame on a GPU); with
    ``both_ways``, plus ``both_ways_weight`` times the mean over a world's vertices of the squared distance to their
    nearest recorded point (brute force over the frame's points); then the mean over observed compared frames
    [m^2]. Not capturable (:attr:`capturable`): the meshes' refits are host calls a CPU graph does not record.
    ValueError: no frame, a frame empty or not (P, 3), a point not finite (naming frame and point), a robust option
    other than None, ("huber", delta > 0) or ("trimmed", 0 < fraction < 1), a negative or non-finite
    both_ways_weight."""

    capturable = False

    def __init__(self, points, *, robust=None, both_ways: bool = False, both_ways_weight: float = 1.0):
        points = list(points)
        if not points:
            raise ValueError("PointCloudFrames: no frame")
        frames = []
        for k, p in enumerate(points):
            if p is None:
                frames.append(None)
                continue
            p = np.asarray(p, dtype=np.float64)
            if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 1:
                raise ValueError(f"PointCloudFrames: frame {k} must be (P, 3) with P >= 1 (None for a dropped "
                                 f"frame), got shape {p.shape}")
            _finite_rows(f"PointCloudFrames: frame {k}", p, "point")
            frames.append(p)
        if all(p is None for p in frames):
            raise ValueError("PointCloudFrames: every frame is dropped (None)")
        if robust is not None:
            if (not isinstance(robust, (tuple, list)) or len(robust) != 2 or robust[0] not in ("huber", "trimmed")
                    or isinstance(robust[1], bool) or not isinstance(robust[1], (int, float, np.floating))):
                raise ValueError("PointCloudFrames: robust must be None, ('huber', delta [m]) or ('trimmed', "
                                 f"fraction), got {robust!r}")
            if robust[0] == "huber" and (not np.isfinite(robust[1]) or robust[1] <= 0.0):
                raise ValueError(f"PointCloudFrames: the Huber delta must be positive and finite, got {robust[1]!r}")
            if robust[0] == "trimmed" and not 0.0 < robust[1] < 1.0:
                raise ValueError(f"PointCloudFrames: the trimmed fraction must be in (0, 1), got {robust[1]!r}")
            robust = (robust[0], float(robust[1]))
        if not isinstance(both_ways, (bool, np.bool_)):
            raise ValueError(f"PointCloudFrames: both_ways must be a bool, got {both_ways!r}")
        if not np.isfinite(both_ways_weight) or both_ways_weight < 0.0:
            raise ValueError(f"PointCloudFrames: both_ways_weight must be finite and >= 0, got {both_ways_weight!r}")
        self.points, self.robust, self.both_ways = frames, robust, bool(both_ways)
        self.both_ways_weight, self.frame_count = float(both_ways_weight), len(frames)

    def bind(self, model) -> ObservationLoss:
        return _PointCloudLoss(self, model)


def points_from_depth(depth, intrinsics, camera_to_world) -> np.ndarray:
    """Back-project a pinhole camera's depth image to world points, (P, 3) float64 [m], row by row.

    ``depth`` (H, W) [m] along the camera's +z; pixels with depth > 0 and finite are kept (others are holes).
    ``intrinsics`` (fx, fy, cx, cy) [pixels], pixel (u = column, v = row) at its centre: x = (u - cx) z / fx,
    y = (v - cy) z / fy. Camera frame of OpenCV: x right, y down, z forward. ``camera_to_world`` (4, 4): a rigid
    transform [m] taking camera coordinates to world coordinates.
    ValueError: shapes, a non-positive or non-finite focal length, a non-finite intrinsic, a transform that is not
    rigid (rotation orthonormal with determinant 1 within 1e-6, last row (0, 0, 0, 1))."""
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must be an (H, W) image, got shape {depth.shape}")
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (4,) or not np.isfinite(k).all() or k[0] <= 0.0 or k[1] <= 0.0:
        raise ValueError(f"intrinsics must be finite (fx, fy, cx, cy) with fx, fy > 0, got {np.asarray(intrinsics)}")
    T = np.asarray(camera_to_world, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"camera_to_world must be a finite (4, 4) matrix, got shape {T.shape}")
    R = T[:3, :3]
    if (not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6)
            or abs(np.linalg.det(R) - 1.0) > 1e-6):
        raise ValueError("camera_to_world must be rigid: an orthonormal rotation (determinant 1) and last row "
                         "(0, 0, 0, 1)")
    fx, fy, cx, cy = k
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0.0))
    z = depth[v, u]
    camera = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=1)
    return camera @ R.T + T[:3, 3]
