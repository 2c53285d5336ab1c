"""The collision stage's error messages: what went wrong, named by step, contact, particle or edge (host code,
run only on the failure path)."""

from __future__ import annotations

import numpy as np
import warp as wp

from warpcloth.errors import CollisionError
from warpcloth.kernels.geometry import segment_parameters, triangle_barycentric


def rounds_error(step: int, rounds: int, found: int, total: int, nodes: np.ndarray, mode: int, start: wp.array,
                 thickness: float, worlds: list[int] | None = None) -> CollisionError:
    """The round limit's error, naming an unresolved contact (``worlds``: those with contacts still found); and,
    where that contact's primitives started the step inside the thickness (a cloth laid on an obstacle or on
    itself), saying so: from there the projection can have no consistent side to push them to."""
    gap = round(start_gap(start.numpy().astype(np.float64)[nodes], mode), 12)  # below a picometre: rounding
    inside = ""
    if gap < thickness:
        inside = (f"; these nodes started the step {gap:.3g} m apart, inside the collision thickness {thickness:g} m, "
                  "where the contact has no consistent side: start the cloth at least the thickness away from "
                  "obstacles and from itself")
    return CollisionError(
        f"step {step}: the collision response did not converge in {rounds} rounds: {found} new contacts (of "
        f"{total}) still found, e.g. nodes {nodes.tolist()}{inside}; raise CollisionOptions.rounds, lower dt, or "
        "check for cloth trapped between obstacles", worlds=worlds)


def start_gap(p: np.ndarray, mode: int) -> float:
    """Distance between a contact's primitives (positions p of its 4 nodes): vertex p[0] and triangle p[1:4]
    (mode VF_PLANE), or segments p[0:2] and p[2:4] (the edge-edge modes); the detection's own closest-point
    functions, evaluated on the host."""
    a, b, c, d = (wp.vec3d(*row) for row in p)
    if mode == 0:  # VF_PLANE
        u, v, w = triangle_barycentric(a, b, c, d)
        return float(wp.length(a - (u * b + v * c + w * d)))
    s, u = segment_parameters(a, b, c, d, wp.float64(1.0e-12))
    return float(wp.length((a + s * (b - a)) - (c + u * (d - c))))


def strain_error(step: int, x_hat: np.ndarray, z: np.ndarray, edge_ends: np.ndarray, edge_rest: np.ndarray,
                 limit: float, particle_world: np.ndarray | None = None) -> CollisionError | None:
    """The projection-strain guard's error naming the edge the projection lengthened most, if by more than ``limit``
    of its rest length (None otherwise); with ``particle_world``, it names every world with such an edge.

    The projection moves particles onto the contacts' linearised constraints; when a step carries the cloth further
    than an element past an obstacle's curvature (a coarse cloth wrapping a small sphere at speed), neighbours land
    on different sides, the edges between them are stretched by the projection, and the next implicit step turns
    that stretch into motion that the next projection stretches again: energy grows step after step (a 20 m/s impact
    on a 0.25 m sphere at dt 0.01: 66 J to 2600 J in 12 steps). Well-resolved contact stays far below the limit (0.23
    at most for that impact at dt 1 ms and a drape at dt 0.01).
    """
    a, b = edge_ends[:, 0], edge_ends[:, 1]
    # lengthening only: stopping a falling strip's lowest vertices shortens edges, which buckling absorbs
    strain = (np.linalg.norm(z[a] - z[b], axis=1) - np.linalg.norm(x_hat[a] - x_hat[b], axis=1)) / edge_rest
    j = int(np.argmax(strain))
    if strain[j] <= limit:
        return None
    worlds = None if particle_world is None else np.unique(particle_world[a[strain > limit]]).tolist()
    return CollisionError(
        f"step {step}: the collision response stretched the edge between particles {int(a[j])} and {int(b[j])} by "
        f"{strain[j]:.3g} of its rest length in one step (CollisionOptions.max_projection_strain {limit:g}): the "
        "cloth moves too far per step for the contacts' linearisation, which then pumps energy into it step after "
        "step; lower dt", worlds=worlds)
