"""The collision stage's phase timings and error messages."""

from __future__ import annotations

import time
from contextlib import contextmanager

import numpy as np
import warp as wp

from warpcloth.errors import CollisionError
from warpcloth.kernels.geometry import segment_parameters, triangle_barycentric
from warpcloth.model import Model


def rounds_error(step: int, rounds: int, found: int, total: int, nodes: np.ndarray, mode: int, start: wp.array,
                 thickness: float, worlds: list[int] | None = None) -> CollisionError:
    """The round limit's error, naming an unresolved contact and saying so where its primitives started the step
    inside the thickness (``worlds``: those with contacts still found)."""
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
    """Distance between a contact's primitives p (4, 3): vertex p[0] and face p[1:4] (VF_PLANE), else p[0:2], p[2:4]."""
    a, b, c, d = (wp.vec3d(*row) for row in p)
    if mode == 0:  # VF_PLANE
        u, v, w = triangle_barycentric(a, b, c, d)
        return float(wp.length(a - (u * b + v * c + w * d)))
    s, u = segment_parameters(a, b, c, d, wp.float64(1.0e-12))
    return float(wp.length((a + s * (b - a)) - (c + u * (d - c))))


def strain_error(step: int, x_hat: np.ndarray, z: np.ndarray, edge_ends: np.ndarray, edge_rest: np.ndarray,
                 limit: float, particle_world: np.ndarray | None = None) -> CollisionError | None:
    """The projection-strain guard's error naming the edge the projection lengthened most, if by more than ``limit``
    of its rest length, else None; with ``particle_world``, it names every world with such an edge. Why the guard:
    docs/decisions.md, "Projection-strain guard"."""
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


@contextmanager
def timed(totals: dict, phase: str):
    """Add the wall time of the ``with`` block to ``totals[phase]``."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        totals[phase] += time.perf_counter() - t0


def worlds_suffix(model: Model, worlds: list[int]) -> str:
    """", world 2" / ", worlds 0, 3" for an error message; "" in a model of one world."""
    if model.world_count == 1 or not worlds:
        return ""
    return f", world{'s' if len(worlds) > 1 else ''} {', '.join(map(str, worlds))}"
