"""Differentiable contact geometry: the normal and weights of each frozen contact, from positions (SPEC.md §4.2).

Detection (kernels/collision.py) freezes each contact's nodes, mode, time of impact t and side sign. Here the
positions at t, x(t) = x0 + t (x1 - x0), give the constraint's unit normal n and weights w; Warp's autodiff carries
dL/dn and dL/dw (from the projection's adjoint) back to the start and end positions of cloth and obstacles.

The time of impact of a continuous contact (t < 1: the four points coplanar, f(t) = (b - a) . (c - a) x (d - a) = 0)
moves with the positions: dt/dx = -(df/dx) / f'(t) (implicit function theorem). It enters as
t - (f(t) - f(t)|const) / f'(t) (``frozen``: a copy with a zero adjoint), exactly the detected t, whose derivative
is that one (why: docs/decisions.md, 'Time of impact takes gradients'). Not differentiated, by design: which
contacts exist, the side sign, and a grazing impact's t (f'(t) near 0, where dt/dx is unbounded).
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.geometry import segment_parameters, span_coordinates
from warpcloth.kernels.implicit import implicit_kernels
from warpcloth.kernels.types import per_precision, types

VF_PLANE = 0
EE_PLANE = 1
EE_DIRECTION = 2  # the modes of kernels/collision.py
WORLD_SKIPPED = wp.constant(-1)
WORLD_KEEPS_START_GAPS = wp.constant(1)
"""A world's mode in one try of the collision stage (an int32 per world, ``ContactDetector.world_mode``): 0 the
full thickness; WORLD_KEEPS_START_GAPS the second try, where a pair that starts inside the thickness keeps its start
gap; WORLD_SKIPPED no contacts (a world left to the fail-safe, or not the fail-safe's)."""
GRAZING = 1.0e-6
"""|f'(t)| below this times |b - a| |c - a| |d - a| at the root: a grazing impact, whose t stays frozen."""


@per_precision
def contact_kernels(scalar):
    t = types(scalar)
    vec3, vec4 = t.vec3, t.vec4
    one = scalar(1.0)
    guard = implicit_kernels(scalar).flag_divergence

    # Nearly parallel segments: this s is differentiated and ds/dx grows like 1/den, so the geometry treats
    # segments as parallel from a larger squared sine than detection (kernels/collision.py's PARALLEL_SINE2).
    parallel_sine2 = scalar(1.0e-12)

    @wp.kernel
    def gather_nodes(cloth_x: wp.array(dtype=vec3), obstacle_x: wp.array(dtype=vec3), cloth_count: int,
                     # out:
                     nodes: wp.array(dtype=vec3)):
        # one array of all positions: cloth particles first, then obstacle vertices
        i = wp.tid()
        if i < cloth_count:
            nodes[i] = cloth_x[i]
        else:
            nodes[i] = obstacle_x[i - cloth_count]

    @wp.kernel(enable_backward=False)
    def gather_two(cloth_a: wp.array(dtype=vec3), obstacle_a: wp.array(dtype=vec3), cloth_b: wp.array(dtype=vec3),
                   obstacle_b: wp.array(dtype=vec3), cloth_count: int,
                   # out:
                   nodes_a: wp.array(dtype=vec3), nodes_b: wp.array(dtype=vec3)):
        # gather_nodes of two sets of positions in one launch (untaped: the collision stage's detection buffers)
        i = wp.tid()
        if i < cloth_count:
            nodes_a[i] = cloth_a[i]
            nodes_b[i] = cloth_b[i]
        else:
            nodes_a[i] = obstacle_a[i - cloth_count]
            nodes_b[i] = obstacle_b[i - cloth_count]

    @wp.func
    def frozen(value: scalar):
        """``value``, seen as a constant by the adjoint."""
        return value

    @wp.func_grad(frozen)
    def adj_frozen(value: scalar, adj_ret: scalar):
        pass

    @wp.func
    def impact_time(a0: vec3, b0: vec3, c0: vec3, d0: vec3, a1: vec3, b1: vec3, c1: vec3, d1: vec3, t: scalar):
        """The coplanarity root t moved by one Newton step: its value, with dt/dx (module docstring)."""
        B = (b0 - a0) + t * ((b1 - a1) - (b0 - a0))
        C = (c0 - a0) + t * ((c1 - a1) - (c0 - a0))
        D = (d0 - a0) + t * ((d1 - a1) - (d0 - a0))
        dB = (b1 - a1) - (b0 - a0)
        dC = (c1 - a1) - (c0 - a0)
        dD = (d1 - a1) - (d0 - a0)
        f = wp.dot(B, wp.cross(C, D))
        slope = wp.dot(dB, wp.cross(C, D)) + wp.dot(B, wp.cross(dC, D)) + wp.dot(B, wp.cross(C, dD))
        scale = wp.length(B) * wp.length(C) * wp.length(D)
        if wp.abs(slope) > scalar(GRAZING) * scale:
            return t - (f - frozen(f)) / slope  # exactly t, with dt/dx = -(df/dx) / f'(t)
        return t

    @wp.func
    def start_distance(mode: int, a: vec3, b: vec3, c: vec3, d: vec3):
        """The distance detection measures a pair's start gap by (kernels/collision.py): vertex a to the plane of
        face (b, c, d), or between the segments (a, b) and (c, d)."""
        if mode == VF_PLANE:
            n = wp.cross(c - b, d - b)
            if wp.length(n) > scalar(0.0):
                return wp.abs(wp.dot(n, a - b)) / wp.length(n)
            return scalar(1.0e30)
        s, u = segment_parameters(a, b, c, d, parallel_sine2)
        return wp.length((a + s * (b - a)) - (c + u * (d - c)))

    @wp.kernel
    def geometry(x0: wp.array(dtype=vec3), x1: wp.array(dtype=vec3), contact_nodes: wp.array2d(dtype=wp.int32),
                 contact_mode: wp.array(dtype=wp.int32), contact_t: wp.array(dtype=wp.float64),
                 contact_sign: wp.array(dtype=wp.float64), thickness: scalar, world_mode: wp.array(dtype=wp.int32),
                 node_world: wp.array(dtype=wp.int32),
                 # out:
                 normal: wp.array(dtype=vec3), weight: wp.array(dtype=vec4), target: wp.array(dtype=scalar)):
        # target: the gap the projection keeps, sum_a w_a n . p_a >= target: the thickness; in the second try,
        # the gap the pair had at the start where that is less (a pair that starts inside the thickness may not come
        # closer; pushed a full thickness apart, such pairs contradict each other in a crumpled cloth)
        j = wp.tid()
        tj = scalar(contact_t[j])
        mode = contact_mode[j]
        if mode != EE_DIRECTION and contact_t[j] < wp.float64(1.0):
            i0 = contact_nodes[j, 0]
            i1 = contact_nodes[j, 1]
            i2 = contact_nodes[j, 2]
            i3 = contact_nodes[j, 3]
            tj = impact_time(x0[i0], x0[i1], x0[i2], x0[i3], x1[i0], x1[i1], x1[i2], x1[i3], tj)
        sign = scalar(contact_sign[j])
        a = x0[contact_nodes[j, 0]] + tj * (x1[contact_nodes[j, 0]] - x0[contact_nodes[j, 0]])
        b = x0[contact_nodes[j, 1]] + tj * (x1[contact_nodes[j, 1]] - x0[contact_nodes[j, 1]])
        c = x0[contact_nodes[j, 2]] + tj * (x1[contact_nodes[j, 2]] - x0[contact_nodes[j, 2]])
        d = x0[contact_nodes[j, 3]] + tj * (x1[contact_nodes[j, 3]] - x0[contact_nodes[j, 3]])
        n = vec3()
        w = vec4()
        if mode == VF_PLANE:
            # vertex a over face (b, c, d): barycentric coordinates (1 - u - v, u, v) of a's projection on the face
            e1 = c - b
            e2 = d - b
            u, v, _det, _scale = span_coordinates(e1, e2, a - b)
            n = sign * wp.normalize(wp.cross(e1, e2))
            w = vec4(one, -(one - u - v), -u, -v)
        elif mode == EE_PLANE:
            # crossing edges (a, b) and (c, d): the normal of the plane they span, the lines' closest points
            # a + s d1 and c + u d2
            d1 = b - a
            d2 = d - c
            s, u, _det, _scale = span_coordinates(d1, c - d, c - a)
            n = sign * wp.normalize(wp.cross(d1, d2))
            w = vec4(one - s, s, -(one - u), -u)
        else:
            # closest points of the two segments; the normal points from the second to the first
            s, u = segment_parameters(a, b, c, d, parallel_sine2)
            gap = (a + s * (b - a)) - (c + u * (d - c))
            n = wp.normalize(gap)
            w = vec4(one - s, s, -(one - u), -u)
        normal[j] = n
        weight[j] = w
        target[j] = thickness
        if world_mode[node_world[contact_nodes[j, 0]]] == WORLD_KEEPS_START_GAPS:
            target[j] = wp.min(thickness, start_distance(mode, x0[contact_nodes[j, 0]], x0[contact_nodes[j, 1]],
                                                         x0[contact_nodes[j, 2]], x0[contact_nodes[j, 3]]))

    @wp.kernel
    def apply_projection(x_hat: wp.array(dtype=vec3), v_hat: wp.array(dtype=vec3), z: wp.array(dtype=vec3),
                         inv_dt: scalar, max_speed: scalar, step: int,
                         # out:
                         x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), record: wp.array(dtype=wp.int32)):
        # the projected positions, and velocities corrected by the displacement (SPEC §2 step 4); then the
        # divergence guard on them (the collision response changed the state), here rather than in a launch of its
        # own
        i = wp.tid()
        x_new = z[i]
        v_new = v_hat[i] + (x_new - x_hat[i]) * inv_dt
        x[i] = x_new
        v[i] = v_new
        guard(i, x_new, v_new, max_speed, step, record)

    @wp.kernel(enable_backward=False)
    def unmoved_adjoint(adj_x: wp.array(dtype=vec3), adj_v: wp.array(dtype=vec3), inv_dt: scalar,
                        # out:
                        x_hat_grad: wp.array(dtype=vec3), v_hat_grad: wp.array(dtype=vec3)):
        # The adjoint of a stage that moved nothing, as a copy z of x^ and apply_projection(x^, v^, z) taped
        # would give it, operation for operation: apply_projection's adjoint adds -(dL/dv inv_dt) to dL/dx^ and
        # dL/dx + dL/dv inv_dt to dL/dz (zero before), the copy's adds dL/dz to dL/dx^.
        i = wp.tid()
        d = adj_v[i] * inv_dt
        v_hat_grad[i] = v_hat_grad[i] + adj_v[i]
        x_hat_grad[i] = (x_hat_grad[i] - d) + (adj_x[i] + d)

    return SimpleNamespace(gather_nodes=gather_nodes, gather_two=gather_two, geometry=geometry,
                           apply_projection=apply_projection, unmoved_adjoint=unmoved_adjoint)

