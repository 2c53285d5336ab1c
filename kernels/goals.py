"""Kernels of the goals a control task puts on the cloth's final state (``warpcloth.goals``): the coverage
surrogate.

Every kernel is differentiable; ``add_coverage`` accumulates into ``loss[w]`` (the caller zeroes it). The per-world
sum runs in one thread per world, in triangle order, so the loss is the same bitwise from run to run.
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import per_precision, types


@per_precision
def goal_kernels(scalar):
    """The goal kernels for ``scalar``: a namespace of ``flat_area``, ``world_area`` and ``add_coverage``."""
    vec3 = types(scalar).vec3

    @wp.func
    def flat_weight(d: scalar, tolerance: scalar):
        # 1 within the tolerance, then 1 / (1 + u^2), u = (d - tol) / tol: C1 at the tolerance, with a tail that
        # still pulls a lifted triangle towards the table (docs/decisions.md, "The coverage surrogate")
        if d <= tolerance:
            return scalar(1.0)
        u = (d - tolerance) / tolerance
        return scalar(1.0) / (scalar(1.0) + u * u)

    @wp.kernel
    def flat_area(
        x: wp.array(dtype=vec3),
        tri: wp.array2d(dtype=wp.int32),
        up: vec3,
        height: scalar,
        tolerance: scalar,
        # out:
        area: wp.array(dtype=scalar),
    ):
        """area[t] = w_t A_t: triangle t's area projected on the table's plane, signed by its orientation about
        ``up``, times the product of its vertices' flat weights; one thread per triangle."""
        t = wp.tid()
        a = x[tri[t, 0]]
        b = x[tri[t, 1]]
        c = x[tri[t, 2]]
        w = (flat_weight(wp.abs(wp.dot(a, up) - height), tolerance)
             * flat_weight(wp.abs(wp.dot(b, up) - height), tolerance)
             * flat_weight(wp.abs(wp.dot(c, up) - height), tolerance))
        area[t] = scalar(0.5) * w * wp.dot(wp.cross(b - a, c - a), up)

    @wp.kernel
    def world_area(
        area: wp.array(dtype=scalar),
        tri_first: wp.array(dtype=wp.int32),
        # out:
        total: wp.array(dtype=scalar),
    ):
        """total[w] = sum_t area[t] over world w's triangles tri_first[w] .. tri_first[w + 1]; one thread per world."""
        w = wp.tid()
        s = scalar(0.0)
        for t in range(tri_first[w], tri_first[w + 1]):
            s = s + area[t]
        total[w] = s

    @wp.kernel
    def add_coverage(
        total: wp.array(dtype=scalar),
        inv_rest_area: wp.array(dtype=scalar),
        scale: scalar,
        # out:
        loss: wp.array(dtype=scalar),
    ):
        """loss[w] += scale (1 - |total[w]| / A_w); one thread per world. Apart from ``world_area``: the adjoint of
        |s| must see the loop's final sum, which Warp's reverse pass of a loop-carried value does not give."""
        w = wp.tid()
        wp.atomic_add(loss, w, scale * (scalar(1.0) - wp.abs(total[w]) * inv_rest_area[w]))

    return SimpleNamespace(flat_area=flat_area, world_area=world_area, add_coverage=add_coverage)
