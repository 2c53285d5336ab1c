"""Collision detection: swept bounding boxes, BVH queries, vertex-face and edge-edge proximity and CCD tests.

Nothing here is differentiated (SPEC.md §3: detection only decides *which* constraints exist and freezes their time
of impact t, side sign and normal mode). The response re-evaluates normals and weights from positions at the frozen t
in kernels/contact.py, which is differentiated. All tests run in float64 whatever the model's precision, because the
cubic coplanarity roots and the barycentric tests lose too much in float32.

Positions live in one "node" array: cloth particles first (0..n-1), then obstacle vertices (n..n+V-1).

A contact is (nodes[4], mode, t, sign):
- mode VF_PLANE: vertex nodes[0] against triangle nodes[1:4]; n = sign * unit face normal at t, weights
  (1, -b0, -b1, -b2) with b the barycentric coordinates of the vertex's projection on the face plane at t.
- mode EE_PLANE: edge nodes[0:2] against edge nodes[2:4] at a crossing; n = sign * unit cross product of the edges.
- mode EE_DIRECTION: closest points of the two segments at t, n = unit vector between them (no sign needed);
  covers vertex-edge and vertex-vertex proximity as well (clamped segment parameters).
The constraint is sum_k w_k n . x_k >= thickness at the end positions (kernels/contact.py,
warpcloth/collision/projection.py).
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.blocks import block_sum
from warpcloth.kernels.contact import WORLD_SKIPPED
from warpcloth.kernels.geometry import box_rounding, segment_parameters, span_coordinates, world_root
from warpcloth.kernels.types import per_precision, types

wp.set_module_options({"enable_backward": False})

VF_PLANE = wp.constant(0)
EE_PLANE = wp.constant(1)
EE_DIRECTION = wp.constant(2)

BARY_EPS = wp.constant(wp.float64(1.0e-6))
"""Tolerance of the 'inside the face / segment' tests (ARCSim accepts barycentrics >= -1e-6)."""

MIN_EDGE_SINE = wp.constant(wp.float64(1.0e-2))
"""Crossing edges closer to parallel than this sine (0.57 degrees) are left to the vertex-face tests of their ends:
the plane they span, and so the constraint's normal, is ill-defined."""

PARALLEL_SINE2 = wp.constant(wp.float64(1.0e-20))
"""Lines or segments whose squared sine is at most this count as parallel (no crossing point; closest points from
the segment ends). Only guards the division: detection needs the values, not their derivatives."""

TOUCHING = wp.constant(wp.float64(1.0e-3))
"""Primitives closer than this fraction of the thickness along their normal at the start of the step touch: their
start side is rounding noise, and the side at the step's unprojected end decides (kernels/collision.py start_side)."""

PROXIMITY_MARGIN = wp.constant(wp.float64(1.0 - 1.0e-2))
"""Proximity contacts need a distance below thickness * margin, so that pairs the projection just left at the
thickness are not found again in the next round. Why 1 %: docs/decisions.md, 'Proximity margin'."""

START_SLACK = wp.constant(wp.float64(1.0e-2))
"""With ``keep_start_gaps`` (the collision stage's second try), a pair that starts inside the thickness keeps its
start gap as its target: it is a proximity contact only where it comes closer than that gap by more than this
fraction of the thickness, and a double crossing that ends no closer than it started is no contact."""


@wp.func
def cubic(c0: wp.float64, c1: wp.float64, c2: wp.float64, c3: wp.float64, t: wp.float64):
    return ((c3 * t + c2) * t + c1) * t + c0


@wp.func
def bisect_root(c0: wp.float64, c1: wp.float64, c2: wp.float64, c3: wp.float64, lo: wp.float64, hi: wp.float64):
    """A root of the cubic in [lo, hi], where it changes sign (60 halvings: float64 resolution on [0, 1])."""
    flo = cubic(c0, c1, c2, c3, lo)
    if flo == wp.float64(0.0):
        return lo
    a = lo
    b = hi
    for _ in range(60):
        m = wp.float64(0.5) * (a + b)
        fm = cubic(c0, c1, c2, c3, m)
        if (fm < wp.float64(0.0)) == (flo < wp.float64(0.0)):
            a = m
            flo = fm
        else:
            b = m
    return wp.float64(0.5) * (a + b)


@wp.func
def cubic_brackets(c0: wp.float64, c1: wp.float64, c2: wp.float64, c3: wp.float64):
    """Split [0, 1] at the cubic's critical points: the returned (t0 <= t1 <= t2 <= t3) bound monotone pieces."""
    one = wp.float64(1.0)
    zero = wp.float64(0.0)
    r0 = one
    r1 = one
    # derivative 3 c3 t^2 + 2 c2 t + c1
    qa = wp.float64(3.0) * c3
    qb = wp.float64(2.0) * c2
    qc = c1
    if wp.abs(qa) > wp.float64(1.0e-300):
        disc = qb * qb - wp.float64(4.0) * qa * qc
        if disc > zero:
            s = wp.sqrt(disc)
            # numerically stable pair of roots
            q = wp.float64(-0.5) * (qb + wp.sign(qb) * s) if qb != zero else wp.float64(-0.5) * s
            ra = q / qa
            rb = qc / q if q != zero else ra
            r0 = wp.min(ra, rb)
            r1 = wp.max(ra, rb)
    elif wp.abs(qb) > wp.float64(1.0e-300):
        r0 = -qc / qb
    r0 = wp.clamp(r0, zero, one)
    r1 = wp.clamp(r1, zero, one)
    if r1 < r0:
        tmp = r0
        r0 = r1
        r1 = tmp
    return zero, r0, r1, one


@wp.func
def face_barycentric(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d):
    """Barycentric coordinates (of a, b, c) of p's projection on the plane of the triangle; (-1,-1,-1) if degenerate."""
    u, v, det, scale = span_coordinates(b - a, c - a, p - a)
    if det <= wp.float64(1.0e-24) * scale or det <= wp.float64(0.0):
        return wp.vec3d(wp.float64(-1.0), wp.float64(-1.0), wp.float64(-1.0))
    return wp.vec3d(wp.float64(1.0) - u - v, u, v)


@wp.func
def line_parameters(p0: wp.vec3d, p1: wp.vec3d, q0: wp.vec3d, q1: wp.vec3d):
    """Parameters (s, u) of the closest points of the infinite lines p0+s(p1-p0), q0+u(q1-q0); valid=False if
    parallel."""
    s, u, den, scale = span_coordinates(p1 - p0, q0 - q1, q0 - p0)
    if den <= PARALLEL_SINE2 * scale or den <= wp.float64(0.0):
        return wp.float64(0.0), wp.float64(0.0), False
    return s, u, True


@wp.func
def lerp3(x0: wp.vec3d, x1: wp.vec3d, t: wp.float64):
    return x0 + t * (x1 - x0)


@wp.func
def coplanarity_roots(A0: wp.vec3d, B0: wp.vec3d, C0: wp.vec3d, A1: wp.vec3d, B1: wp.vec3d, C1: wp.vec3d):
    """Times t in [0, 1] (ascending, up to 3, padded with 2) at which A(t) x B(t) . C(t) = 0, each vector moving
    linearly from its start (A0) to its end (A1) value: the moments four linearly moving points are coplanar
    (Provot 1997; ARCSim's CCD)."""
    zero = wp.float64(0.0)
    dA = A1 - A0
    dB = B1 - B0
    dC = C1 - C0
    k0 = wp.dot(wp.cross(A0, B0), C0)
    k1 = wp.dot(wp.cross(dA, B0), C0) + wp.dot(wp.cross(A0, dB), C0) + wp.dot(wp.cross(A0, B0), dC)
    k2 = wp.dot(wp.cross(dA, dB), C0) + wp.dot(wp.cross(dA, B0), dC) + wp.dot(wp.cross(A0, dB), dC)
    k3 = wp.dot(wp.cross(dA, dB), dC)
    roots = wp.vec3d(wp.float64(2.0), wp.float64(2.0), wp.float64(2.0))
    count = int(0)
    if wp.abs(k0) + wp.abs(k1) + wp.abs(k2) + wp.abs(k3) == zero:
        return roots, count  # coplanar throughout: left to the proximity tests
    t0, t1, t2, t3 = cubic_brackets(k0, k1, k2, k3)
    for piece in range(3):
        lo = t0
        hi = t1
        if piece == 1:
            lo = t1
            hi = t2
        elif piece == 2:
            lo = t2
            hi = t3
        if hi > lo and cubic(k0, k1, k2, k3, lo) * cubic(k0, k1, k2, k3, hi) <= zero:
            roots[count] = bisect_root(k0, k1, k2, k3, lo, hi)
            count += 1
    return roots, count


@wp.func
def signed_volume(vertex_face: bool, x: wp.vec3d, y: wp.vec3d, z: wp.vec3d, w: wp.vec3d):
    """Which side of the face (y, z, w) vertex x is on, along the face normal (vertex_face); otherwise which side
    of edge (z, w) edge (x, y) is on, along the edges' cross product (the sign conventions of the contact normals)."""
    if vertex_face:
        return wp.dot(wp.cross(z - y, w - y), x - y)
    return wp.dot(wp.cross(y - x, w - z), x - z)


@wp.func
def start_side(vertex_face: bool, x0: wp.vec3d, y0: wp.vec3d, z0: wp.vec3d, w0: wp.vec3d,
               xr: wp.vec3d, yr: wp.vec3d, zr: wp.vec3d, wr: wp.vec3d, thickness: wp.float64):
    """(+1 or -1, touching): the side (signed_volume's convention) the primitives start on; ``touching`` when they
    start closer than TOUCHING * thickness along the normal, the side then being the one at the reference positions
    xr.. (the step's unprojected end, the same in every round), or +1 if those touch too."""
    one = wp.float64(1.0)
    volume = signed_volume(vertex_face, x0, y0, z0, w0)
    if wp.abs(volume) > TOUCHING * thickness * normal_length(vertex_face, x0, y0, z0, w0):
        return wp.sign(volume), False
    volume = signed_volume(vertex_face, xr, yr, zr, wr)
    if wp.abs(volume) > TOUCHING * thickness * normal_length(vertex_face, xr, yr, zr, wr):
        return wp.sign(volume), True
    return one, True


@wp.func
def normal_length(vertex_face: bool, x: wp.vec3d, y: wp.vec3d, z: wp.vec3d, w: wp.vec3d):
    """Length of the unnormalised normal of signed_volume (face normal, or the edges' cross product)."""
    if vertex_face:
        return wp.length(wp.cross(z - y, w - y))
    return wp.length(wp.cross(y - x, w - z))


@wp.func
def earliest_crossing(vertex_face: bool, roots: wp.vec3d, count: int, side0: wp.float64, touching: bool,
                      x0: wp.vec3d, y0: wp.vec3d, z0: wp.vec3d, w0: wp.vec3d,
                      x1: wp.vec3d, y1: wp.vec3d, z1: wp.vec3d, w1: wp.vec3d):
    """(crossed, t, sign): the earliest of the coplanarity times ``roots[:count]`` at which the primitives touch (CCD).

    ``vertex_face``: vertex x against triangle (y, z, w), touching when the vertex is inside the face; otherwise edge
    (x, y) against edge (z, w), touching when the segments cross and are not closer to parallel than MIN_EDGE_SINE.
    Positions x0.. are at the start of the step, x1.. at its end. ``sign`` makes the normal at t (the face's, or the
    cross product of the edges) point to the side the primitives were on just before t: the sign of their signed
    volume halfway between the previous root (or the start) and t. A pair that starts ``touching`` keeps ``side0``.
    """
    one = wp.float64(1.0)
    zero = wp.float64(0.0)
    previous = zero
    for r in range(count):
        t = roots[r]
        sign = side0
        if not touching:
            before = wp.float64(0.5) * (previous + t)
            volume = signed_volume(vertex_face, lerp3(x0, x1, before), lerp3(y0, y1, before),
                                   lerp3(z0, z1, before), lerp3(w0, w1, before))
            if volume < zero:
                sign = -one
            elif volume > zero:
                sign = one
        previous = t
        x = lerp3(x0, x1, t)
        y = lerp3(y0, y1, t)
        z = lerp3(z0, z1, t)
        w = lerp3(w0, w1, t)
        if vertex_face:
            b = face_barycentric(x, y, z, w)
            if b[0] >= -BARY_EPS and b[1] >= -BARY_EPS and b[2] >= -BARY_EPS:
                return True, t, sign
        else:
            s, u, ok = line_parameters(x, y, z, w)
            sine = wp.length(wp.cross(y - x, w - z)) / (wp.length(y - x) * wp.length(w - z))
            inside = s >= -BARY_EPS and s <= one + BARY_EPS and u >= -BARY_EPS and u <= one + BARY_EPS
            if ok and sine > MIN_EDGE_SINE and inside:
                return True, t, sign
    return False, one, one


@wp.func
def apart_along(n: wp.vec3d, p0: wp.vec3d, p1: wp.vec3d, q0: wp.vec3d, q1: wp.vec3d, q2: wp.vec3d):
    """(gap, spread): how far the points p0, p1 lie beyond the points q0, q1, q2 along the unit direction n,
    min(n.p) - max(n.q) (negative where they overlap), and the spread of both sets along n."""
    lo_p = wp.min(wp.dot(n, p0), wp.dot(n, p1))
    hi_p = wp.max(wp.dot(n, p0), wp.dot(n, p1))
    lo_q = wp.min(wp.min(wp.dot(n, q0), wp.dot(n, q1)), wp.dot(n, q2))
    hi_q = wp.max(wp.max(wp.dot(n, q0), wp.dot(n, q1)), wp.dot(n, q2))
    return lo_p - hi_q, (hi_p - lo_p) + (hi_q - lo_q)


@wp.func
def stay_apart(vertex_face: bool, x0: wp.vec3d, y0: wp.vec3d, z0: wp.vec3d, w0: wp.vec3d,
               x1: wp.vec3d, y1: wp.vec3d, z1: wp.vec3d, w1: wp.vec3d, thickness: wp.float64):
    """True where vertex x and triangle (y, z, w) (``vertex_face``), or edge (x, y) and edge (z, w), stay further
    apart than the thickness through the whole step, so that vertex_face_test or edge_edge_test cannot report them:
    a cheap exact filter in front of those tests. The gap along a fixed direction n is linear in time, so smallest at
    the start or the end, and bounds the distance from below; n runs from the other primitive's centroid to the
    vertex, or between the edges' midpoints, at the start."""
    # the two point sets: the vertex (twice) and the triangle's corners, or one edge's ends and the other's (its
    # second end twice)
    if vertex_face:
        n = x0 - (y0 + z0 + w0) / wp.float64(3.0)
        second0, second1, third0, third1 = x0, x1, y0, y1
    else:
        n = (x0 + y0) * wp.float64(0.5) - (z0 + w0) * wp.float64(0.5)
        second0, second1, third0, third1 = y0, y1, w0, w1
    length = wp.length(n)
    if not (length > wp.float64(0.0)):
        return False
    n = n / length
    gap0, spread0 = apart_along(n, x0, second0, third0, z0, w0)
    gap1, spread1 = apart_along(n, x1, second1, third1, z1, w1)
    slack = wp.float64(4.0) * BARY_EPS * wp.max(spread0, spread1)
    return wp.min(gap0, gap1) > thickness + slack


@wp.func
def vertex_face_test(p0: wp.vec3d, a0: wp.vec3d, b0: wp.vec3d, c0: wp.vec3d,
                     p1: wp.vec3d, a1: wp.vec3d, b1: wp.vec3d, c1: wp.vec3d,
                     pr: wp.vec3d, ar: wp.vec3d, br: wp.vec3d, cr: wp.vec3d, thickness: wp.float64,
                     keep_start_gaps: int):
    """(hit, mode, t, sign, rank) of a vertex against a triangle moving linearly over the step.

    First the earliest coplanarity time t in [0, 1] at which the vertex is inside the face (CCD, signed towards the
    side the vertex started on); otherwise proximity at the end positions:
    vertex over the face's interior and closer than the thickness (signed towards the side it started on).
    rank orders hits by urgency: t - 1 (in [-1, 0]) for a crossing, distance / thickness (in [0, 1)) otherwise.
    """
    side0, touching = start_side(True, p0, a0, b0, c0, pr, ar, br, cr, thickness)
    roots, count = coplanarity_roots(b0 - a0, c0 - a0, p0 - a0, b1 - a1, c1 - a1, p1 - a1)
    crossed, t, sign = earliest_crossing(True, roots, count, side0, touching, p0, a0, b0, c0, p1, a1, b1, c1)
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    n1 = wp.cross(b1 - a1, c1 - a1)
    nl = wp.length(n1)
    start = thickness
    if keep_start_gaps != 0:
        n0 = wp.cross(b0 - a0, c0 - a0)
        if wp.length(n0) > zero:
            start = wp.abs(wp.dot(n0, p0 - a0)) / wp.length(n0)
    if crossed and start < thickness and nl > zero:
        # A vertex that started inside the thickness and ends on its start side no closer than it started: its
        # linear path dips through the face's plane and back (a double crossing), which no constraint on the end
        # positions can exclude; taking it for a crossing re-finds it in every round.
        if sign * wp.dot(n1, p1 - a1) / nl >= start - START_SLACK * thickness:
            crossed = False
    if crossed:
        return True, VF_PLANE, t, sign, t - wp.float64(1.0)
    if nl <= zero:
        return False, VF_PLANE, one, one, wp.float64(2.0)
    w1 = face_barycentric(p1, a1, b1, c1)
    if w1[0] < -BARY_EPS or w1[1] < -BARY_EPS or w1[2] < -BARY_EPS:
        return False, VF_PLANE, one, one, wp.float64(2.0)
    dist = wp.dot(n1, p1 - a1) / nl
    # a vertex that started inside the thickness: a contact where it comes closer than its start gap
    limit = wp.min(thickness * PROXIMITY_MARGIN, start - START_SLACK * thickness)
    if wp.abs(dist) >= limit:
        return False, VF_PLANE, one, one, wp.float64(2.0)
    # the side the vertex started on: a vertex that crossed the face's plane outside the face (through a
    # neighbour, whose CCD test catches it) must come back to that side here too, not be pushed on through
    return True, VF_PLANE, one, side0, wp.abs(dist) / thickness


@wp.func
def edge_edge_test(p0: wp.vec3d, p1: wp.vec3d, q0: wp.vec3d, q1: wp.vec3d,
                   P0: wp.vec3d, P1: wp.vec3d, Q0: wp.vec3d, Q1: wp.vec3d,
                   pr0: wp.vec3d, pr1: wp.vec3d, qr0: wp.vec3d, qr1: wp.vec3d, thickness: wp.float64,
                   keep_start_gaps: int):
    """(hit, mode, t, sign, rank) of edge (p0, p1) against edge (q0, q1); lower case at the start, upper at the end,
    r at the reference positions (start_side).

    CCD: the earliest coplanarity time at which the two segments cross (EE_PLANE, signed by the start side);
    otherwise proximity of the two segments at the end positions (EE_DIRECTION, or EE_PLANE signed by the
    start side when the segments touch so closely that their connecting direction is undefined).
    """
    side0, touching = start_side(False, p0, p1, q0, q1, pr0, pr1, qr0, qr1, thickness)
    roots, count = coplanarity_roots(p1 - p0, q1 - q0, q0 - p0, P1 - P0, Q1 - Q0, Q0 - P0)
    crossed, t, sign = earliest_crossing(False, roots, count, side0, touching, p0, p1, q0, q1, P0, P1, Q0, Q1)
    s, u = segment_parameters(P0, P1, Q0, Q1, PARALLEL_SINE2)
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    gap = ((one - s) * P0 + s * P1) - ((one - u) * Q0 + u * Q1)
    dist = wp.length(gap)
    start = thickness
    if keep_start_gaps != 0:
        s0, u0 = segment_parameters(p0, p1, q0, q1, PARALLEL_SINE2)
        start = wp.length(((one - s0) * p0 + s0 * p1) - ((one - u0) * q0 + u0 * q1))
    n1 = wp.cross(P1 - P0, Q1 - Q0)
    if crossed and start < thickness and wp.length(n1) > zero:
        # edges that started inside the thickness and end on their start side no closer than they started: a
        # double crossing of their linear paths (as in vertex_face_test)
        if sign * wp.dot(n1, gap) / wp.length(n1) >= start - START_SLACK * thickness:
            crossed = False
    if crossed:
        return True, EE_PLANE, t, sign, t - wp.float64(1.0)
    gap0 = ((one - s) * p0 + s * p1) - ((one - u) * q0 + u * q1)
    # edges that started inside the thickness: a contact where they come closer than their start gap
    if dist >= wp.min(thickness * PROXIMITY_MARGIN, start - START_SLACK * thickness):
        return False, EE_DIRECTION, one, one, wp.float64(2.0)
    if wp.length(gap0) <= TOUCHING * thickness:  # touching at the start: the reference side decides
        gap0 = ((one - s) * pr0 + s * pr1) - ((one - u) * qr0 + u * qr1)
    if dist > wp.float64(1.0e-3) * thickness:
        if wp.dot(gap, gap0) <= zero:
            # the closest points changed sides over the step: a crossing the CCD above did not accept (near
            # parallel edges); the direction between them would point the wrong way, the ends' vertex-face tests
            # cover it
            return False, EE_DIRECTION, one, one, wp.float64(2.0)
        return True, EE_DIRECTION, one, one, dist / thickness
    n = wp.cross(P1 - P0, Q1 - Q0)
    if wp.length(n) <= MIN_EDGE_SINE * wp.length(P1 - P0) * wp.length(Q1 - Q0):
        # touching and parallel: the vertex-face tests of the ends cover it
        return False, EE_DIRECTION, one, one, wp.float64(2.0)
    return True, EE_PLANE, one, side0, dist / thickness


@wp.func
def keep_most_urgent(hit: bool, rank: wp.float64, sign: wp.float64, t: wp.float64, mode: int, target: int,
                     best: wp.vec2d, best_target: wp.vec2i, best_t: wp.vec2d, best_mode: wp.vec2i):
    """The lowest-rank hit so far on each side of a query primitive (+ side first), with one more test result.

    A query keeps one contact per side (ARCSim keeps the closest primitive per side); others that matter are found in
    the next round, after these are resolved. Returns the updated (best, best_target, best_t, best_mode).
    """
    side = 0 if sign > wp.float64(0.0) else 1
    # a tie goes to the lower target index, not to the one the BVH visits first: the CPU's and CUDA's BVHs differ,
    # and a cloth placed symmetrically over an obstacle's vertex ties exactly
    if hit and (rank < best[side] or (rank == best[side] and target < best_target[side])):
        best[side] = rank
        best_target[side] = target
        best_t[side] = t
        best_mode[side] = mode
    return best, best_target, best_t, best_mode


@wp.func
def emit(query: int, side: int, n0: int, n1: int, n2: int, n3: int, mode: int, t: wp.float64, capacity: int,
         count: wp.array(dtype=wp.int32), contact_key: wp.array(dtype=wp.int64), slot_of: wp.array(dtype=wp.int32),
         contact_nodes: wp.array2d(dtype=wp.int32), contact_mode: wp.array(dtype=wp.int32),
         contact_t: wp.array(dtype=wp.float64), contact_sign: wp.array(dtype=wp.float64)):
    """Append query thread ``query``'s contact on side 0 (sign +1) or 1 (sign -1); beyond ``capacity`` it is only
    counted. Its key (query, side) orders the contacts afterwards (sort_found), whatever order the appends ran in."""
    sign = wp.float64(1.0) if side == 0 else wp.float64(-1.0)
    slot = wp.atomic_add(count, 0, 1)
    if slot < capacity:
        contact_key[slot] = wp.int64(2 * query + side)
        slot_of[slot] = slot
        contact_nodes[slot, 0] = n0
        contact_nodes[slot, 1] = n1
        contact_nodes[slot, 2] = n2
        contact_nodes[slot, 3] = n3
        contact_mode[slot] = mode
        contact_t[slot] = t
        contact_sign[slot] = sign


@per_precision
def collision_kernels(scalar):
    """Detection kernels for node positions of one precision (``wp.float32`` or ``wp.float64``)."""
    vec3 = types(scalar).vec3

    @wp.kernel
    def world_motion(x0: wp.array(dtype=vec3), x1: wp.array(dtype=vec3), particle_start: wp.array(dtype=wp.int32),
                     # out:
                     shift: wp.array(dtype=wp.vec3)):
        # one thread block a world (launch_tiled): the mean displacement of its cloth particles over the step (0 for a
        # world without), its threads' sums reduced in a fixed order
        w, lane = wp.tid()
        total = wp.vec3d()
        i = particle_start[w] + lane
        while i < particle_start[w + 1]:
            total += wp.vec3d(x1[i]) - wp.vec3d(x0[i])
            i += wp.block_dim()
        total = wp.vec3d(block_sum(total[0]), block_sum(total[1]), block_sum(total[2]))
        count = particle_start[w + 1] - particle_start[w]
        if lane == 0:
            shift[w] = wp.vec3(total / wp.float64(wp.max(count, 1)))

    @wp.kernel
    def primitive_bounds(x0: wp.array(dtype=vec3), x1: wp.array(dtype=vec3), shift: wp.array(dtype=wp.vec3),
                         node_world: wp.array(dtype=wp.int32), prims: wp.array2d(dtype=wp.int32), corners: int,
                         pad: float,
                         # out:
                         lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
        # swept box of a triangle (corners=3), edge (2) or vertex (1) over the step, grown by pad, in a frame that
        # moves with its world's cloth (world_motion): every node of world w ends at x1 - shift[w]. Two primitives
        # that touch at some moment of the step touch in that frame too (a uniform motion moves both alike), so
        # their boxes there still overlap wherever they can meet, and a cloth falling or swinging as a whole sweeps
        # small boxes: fewer neighbours for the queries to test
        i = wp.tid()
        lo = wp.vec3(1.0e30, 1.0e30, 1.0e30)
        hi = wp.vec3(-1.0e30, -1.0e30, -1.0e30)
        for c in range(corners):
            j = prims[i, c]
            a = wp.vec3(x0[j])
            b = wp.vec3(x1[j]) - shift[node_world[j]]
            lo = wp.min(lo, wp.min(a, b))
            hi = wp.max(hi, wp.max(a, b))
        g = pad + box_rounding(lo, hi)
        lowers[i] = lo - wp.vec3(g, g, g)
        uppers[i] = hi + wp.vec3(g, g, g)

    @wp.kernel
    def query_all(x0: wp.array(dtype=vec3), x1: wp.array(dtype=vec3), x_ref: wp.array(dtype=vec3),
                  queries: wp.array2d(dtype=wp.int32), prims: wp.array2d(dtype=wp.int32),
                  lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3), query_start: wp.array(dtype=int),
                  query_offset: wp.array(dtype=int), bvhs: wp.array(dtype=wp.uint64),
                  target_offset: wp.array(dtype=int), vertex_face: wp.array(dtype=int), same: wp.array(dtype=int),
                  thickness: wp.float64, world_mode: wp.array(dtype=wp.int32), capacity: int,
                  node_world: wp.array(dtype=wp.int32), grouped: int, skip: wp.array(dtype=wp.int32),
                  # out:
                  count: wp.array(dtype=wp.int32), contact_key: wp.array(dtype=wp.int64),
                  slot_of: wp.array(dtype=wp.int32), contact_nodes: wp.array2d(dtype=wp.int32),
                  contact_mode: wp.array(dtype=wp.int32), contact_t: wp.array(dtype=wp.float64),
                  contact_sign: wp.array(dtype=wp.float64)):
        # Every query of a detection in one launch: thread i is query primitive i - query_start[k] of query k (the
        # queries one after another, in the detector's order; the contacts are sorted into that order afterwards,
        # sort_found, which on the CPU, whose threads run in order, is the order they were appended in). Query k:
        # its rows (a vertex as (v, v), an edge as (a, b)) against the BVH bvhs[k] of the primitives
        # prims[target_offset[k]:], their boxes lowers and uppers at query_offset[k] + its index; a
        # vertex-face query (vertex_face[k]) or an edge-edge one; same[k] != 0: queries and targets are the same
        # cloth's, so incident primitives are skipped (each edge pair once). skip[0] != 0 (an error latched in the
        # failure record): no query runs.
        i = wp.tid()
        if skip[0] != 0:
            return
        k = int(0)
        while query_start[k + 1] <= i:
            k += 1
        local = i - query_start[k]
        q0 = queries[i, 0]
        q1 = queries[i, 1]
        vf = vertex_face[k]
        same_cloth = same[k]
        toff = target_offset[k]
        bvh = bvhs[k]
        # the query's world's mode in this try of the step (WORLD_SKIPPED, 0, or WORLD_KEEPS_START_GAPS)
        keep_start_gaps = world_mode[node_world[q0]]
        if keep_start_gaps == WORLD_SKIPPED:
            return
        root = world_root(bvh, grouped, node_world[q0])  # only the query's own world (ModelBuilder.add_world)
        if root == -2:
            return
        query = wp.bvh_query_aabb(bvh, lowers[query_offset[k] + local], uppers[query_offset[k] + local], root)
        j = int(0)
        # the most urgent contact on each side of the query primitive (EE_DIRECTION counts as the + side)
        best = wp.vec2d(wp.float64(2.0), wp.float64(2.0))
        best_target = wp.vec2i(-1, -1)
        best_t = wp.vec2d()
        best_mode = wp.vec2i()
        while wp.bvh_query_next(query, j):
            a = prims[toff + j, 0]
            b = prims[toff + j, 1]
            hit = bool(False)
            mode = int(0)
            t = wp.float64(0.0)
            sign = wp.float64(0.0)
            rank = wp.float64(0.0)
            if vf != 0:
                c = prims[toff + j, 2]
                if same_cloth != 0 and (q0 == a or q0 == b or q0 == c):
                    continue
                if stay_apart(True, wp.vec3d(x0[q0]), wp.vec3d(x0[a]), wp.vec3d(x0[b]), wp.vec3d(x0[c]),
                              wp.vec3d(x1[q0]), wp.vec3d(x1[a]), wp.vec3d(x1[b]), wp.vec3d(x1[c]), thickness):
                    continue
                hit, mode, t, sign, rank = vertex_face_test(
                    wp.vec3d(x0[q0]), wp.vec3d(x0[a]), wp.vec3d(x0[b]), wp.vec3d(x0[c]),
                    wp.vec3d(x1[q0]), wp.vec3d(x1[a]), wp.vec3d(x1[b]), wp.vec3d(x1[c]),
                    wp.vec3d(x_ref[q0]), wp.vec3d(x_ref[a]), wp.vec3d(x_ref[b]), wp.vec3d(x_ref[c]), thickness,
                    keep_start_gaps)
            else:
                if same_cloth != 0 and (j <= local or q0 == a or q0 == b or q1 == a or q1 == b):
                    continue  # each pair once; edges sharing a vertex do not collide
                if stay_apart(False, wp.vec3d(x0[q0]), wp.vec3d(x0[q1]), wp.vec3d(x0[a]), wp.vec3d(x0[b]),
                              wp.vec3d(x1[q0]), wp.vec3d(x1[q1]), wp.vec3d(x1[a]), wp.vec3d(x1[b]), thickness):
                    continue
                hit, mode, t, sign, rank = edge_edge_test(
                    wp.vec3d(x0[q0]), wp.vec3d(x0[q1]), wp.vec3d(x0[a]), wp.vec3d(x0[b]),
                    wp.vec3d(x1[q0]), wp.vec3d(x1[q1]), wp.vec3d(x1[a]), wp.vec3d(x1[b]),
                    wp.vec3d(x_ref[q0]), wp.vec3d(x_ref[q1]), wp.vec3d(x_ref[a]), wp.vec3d(x_ref[b]),
                    thickness, keep_start_gaps)
            best, best_target, best_t, best_mode = keep_most_urgent(hit, rank, sign, t, mode, j, best,
                                                                    best_target, best_t, best_mode)
        for side in range(2):
            jb = best_target[side]
            if jb >= 0:
                if vf != 0:
                    emit(i, side, q0, prims[toff + jb, 0], prims[toff + jb, 1], prims[toff + jb, 2], best_mode[side],
                         best_t[side], capacity, count, contact_key, slot_of, contact_nodes, contact_mode, contact_t,
                         contact_sign)
                else:
                    emit(i, side, q0, q1, prims[toff + jb, 0], prims[toff + jb, 1], best_mode[side], best_t[side],
                         capacity, count, contact_key, slot_of, contact_nodes, contact_mode, contact_t, contact_sign)

    @wp.kernel(enable_backward=False)
    def sort_found(order: wp.array(dtype=wp.int32), nodes: wp.array2d(dtype=wp.int32), mode: wp.array(dtype=wp.int32),
                   t: wp.array(dtype=wp.float64), sign: wp.array(dtype=wp.float64),
                   # out:
                   sorted_nodes: wp.array2d(dtype=wp.int32), sorted_mode: wp.array(dtype=wp.int32),
                   sorted_t: wp.array(dtype=wp.float64), sorted_sign: wp.array(dtype=wp.float64)):
        # the contacts as found, in the order of their keys (order: wp.utils.radix_sort_pairs's)
        k = wp.tid()
        j = order[k]
        for c in range(4):
            sorted_nodes[k, c] = nodes[j, c]
        sorted_mode[k] = mode[j]
        sorted_t[k] = t[j]
        sorted_sign[k] = sign[j]

    @wp.kernel
    def inside_mesh(mesh: wp.uint64, x: wp.array(dtype=vec3), max_dist: float,
                    # out:
                    inside: wp.array(dtype=wp.int32)):
        # generalised winding number > 1/2: the particle is inside the closed mesh
        i = wp.tid()
        q = wp.mesh_query_point_sign_winding_number(mesh, wp.vec3(x[i]), max_dist, 2.0, 0.5)
        if q.result and q.sign < 0.0:
            inside[i] = 1

    return SimpleNamespace(world_motion=world_motion, primitive_bounds=primitive_bounds, query_all=query_all,
                           sort_found=sort_found, inside_mesh=inside_mesh)

