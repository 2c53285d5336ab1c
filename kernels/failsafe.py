"""Rigid impact zones, the collision stage's fail-safe (Provot 1997; Bridson, Fedkiw and Anderson 2002), differentiated
by Warp.

Each zone's free particles move as one rigid body from their start positions x0: the translation and the small
rotation that best fit the step's unprojected displacements d = x^ - x0, weighted by the masses,

    T = sum m d / M,   theta = I^-1 sum m r x d   (r = x0 - c about the zone's centre of mass c, I its inertia),

which is what the zone's linear and angular momentum give it (conserved to first order in the rotation); the
rotation is applied exactly (Rodrigues), so the zone's relative configuration, collision-free or not at x0, is that
of x0. A zone that touches an obstacle or a pinned particle (an anchor) moves with the anchors' mean displacement
instead. Particles in no zone keep x^.
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import per_precision, types

INERTIA_FLOOR = 1.0e-12
"""A zone's inertia is regularised by this times its trace (a zone of one particle, or of particles on a line, has a
singular one: it takes no rotation about the singular axes)."""


@per_precision
def failsafe_kernels(scalar):
    t = types(scalar)
    vec3, mat33 = t.vec3, t.mat33

    @wp.kernel
    def zone_sums(x0: wp.array(dtype=vec3), x_hat: wp.array(dtype=vec3), mass: wp.array(dtype=scalar),
                  zone: wp.array(dtype=wp.int32),
                  # out:
                  total: wp.array(dtype=scalar), first: wp.array(dtype=vec3), moved: wp.array(dtype=vec3)):
        # per zone: M, sum m x0, sum m d
        i = wp.tid()
        z = zone[i]
        if z >= 0:
            m = mass[i]
            wp.atomic_add(total, z, m)
            wp.atomic_add(first, z, m * x0[i])
            wp.atomic_add(moved, z, m * (x_hat[i] - x0[i]))

    @wp.kernel
    def zone_rotation_sums(x0: wp.array(dtype=vec3), x_hat: wp.array(dtype=vec3), mass: wp.array(dtype=scalar),
                           zone: wp.array(dtype=wp.int32), total: wp.array(dtype=scalar),
                           first: wp.array(dtype=vec3),
                           # out:
                           turn: wp.array(dtype=vec3), inertia: wp.array(dtype=mat33)):
        # per zone: sum m r x d and the inertia sum m (|r|^2 I - r r^T) about the centre of mass
        i = wp.tid()
        z = zone[i]
        if z >= 0:
            m = mass[i]
            r = x0[i] - first[z] / total[z]
            wp.atomic_add(turn, z, m * wp.cross(r, x_hat[i] - x0[i]))
            wp.atomic_add(inertia, z, m * (wp.dot(r, r) * wp.identity(n=3, dtype=scalar) - wp.outer(r, r)))

    @wp.kernel
    def anchor_sums(start: wp.array(dtype=vec3), end: wp.array(dtype=vec3), anchor_zone: wp.array(dtype=wp.int32),
                    anchor_node: wp.array(dtype=wp.int32),
                    # out:
                    shift: wp.array(dtype=vec3), count: wp.array(dtype=scalar)):
        # per anchored zone: the sum of its anchors' displacements (obstacle vertices, pinned particles) and their
        # number
        k = wp.tid()
        z = anchor_zone[k]
        a = anchor_node[k]
        wp.atomic_add(shift, z, end[a] - start[a])
        wp.atomic_add(count, z, scalar(1.0))

    @wp.func
    def rotate(theta: vec3, r: vec3):
        angle = wp.length(theta)
        if angle < scalar(1.0e-12):
            return r + wp.cross(theta, r)
        k = theta / angle
        c = wp.cos(angle)
        s = wp.sin(angle)
        return r * c + wp.cross(k, r) * s + k * (wp.dot(k, r) * (scalar(1.0) - c))

    @wp.kernel
    def rigid_positions(x0: wp.array(dtype=vec3), x_hat: wp.array(dtype=vec3), zone: wp.array(dtype=wp.int32),
                        total: wp.array(dtype=scalar), first: wp.array(dtype=vec3), moved: wp.array(dtype=vec3),
                        turn: wp.array(dtype=vec3), inertia: wp.array(dtype=mat33), shift: wp.array(dtype=vec3),
                        count: wp.array(dtype=scalar),
                        # out:
                        z_out: wp.array(dtype=vec3)):
        i = wp.tid()
        z = zone[i]
        p = x_hat[i]
        if z >= 0:
            if count[z] > scalar(0.0):  # anchored: moves with its anchors
                p = x0[i] + shift[z] / count[z]
            else:
                c = first[z] / total[z]
                inert = inertia[z]
                floor = scalar(INERTIA_FLOOR) * (inert[0, 0] + inert[1, 1] + inert[2, 2]) + scalar(1.0e-300)
                theta = wp.inverse(inert + floor * wp.identity(n=3, dtype=scalar)) * turn[z]
                p = c + moved[z] / total[z] + rotate(theta, x0[i] - c)
        z_out[i] = p

    return SimpleNamespace(zone_sums=zone_sums, zone_rotation_sums=zone_rotation_sums, anchor_sums=anchor_sums,
                           rigid_positions=rigid_positions)
