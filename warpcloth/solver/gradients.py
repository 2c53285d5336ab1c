"""How a rollout's gradient is taken, decided in one place for the control tasks, the estimation fits and the torch
bridge: taped whole or checkpointed within a memory budget, replayed from graphs or run uncaptured, and the cache of
the captured rollouts. Why these thresholds: docs/decisions.md, "Rollout gradients within a memory budget"."""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Generic, TypeVar

from warpcloth.solver.capture import CapturedRollout
from warpcloth.solver.simulator import Simulator

WHOLE_TAPE_PARTICLE_STEPS = 200_000
"""A rollout is taped whole up to this many particle-steps (particles of all worlds times steps); beyond it, it is
checkpointed in segments of ceil(sqrt(steps)) steps."""
CAPTURED_SEGMENTS_PARTICLE_STEPS = 2_000_000
"""A checkpointed rollout with a loss replays from graphs in segments up to this many particle-steps (the replay
keeps every State); beyond it, it runs uncaptured (``wc.checkpointed_backward``)."""


@dataclass(frozen=True)
class GradientPlan:
    """How one rollout of ``steps`` steps is run (:func:`plan_gradient`)."""

    steps: int
    segment_steps: int
    """Checkpoint segment length; ``steps``: taped whole."""
    uncaptured_because: str | None
    """Why the rollout runs uncaptured, or None where it replays from graphs."""

    @property
    def captured(self) -> bool:
        return self.uncaptured_because is None

    @property
    def mode(self) -> str:
        """``"whole"``, ``"checkpointed"``, ``"captured"`` or ``"captured-segments"``."""
        segmented = self.segment_steps < self.steps
        if self.captured:
            return "captured-segments" if segmented else "captured"
        return "checkpointed" if segmented else "whole"


def default_segment_steps(particle_count: int, steps: int) -> int:
    """The horizon where ``particle_count * steps <= WHOLE_TAPE_PARTICLE_STEPS``, else ceil(sqrt(steps))."""
    return steps if particle_count * steps <= WHOLE_TAPE_PARTICLE_STEPS else math.ceil(math.sqrt(steps))


def plan_gradient(sim: Simulator, steps: int, *, segment_steps: int | None = None, backward: bool = True,
                  capture: bool = True) -> GradientPlan:
    """The plan of a rollout of ``sim`` over ``steps`` steps.

    Args:
        sim: the Simulator.
        steps: the horizon (>= 1).
        segment_steps: checkpoint segment length; None: :func:`default_segment_steps`.
        backward: whether the rollout is differentiated (a forward pass alone is captured on any device).
        capture: False where the caller does not want graphs at all.
    """
    particle_steps = sim.model.particle_count * steps
    segment = int(segment_steps or default_segment_steps(sim.model.particle_count, steps))
    reason = None if capture else "capture is off"
    reason = reason or CapturedRollout.unsupported(sim)
    if reason is None and backward:
        if not sim.device.is_cpu:
            reason = f"a rollout's backward pass replays from graphs on the CPU only, not on {sim.device}"
        elif segment < steps:
            reason = CapturedRollout.segments_unsupported(sim)
            if reason is None and particle_steps > CAPTURED_SEGMENTS_PARTICLE_STEPS:
                reason = (f"{particle_steps} particle-steps exceed CAPTURED_SEGMENTS_PARTICLE_STEPS "
                          f"({CAPTURED_SEGMENTS_PARTICLE_STEPS})")
    return GradientPlan(steps=int(steps), segment_steps=segment, uncaptured_because=reason)


T = TypeVar("T")


class GraphCache(Generic[T]):
    """Captured rollouts by key. A key asked for the ``after``-th time gets its capture made, later asks replay it;
    a capture that is no longer current (``current(capture)`` False: options or arrays replaced) is made again.
    At most ``size`` captures and ``size`` counts of keys not yet captured are kept, the least recently used
    dropped first.

    Capturing costs several uncaptured evaluations, so a key asked for once is not captured (``after`` >= 2).
    """

    def __init__(self, *, after: int = 2, size: int | None = None):
        if isinstance(after, bool) or not isinstance(after, int) or after < 1:
            raise ValueError(f"GraphCache: after must be an integer >= 1, got {after!r}")
        if size is not None and (isinstance(size, bool) or not isinstance(size, int) or size < 1):
            raise ValueError(f"GraphCache: size must be None or an integer >= 1, got {size!r}")
        self.after, self.size = after, size
        self._asked: dict[Hashable, int] = {}  # uncaptured keys: how often asked, least recently used first
        self._captures: dict[Hashable, T] = {}  # least recently used first
        self.made = 0
        """Captures made so far (recaptures of stale ones included)."""

    def get(self, key: Hashable, make: Callable[[], T],
            current: Callable[[T], bool] = lambda c: c.current()) -> T | None:
        """The key's capture (made now where this ask is the ``after``-th, or the old one is stale), or None."""
        capture = self._captures.pop(key, None)
        if capture is None:
            asked = self._asked.pop(key, 0) + 1
            if asked < self.after:
                self._asked[key] = asked
                self._trim(self._asked)
                return None
        if capture is None or not current(capture):
            capture = make()
            self.made += 1
        self._captures[key] = capture
        self._trim(self._captures)
        return capture

    def peek(self, key: Hashable) -> T | None:
        """The key's capture if one is kept (current or not), without counting an ask."""
        return self._captures.get(key)

    def __len__(self) -> int:
        return len(self._captures)

    def _trim(self, entries: dict) -> None:
        while self.size is not None and len(entries) > self.size:
            del entries[next(iter(entries))]
