"""The collision stage of a step: detection, contact geometry, the device projection with its adjoint, the fail-safe;
the NumPy reference solver in :mod:`warpcloth.collision.reference`."""

from warpcloth.collision.stage import CollisionReport, CollisionStage

__all__ = ["CollisionReport", "CollisionStage"]
