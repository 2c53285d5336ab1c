"""Dihedral-angle bending (Bridson et al. 2003) with the data-driven stiffness of Wang et al. 2011.

Formulas follow SPEC.md §1.3 (ARCSim ``physics.cpp`` bending force, ``geometry.cpp`` dihedral angle,
``dde.cpp`` bending stiffness). Hinge layout: x0, x1 on the shared edge; x2 opposite in face 0 (which holds the
edge as x0 -> x1 in its winding), x3 opposite in face 1.
"""

import functools
from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import types


@functools.cache
def bending_funcs(scalar):
    t = types(scalar)
    vec2, vec3 = t.vec2, t.vec3

    @wp.func
    def face_normals(x0: vec3, x1: vec3, x2: vec3, x3: vec3):
        n0 = wp.normalize(wp.cross(x1 - x0, x2 - x0))
        n1 = wp.normalize(wp.cross(x3 - x0, x1 - x0))
        return n0, n1

    @wp.func
    def dihedral_angle(x0: vec3, x1: vec3, x2: vec3, x3: vec3):
        """Signed dihedral angle [rad]; 0 when flat, positive when the hinge folds towards face 0's normal."""
        n0, n1 = face_normals(x0, x1, x2, x3)
        e = wp.normalize(x0 - x1)
        return wp.atan2(wp.dot(e, wp.cross(n0, n1)), wp.dot(n0, n1))

    @wp.func
    def angle_gradient(x0: vec3, x1: vec3, x2: vec3, x3: vec3):
        """d(theta)/d(x0, x1, x2, x3), with ARCSim's height floor of 1e-3 |e| for thin triangles."""
        n0, n1 = face_normals(x0, x1, x2, x3)
        e = x1 - x0
        ee = wp.dot(e, e)
        t0 = wp.dot(e, x2 - x0) / ee
        t1 = wp.dot(e, x3 - x0) / ee
        floor = scalar(1.0e-3) * wp.sqrt(ee)
        h0 = wp.max(wp.length(x2 - x0 - e * t0), floor)
        h1 = wp.max(wp.length(x3 - x0 - e * t1), floor)
        g2 = n0 / h0
        g3 = n1 / h1
        one = scalar(1.0)
        g0 = (t0 - one) * g2 + (t1 - one) * g3
        g1 = -t0 * g2 - t1 * g3
        return g0, g1, g2, g3

    @wp.func
    def table_sample(bending: wp.array3d(dtype=scalar), material: int, angle: scalar, curvature: scalar):
        """Bilinear, align-corners sample of the 3x5 table at (direction index, curvature index), relu'd."""
        r = wp.min(int(wp.floor(angle)), 1)
        fr = angle - scalar(r)
        c = wp.min(int(wp.floor(curvature)), 3)
        fc = curvature - scalar(c)
        one = scalar(1.0)
        top = (one - fc) * bending[material, r, c] + fc * bending[material, r, c + 1]
        bottom = (one - fc) * bending[material, r + 1, c] + fc * bending[material, r + 1, c + 1]
        return wp.max((one - fr) * top + fr * bottom, scalar(0.0))

    @wp.func
    def stiffness(
        bending: wp.array3d(dtype=scalar), material: int, direction: vec2, theta: scalar, length_over_area: scalar
    ):
        """ke [N*m] before ``thicken``: the smaller of the two faces' samples; curvature sampled every 5 m^-1."""
        curvature = wp.clamp(scalar(0.1) * theta * length_over_area, scalar(0.0), scalar(4.0))
        k0 = table_sample(bending, material, direction[0], curvature)
        k1 = table_sample(bending, material, direction[1], curvature)
        return wp.min(k0, k1)

    return SimpleNamespace(
        face_normals=face_normals,
        dihedral_angle=dihedral_angle,
        angle_gradient=angle_gradient,
        stiffness=stiffness,
    )
