"""Options of the step: :class:`SolverOptions` and its collision stage, :class:`CollisionOptions`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field


def _check_positive(owner: str, obj, names) -> None:
    for name in names:
        val = getattr(obj, name)
        if val is None:
            continue
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val) or val <= 0.0:
            raise ValueError(f"{owner}.{name} must be finite and > 0, got {val!r}")


def _check_int(owner: str, obj, lows: dict[str, int]) -> None:
    for name, low in lows.items():
        val = getattr(obj, name)
        if isinstance(val, bool) or not isinstance(val, int) or val < low:
            raise ValueError(f"{owner}.{name} must be an integer >= {low}, got {val!r}")


def _check_choice(owner: str, obj, choices: dict[str, tuple]) -> None:
    for name, allowed in choices.items():
        if getattr(obj, name) not in allowed:
            raise ValueError(f"{owner}.{name} must be one of {allowed}, got {getattr(obj, name)!r}")


@dataclass(frozen=True)
class CollisionOptions:
    """Options of the collision stage (detect -> project rounds)."""

    rounds: int = 20
    """Most detect -> project rounds per step, then the rigid-impact-zone fail-safe; 0: the fail-safe alone."""
    contact_capacity: int = 0
    """Most contacts per detection and proximity pairs per step (0: 16 and 8 per cloth particle and obstacle
    vertex); more raises CollisionError with the capacity needed."""
    adjoint: str = "qr"
    """Adjoint of the ``solver="numpy"`` projection: ``"qr"`` (of the active constraints) or ``"kkt"`` (dense)."""
    max_projection_strain: float = 0.5
    """Most an edge may lengthen in one step's projection [rest lengths]; beyond it the step goes to the fail-safe.
    Why: docs/decisions.md, "Projection-strain guard"."""
    qp_tol: float = 1.0e-10
    """Tolerance [m] of the projection's KKT conditions (constraint violation and complementarity)."""
    solver: str = "device"
    """Projection solver: ``"device"`` (Warp kernels, all contacts at once) or ``"numpy"`` (per impact zone on the
    host; the tests' oracle)."""
    bvh: str = "refit"
    """BVH update per detection: ``"refit"`` (first topology, boxes moved) or ``"rebuild"``; the same contacts.
    Why: docs/decisions.md, "BVH refit by default"."""

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        """Raise ValueError naming the first option out of range."""
        _check_positive("CollisionOptions", self, ("max_projection_strain", "qp_tol"))
        _check_int("CollisionOptions", self, {"rounds": 0, "contact_capacity": 0})
        _check_choice("CollisionOptions", self, {"adjoint": ("qr", "kkt"), "solver": ("numpy", "device"),
                                                 "bvh": ("rebuild", "refit")})
        if self.adjoint == "kkt" and self.solver != "numpy":
            raise ValueError("CollisionOptions.adjoint 'kkt' is the NumPy solver's; set solver='numpy' with it "
                             f"(solver is {self.solver!r})")


@dataclass(frozen=True)
class SolverOptions:
    """Options of the linear solve, the divergence guard and (``collision``) the collision stage."""

    cg_tol: float = 1.0e-5
    """Relative residual tolerance, |b - A dv| <= cg_tol |b|, of the forward CG solve (and the adjoint's)."""
    adjoint_cg_tol: float | None = None
    """Relative residual tolerance of the backward pass's adjoint CG solve; None: ``cg_tol``."""
    cg_atol: float = 1.0e-12
    """Absolute residual floor [N*s]."""
    cg_max_iters: int = 1000
    """Iteration cap of each CG solve."""
    preconditioner: str = "auto"
    """``"multigrid"`` (a V-cycle of a mesh aggregation hierarchy), ``"block_ssor"`` (sequential backend only),
    ``"block_jacobi"``, ``"jacobi"`` or ``"auto"``: multigrid with the sequential backend and for one world with warp,
    else block Jacobi; block SSOR where a world has no free particle. Block SSOR can be faster at small dt.
    Why: docs/decisions.md, "Automatic preconditioner"."""
    ssor_omega: float = 1.5
    """Relaxation factor of the block SSOR preconditioner, in (0, 2)."""
    cg_backend: str = "auto"
    """``"sequential"`` (a world's CG on one thread, one launch), ``"tiled"`` (on one thread block, one launch),
    ``"warp"`` (``warp.optim.linear.cg``) or ``"auto"``: sequential on the CPU; on CUDA tiled up to
    ``linear.TILED_MAX_PARTICLES`` particles a world, else warp (but tiled for several such worlds with the
    multigrid). Why: docs/decisions.md, "Tiled CG up to 1024 particles"."""
    cg_block_dim: int = 0
    """Threads per world of the tiled backend, a power of two up to 256; 0: chosen from the worlds."""
    on_cg_failure: str = "warn"
    """What a solve that misses its tolerance does: ``"warn"`` (with the residual) or ``"raise"``."""
    warm_start: bool = True
    """Start each CG solve from the previous solution (the State's ``particle_dv``, the later step's adjoint);
    results then differ only within the tolerance."""
    max_speed: float = 1.0e3
    """A particle faster than this [m/s], or a NaN/inf, raises SimulationError naming the step."""
    integrator: str = "euler"
    """``"euler"`` (ARCSim's linearised backward Euler) or ``"bdf2"`` (Choi and Ko 2002: a backward Euler step of
    2/3 dt from (4 x_n - x_{n-1}) / 3; wind at 2 x_n - x_{n-1}, detection from x_n; a trajectory's first step is
    Euler). Why: docs/decisions.md, "BDF2 without Newton corrections"."""
    sync_every: int = 1
    """Steps between reads of the device's failure record, which raise or warn naming step, world and particle (a
    read waits for the device; graph capture never reads): 1 every step, 0 only at ``Simulator.check`` and at the
    end of rollouts and replays. Collision scenes also check after each integration; a contact replay checks
    whether a step left its contact plan this often (0: once, after its forward pass)."""
    collision: CollisionOptions = field(default_factory=CollisionOptions)
    """Collision stage options (scenes with collisions only)."""

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        """Raise ValueError naming the first option out of range."""
        _check_positive("SolverOptions", self, ("cg_tol", "adjoint_cg_tol", "cg_atol", "max_speed"))
        if not 0.0 < self.ssor_omega < 2.0:
            raise ValueError(f"SolverOptions.ssor_omega must be in (0, 2), got {self.ssor_omega}")
        _check_int("SolverOptions", self, {"cg_max_iters": 1, "sync_every": 0, "cg_block_dim": 0})
        if self.cg_block_dim & (self.cg_block_dim - 1) or self.cg_block_dim > 256:
            raise ValueError(f"SolverOptions.cg_block_dim must be 0 or a power of two up to 256, got "
                             f"{self.cg_block_dim!r}")
        if not isinstance(self.warm_start, bool):
            raise ValueError(f"SolverOptions.warm_start must be True or False, got {self.warm_start!r}")
        _check_choice("SolverOptions", self, {
            "preconditioner": ("auto", "block_jacobi", "jacobi", "block_ssor", "multigrid"),
            "cg_backend": ("auto", "sequential", "tiled", "warp"),
            "on_cg_failure": ("warn", "raise"),
            "integrator": ("euler", "bdf2"),
        })
        if not isinstance(self.collision, CollisionOptions):
            raise ValueError(f"SolverOptions.collision must be a CollisionOptions, got {self.collision!r}")
