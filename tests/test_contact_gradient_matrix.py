"""Every gradient path through contact against central differences, over scenes x contact models x projection
solvers (issue 22): the tape's derivative of a random linear loss of the final state along a random direction of
each parameter a user can optimise, wherever central differences at two consecutive step sizes agree within 1 %:
the tape within 1 % of them.

Where contact is not smooth (an active set or a stick/slide state that changes between the two sides of a
difference) the differences do not converge and nothing is asserted; each case asserts that most of its
parameters converged, so a scene that drifted into such a state fails instead of testing nothing.
"""

import math

import numpy as np
import pytest
import warp as wp

import warpcloth as wc

G = 9.8
STEPS_H = (1e-3, 1e-4, 1e-5)  # relative central-difference steps
AGREE = 0.01
FLOOR = 1e-6
"""A derivative below this times the case's largest one is zero for the test (both ways: converged, and met)."""


def _rotation_y(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def _patch(b, res, size, origin, R, *, vel=(0.0, 0.0, 0.0), material="gray-interlock", seed=7):
    # sheared and bent a little: off the stretching lookup's kink at zero shear and the bending lookup's at zero
    # curvature (tests/test_contact.py), where central differences average two one-sided derivatives
    mesh = wc.grid_mesh(res, res, size, size)
    jitter = np.random.default_rng(seed).uniform(-1.0, 1.0, mesh.positions.shape) * [5e-4, 5e-4, 1e-4]
    mesh.positions = (mesh.positions + jitter + origin) @ R.T
    mesh.velocities = np.tile(np.asarray(vel, dtype=np.float64) @ R.T, (len(mesh.positions), 1))
    b.add_cloth_mesh(mesh, material=wc.preset(material, thicken=2))


def _gap(contact):
    # inside the repulsion layer (where a gray-interlock patch rests), or just above the collision thickness
    return 0.0008 if contact in PROJECTION_ONLY else 0.00486


def sliding(contact):
    """A patch sliding down a 30-degree plane."""
    R = _rotation_y(30.0)
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_obstacle_plane((4.0, 4.0), rot=R)
    _patch(b, 2, 0.1, [0.45, 1.15, _gap(contact)], R, vel=(-0.05, 0.02, 0.0))
    return b, 6


def resting(contact):
    """A patch at rest on a 10-degree plane (below the friction angle: it sticks)."""
    R = _rotation_y(10.0)
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_obstacle_plane((4.0, 4.0), rot=R)
    _patch(b, 2, 0.1, [0.45, 1.15, _gap(contact)], R)
    return b, 6


def edge_landing(contact):
    """A patch falling onto a box's top edge, across it: edge-edge contacts with the box's edge."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_obstacle_box((0.2, 0.2, 0.2))
    _patch(b, 2, 0.1, [0.15, -0.05, 0.2 + _gap(contact) + 0.002], np.eye(3), vel=(0.0, 0.0, -0.3))
    return b, 6


def cloth_on_cloth(contact):
    """A free patch sliding on a free sheet that lies on a plane: cloth-cloth pairs with both sides free."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -G))
    b.add_obstacle_plane((2.0, 2.0))
    gap = _gap(contact)
    _patch(b, 3, 0.3, [-0.15, -0.15, gap], np.eye(3), seed=3)
    _patch(b, 1, 0.06, [-0.0313, -0.0287, 2.0 * gap], np.eye(3), vel=(0.04, 0.01, 0.0), seed=5)
    return b, 4


CONTACT = {
    "repulsion and friction": dict(friction=0.4, obstacle_friction=0.4),
    "repulsion, frictionless": dict(friction=0.0, obstacle_friction=0.0),
    "projection only": dict(repulsion_stiffness=0.0),
    "fail-safe only": dict(repulsion_stiffness=0.0),
}
PROJECTION_ONLY = ("projection only", "fail-safe only")
"""Contact models without repulsion. "fail-safe only" refuses every projection (a strain limit of 1e-9 that any
projection passes), so the collision stage's fail-safe, rigid impact zones, resolves every step with contacts."""


def build(scene, contact, solver, device):
    b, steps = scene(contact)
    b.set_collision(self_collision=scene is cloth_on_cloth, **CONTACT[contact])
    model = b.finalize(device, dtype=wp.float64, requires_grad=True)
    rounds = 0 if contact == "fail-safe only" else wc.CollisionOptions().rounds
    options = wc.SolverOptions(cg_tol=1e-12, cg_atol=1e-30, cg_max_iters=2000,
                               collision=wc.CollisionOptions(solver=solver, qp_tol=1e-12, rounds=rounds))
    return model, wc.Simulator(model, 0.005, options=options), steps


@wp.kernel
def _linear_loss(x: wp.array(dtype=wp.vec3d), v: wp.array(dtype=wp.vec3d), cx: wp.array(dtype=wp.vec3d),
                 cv: wp.array(dtype=wp.vec3d), loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(x[i], cx[i]) + wp.dot(v[i], cv[i]))


def parameters(model, control, state, contact):
    """(name, array, direction): every differentiable input of a contact scene, each along a random direction of
    its own scale (relative for materials and coefficients)."""
    rng = np.random.default_rng(11)
    n = model.particle_count

    def rel(a):
        v = a.numpy()
        return v * rng.choice([-1.0, 1.0], size=v.shape)

    out = [("x0", state.particle_x, 1e-2 * rng.standard_normal((n, 3))),
           ("v0", state.particle_v, 0.1 * rng.standard_normal((n, 3))),
           ("density", model.material_density, rel(model.material_density)),
           ("stretching", model.material_stretching, rel(model.material_stretching)),
           ("bending", model.material_bending, rel(model.material_bending)),
           ("force", control.particle_force, (model.particle_mass()[:, None] * G) * rng.standard_normal((n, 3))),
           ("obstacle", control.obstacle_transform,
            np.concatenate([1e-2 * rng.standard_normal((model.obstacle_count, 3)),
                            1e-2 * rng.standard_normal((model.obstacle_count, 3)),
                            np.zeros((model.obstacle_count, 1))], axis=1))]
    if contact not in PROJECTION_ONLY:
        # at a stiffness or coefficient of 0 the term is absent and a derivative one-sided: not perturbed there
        out.append(("stiffness", model.contact_repulsion_stiffness, rel(model.contact_repulsion_stiffness)))
        if contact == "repulsion and friction":
            out.append(("friction", model.contact_friction, rel(model.contact_friction)))
    return out


def check(scene, contact, solver, device):
    model, sim, steps = build(scene, contact, solver, device)
    rng = np.random.default_rng(4)
    n = model.particle_count
    cx = wp.array(rng.standard_normal((n, 3)), dtype=wp.vec3d, device=model.device)
    cv = wp.array(1e-2 * rng.standard_normal((n, 3)), dtype=wp.vec3d, device=model.device)
    state, control = model.state(), model.control(particle_force=True)

    def loss(tape=None):
        out = wp.zeros(1, dtype=wp.float64, requires_grad=True, device=model.device)
        start = wc.State(wp.clone(state.particle_x), wp.clone(state.particle_v)) if tape is None else state
        if tape is not None:
            with tape:
                final = wc.rollout(sim, start, control, steps=steps)[-1]
                wp.launch(_linear_loss, n, inputs=[final.particle_x, final.particle_v, cx, cv], outputs=[out],
                          device=model.device)
        else:
            final = wc.rollout(sim, start, control, steps=steps)[-1]
            wp.launch(_linear_loss, n, inputs=[final.particle_x, final.particle_v, cx, cv], outputs=[out],
                      device=model.device)
        return out

    tape = wp.Tape()
    out = loss(tape)
    assert sim.proximity is None or sim.proximity.last_count > 0 or sim.collision.last.contacts > 0
    assert (sim.collision.fail_safe_steps > 0) == (contact == "fail-safe only")
    tape.backward(out)
    params = parameters(model, control, state, contact)
    grads = {name: array.grad.numpy().copy() for name, array, _ in params}
    tape.zero()
    results = {}
    for name, array, direction in params:
        tape_value = float(np.sum(grads[name] * direction))
        base = array.numpy().copy()
        fds = []
        for h in STEPS_H:
            values = []
            for sign in (1.0, -1.0):
                array.assign(base + sign * h * direction)
                values.append(float(loss().numpy()[0]))
            array.assign(base)
            fds.append((values[0] - values[1]) / (2.0 * h))
        results[name] = (tape_value, fds)
    return results


def converged_reference(fds, floor):
    """The finer of the first two consecutive differences that agree within AGREE (or are both below ``floor``),
    else None."""
    for a, b in zip(fds[:-1], fds[1:]):
        if abs(a - b) <= AGREE * max(abs(a), abs(b)) or max(abs(a), abs(b)) < floor:
            return b
    return None


SCENES = [sliding, resting, edge_landing, cloth_on_cloth]


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["device", "numpy"])
@pytest.mark.parametrize("contact", list(CONTACT))
@pytest.mark.parametrize("scene", SCENES, ids=lambda s: s.__name__)
def test_tape_matches_converged_central_differences(scene, contact, solver, device):
    results = check(scene, contact, solver, device)
    floor = FLOOR * max(abs(fd) for _, fds in results.values() for fd in fds)
    checked, failures = [], []
    for name, (tape_value, fds) in results.items():
        ref = converged_reference(fds, floor)
        if ref is None:
            continue
        checked.append(name)
        if abs(tape_value - ref) > AGREE * abs(ref) + floor:
            failures.append(f"{name}: tape {tape_value:.6e}, central differences {fds}")
    assert not failures, "; ".join(failures)
    assert len(checked) >= len(results) - 2, f"only {checked} of {list(results)} converged: {results}"
