"""Run many steps, on the active tape if there is one."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from warpcloth.model import Control, State
from warpcloth.progress import progress_bar
from warpcloth.solver.simulator import Simulator
from warpcloth.tape import capturing, paused_gc

ControlSchedule = Control | Sequence[Control] | Callable[[int], Control] | None
"""One Control for every step, a sequence with one per step, or a function of the step index."""


def check_schedule(control: ControlSchedule, steps: int) -> None:
    """Raise ValueError when a per-step sequence is shorter than ``steps``."""
    if isinstance(control, Sequence) and len(control) < steps:
        raise ValueError(f"control has {len(control)} entries but {steps} steps were asked for")


def control_at(control: ControlSchedule, i: int) -> Control | None:
    if callable(control):
        return control(i)
    if isinstance(control, Sequence):
        return control[i]
    return control


def rollout(
    sim: Simulator,
    state: State,
    control: ControlSchedule = None,
    *,
    steps: int,
    progress: bool = False,
) -> list[State]:
    """Simulate ``steps`` steps from ``state`` and return the trajectory ``[state, s1, ..., s_steps]``, each a fresh
    State, so a surrounding ``wp.Tape`` can differentiate it all.

    Args:
        control: one Control for every step, a sequence with one per step, or a function of the step index.
        progress: show a tqdm progress bar.

    Raises:
        ValueError: ``steps`` negative or not an integer, or a control sequence shorter than ``steps``.
        SimulationError: a step diverged or (``on_cg_failure="raise"``) a solve failed (checked at the end)."""
    if int(steps) != steps or steps < 0:
        raise ValueError(f"steps must be a non-negative integer, got {steps!r}")
    check_schedule(control, steps)
    trajectory = [state]
    bar = progress_bar(int(steps), "simulate", "step") if progress else None
    try:
        with paused_gc():  # tape.py says why
            for i in range(int(steps)):
                nxt = sim.model.empty_state()
                sim.step(trajectory[-1], nxt, control_at(control, i))
                trajectory.append(nxt)
                if bar is not None:
                    bar.update()
    finally:
        if bar is not None:
            bar.close()
    if not capturing(sim.device):
        sim.check(trajectory)  # what steps that did not check themselves (SolverOptions.sync_every) latched
    return trajectory
