"""Closest-point routines shared by detection (kernels/collision.py, float64) and the differentiable contact geometry
(kernels/contact.py, the model's precision): generic ``@wp.func`` over the vector type of their arguments."""

from typing import Any

import warp as wp


@wp.func
def span_coordinates(e1: Any, e2: Any, r: Any):
    """(u, v, det, scale): u e1 + v e2 is the point of the plane spanned by e1 and e2 closest to r.

    Solves the 2x2 Gram system [[e1.e1, e1.e2], [e1.e2, e2.e2]] (u, v) = (e1.r, e2.r) by Cramer's rule; det is its
    determinant and scale = (e1.e1)(e2.e2), so det / scale is the squared sine of the angle between e1 and e2.
    The caller decides what counts as degenerate (u and v are inf or nan where det is 0).
    Barycentric coordinates of p over triangle (a, b, c): (1 - u - v, u, v) of (b - a, c - a, p - a).
    Closest points a + s (b - a), c + u (d - c) of two lines: (s, u) of (b - a, c - d, c - a).
    """
    d11 = wp.dot(e1, e1)
    d12 = wp.dot(e1, e2)
    d22 = wp.dot(e2, e2)
    d1r = wp.dot(e1, r)
    d2r = wp.dot(e2, r)
    det = d11 * d22 - d12 * d12
    u = (d22 * d1r - d12 * d2r) / det
    v = (d11 * d2r - d12 * d1r) / det
    return u, v, det, d11 * d22


@wp.func
def segment_parameters(p0: Any, p1: Any, q0: Any, q1: Any, parallel: Any):
    """Parameters (s, u) in [0, 1] of the closest points p0 + s (p1 - p0), q0 + u (q1 - q0) of two segments
    (Ericson, Real-Time Collision Detection 5.1.9).

    Segments whose squared sine is at most ``parallel`` count as parallel: s starts at 0 and only the clamping
    moves it. A segment shorter than 1e-15 counts as a point.
    """
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    zero = type(a)(0.0)
    one = type(a)(1.0)
    s = zero
    u = zero
    tiny = type(a)(1.0e-30)
    if a <= tiny and e <= tiny:
        return zero, zero
    if a <= tiny:
        u = wp.clamp(f / e, zero, one)
        return zero, u
    c = wp.dot(d1, r)
    if e <= tiny:
        s = wp.clamp(-c / a, zero, one)
        return s, zero
    b = wp.dot(d1, d2)
    den = a * e - b * b
    if den > parallel * a * e:
        s = wp.clamp((b * f - c * e) / den, zero, one)
    u = (b * s + f) / e
    if u < zero:
        u = zero
        s = wp.clamp(-c / a, zero, one)
    elif u > one:
        u = one
        s = wp.clamp((b - c) / a, zero, one)
    return s, u


@wp.func
def triangle_barycentric(p: Any, a: Any, b: Any, c: Any):
    """Barycentric coordinates (u, v, w) of the point of triangle (a, b, c) closest to p: u a + v b + w c
    (Ericson, Real-Time Collision Detection 5.1.5, by Voronoi regions). A degenerate triangle gives a vertex or
    edge point."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    zero = type(d1)(0.0)
    one = type(d1)(1.0)
    if d1 <= zero and d2 <= zero:
        return one, zero, zero
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return zero, one, zero
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        s = d1 / (d1 - d3)
        return one - s, s, zero
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return zero, zero, one
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        s = d2 / (d2 - d6)
        return one - s, zero, s
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        s = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return zero, one - s, s
    denom = one / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return one - v - w, v, w


@wp.func
def box_rounding(lo: wp.vec3, hi: wp.vec3):
    """What a float32 bounding box is widened by, beyond any search distance: the rounding of its coordinates, many
    times over (detection's swept boxes and the proximity pairs' boxes alike)."""
    return 1.0e-6 * (wp.max(wp.abs(lo)) + wp.max(wp.abs(hi)))


KEY_END = wp.constant(wp.int64(0x7FFFFFFFFFFFFFFF))
"""The sort key of an empty slot: after every row's."""


@wp.func
def first_at_least(keys: wp.array(dtype=wp.int64), n: int, value: wp.int64):
    """The first of the ascending ``keys[0:n]`` that is >= ``value`` (n where none is): a binary search."""
    lo = int(0)
    hi = n
    while lo < hi:
        mid = (lo + hi) // 2
        if keys[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.kernel(enable_backward=False)
def world_starts(keys: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32), span: wp.int64,
                 start: wp.array(dtype=wp.int32)):
    """Rows (contacts, proximity pairs) sorted by a key whose world w owns [w span, (w + 1) span): ``start[w]``,
    world w's first row, one thread a world (launch world_count + 1 threads: ``start[world_count]`` is the count).
    Sorted by ``wp.utils.radix_sort_pairs`` (stable), a world's rows are those a model of it alone finds, in order."""
    w = wp.tid()
    start[w] = first_at_least(keys, count[0], wp.int64(w) * span)


@wp.func
def world_root(bvh: wp.uint64, grouped: int, world: int):
    """The BVH node a query of a primitive in ``world`` starts from: the root of that world's group in a BVH grouped
    by world (``grouped`` != 0), so it meets only its own world's primitives; -1 (the global root) otherwise, and
    -2 where the world has no primitive in the BVH (the query must be skipped: -1 would search every world)."""
    if grouped == 0:
        return int(-1)
    root = wp.bvh_get_group_root(bvh, world)
    if root < 0:
        return int(-2)
    return root
