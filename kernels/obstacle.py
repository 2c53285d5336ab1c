"""Rigid obstacles: vertices from their body frame to the world.

An obstacle vertex ``u`` (body frame) of obstacle ``b`` sits in the world at

    x = motion_b(t) * (base_b * u)

where ``base_b`` is the obstacle's placement (``Control.obstacle_transform``, differentiable) and ``motion_b(t)`` the
scripted keyframed motion evaluated on the host at time t (identity for a static obstacle; no gradient).
Warp's autodiff carries gradients from ``x`` to ``base_b`` (position and all four quaternion components, the
quaternion taken as given, not renormalised) and to ``u``.
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import per_precision, types


@per_precision
def obstacle_kernels(scalar):
    t = types(scalar)
    vec3, transform = t.vec3, t.transform

    @wp.kernel
    def world_points(
        # Model:
        vertex_local: wp.array(dtype=vec3),
        vertex_body: wp.array(dtype=wp.int32),
        # Control:
        base_transform: wp.array(dtype=transform),
        # Scripted motion at the current time (host-evaluated, no gradient wanted):
        motion_transform: wp.array(dtype=transform),
        # out:
        world: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        b = vertex_body[i]
        world[i] = wp.transform_point(motion_transform[b], wp.transform_point(base_transform[b], vertex_local[i]))

    return SimpleNamespace(world_points=world_points)

