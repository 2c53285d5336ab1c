"""Kernels of the observation losses (``warpcloth.observations``): markers on the cloth's surface and point clouds.

The ``*_loss`` kernels are differentiable and accumulate into ``loss[w]`` (the caller zeroes it); the others find
closest points and nearest neighbours and run off the tape: their results are held fixed by the taped kernels
(the envelope theorem makes that the exact gradient where the closest point is unique).
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import per_precision, types


@per_precision
def observation_kernels(scalar):
    """The observation kernels for ``scalar``: a namespace of ``marker_loss``, ``to_mesh_points``,
    ``closest_on_surface``, ``surface_loss``, ``surface_distance2``, ``nearest_point`` and ``nearest_loss``."""
    vec3 = types(scalar).vec3

    @wp.func
    def closest_on_triangle(p: vec3, a: vec3, b: vec3, c: vec3):
        """Barycentric coordinates (of a, b, c) of the point of triangle abc closest to p (Ericson, 5.1.5)."""
        zero = scalar(0.0)
        one = scalar(1.0)
        ab = b - a
        ac = c - a
        ap = p - a
        d1 = wp.dot(ab, ap)
        d2 = wp.dot(ac, ap)
        if d1 <= zero and d2 <= zero:
            return vec3(one, zero, zero)
        bp = p - b
        d3 = wp.dot(ab, bp)
        d4 = wp.dot(ac, bp)
        if d3 >= zero and d4 <= d3:
            return vec3(zero, one, zero)
        vc = d1 * d4 - d3 * d2
        if vc <= zero and d1 >= zero and d3 <= zero:
            t = d1 / (d1 - d3)
            return vec3(one - t, t, zero)
        cp = p - c
        d5 = wp.dot(ab, cp)
        d6 = wp.dot(ac, cp)
        if d6 >= zero and d5 <= d6:
            return vec3(zero, zero, one)
        vb = d5 * d2 - d1 * d6
        if vb <= zero and d2 >= zero and d6 <= zero:
            t = d2 / (d2 - d6)
            return vec3(one - t, zero, t)
        va = d3 * d6 - d5 * d4
        if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
            t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            return vec3(zero, one - t, t)
        denom = one / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        return vec3(one - v - w, v, w)

    @wp.func
    def surface_point(x: wp.array(dtype=vec3), tri: wp.array2d(dtype=wp.int32), t: int, first: int, b: vec3):
        return (b[0] * x[first + tri[t, 0]] + b[1] * x[first + tri[t, 1]] + b[2] * x[first + tri[t, 2]])

    @wp.kernel
    def marker_loss(
        x: wp.array(dtype=vec3),
        tri: wp.array2d(dtype=wp.int32),
        marker_tri: wp.array(dtype=wp.int32),
        marker_bary: wp.array(dtype=vec3),
        visible: wp.array(dtype=wp.int32),
        target: wp.array(dtype=vec3),
        offset: int,
        count: int,
        first: wp.array(dtype=wp.int32),
        scale: scalar,
        # out:
        loss: wp.array(dtype=scalar),
    ):
        """loss[w] += scale |p_m - target_j|^2 for the frame's visible entries j in [offset, offset + count),
        m = visible[j], p_m the marker's point on world w's cloth (``tri``: one world's triangles, local indices);
        one thread per world and entry."""
        t = wp.tid()
        w = t / count
        j = offset + t - w * count
        m = visible[j]
        d = surface_point(x, tri, marker_tri[m], first[w], marker_bary[m]) - target[j]
        wp.atomic_add(loss, w, scale * wp.dot(d, d))

    @wp.kernel
    def to_mesh_points(
        x: wp.array(dtype=vec3),
        # out:
        points: wp.array(dtype=wp.vec3f),
    ):
        """points[i] = x[i] in single precision (the query meshes' points); one thread per particle."""
        i = wp.tid()
        p = x[i]
        points[i] = wp.vec3f(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))

    @wp.kernel
    def closest_on_surface(
        meshes: wp.array(dtype=wp.uint64),
        x: wp.array(dtype=vec3),
        tri: wp.array2d(dtype=wp.int32),
        first: wp.array(dtype=wp.int32),
        q: wp.array(dtype=vec3),
        offset: int,
        count: int,
        base: int,
        # out:
        face: wp.array(dtype=wp.int32),
        bary: wp.array(dtype=vec3),
    ):
        """For recorded point q[offset + i] and world w: the closest face of world w's mesh (a single-precision
        query, then the faces within its rounding compared in ``scalar``) and the closest point's barycentric
        coordinates on it: face/bary[base + w count + i]; one thread per world and point. Not taped."""
        t = wp.tid()
        w = t / count
        i = t - w * count
        p = q[offset + i]
        pf = wp.vec3f(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))
        o = first[w]
        f = int(0)
        hit = wp.mesh_query_point_no_sign(meshes[w], pf, wp.float32(1.0e30))
        if hit.result:
            f = hit.face
        b = closest_on_triangle(p, x[o + tri[f, 0]], x[o + tri[f, 1]], x[o + tri[f, 2]])
        r = p - surface_point(x, tri, f, o, b)
        best = wp.dot(r, r)
        # the faces within the single-precision query's rounding of it, compared in ``scalar``
        pad = scalar(1.0e-5) * (scalar(1.0) + wp.max(wp.abs(p[0]), wp.max(wp.abs(p[1]), wp.abs(p[2]))))
        near = wp.mesh_query_sphere(meshes[w], pf, wp.float32(wp.sqrt(best) + pad))
        g = int(0)
        while wp.mesh_query_next(near, g):
            c = closest_on_triangle(p, x[o + tri[g, 0]], x[o + tri[g, 1]], x[o + tri[g, 2]])
            r = p - surface_point(x, tri, g, o, c)
            d2 = wp.dot(r, r)
            if d2 < best or (d2 == best and g < f):
                best = d2
                f = g
                b = c
        face[base + t] = f
        bary[base + t] = b

    @wp.kernel
    def surface_loss(
        x: wp.array(dtype=vec3),
        tri: wp.array2d(dtype=wp.int32),
        first: wp.array(dtype=wp.int32),
        q: wp.array(dtype=vec3),
        offset: int,
        count: int,
        base: int,
        face: wp.array(dtype=wp.int32),
        bary: wp.array(dtype=vec3),
        delta: scalar,
        keep: wp.array(dtype=wp.int32),
        scale: scalar,
        # out:
        loss: wp.array(dtype=scalar),
    ):
        """loss[w] += scale rho(|q_i - c_i|), c_i world w's surface point at the fixed (face, bary); rho(d) = d^2
        for delta <= 0, else Huber: d^2 / 2 up to delta, delta (d - delta / 2) beyond; a point whose
        ``keep[base + t]`` is 0 is left out (an empty ``keep``: none is); one thread per world and point."""
        t = wp.tid()
        if keep.shape[0] > 0:
            if keep[base + t] == 0:
                return
        w = t / count
        i = t - w * count
        r = q[offset + i] - surface_point(x, tri, face[base + t], first[w], bary[base + t])
        d2 = wp.dot(r, r)
        rho = d2
        if delta > scalar(0.0):
            if d2 <= delta * delta:
                rho = scalar(0.5) * d2
            else:
                rho = delta * (wp.sqrt(d2) - scalar(0.5) * delta)
        wp.atomic_add(loss, w, scale * rho)

    @wp.kernel
    def surface_distance2(
        x: wp.array(dtype=vec3),
        tri: wp.array2d(dtype=wp.int32),
        first: wp.array(dtype=wp.int32),
        q: wp.array(dtype=vec3),
        offset: int,
        count: int,
        base: int,
        face: wp.array(dtype=wp.int32),
        bary: wp.array(dtype=vec3),
        # out:
        d2: wp.array(dtype=scalar),
    ):
        """d2[t] = |q_i - c_i|^2 as surface_loss measures it; one thread per world and point. Not taped."""
        t = wp.tid()
        w = t / count
        i = t - w * count
        r = q[offset + i] - surface_point(x, tri, face[base + t], first[w], bary[base + t])
        d2[t] = wp.dot(r, r)

    @wp.kernel
    def nearest_point(
        x: wp.array(dtype=vec3),
        q: wp.array(dtype=vec3),
        offset: int,
        count: int,
        base: int,
        # out:
        nearest: wp.array(dtype=wp.int32),
    ):
        """nearest[base + i] = offset + the index of the recorded point q[offset:offset + count] nearest to x[i]
        (brute force, first of ties); one thread per particle. Not taped."""
        i = wp.tid()
        p = x[i]
        best = int(0)
        d = q[offset] - p
        best_d2 = wp.dot(d, d)
        for j in range(1, count):
            d = q[offset + j] - p
            d2 = wp.dot(d, d)
            if d2 < best_d2:
                best_d2 = d2
                best = j
        nearest[base + i] = offset + best

    @wp.kernel
    def nearest_loss(
        x: wp.array(dtype=vec3),
        q: wp.array(dtype=vec3),
        nearest: wp.array(dtype=wp.int32),
        base: int,
        particle_world: wp.array(dtype=wp.int32),
        scale: scalar,
        # out:
        loss: wp.array(dtype=scalar),
    ):
        """loss[w] += scale |x_i - q[nearest[base + i]]|^2, w particle i's world; one thread per particle."""
        i = wp.tid()
        d = x[i] - q[nearest[base + i]]
        wp.atomic_add(loss, particle_world[i], scale * wp.dot(d, d))

    return SimpleNamespace(
        marker_loss=marker_loss,
        to_mesh_points=to_mesh_points,
        closest_on_surface=closest_on_surface,
        surface_loss=surface_loss,
        surface_distance2=surface_distance2,
        nearest_point=nearest_point,
        nearest_loss=nearest_loss,
    )
