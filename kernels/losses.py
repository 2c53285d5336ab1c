"""Loss and control kernels of the inverse problems (``warpcloth.tasks``): distances to targets, the centre of mass,
and forces on chosen particles.

Every kernel is differentiable (Warp's tape runs their adjoints), so a loss built from them back-propagates into
the trajectory and a force built by ``push_forces`` into its parameters. Sums accumulate into ``loss[0]`` /
``com[0]``: the caller zeroes them and may launch several times into the same array (one launch per compared frame).
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import per_precision, types


@per_precision
def loss_kernels(scalar):
    """The loss kernels for one precision.

    Args:
        scalar: ``wp.float32`` or ``wp.float64``; vectors are ``types(scalar).vec3``.

    Returns:
        A namespace with the kernels ``squared_distance``, ``centre_of_mass``, ``add_component``,
        ``point_squared_distance`` and ``push_forces``.
    """
    vec3 = types(scalar).vec3

    @wp.kernel
    def squared_distance(
        x: wp.array(dtype=vec3),
        target: wp.array(dtype=vec3),
        scale: scalar,
        # out:
        loss: wp.array(dtype=scalar),
    ):
        """loss[0] += scale sum_i |x_i - target_i|^2; one thread per particle."""
        i = wp.tid()
        d = x[i] - target[i]
        wp.atomic_add(loss, 0, scale * wp.dot(d, d))

    @wp.kernel
    def centre_of_mass(
        x: wp.array(dtype=vec3),
        inv_n: scalar,
        # out:
        com: wp.array(dtype=vec3),
    ):
        """com[0] += inv_n sum_i x_i (the vertex mean for inv_n = 1/n); one thread per particle."""
        wp.atomic_add(com, 0, inv_n * x[wp.tid()])

    @wp.kernel
    def add_component(
        com: wp.array(dtype=vec3),
        k: int,
        # out:
        loss: wp.array(dtype=scalar),
    ):
        """loss[0] += com[0][k]; one thread."""
        loss[0] = loss[0] + com[0][k]

    @wp.kernel
    def point_squared_distance(
        p: wp.array(dtype=vec3),
        target: vec3,
        scale: scalar,
        # out:
        loss: wp.array(dtype=scalar),
    ):
        """loss[0] += scale |p[0] - target|^2 (e.g. scale 1/2 on the centre of mass); one thread."""
        d = p[0] - target
        loss[0] = loss[0] + scale * wp.dot(d, d)

    @wp.kernel
    def push_forces(
        push: wp.array(dtype=vec3),
        block: int,
        particles: wp.array(dtype=wp.int32),
        scale: scalar,
        # out:
        force: wp.array(dtype=vec3),
    ):
        """force[particles[j]] = scale push[block m + j], m = len(particles): block ``block`` of the pushes (one per
        particle) as forces on those particles; one thread per particle of ``particles``."""
        j = wp.tid()
        force[particles[j]] = scale * push[block * particles.shape[0] + j]

    return SimpleNamespace(
        squared_distance=squared_distance,
        centre_of_mass=centre_of_mass,
        add_component=add_component,
        point_squared_distance=point_squared_distance,
        push_forces=push_forces,
    )

