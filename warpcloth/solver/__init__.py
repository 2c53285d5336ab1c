"""The step: options, the implicit Euler simulator, its linear solver, rollouts, checkpointed backward passes and
the speed/accuracy presets."""

from warpcloth.solver.capture import CapturedRollout
from warpcloth.solver.checkpoint import checkpointed_backward
from warpcloth.solver.linear import LinearSolver, SolveInfo
from warpcloth.solver.options import CollisionOptions, SolverOptions
from warpcloth.solver.presets import PRESET_SOLVER_NAMES, SolverPreset, solver_preset
from warpcloth.solver.rollout import ControlSchedule, rollout
from warpcloth.solver.simulator import Simulator

__all__ = [
    "CapturedRollout",
    "PRESET_SOLVER_NAMES",
    "CollisionOptions",
    "ControlSchedule",
    "LinearSolver",
    "SolveInfo",
    "SolverOptions",
    "SolverPreset",
    "Simulator",
    "checkpointed_backward",
    "rollout",
    "solver_preset",
]
