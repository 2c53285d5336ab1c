"""The collision stage of a step: detection, contact geometry and the impact-zone projection with its adjoints."""

from warpcloth.collision.stage import CollisionStage

__all__ = ["CollisionStage"]
