"""Named speed/accuracy presets of the solver, chosen from docs/results/speed-accuracy.md, "The trade"."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from warpcloth.solver.options import CollisionOptions, SolverOptions


@dataclass(frozen=True)
class SolverPreset:
    """A named time-step ceiling and SolverOptions (:func:`solver_preset`), used as
    ``wc.Simulator(model, preset.dt(frame_dt), options=preset.options)``."""

    name: str
    description: str
    max_dt: float
    """Largest time step [s] of the preset (see :meth:`dt`)."""
    options: SolverOptions

    def dt(self, frame_dt: float) -> float:
        """The time step for frames ``frame_dt`` [s] apart: ``frame_dt / k``, the smallest integer k keeping it at
        most ``max_dt``. Raises ValueError unless ``frame_dt > 0``."""
        if not (isinstance(frame_dt, (int, float)) and math.isfinite(frame_dt) and frame_dt > 0.0):
            raise ValueError(f"frame_dt must be a finite number > 0, got {frame_dt!r}")
        return frame_dt / max(1, math.ceil(frame_dt / self.max_dt - 1e-9))

    def with_options(self, **overrides) -> SolverPreset:
        """A copy with some SolverOptions fields changed (e.g. ``on_cg_failure="raise"``)."""
        return replace(self, options=replace(self.options, **overrides))


PRESETS = {
    # BDF2 in all three: docs/results/speed-accuracy.md, "The trade"
    "fast": SolverPreset(
        "fast", "previews, and the first iterations of an optimisation", max_dt=1.0 / 50,
        options=SolverOptions(cg_tol=1.0e-3, integrator="bdf2", collision=CollisionOptions(rounds=50))),
    "balanced": SolverPreset(
        "balanced", "two thirds of the fast preset's error for twice its time", max_dt=1.0 / 100,
        options=SolverOptions(cg_tol=1.0e-4, integrator="bdf2", collision=CollisionOptions(rounds=50))),
    "accurate": SolverPreset(
        "accurate", "near-converged trajectories and gradients (references, gradient checks)", max_dt=1.0 / 400,
        options=SolverOptions(cg_tol=1.0e-6, cg_max_iters=5000, integrator="bdf2",
                              collision=CollisionOptions(rounds=100))),
}
PRESET_SOLVER_NAMES = tuple(PRESETS)


def solver_preset(name: str) -> SolverPreset:
    """The named preset, one of ``PRESET_SOLVER_NAMES``; else ValueError."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown solver preset {name!r}; one of: {', '.join(PRESET_SOLVER_NAMES)}") from None
