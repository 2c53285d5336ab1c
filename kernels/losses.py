"""Loss and control kernels of the inverse problems (``warpcloth.tasks``): distances to targets, the centre of mass,
and forces on chosen particles.

Every kernel is differentiable (Warp's tape runs their adjoints), so a loss built from them back-propagates into
the trajectory and a force built by ``push_forces`` into its parameters. Sums accumulate into ``loss[0]`` /
``com[0]``, or per world into ``loss[w]`` / ``com[w]``: the caller zeroes them and may launch several times into the
same array (one launch per compared frame).
"""

from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import per_precision, types


@per_precision
def loss_kernels(scalar):
    """The loss kernels for ``scalar`` (``wp.float32`` or ``wp.float64``): a namespace of ``squared_distance``,
    ``world_squared_distance``, ``centre_of_mass``, ``add_component``, ``point_squared_distance``, ``add_sum`` and
    ``push_forces`` (from ``world_`` on, one entry per world), and ``store_frame``."""
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
    def world_squared_distance(
        x: wp.array(dtype=vec3),
        target: wp.array(dtype=vec3),
        particle_world: wp.array(dtype=wp.int32),
        first: wp.array(dtype=wp.int32),
        scale: scalar,
        # out:
        loss: wp.array(dtype=scalar),
    ):
        """loss[w] += scale sum_i |x_i - target_(i - first[w])|^2 over world w's particles (one target for every
        world, of one world's length); one thread per particle."""
        i = wp.tid()
        w = particle_world[i]
        d = x[i] - target[i - first[w]]
        wp.atomic_add(loss, w, scale * wp.dot(d, d))

    @wp.kernel
    def centre_of_mass(
        x: wp.array(dtype=vec3),
        particle_world: wp.array(dtype=wp.int32),
        weight: wp.array(dtype=scalar),
        # out:
        com: wp.array(dtype=vec3),
    ):
        """com[w] += sum_i weight_i x_i over world w's particles (the centre of mass for weight_i = m_i / M_w, the
        world's mass M_w); one thread per particle."""
        i = wp.tid()
        wp.atomic_add(com, particle_world[i], weight[i] * x[i])

    @wp.kernel
    def add_component(
        com: wp.array(dtype=vec3),
        k: wp.array(dtype=wp.int32),
        # out:
        loss: wp.array(dtype=scalar),
    ):
        """loss[w] += com[w][k[w]]; one thread per world."""
        w = wp.tid()
        loss[w] = loss[w] + com[w][k[w]]

    @wp.kernel
    def point_squared_distance(
        p: wp.array(dtype=vec3),
        target: vec3,
        scale: scalar,
        # out:
        loss: wp.array(dtype=scalar),
    ):
        """loss[w] += scale |p[w] - target|^2 (e.g. scale 1/2 on each world's centre of mass); one thread per
        world."""
        w = wp.tid()
        d = p[w] - target
        loss[w] = loss[w] + scale * wp.dot(d, d)

    @wp.kernel
    def add_sum(
        values: wp.array(dtype=scalar),
        # out:
        total: wp.array(dtype=scalar),
    ):
        """total[0] += sum_w values[w], in order; one thread (the tape's loss of independent worlds' losses)."""
        s = total[0]
        for w in range(values.shape[0]):
            s = s + values[w]
        total[0] = s

    @wp.kernel
    def push_forces(
        push: wp.array(dtype=vec3),
        block: int,
        blocks: int,
        particles: wp.array(dtype=wp.int32),
        first: wp.array(dtype=wp.int32),
        scale: scalar,
        bound: scalar,
        # out:
        force: wp.array(dtype=vec3),
    ):
        """force[first[w] + particles[j]] = scale a(push[(w blocks + block) m + j]), m = len(particles): block
        ``block`` of world w's ``blocks`` blocks of pushes (one per particle) as forces on those particles of world
        w; one thread per world and particle of ``particles``. a(p) = p where ``bound`` <= 0, else
        ``bound tanh(|p| / bound) p / |p|``: shorter than ``bound``, and p itself to first order."""
        t = wp.tid()
        m = particles.shape[0]
        w = t / m
        j = t - w * m
        p = push[(w * blocks + block) * m + j]
        if bound > scalar(0.0):
            r = wp.length(p)
            if r > bound * scalar(1.0e-6):  # below, tanh(x) / x = 1 to 1e-13
                p = p * (bound * wp.tanh(r / bound) / r)
        force[first[w] + particles[j]] = scale * p

    @wp.kernel
    def store_frame(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        frame: int,
        # out:
        xs: wp.array2d(dtype=vec3),
        vs: wp.array2d(dtype=vec3),
    ):
        """xs[frame] = x, vs[frame] = v: one state into a trajectory's rows (the torch bridge's replayed rollouts
        hand their trajectory over, and take its gradient back, through it); one thread per particle."""
        i = wp.tid()
        xs[frame, i] = x[i]
        vs[frame, i] = v[i]

    return SimpleNamespace(
        squared_distance=squared_distance,
        world_squared_distance=world_squared_distance,
        add_sum=add_sum,
        centre_of_mass=centre_of_mass,
        add_component=add_component,
        point_squared_distance=point_squared_distance,
        push_forces=push_forces,
        store_frame=store_frame,
    )

