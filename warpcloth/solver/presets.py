"""Named speed/accuracy presets of the solver, chosen from the measurements of benchmarks/tradeoff.py.

A preset is a time-step ceiling and SolverOptions::

    preset = wc.solver_preset("balanced")
    sim = wc.Simulator(model, preset.dt(0.02), options=preset.options)   # 0.02 s frames -> the preset's step

The README's "Choosing speed or accuracy" section has the measured error and wall time of each.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from warpcloth.solver.options import CollisionOptions, SolverOptions


@dataclass(frozen=True)
class SolverPreset:
    name: str
    description: str
    max_dt: float
    """Largest time step [s] of the preset: the time step is the biggest that is at most this and divides a frame."""
    options: SolverOptions

    def dt(self, frame_dt: float) -> float:
        """The time step for frames ``frame_dt`` apart: ``frame_dt / k`` with the smallest integer k that keeps it at
        most ``max_dt`` (take ``round(frame_dt / dt)`` steps per frame)."""
        if not (isinstance(frame_dt, (int, float)) and math.isfinite(frame_dt) and frame_dt > 0.0):
            raise ValueError(f"frame_dt must be a finite number > 0, got {frame_dt!r}")
        return frame_dt / max(1, math.ceil(frame_dt / self.max_dt - 1e-9))

    def with_options(self, **overrides) -> SolverPreset:
        """A copy with some SolverOptions fields changed (e.g. ``on_cg_failure="raise"``)."""
        return replace(self, options=replace(self.options, **overrides))


PRESETS = {
    # BDF2 in all three: on the hanging sheet it halves backward Euler's error at the same step and cost (and cuts
    # the gradient's error by 2-3x); through contact the two are alike (benchmarks/tradeoff.py, README)
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
    """The named preset: one of ``PRESET_SOLVER_NAMES`` (``"fast"``, ``"balanced"``, ``"accurate"``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown solver preset {name!r}; one of: {', '.join(PRESET_SOLVER_NAMES)}") from None
