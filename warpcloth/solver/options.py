"""Options of the step: the linear solve and divergence guard (SolverOptions), the collision stage
(CollisionOptions, one field of SolverOptions)."""

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
    """Options of the collision stage (detect -> project rounds, warpcloth/collision)."""

    rounds: int = 20
    """Most detect -> project rounds per step; a step still finding new contacts after them goes to the fail-safe
    (rigid impact zones, warpcloth/collision/failsafe.py). 0: no projection at all, every step with contacts is
    resolved by rigid impact zones alone (Provot 1997)."""
    contact_capacity: int = 0
    """Contacts one detection may find, and proximity pairs one step may have (0: 16 contacts and 8 pairs per cloth
    particle and obstacle vertex); more raises CollisionError with the capacity needed."""
    adjoint: str = "qr"
    """Adjoint of the NumPy solver's projection (``solver="numpy"``): ``"qr"`` (QR of the active constraints,
    SPEC §4.2) or ``"kkt"`` (the dense KKT system of the whole zone: the seed's baseline, for comparison)."""
    max_projection_strain: float = 0.5
    """Most an edge may lengthen in the collision projection of one step, in rest lengths; beyond it the step goes to
    the fail-safe (rigid impact zones): contact resolved that coarsely pumps energy into the cloth
    (warpcloth/collision/diagnostics.py, strain_error)."""
    qp_tol: float = 1.0e-10
    """Tolerance [m] of the projection's KKT conditions (constraint violation and complementarity)."""
    solver: str = "device"
    """The projection's solver: ``"device"`` (Warp kernels over all contacts at once, no zones: MPRGP on the dual and
    the adjoint by CG on the active set; contacts and gradients stay on the device) or ``"numpy"`` (per impact zone
    on the host: dual Gauss-Seidel, then an active set; its adjoint by the QR formula or, ``adjoint="kkt"``, the dense
    KKT system: the seed's method and the tests' oracle)."""
    bvh: str = "refit"
    """How each detection brings its BVHs to the current positions: ``"refit"`` (the topology of the Simulator's
    first detection, its boxes moved) or ``"rebuild"`` (a new topology from the current boxes, in place). The results
    are the same, bitwise on the CPU: a BVH's topology orders a query's visits only, and the contacts and proximity
    pairs are sorted by key afterwards (warpcloth/collision/detection.py RowSort). Refitting was faster in every
    scene measured (benchmarks/bvh_update.py, uncaptured, medians of three runs: 3.85 against 5.66 ms a step of the
    24x24 cloth draped on a sphere, 18.3 against 23.9 at 64x64, 7.8 against 10.5 with self-collision, 0.53 against
    0.57 ms for the throw), a sheet dropped upright that buckles and piles onto itself included (8.2 against 9.6
    ms), far from the flat shape its BVHs were built on. ``"rebuild"`` stays for a cloth whose refitted boxes grow
    until queries slow down more than a rebuild costs; no scene here has shown one."""

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
    """Relative residual tolerance |b - A dv| <= cg_tol |b| of the forward CG solve (and of the adjoint one, unless
    ``adjoint_cg_tol`` is given)."""
    adjoint_cg_tol: float | None = None
    """Relative residual tolerance of the adjoint CG solve of the backward pass; None: the same as ``cg_tol``.
    The gradient's error follows it as the trajectory's follows cg_tol (benchmarks/tradeoff.py)."""
    cg_atol: float = 1.0e-12
    """Absolute residual floor (in the units of b, N*s)."""
    cg_max_iters: int = 1000
    """Iteration cap of each CG solve."""
    preconditioner: str = "auto"
    """``"multigrid"`` (one symmetric V-cycle of an aggregation hierarchy built from the mesh: block Gauss-Seidel
    smoothing with the sequential backend, two damped block-Jacobi sweeps per level in its parallel form with the
    warp backend (34 CG iterations against the sequential form's 28 on a cold 64x64 solve, block Jacobi's 324:
    multigrid.py's ParallelMultigrid) and, the same arithmetic, on each world's thread block with the tiled backend
    (43 iterations to 1e-6 against block Jacobi's 375 at 64x64, 24 against 88 at 16x16; on the CPU, where a block
    is one thread, 1.7x faster than tiled block Jacobi at 64x64 and 0.74x at 16x16, benchmarks/cg_solvers.py; not
    yet timed on a GPU, so ``"auto"`` keeps block Jacobi there), a dense solve on the coarsest level; 26 CG
    iterations per step against
    block SSOR's 84 on the 64x64 hanging sheet at dt 0.02, 1.8x faster per step, benchmarks/step_time.py),
    ``"block_ssor"`` (symmetric block Gauss-Seidel sweeps; sequential backend only: ~3x fewer iterations than block
    Jacobi at 64x64, benchmarks/cg_solvers.py), ``"block_jacobi"`` (inverse 3x3 diagonal blocks), ``"jacobi"``
    (inverse scalar diagonal) or ``"auto"`` (multigrid with the sequential backend, a hierarchy per world, and with
    the warp backend for a model of one world; block Jacobi with the tiled backend and for several worlds with the
    warp backend; block SSOR where a world has no free particle).
    Where the mass dominates the system (small dt), block SSOR is the faster one: measured on warm solves of the
    hanging sheet in the wind and of benchmarks/peers.py's pinned sheet, 16x16 to 128x128, dt 1/50 to 1/4000, the
    multigrid won every system that block SSOR needed more than 23 iterations for (by up to 2.1x: 128x128 at
    dt 1/50, 371 against 174 ms) and lost every one it solved in at most 17 (by up to 1.5x: 64x64 at dt 1/4000,
    2.0 against 3.0 ms, the multigrid's setup outweighing block SSOR's 5 iterations). With k_s and k_m the two
    iteration counts, the multigrid was the faster where k_s > 1.6 k_m + 1.75 (39 of the 40 systems; the 40th a
    0.4 % tie). Two ways of choosing automatically were tried and dropped: a per-system stiffness measure
    (off-diagonal against diagonal blocks) does not track the crossover across resolutions (it called the 128x128
    sheet at dt 1/50, where the multigrid is 1.9x faster, light); and applying the iteration rule once, to the
    model's first step, sees a cloth at rest without tension, lighter than it soon is: it took block SSOR for the
    16x16 and 32x32 hanging sheets at dt 0.02, whose steps the multigrid makes 1.15x and 1.35x faster, and for
    the 64x64 pinned sheet at dt 1/100, whose solves it makes 1.6x faster."""
    ssor_omega: float = 1.5
    """Relaxation factor of the block SSOR preconditioner, in (0, 2)."""
    cg_backend: str = "auto"
    """``"sequential"`` (the whole CG of a world on one thread, in one launch: fastest on the CPU, and the only
    one with the block SSOR preconditioner), ``"tiled"`` (the whole CG of a world on one thread
    block, in one launch, with tile reductions: the GPU's form of the sequential one), ``"warp"``
    (``warp.optim.linear.cg``, a launch per operation, convergence tested on the device on CUDA), or ``"auto"``
    (sequential on the CPU; on CUDA tiled for worlds of up to ``linear.TILED_MAX_PARTICLES`` particles, warp for
    larger ones, but tiled for several larger worlds with the multigrid, which warp's CG takes for one world
    only). See benchmarks/cg_solvers.py and benchmarks/graph_step.py."""
    cg_block_dim: int = 0
    """Threads per world of the tiled backend (a power of two up to 256: the kernel's registers allow no more; 0:
    chosen from the worlds' sizes and count)."""
    on_cg_failure: str = "warn"
    """What a solve that misses its tolerance does: ``"warn"`` (with the residual) or ``"raise"``."""
    warm_start: bool = True
    """Start each CG solve from the previous solution (forward: the velocity change the input State carries;
    adjoint: the later step's adjoint): fewer iterations, and results that differ only within the tolerance.
    Extrapolating from the last two steps' velocity changes (2 dv_n - dv_{n-1}) was measured and rejected: 100.6 CG
    iterations per step against 99.2 at 64x64, 34.2 against 34.5 at 16x16 (hanging sheet in the wind, dt 0.02,
    steps 10-40; cold starts: 100.8 and 38.0)."""
    max_speed: float = 1.0e3
    """A particle faster than this [m/s], or a NaN/inf, raises SimulationError naming the step."""
    integrator: str = "euler"
    """``"euler"``: ARCSim's linearised backward Euler (first order; reproduces the seed). ``"bdf2"``: the
    second-order backward differentiation formula (Choi and Ko 2002), written as a backward Euler step of 2/3 dt
    from the blend (4 x_n - x_{n-1}) / 3, (4 v_n - v_{n-1}) / 3, so it reuses the same assembly, solve and adjoint;
    a trajectory's first step, which has no previous state, is backward Euler. The explicit wind force is taken
    at the extrapolation 2 x_n - x_{n-1}; contact detection runs from x_n, and the collision response's velocity
    change is (z - x^) / (2/3 dt). Its observed order on cloth is below 2 because the linearisation uses ARCSim's
    stiffness, not the exact Jacobian. Newton corrections per step were measured and not adopted
    (benchmarks/newton_corrections.py, 16x16, error against the same method at dt 1/2000): one more solve per step
    restores the order on the pinned sheet (1.01 % -> 0.21 % from dt 1/200 to 1/400) but at equal solves per
    second gains at most 1.4x in error (1.01 % against 1.36 % for two solves at 1/200 against one at 1/400), and
    on the hanging sheet in the wind it loses (2.20 % against 1.78 %); fully converged (three corrections),
    BDF2 itself is still at 1.42 % at dt 1/100 there."""
    sync_every: int = 1
    """How often, in steps, a step reads the device's failure record (warpcloth/solver/status.py) and raises or
    warns: 1 every step (the error comes from the step that failed, with its state), N every N-th step, 0 only at
    ``Simulator.check`` (``wc.rollout`` and captured replays check at their end). Errors name the step, world and
    particle whichever is chosen. On the CPU a read costs nothing; on CUDA it waits for the device, so a rollout that
    should run ahead of the host uses 0 (graph capture never reads, whatever this says). Scenes with a collision
    stage check after every step's integration regardless: that stage is still driven from the host. A replay of
    ``wc.CapturedRollout`` in contact reads, every this many steps (0: once, at the end of its forward pass), the
    first step that left its contact plan: more steps a read save waits on CUDA, but a step that leaves its plan
    costs the replays after it up to the read."""
    collision: CollisionOptions = field(default_factory=CollisionOptions)
    """Options of the collision stage (used only by scenes with collisions)."""

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
