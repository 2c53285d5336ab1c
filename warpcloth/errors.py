"""Errors a running simulation raises (bad input raises ValueError where it is given)."""


class SimulationError(RuntimeError):
    """The simulation diverged (NaN/inf or a speed beyond ``SolverOptions.max_speed``) or a solve failed.

    ``worlds``: the worlds whose step failed, where known; None: every world."""

    def __init__(self, message: str, worlds: list[int] | None = None):
        super().__init__(message)
        self.worlds = None if worlds is None else [int(w) for w in worlds]


class CollisionError(SimulationError):
    """The collision response could not make a step collision-free, or a contact buffer overflowed."""


class ContactCapacityError(CollisionError):
    """A contact buffer overflowed (raise ``CollisionOptions.contact_capacity``): no fail-safe can work around it."""
