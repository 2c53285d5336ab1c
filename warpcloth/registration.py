"""A template cloth placed on a recorded point cloud, so that a recording needs no hand-made start: a rigid placement
(:func:`register_rigid`, iterative closest points from several starts), then a smooth deformation
(:func:`register_nonrigid`, in the template's low-frequency Laplacian eigenvectors, :class:`SmoothDeformation`) that
keeps the edges near their rest lengths; :func:`start_from_points` chains both for a model or a mesh.

Each recorded point is matched to its closest point on the template's surface (a ``wp.Mesh`` query); the other way
(each vertex to its nearest point) only where ``both_ways`` asks: a camera sees one side and part of the cloth, and
what it does not see holds no point. Each point counts
with the Cauchy weight ``1 / (1 + d^2 / s^2)`` of its distance d, ``s`` ``trim`` robust spreads of the distances
(1.4826 times their median) but at least the mean edge length, so stray points barely pull the cloth. A symmetric
template (a square grid) fits the points equally well in each of its symmetric placements; the one found is the one
with the least residual, and ``init`` chooses another."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import warp as wp

from warpcloth.kernels.registration import closest_points, nearest_points

__all__ = ["MIN_POINTS", "NonrigidFit", "SmoothDeformation", "register_nonrigid", "register_rigid",
           "start_from_points"]

MIN_POINTS = 10
"""The fewest recorded points a registration takes."""
DEFAULT_MODES = 64
"""register_nonrigid's number of deformation modes when none is given (or the vertex count, if fewer)."""
MAX_DENSE_VERTICES = 6000  # SmoothDeformation's dense eigen-decomposition: n^2 memory, n^3 time
MAX_POLISH_VERTICES = 1500
"""register_nonrigid's polish (every vertex free, a dense solve) takes at most this many vertices."""
_TANGENTIAL = 0.2  # weight of a residual's part along the surface beside its part along the normal
_START_ANGLES = 8  # rigid starts: turns about the points' least-spread axis, each with the normal both ways
_START_ITERATIONS = 8
_FLOOR = 1.0  # the robust weights' scale is at least this many mean edge lengths: a misfit of a cell still counts


def _rows(value, name, what, minimum=1):
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: {name} must be an (N, 3) array of numbers: {exc}") from None
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what}: {name} must have shape (N, 3), got {a.shape}")
    if len(a) < minimum:
        raise ValueError(f"{what}: {name} holds {len(a)} rows, at least {minimum} needed")
    bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1))
    if bad.size:
        raise ValueError(f"{what}: {name} row {int(bad[0])} is not finite: {a[bad[0]].tolist()}")
    return a


def _template(positions, triangles, what):
    x = _rows(positions, "template_positions", what, minimum=3)
    tris = np.asarray(triangles)
    if tris.ndim != 2 or tris.shape[1] != 3 or len(tris) == 0:
        raise ValueError(f"{what}: template_triangles must have shape (T, 3) with T >= 1, got {tris.shape}")
    if not np.issubdtype(tris.dtype, np.integer):
        raise ValueError(f"{what}: template_triangles must hold integers, got dtype {tris.dtype}")
    bad = np.argwhere((tris < 0) | (tris >= len(x)))
    if len(bad):
        t = int(bad[0][0])
        raise ValueError(f"{what}: template_triangles row {t} {tris[t].tolist()} has an index out of range "
                         f"[0, {len(x)})")
    tris = tris.astype(np.int64)
    area = 0.5 * np.linalg.norm(_cross_rows(x, tris), axis=1)
    flat = np.flatnonzero(area <= 1e-12 * max(float(np.ptp(x, axis=0).max()) ** 2, 1e-300))
    if flat.size:
        raise ValueError(f"{what}: template_triangles row {int(flat[0])} {tris[flat[0]].tolist()} has no area")
    return x, tris


def _cross_rows(x, tris):
    return np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]])


def _trim(value, what):
    ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
    if not ok or not math.isfinite(value) or value <= 0.0:
        raise ValueError(f"{what}: trim (how many robust spreads of the distances a point may lie off the surface "
                         f"and count) must be a finite number > 0, got {value!r}")
    return float(value)


def _count(value, name, what, minimum=1):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{what}: {name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _vertices(value, n, name, what):
    # sorted unique vertex indices in [0, n) (None: none)
    if value is None:
        return np.zeros(0, dtype=np.int64)
    a = np.asarray(value).ravel()
    if a.size and not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{what}: {name} must hold vertex indices (integers), got dtype {a.dtype}")
    a = a.astype(np.int64)
    bad = np.flatnonzero((a < 0) | (a >= n))
    if bad.size:
        raise ValueError(f"{what}: {name} entry {int(bad[0])} ({int(a[bad[0]])}) is no vertex of the {n}")
    return np.unique(a)


def _weight(value, name, what):
    ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
    if not ok or not math.isfinite(value) or value < 0.0:
        raise ValueError(f"{what}: {name} must be a finite number >= 0, got {value!r}")
    return float(value)


def _scale(d2, trim, floor):
    # trim robust spreads of the distances (1.4826 times their median), at least floor
    return max(trim * 1.4826 * math.sqrt(float(np.median(d2))), floor)


def _weights(d2, trim, floor):
    # Cauchy weights 1 / (1 + d^2 / s^2), s = _scale, summing to one: a point many spreads off barely counts
    w = 1.0 / (1.0 + d2 / _scale(d2, trim, floor) ** 2)
    return w / w.sum()


def _rms(d2, trim, floor):
    # the root-mean-square distance of the points within _scale of the surface
    return math.sqrt(float(np.mean(d2[d2 <= _scale(d2, trim, floor) ** 2])))


class _Surface:
    # a wp.Mesh of the template's triangles; update() moves its points (in place, then a refit)

    def __init__(self, x, tris, device):
        self.device = wp.get_device(device)
        self.tris = tris
        self.x = x
        self.points = wp.array(x.astype(np.float32), dtype=wp.vec3, device=self.device)
        indices = wp.array(tris.astype(np.int32).ravel(), dtype=wp.int32, device=self.device)
        self.mesh = wp.Mesh(points=self.points, indices=indices)

    def update(self, x):
        self.x = x
        self.points.assign(x.astype(np.float32))
        self.mesh.refit()

    def closest(self, q):
        """(face (P,), barycentric (P, 3), closest point (P, 3)) of each point q (P, 3) on the surface."""
        face = wp.empty(len(q), dtype=wp.int32, device=self.device)
        bary = wp.empty(len(q), dtype=wp.vec3, device=self.device)
        wp.launch(closest_points, dim=len(q), device=self.device, record_tape=False,
                  inputs=[self.mesh.id, wp.array(q.astype(np.float32), dtype=wp.vec3, device=self.device)],
                  outputs=[face, bary])
        f, b = face.numpy().astype(np.int64), bary.numpy().astype(np.float64)
        if np.any(f < 0):  # a mesh with triangles always answers an unbounded query
            raise RuntimeError("registration: the closest-point query found no face")
        return f, b, np.einsum("pk,pkc->pc", b, self.x[self.tris[f]])


def _rotation(w):
    angle = float(np.linalg.norm(w))
    if angle < 1e-300:
        return np.eye(3)
    k = _skew(w / angle)
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def _skew(v):
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return out


def _nearest(a, b, device):
    # index into b of each row of a's nearest row
    out = wp.empty(len(a), dtype=wp.int32, device=device)
    wp.launch(nearest_points, dim=len(a), device=device, record_tape=False,
              inputs=[wp.array(a.astype(np.float32), dtype=wp.vec3, device=device),
                      wp.array(b.astype(np.float32), dtype=wp.vec3, device=device)], outputs=[out])
    return out.numpy().astype(np.int64)


def _icp(surface, normals, p, A, b, iterations, trim, size, both_ways, floor):
    # points p mapped into the template's frame by q = A p + b; each step turns and shifts them about their kept
    # centroid to least squares at the current matches: each point to its closest point on the surface (along the
    # normal, plus _TANGENTIAL along the surface) and, both_ways, each template vertex's nearest point to the vertex
    for _ in range(iterations):
        q = p @ A.T + b
        f, _, c = surface.closest(q)
        r = c - q
        w = _weights(np.einsum("pc,pc->p", r, r), trim, floor)
        n = normals[f]
        m = w @ q
        y = q - m
        a = np.concatenate([np.cross(y, n), n], axis=1)
        B = np.concatenate([-_skew(y), np.broadcast_to(np.eye(3), (len(y), 3, 3))], axis=2)
        H = (a.T * w) @ a + _TANGENTIAL * np.einsum("k,kia,kib->ab", w, B, B)
        g = (a.T * w) @ np.einsum("kc,kc->k", n, r) + _TANGENTIAL * np.einsum("k,kia,ki->a", w, B, r)
        if both_ways:
            near = _nearest(surface.x, q, surface.device)
            r = surface.x - q[near]
            w = _weights(np.einsum("pc,pc->p", r, r), trim, floor)
            B = np.concatenate([-_skew(q[near] - m), np.broadcast_to(np.eye(3), (len(near), 3, 3))], axis=2)
            H += np.einsum("k,kia,kib->ab", w, B, B)
            g += np.einsum("k,kia,ki->a", w, B, r)
        step = np.linalg.lstsq(H, g, rcond=None)[0]
        rot = _rotation(step[:3])
        A, b = rot @ A, rot @ (b - m) + m + step[3:]
        if max(np.linalg.norm(step[:3]), np.linalg.norm(step[3:]) / size) < 1e-9:
            break
    q = p @ A.T + b
    d2 = np.sum((surface.closest(q)[2] - q) ** 2, axis=1)
    return A, b, _rms(d2, trim, floor), float(np.median(d2))


def _moments(x, tris):
    # area-weighted centroid and covariance of the surface (uniform density on each triangle)
    corners = x[tris]
    area = 0.5 * np.linalg.norm(_cross_rows(x, tris), axis=1)
    centroid = np.einsum("t,tc->c", area, corners.mean(axis=1)) / area.sum()
    d = corners - centroid
    s = d.sum(axis=1)
    second = (np.einsum("tkc,tkd->tcd", d, d) + np.einsum("tc,td->tcd", s, s)) / 12.0
    return centroid, np.einsum("t,tcd->cd", area, second) / area.sum()


def _proper_axes(cov):
    axes = np.linalg.eigh(cov)[1]  # columns by increasing spread
    if np.linalg.det(axes) < 0:
        axes[:, 0] = -axes[:, 0]
    return axes


def _placement(init, what, name="init"):
    try:
        R, t = (np.asarray(v, dtype=np.float64) for v in tuple(init)[:2])
    except (TypeError, ValueError):
        raise ValueError(f"{what}: {name} must be (R (3, 3), t (3,)), got {init!r}") from None
    if R.shape != (3, 3) or t.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ValueError(f"{what}: {name} must be a finite (R (3, 3), t (3,)), got shapes {R.shape}, {t.shape}")
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError(f"{what}: {name}'s R is not a rotation (orthonormal with determinant +1): {R.tolist()}")
    return R, t


def register_rigid(template_positions, template_triangles, points, *, init=None, iterations: int = 150,
                   trim: float = 5.0, both_ways: bool = True, device=None) -> tuple[np.ndarray, np.ndarray, float]:
    """The rigid placement ``x -> R x + t`` of a template (positions (n, 3) [m], triangles (T, 3)) that brings its
    surface closest to ``points`` (P, 3) [m], P >= :data:`MIN_POINTS`: ``(R (3, 3), t (3,) [m], rms [m])``, rms the
    root-mean-square distance to the placed surface of the points within ``s`` of it (module docstring). Without
    ``init`` ((R, t)), starts from both principal axes, turned about the least-spread one and with it both ways,
    and refines the best. ``both_ways``: also pull each template vertex to its nearest point in the first quarter
    of the ``iterations`` (a wider basin; the last steps match points to the surface only). ValueError naming a bad
    argument (shape, non-finite row, a triangle out of range or of no area, too few points)."""
    what = "register_rigid"
    x, tris = _template(template_positions, template_triangles, what)
    p = _rows(points, "points", what, minimum=MIN_POINTS)
    iterations, trim = _count(iterations, "iterations", what), _trim(trim, what)
    center, cov_t = _moments(x, tris)
    size = float(np.ptp(x, axis=0).max())
    floor = _FLOOR * _mean_edge(x, tris)
    xc = x - center
    surface = _Surface(xc, tris, device)
    normals = _cross_rows(xc, tris)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    if init is not None:
        R, t = _placement(init, what)
        A, b = R.T, -center - R.T @ t
    else:
        pc = p.mean(axis=0)
        ep, et = _proper_axes(np.cov(p.T, bias=True)), _proper_axes(cov_t)
        best = None
        for flip in (np.eye(3), np.diag([-1.0, 1.0, -1.0])):
            for k in range(_START_ANGLES):
                R = ep @ _rotation(np.array([2.0 * math.pi * k / _START_ANGLES, 0.0, 0.0])) @ flip @ et.T
                found = _icp(surface, normals, p, R.T, -R.T @ pc, _START_ITERATIONS, trim, size, both_ways, floor)
                if best is None or found[3] < best[3]:
                    best = found
        A, b = best[0], best[1]
    if both_ways:
        A, b = _icp(surface, normals, p, A, b, max(1, iterations // 4), trim, size, True, floor)[:2]
    A, b, rms, _ = _icp(surface, normals, p, A, b, iterations, trim, size, False, floor)
    return A.T, -A.T @ (center + b), rms


def _mean_edge(x, tris):
    e = _edges(tris)[0]
    return float(np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1).mean())


def _edges(tris):
    e = np.sort(tris[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    e, counts = np.unique(e, axis=0, return_counts=True)
    return e, e[counts == 1]


class SmoothDeformation:
    """Smooth displacements of a cloth: the ``modes`` lowest eigenvectors of its cotangent Laplacian (lumped vertex
    areas as the mass), the vibration modes of a membrane over its rest shape (positions (n, 3) [m], triangles
    (T, 3)), from the uniform translation up in spatial frequency; intrinsic to the surface, so they follow it
    through any rigid placement. ``fixed`` (vertex indices): vertices no mode moves (a held cloth's). ``basis``
    (n, modes): mass-orthonormal columns; ``eigenvalues`` (modes,) [1/m^2]; ``displacements(c)`` = ``basis @ c``.
    ValueError naming a bad argument; above :data:`MAX_DENSE_VERTICES` vertices (a dense eigen-decomposition)
    refused."""

    def __init__(self, rest_positions, triangles, modes: int = DEFAULT_MODES, fixed=None):
        what = "SmoothDeformation"
        x, tris = _template(rest_positions, triangles, what)
        n = len(x)
        if n > MAX_DENSE_VERTICES:
            raise ValueError(f"{what}: {n} vertices; at most {MAX_DENSE_VERTICES} (a dense eigen-decomposition)")
        fixed = _vertices(fixed, n, "fixed", what)
        free = np.setdiff1d(np.arange(n), fixed)
        modes = _count(modes, "modes", what)
        if modes > len(free):
            raise ValueError(f"{what}: modes {modes} exceeds the template's {len(free)} vertices that are not fixed")
        stiffness = np.zeros((n, n))
        mass = np.zeros(n)
        area = 0.5 * np.linalg.norm(_cross_rows(x, tris), axis=1)
        for k in range(3):
            i, j, o = tris[:, (k + 1) % 3], tris[:, (k + 2) % 3], tris[:, k]
            u, v = x[i] - x[o], x[j] - x[o]
            w = 0.5 * np.einsum("tc,tc->t", u, v) / np.linalg.norm(np.cross(u, v), axis=1)  # cot(angle at o) / 2
            np.add.at(stiffness, (i, j), -w)
            np.add.at(stiffness, (j, i), -w)
            np.add.at(stiffness, (i, i), w)
            np.add.at(stiffness, (j, j), w)
            np.add.at(mass, o, area / 3.0)
        if np.any(mass <= 0.0):
            raise ValueError(f"{what}: vertex {int(np.flatnonzero(mass <= 0.0)[0])} is on no triangle")
        scale = 1.0 / np.sqrt(mass[free])
        # the fixed vertices as a Dirichlet condition: the eigenproblem of the free vertices alone
        values, vectors = np.linalg.eigh(scale[:, None] * stiffness[np.ix_(free, free)] * scale[None, :])
        self.rest_positions, self.triangles, self.fixed = x, tris, fixed
        self.mass = mass  # lumped vertex areas [m^2]
        self.basis = np.zeros((n, modes))
        self.basis[free] = scale[:, None] * vectors[:, :modes]
        self.eigenvalues = np.maximum(values[:modes], 0.0)
        self._stiffness = stiffness

    @property
    def modes(self) -> int:
        return self.basis.shape[1]

    def displacements(self, coefficients) -> np.ndarray:
        """The vertex displacements (n, 3) [m] of ``coefficients`` (modes, 3) [m]; ValueError for another shape or a
        non-finite value."""
        c = np.asarray(coefficients, dtype=np.float64)
        if c.shape != (self.modes, 3) or not np.all(np.isfinite(c)):
            raise ValueError(f"SmoothDeformation.displacements: coefficients must be a finite ({self.modes}, 3) "
                             f"array, got shape {c.shape}")
        return self.basis @ c


class NonrigidFit(NamedTuple):
    """:func:`register_nonrigid`'s result: ``positions`` (n, 3) [m], the deformed template (polished);
    ``coefficients`` (modes, 3) [m]: the smooth fit before the polish, the rigidly placed template (or the
    ``initial`` positions) displaced by ``deformation.displacements(coefficients)``; ``rms`` [m], as
    :func:`register_rigid`'s; ``strain`` (E,), each edge's length over its rest length, less one; ``rigid`` (R, t,
    rms) of the placement it started from."""

    positions: np.ndarray
    coefficients: np.ndarray
    rms: float
    strain: np.ndarray
    deformation: SmoothDeformation
    rigid: tuple


def register_nonrigid(template_positions, template_triangles, points, *, rigid=None, modes: int | None = None,
                      smoothness: float = 0.1, preserve_lengths: float = 30.0, iterations: int = 40,
                      trim: float = 5.0, both_ways: bool = False, polish: int = 10,
                      deformation: SmoothDeformation | None = None, fixed=None, initial=None,
                      device=None) -> NonrigidFit:
    """The template (positions (n, 3) [m], its rest shape, triangles (T, 3)) rigidly placed (``rigid`` (R, t) or
    (R, t, rms); None: :func:`register_rigid`), then deformed by the ``modes`` smoothest displacements
    (:class:`SmoothDeformation`, or ``deformation`` built on the same template) to least squares: the mean squared
    distance [m^2] of the points (weighted, ``trim``) to its surface (``both_ways``: and of each vertex to its
    nearest point), plus ``preserve_lengths`` times the mean squared change of the edges' lengths [m^2], plus
    ``smoothness`` times the mean squared Laplacian of the displacement at the interior vertices, scaled by the
    squared mean edge length to metres (a change of curvature). Fits the modes coarse to fine (4, 8, 16, then all),
    ``iterations`` closest-point steps in all, then ``polish`` steps with every vertex free under the same energy
    (weights scaled by the spread alone; at most :data:`MAX_POLISH_VERTICES` vertices; 0: none). ``fixed`` (vertex
    indices, a held cloth's): no rigid step unless ``rigid`` is given, and these vertices stay where it places them
    (``deformation``, if given, must fix the same). ``initial`` (n, 3) [m]: deform from these positions instead of
    the placed template (no rigid step; the edges' rest lengths stay the template's). Returns a
    :class:`NonrigidFit`; ValueError naming a bad argument."""
    what = "register_nonrigid"
    x, tris = _template(template_positions, template_triangles, what)
    p = _rows(points, "points", what, minimum=MIN_POINTS)
    smoothness = _weight(smoothness, "smoothness", what)
    preserve_lengths = _weight(preserve_lengths, "preserve_lengths", what)
    iterations, trim = _count(iterations, "iterations", what), _trim(trim, what)
    polish = _count(polish, "polish", what, minimum=0)
    fixed = _vertices(fixed, len(x), "fixed", what)
    if deformation is None:
        count = len(x) - len(fixed)
        deformation = SmoothDeformation(x, tris, min(DEFAULT_MODES, count) if modes is None else modes, fixed)
    elif not isinstance(deformation, SmoothDeformation) or deformation.rest_positions.shape != x.shape \
            or not np.array_equal(deformation.triangles, tris) or not np.array_equal(deformation.fixed, fixed):
        raise ValueError(f"{what}: deformation must be a SmoothDeformation of this template with the same fixed "
                         "vertices")
    if initial is not None:
        initial = _rows(initial, "initial", what)
        if initial.shape != x.shape:
            raise ValueError(f"{what}: initial has shape {initial.shape}, the template {x.shape}")
        if rigid is not None:
            raise ValueError(f"{what}: initial positions take no rigid placement; give one or the other")
        rigid = (np.eye(3), np.zeros(3), float("nan"))
    if rigid is None:
        rigid = (np.eye(3), np.zeros(3), float("nan")) if len(fixed) else register_rigid(x, tris, p, trim=trim,
                                                                                         device=device)
    R, t = _placement(rigid, what, "rigid")
    rigid = tuple(rigid) if len(tuple(rigid)) == 3 else (R, t, float("nan"))
    phi, m = deformation.basis, deformation.modes
    if polish and len(x) > MAX_POLISH_VERTICES:
        raise ValueError(f"{what}: polish needs at most {MAX_POLISH_VERTICES} vertices (a dense solve), the template "
                         f"has {len(x)}; pass polish=0")
    center = p.mean(axis=0)
    placed = (x @ R.T + t if initial is None else initial) - center
    q = p - center
    edges, boundary = _edges(tris)
    rest = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)
    h = float(rest.mean())
    interior = np.ones(len(x), dtype=bool)
    interior[boundary.ravel()] = False
    # the displacement's Laplacian at the interior vertices, in metres (h^2 M^-1 K), per vertex
    smooth = h * h * (deformation._stiffness / deformation.mass[:, None])[interior]
    smooth /= math.sqrt(max(int(interior.sum()), 1))
    surface = _Surface(placed, tris, device)

    def fit(start, basis, stages, iterations, smooth_offset, floor):
        # Gauss-Newton steps on the coefficients c of displacements basis @ c from start, modes coarse to fine
        c = np.zeros((basis.shape[1], 3))
        dbasis = basis[edges[:, 0]] - basis[edges[:, 1]]
        sb = smooth @ basis
        smooth_normal = sb.T @ sb
        smooth_rhs = sb.T @ smooth_offset
        per_stage = max(2, iterations // len(stages))
        for s, active in enumerate(stages):
            for _ in range(per_stage if s < len(stages) - 1 else max(2, iterations - (len(stages) - 1) * per_stage)):
                xs = start + basis @ c
                surface.update(xs)
                f, bary, closest = surface.closest(q)
                r = q - closest
                w = _weights(np.einsum("pc,pc->p", r, r), trim, floor)
                g = np.einsum("pk,pkj->pj", bary, basis[tris[f], :active])
                normal = _cross_rows(xs, tris)[f]
                normal /= np.linalg.norm(normal, axis=1, keepdims=True)
                gn = (g[:, :, None] * normal[:, None, :]).reshape(len(f), -1)
                H = (1.0 - _TANGENTIAL) * ((gn.T * w) @ gn) + _TANGENTIAL * np.kron((g.T * w) @ g, np.eye(3))
                rhs = ((1.0 - _TANGENTIAL) * ((gn.T * w) @ np.einsum("pc,pc->p", normal, r))
                       + _TANGENTIAL * ((g.T * w) @ r).reshape(-1))
                if both_ways:
                    near = _nearest(xs, q, surface.device)
                    r = q[near] - xs
                    w = _weights(np.einsum("pc,pc->p", r, r), trim, floor)
                    g = basis[:, :active]
                    H += np.kron((g.T * w) @ g, np.eye(3))
                    rhs += ((g.T * w) @ r).reshape(-1)
                d = xs[edges[:, 0]] - xs[edges[:, 1]]
                length = np.linalg.norm(d, axis=1)
                J = (dbasis[:, :active, None] * (d / length[:, None])[:, None, :]).reshape(len(edges), -1)
                H += preserve_lengths * (J.T @ J) / len(edges)
                rhs -= preserve_lengths * (J.T @ (length - rest)) / len(edges)
                H += smoothness * np.kron(smooth_normal[:active, :active], np.eye(3))
                rhs -= smoothness * (smooth_normal[:active] @ c + smooth_rhs[:active]).reshape(-1)
                H += 1e-10 * (np.trace(H) / len(H) + 1e-300) * np.eye(len(H))
                step = np.linalg.solve(H, rhs).reshape(active, 3)
                c[:active] += step
                if np.abs(basis[:, :active] @ step).max() < 1e-7 * h:
                    break
        return c

    c = fit(placed, phi, sorted({min(m, k) for k in (4, 8, 16, m)}), iterations, np.zeros((int(interior.sum()), 3)),
            _FLOOR * h)
    xs = placed + phi @ c
    if polish:
        free = np.setdiff1d(np.arange(len(x)), fixed)
        each = np.eye(len(x))[:, free]
        xs = xs + each @ fit(xs, each, [len(free)], polish, smooth @ (phi @ c), 1e-6 * h)
    surface.update(xs)
    d2 = np.sum((surface.closest(q)[2] - q) ** 2, axis=1)
    rms = _rms(d2, trim, _FLOOR * h)
    strain = np.linalg.norm(xs[edges[:, 0]] - xs[edges[:, 1]], axis=1) / rest - 1.0
    return NonrigidFit(xs + center, c, rms, strain, deformation, rigid)


def _template_of(model_or_template, what):
    if hasattr(model_or_template, "particle_x0") and hasattr(model_or_template, "triangles_np"):
        from warpcloth.observations import _world_layout

        count, tris = _world_layout(model_or_template, what)
        return model_or_template.particle_x0.numpy()[:count].astype(np.float64), tris
    if hasattr(model_or_template, "positions") and hasattr(model_or_template, "triangles"):
        return model_or_template.positions, model_or_template.triangles
    if isinstance(model_or_template, tuple) and len(model_or_template) == 2:
        return model_or_template
    raise ValueError(f"{what}: model_or_template must be a Model, a TriangleMesh or (positions (n, 3), triangles "
                     f"(T, 3)), got {type(model_or_template).__name__}")


def start_from_points(model_or_template, points, *, modes: int | None = None, trim: float = 5.0,
                      device=None) -> np.ndarray:
    """The start positions (n, 3) [m] of a cloth that match a recorded point cloud ``points`` (P, 3) [m]: its
    template (a Model's initial positions, one world's, or a TriangleMesh, or (positions, triangles)) placed by
    :func:`register_rigid`, then deformed by :func:`register_nonrigid`, polished when it has at most
    :data:`MAX_POLISH_VERTICES` vertices. ValueError naming a bad argument."""
    what = "start_from_points"
    x, tris = _template_of(model_or_template, what)
    polish = 10 if len(np.asarray(x)) <= MAX_POLISH_VERTICES else 0
    return register_nonrigid(x, tris, points, modes=modes, trim=trim, polish=polish, device=device).positions
