"""The NumPy reference solver of the collision projection (float64, host, zone by zone) with its QR and dense KKT
adjoints: the device projection's test oracle and the seed's KKT baseline (``CollisionOptions.solver="numpy"``).
The problem and the method: :mod:`warpcloth.collision.reference.qp`."""

from warpcloth.collision.reference.adjoint import backward, mass_gradient, mass_gradient_of, push_onto_contacts
from warpcloth.collision.reference.qp import ProjectionError, project
from warpcloth.collision.reference.zones import ProjectionResult, Zone

__all__ = ["ProjectionError", "ProjectionResult", "Zone", "backward", "mass_gradient", "mass_gradient_of", "project",
           "push_onto_contacts"]
