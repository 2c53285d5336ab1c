"""Goals on the cloth's final state: :class:`Coverage`, :class:`TargetPoints`, :class:`TargetPositions`.

``goal.add(state, out, weight=1.0)`` launches taped kernels adding each world's loss times ``weight`` into
``out[w]`` (``out`` (world_count,) of the model's scalar); back-propagate one ``add`` before the next (shared
buffers). ``goal.measure(positions, world=0)``: the score reported to users, on the host, without gradient.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from warpcloth.kernels.goals import goal_kernels
from warpcloth.kernels.losses import loss_kernels
from warpcloth.model import Model, State
from warpcloth.observations import PointCloudFrames
from warpcloth.obstacles import obstacle_points_numpy

__all__ = ["Coverage", "Goal", "TargetPoints", "TargetPositions"]


def _finite_rows(what: str, rows: np.ndarray, item: str) -> None:
    bad = ~np.isfinite(rows).all(axis=-1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{what}: {item} {i} is not finite ({rows[i].tolist()})")


def _number(what: str, value, *, positive: bool = True) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{what} must be a number, got {value!r}")
    if not math.isfinite(value) or (positive and value <= 0.0):
        raise ValueError(f"{what} must be finite{' and > 0' if positive else ''}, got {value!r}")
    return float(value)


class Goal:
    """A goal's ``name``, whether ``add`` can be captured into a CPU graph, and its argument checks."""

    name = ""
    capturable = True

    def __init__(self, model: Model):
        if not isinstance(model, Model):
            raise ValueError(f"{type(self).__name__}: model must be a warpcloth Model, got {type(model).__name__}")
        starts = np.asarray(model.world_particle_start, dtype=np.int64)
        sizes = np.diff(starts)
        if np.any(sizes != sizes[0]):
            raise ValueError(f"{type(self).__name__}: the model's worlds must be copies of one cloth; their particle "
                             f"counts differ: {sizes.tolist()}")
        self.model, self.world_particles = model, int(sizes[0])
        self._first = wp.array(starts[:-1].astype(np.int32), dtype=wp.int32, device=model.device)

    def _check_add(self, state: State, out: wp.array, weight: float) -> None:
        model, what = self.model, type(self).__name__
        x = getattr(state, "particle_x", None)
        if (not isinstance(x, wp.array) or x.shape != (model.particle_count,)
                or not wp.types.types_equal(x.dtype, model.types.vec3) or x.device != model.device):
            raise ValueError(f"{what}.add: state.particle_x must be a ({model.particle_count},) array of vec3 of "
                             f"{model.scalar.__name__} on {model.device}, got {x!r}")
        if (not isinstance(out, wp.array) or out.shape != (model.world_count,) or out.dtype != model.scalar
                or out.device != model.device):
            raise ValueError(f"{what}.add: out must be a ({model.world_count},) array of {model.scalar.__name__} on "
                             f"{model.device} (one loss per world), got {out!r}")
        _number(f"{what}.add: weight", weight, positive=False)

    def _positions(self, positions, world: int) -> np.ndarray:
        what = f"{type(self).__name__}.measure"
        W = self.model.world_count
        if isinstance(world, (bool, np.bool_)) or not isinstance(world, (int, np.integer)) or not 0 <= world < W:
            raise ValueError(f"{what}: world {world!r} out of range [0, {self.model.world_count})")
        x = np.asarray(positions, dtype=np.float64)
        if x.shape != (self.world_particles, 3):
            raise ValueError(f"{what}: positions must be one world's ({self.world_particles}, 3), got {x.shape}")
        _finite_rows(what, x, "particle")
        return x


# -- coverage ----------------------------------------------------------------------------------------------------


def _plane_basis(up: np.ndarray) -> np.ndarray:
    # for up = z: x and y
    axis = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = axis - (axis @ up) * up
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1)])


def _union_area(points: np.ndarray, triangles: np.ndarray, spacing: float) -> float:
    # the union of 2D triangles: exact along rows of constant y, the rows' lengths summed every `spacing` or closer
    # (docs/decisions.md, "Coverage is measured on rows")
    if len(triangles) == 0:
        return 0.0
    p = points[triangles]  # (T, 3, 2)
    y = p[..., 1]
    lo, hi = float(y.min()), float(y.max())
    if not hi > lo:
        return 0.0
    rows = max(1, int(math.ceil((hi - lo) / spacing * (1.0 - 1e-12))))
    h = (hi - lo) / rows
    # the rows whose centre line lo + (k + 1/2) h crosses each triangle
    k0 = np.maximum(np.ceil((y.min(axis=1) - lo) / h - 0.5).astype(np.int64), 0)
    k1 = np.minimum(np.floor((y.max(axis=1) - lo) / h - 0.5).astype(np.int64), rows - 1)
    count = np.maximum(k1 - k0 + 1, 0)
    if not count.any():
        return 0.0
    t = np.repeat(np.arange(len(triangles)), count)
    k = np.repeat(k0 - (np.cumsum(count) - count), count) + np.arange(int(count.sum()))
    yk = lo + (k + 0.5) * h
    a, b = np.full(len(t), np.inf), np.full(len(t), -np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        ya, yb, xa, xb = y[t, i], y[t, j], p[t, i, 0], p[t, j, 0]
        crosses = (np.minimum(ya, yb) <= yk) & (yk <= np.maximum(ya, yb)) & (ya != yb)
        s = (yk - ya) / np.where(crosses, yb - ya, 1.0)
        x = np.where(crosses, xa + s * (xb - xa), 0.0)
        a = np.where(crosses, np.minimum(a, x), a)
        b = np.where(crosses, np.maximum(b, x), b)
    keep = a <= b
    # one sorted sweep over all rows: each row's coordinates shifted past the previous row's
    x0 = float(points[:, 0].min())
    span = 2.0 * (float(points[:, 0].max()) - x0) + 1.0
    a, b = a[keep] - x0 + k[keep] * span, b[keep] - x0 + k[keep] * span
    order = np.argsort(a, kind="stable")
    a, b = a[order], b[order]
    reach = np.concatenate([[-np.inf], np.maximum.accumulate(b)[:-1]])
    return float(np.maximum(b - np.maximum(a, reach), 0.0).sum() * h)


class Coverage(Goal):
    """The share of the cloth's rest area lying flat on a table, as robot-learning papers measure it.

    :meth:`measure`: the area of the union of the projections onto the table's plane of the triangles whose vertices
    all lie within ``flat_tolerance`` of the table, over the rest area [-], on rows every sqrt(rest area) /
    ``resolution`` (docs/decisions.md, "Coverage is measured on rows"). ``add``: 1 - S, S = abs(sum_t w_t A_t) / rest
    area, A_t triangle t's projected area signed by its orientation about ``up``, w_t 1 within the tolerance and
    decaying beyond: S is the measure where the projection does not overlap itself, and lower by a layer's area where
    a fold turns it over onto the cloth (docs/decisions.md, "The coverage surrogate").

    Args:
        table_height, up: The table's top [m] along its normal ``up``: a static obstacle face there in every world
            (base placement; with ``table``, of the obstacle of that name).
        flat_tolerance: [m], more than the repulsion thickness (where a resting cloth lies).

    Raises:
        ValueError: no table there (listing the upward faces' heights), a bad ``up``, tolerance or resolution.
    """

    name = "coverage"

    def __init__(self, model: Model, *, table_height: float, up=(0.0, 0.0, 1.0), flat_tolerance: float = 0.02,
                 table: str | None = None, resolution: int = 2048):
        super().__init__(model)
        if table_height is None:
            raise ValueError("Coverage needs a table: give table_height, the height of its top along up [m]")
        height = _number("Coverage: table_height", table_height, positive=False)
        u = np.asarray(up, dtype=np.float64)
        if u.shape != (3,) or not np.isfinite(u).all() or np.linalg.norm(u) == 0.0:
            raise ValueError(f"Coverage: up must be a finite non-zero 3-vector, got {up!r}")
        u = u / np.linalg.norm(u)
        tolerance = _number("Coverage: flat_tolerance", flat_tolerance)
        if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 1:
            raise ValueError(f"Coverage: resolution must be a positive integer, got {resolution!r}")
        _require_table(model, u, height, table)
        resting = model.collision.repulsion_thickness
        if tolerance <= resting:
            raise ValueError(f"Coverage: flat_tolerance {tolerance} m must exceed the repulsion thickness {resting} m: "
                             "a cloth resting on the table lies about that high above it")
        self.table_height, self.up, self.flat_tolerance, self.resolution = height, u, tolerance, int(resolution)
        starts = np.asarray(model.world_particle_start, dtype=np.int64)
        tris = np.asarray(model.triangles_np, dtype=np.int64)
        tri_world = np.searchsorted(starts, tris[:, 0], side="right") - 1
        if np.any(np.diff(tri_world) < 0):
            raise ValueError("Coverage: the model's triangles are not ordered by world")
        tri_first = np.searchsorted(tri_world, np.arange(model.world_count + 1))
        self.triangles = tris[tri_first[0]:tri_first[1]] - starts[0]
        area = np.asarray(model.tri_area.numpy(), dtype=np.float64)
        self.rest_area = float(area[tri_first[0]:tri_first[1]].sum())
        world_area = np.add.reduceat(area, tri_first[:-1])
        device = model.device
        self._tri_first = wp.array(tri_first.astype(np.int32), dtype=wp.int32, device=device)
        self._inv_area = wp.array(1.0 / world_area, dtype=model.scalar, device=device)
        self._area = wp.zeros(model.tri_count, dtype=model.scalar, device=device, requires_grad=model.requires_grad)
        self._total = wp.zeros(model.world_count, dtype=model.scalar, device=device, requires_grad=model.requires_grad)
        self._kernels = goal_kernels(model.scalar)
        self._basis = _plane_basis(u)

    def add(self, state: State, out: wp.array, weight: float = 1.0) -> None:
        self._check_add(state, out, weight)
        model, K = self.model, self._kernels
        s = model.scalar
        wp.launch(K.flat_area, model.tri_count, inputs=[state.particle_x, model.tri_indices,
                                                         model.types.vec3(*self.up), s(self.table_height),
                                                         s(self.flat_tolerance)],
                  outputs=[self._area], device=model.device)
        wp.launch(K.world_area, model.world_count, inputs=[self._area, self._tri_first], outputs=[self._total],
                  device=model.device)
        wp.launch(K.add_coverage, model.world_count, inputs=[self._total, self._inv_area, s(weight)], outputs=[out],
                  device=model.device)

    def flat(self, positions, world: int = 0) -> np.ndarray:
        """Which of one world's triangles lie within the tolerance of the table, (T,) bool."""
        x = self._positions(positions, world)
        d = np.abs(x @ self.up - self.table_height)
        return (d[self.triangles] <= self.flat_tolerance).all(axis=1)

    def measure(self, positions, world: int = 0) -> float:
        """The covered share [-] of one world's positions (particles of a world, 3) [m]."""
        x = self._positions(positions, world)
        flat = self.flat(x, world)
        spacing = math.sqrt(self.rest_area) / self.resolution
        return _union_area(x @ self._basis.T, self.triangles[flat], spacing) / self.rest_area

    def surrogate(self, positions, world: int = 0) -> float:
        """S of one world's positions [-], on the host (``add``'s loss is 1 - S)."""
        x = self._positions(positions, world)
        tol, d = self.flat_tolerance, np.abs(x @ self.up - self.table_height)
        u = np.maximum(d - tol, 0.0) / tol
        w = np.prod((1.0 / (1.0 + u * u))[self.triangles], axis=1)
        a, b, c = (x[self.triangles[:, i]] for i in range(3))
        return abs(float(np.sum(w * 0.5 * (np.cross(b - a, c - a) @ self.up)))) / self.rest_area


def _require_table(model: Model, up: np.ndarray, height: float, table: str | None) -> None:
    # every world needs a static obstacle face facing up at the height (within 1e-6 m)
    hint = ("a table is a static obstacle whose top faces up at table_height (ModelBuilder.add_obstacle_plane or "
            "add_obstacle_box)")
    if model.obstacle_count == 0:
        raise ValueError(f"Coverage: the model has no obstacle, so no table; {hint}")
    names = list(model.obstacle_names)
    obstacle_world = np.asarray(model.obstacle_world)
    # ModelBuilder.replicate names world w's copy of obstacle "table" "table_w"
    named = np.array([n in (table, f"{table}_{w}") for n, w in zip(names, obstacle_world)])
    if table is not None and not named.any():
        raise ValueError(f"Coverage: no obstacle named {table!r}; the model's obstacles are {names}")
    x = obstacle_points_numpy(model, 0.0)
    tris = np.asarray(model.obstacle_triangles_np, dtype=np.int64)
    body = np.searchsorted(np.asarray(model.obstacle_tri_start), np.arange(len(tris)), side="right") - 1
    n = np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]])
    upward = (n @ up) >= (1.0 - 1e-6) * np.linalg.norm(n, axis=1)
    static = np.array([m is None for m in model.obstacle_motion])[body]
    chosen = np.ones(len(tris), dtype=bool) if table is None else named[body]
    level = np.all(np.abs(x[tris] @ up - height) <= 1e-6, axis=1)
    world = obstacle_world[body]
    for w in range(model.world_count):
        candidates = upward & static & chosen & (world == w)
        if not (candidates & level).any():
            tops = sorted({round(float(v), 6) for v in (x[tris[candidates, 0]] @ up)})
            where = f"obstacle {table!r}" if table is not None else "no static obstacle"
            raise ValueError(f"Coverage: world {w} has no table at height {height} m along up {up.tolist()}: "
                             f"{where} has an upward face there (upward faces at {tops} m); {hint}")


# -- target points -----------------------------------------------------------------------------------------------


def _pair_distances(p: np.ndarray, y: np.ndarray) -> np.ndarray:
    # |p_i - y_j| for every pair by one matrix product: to a few 1e-8 m, for bounds
    return np.sqrt(np.maximum(np.sum(p * p, 1)[:, None] - 2.0 * p @ y.T + np.sum(y * y, 1)[None], 0.0))


def _closest_distances(q: np.ndarray, x: np.ndarray, tri: np.ndarray) -> np.ndarray:
    # each point's distance to the surface: bounding spheres prune, then exact
    A, B, C = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    centre = (A + B + C) / 3.0
    radius = np.sqrt(np.max([np.sum((V - centre) ** 2, axis=1) for V in (A, B, C)], axis=0))
    margin = 1e-6 * (1.0 + float(np.abs(x).max()) + float(np.abs(q).max()))  # the expansions' rounding, and more
    out = np.empty(len(q))
    for s in range(0, len(q), 512):
        p = q[s:s + 512]
        bound = _pair_distances(p, x).min(axis=1)  # to the nearest vertex
        i, t = np.nonzero(_pair_distances(p, centre) - radius[None] <= bound[:, None] + margin)
        best = np.full(len(p), np.inf)
        np.minimum.at(best, i, _point_triangle(p[i], A[t], B[t], C[t]))
        out[s:s + 512] = best
    return out


def _point_triangle(p, a, b, c) -> np.ndarray:
    # the plane's foot where it is inside the triangle, else the nearest edge point
    n = np.cross(b - a, c - a)
    nn = np.sum(n * n, axis=1)
    safe = np.where(nn > 0.0, nn, 1.0)
    foot = p - (np.sum((p - a) * n, axis=1) / safe)[:, None] * n
    inside = nn > 0.0
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.sum(np.cross(v - u, foot - u) * n, axis=1) >= 0.0
    d = np.where(inside, np.linalg.norm(p - foot, axis=1), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        ee = np.sum(e * e, axis=1)
        s = np.clip(np.sum((p - u) * e, axis=1) / np.where(ee > 0.0, ee, 1.0), 0.0, 1.0)
        d = np.minimum(d, np.linalg.norm(p - (u + s[:, None] * e), axis=1))
    return d


class TargetPoints(Goal):
    """Target points the final surface should pass through: the loss of a one-frame
    :class:`~warpcloth.observations.PointCloudFrames`, the mean over the points of rho(d_i), d_i a point's distance
    to the cloth's surface, rho(d) = d^2 or with ``huber`` (delta [m]) Huber's; with ``both_ways``, plus the mean
    over the vertices of the squared distance to their nearest point [m^2]. :meth:`measure`: the RMS of the d_i
    [m]; with ``both_ways``, the larger of it and the vertices' RMS distance to their nearest point.

    Raises:
        ValueError: points empty, not (P, 3) or not finite (naming the point), a bad ``huber`` or ``both_ways``.
    """

    name = "target_points"
    capturable = False  # PointCloudFrames: the meshes' refits are host calls

    def __init__(self, model: Model, points, *, both_ways: bool = False, huber: float | None = None):
        super().__init__(model)
        q = np.asarray(points, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != 3 or q.shape[0] < 1:
            raise ValueError(f"TargetPoints: points must be (P, 3) with P >= 1, got shape {q.shape}")
        _finite_rows("TargetPoints", q, "point")
        if not isinstance(both_ways, (bool, np.bool_)):
            raise ValueError(f"TargetPoints: both_ways must be a bool, got {both_ways!r}")
        robust = None if huber is None else ("huber", _number("TargetPoints: huber", huber))
        self.points, self.both_ways, self.huber = q, bool(both_ways), None if huber is None else robust[1]
        self._loss = PointCloudFrames([q], robust=robust, both_ways=self.both_ways).bind(model)
        self.triangles = self._loss.triangles_np.astype(np.int64)

    def add(self, state: State, out: wp.array, weight: float = 1.0) -> None:
        self._check_add(state, out, weight)
        self._loss([state.particle_x], [0], out=out, weight=float(weight))

    def measure(self, positions, world: int = 0) -> float:
        """The RMS distance [m] of one world's positions (particles of a world, 3) [m] from the targets."""
        x = self._positions(positions, world)
        rms = math.sqrt(float(np.mean(_closest_distances(self.points, x, self.triangles) ** 2)))
        if self.both_ways:
            nearest = np.concatenate([np.argmin(_pair_distances(x[s:s + 512], self.points), axis=1)
                                      for s in range(0, len(x), 512)])  # then exact, in float64
            rms = max(rms, math.sqrt(float(np.mean(np.sum((x - self.points[nearest]) ** 2, axis=1)))))
        return rms


# -- target positions --------------------------------------------------------------------------------------------


class TargetPositions(Goal):
    """A target for every vertex of a world, ``positions`` (particles of a world, 3) [m]: the loss, half the mean
    over the vertices of the squared distance to their targets [m^2] (``ControlTask``'s positions loss);
    :meth:`measure`: the RMS distance [m].

    Raises:
        ValueError: a shape other than (particles of a world, 3), a position not finite (naming the particle).
    """

    name = "target_positions"

    def __init__(self, model: Model, positions):
        super().__init__(model)
        t = np.asarray(positions, dtype=np.float64)
        if t.shape != (self.world_particles, 3):
            raise ValueError(f"TargetPositions: positions must be ({self.world_particles}, 3), one per particle of a "
                             f"world, got {t.shape}")
        _finite_rows("TargetPositions", t, "particle")
        self.positions = t
        self._target = wp.array(t, dtype=model.types.vec3, device=model.device)
        self._kernel = loss_kernels(model.scalar).world_squared_distance

    def add(self, state: State, out: wp.array, weight: float = 1.0) -> None:
        self._check_add(state, out, weight)
        model = self.model
        wp.launch(self._kernel, model.particle_count,
                  inputs=[state.particle_x, self._target, model.particle_world, self._first,
                          model.scalar(0.5 * weight / self.world_particles)], outputs=[out], device=model.device)

    def measure(self, positions, world: int = 0) -> float:
        """The RMS distance [m] of one world's positions (particles of a world, 3) [m] from the targets."""
        x = self._positions(positions, world)
        return math.sqrt(float(np.mean(np.sum((x - self.positions) ** 2, axis=1))))
