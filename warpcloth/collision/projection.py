"""Collision response as a quadratic program over impact zones, and its adjoint (SPEC.md §3 and §4.2): the one
place to import the projection from.

Pure NumPy (float64) on the host; one call of :func:`project` per collision round, one call of :func:`backward` per
backward pass through that round. Each zone solves min_z ½ (z − x̂)ᵀ W (z − x̂) s.t. G z + h ≤ 0 (one row per
contact: δ − Σ_a w_ja n_j·p(node_ja) ≤ 0). The code lives in

* :mod:`warpcloth.collision.qp`: :func:`project`, :class:`ProjectionError`; the
  formulation and the solver in its docstring;
* :mod:`warpcloth.collision.zones`: impact zones (connected components), :class:`Zone`, :class:`ProjectionResult`,
  the dual matrix and the contact colouring;
* :mod:`warpcloth.collision.dual`: the dual active-set solver of one zone and its Gauss–Seidel warm start;
* :mod:`warpcloth.collision.adjoint`: :func:`backward`, by the QR formula or the dense KKT system, and
  :func:`mass_gradient` (the masses in W);
* :mod:`warpcloth.collision.linalg`: triangular and semidefinite solves, the Gram matrix's Cholesky factor;
* :mod:`warpcloth.collision.checks`: argument checks.
"""

from warpcloth.collision.adjoint import backward, mass_gradient, mass_gradient_of, push_onto_contacts
from warpcloth.collision.qp import ProjectionError, project
from warpcloth.collision.zones import ProjectionResult, Zone

__all__ = ["ProjectionError", "ProjectionResult", "Zone", "backward", "mass_gradient", "mass_gradient_of", "project",
           "push_onto_contacts"]
