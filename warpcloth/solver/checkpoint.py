"""Back-propagation through long rollouts with O(sqrt(T)) stored states: segments re-simulated on their own tapes."""

from __future__ import annotations

import math
from collections.abc import Callable

import warp as wp

from warpcloth.model import State
from warpcloth.progress import progress_bar
from warpcloth.solver.rollout import ControlSchedule, check_schedule, control_at
from warpcloth.solver.simulator import Simulator
from warpcloth.tape import paused_gc

StepLoss = Callable[[int, State, wp.array], None]
"""``loss(i, state_i, out)``: launch kernels that add step i's loss term (i = 1..steps) to ``out[0]``."""


@paused_gc()  # the garbage collector walks the tapes' records: warpcloth/tape.py paused_gc
def checkpointed_backward(
    sim: Simulator,
    state: State,
    control: ControlSchedule,
    *,
    steps: int,
    loss: StepLoss,
    segment_steps: int | None = None,
    progress: bool = False,
) -> tuple[float, State]:
    """Simulate ``steps`` steps, sum the per-step loss terms, and add the loss's gradient to the ``.grad`` of every
    differentiable array the rollout reads (``state``'s arrays, the model's materials, the controls' arrays).

    The gradients equal a full tape's bitwise, for about ``steps / segment_steps + segment_steps`` states of memory
    and a second forward pass of every segment but the last. Replayed from graphs: ``wc.CapturedRollout``.

    Args:
        sim: its model should have ``requires_grad=True``.
        control: one Control for every step, a list with one per step, or a function of the step index.
        loss: ``loss(i, state_i, out)`` adds step i's loss term (i = 1..steps) to ``out[0]``.
        segment_steps: steps per re-simulated segment; None: ceil(sqrt(steps)), the least memory.

    Returns:
        (loss value, final State).

    Raises:
        ValueError: ``steps`` or ``segment_steps`` not a positive integer, or a control sequence shorter than
            ``steps``."""
    if int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    steps = int(steps)
    seg = math.ceil(math.sqrt(steps)) if segment_steps is None else segment_steps
    if int(seg) != seg or seg < 1:
        raise ValueError(f"segment_steps must be a positive integer, got {segment_steps!r}")
    check_schedule(control, steps)
    model = sim.model
    starts = list(range(0, steps, int(seg)))
    out = wp.zeros(1, dtype=model.types.scalar, device=model.device, requires_grad=True)

    def advance(start: State, first: int, last: int, *, requires_grad: bool, out: wp.array) -> State:
        current = start
        for i in range(first, last):
            nxt = model.empty_state(requires_grad=requires_grad)
            sim.step(current, nxt, control_at(control, i))
            loss(i + 1, nxt, out)
            current = nxt
        return current

    def taped(checkpoint: State, k: int, out: wp.array) -> tuple[State, wp.Tape, State, wp.array]:
        """Segment k from its checkpoint on a tape, loss into ``out``: (start state, tape, end state, ``out``)."""
        start = checkpoint.clone(requires_grad=True)
        start.solve_adjoint = wp.zeros_like(start.particle_x, requires_grad=False)  # receives its first step's
        tape = wp.Tape()
        with tape:
            end = advance(start, starts[k], min(starts[k] + seg, steps), requires_grad=True, out=out)
        return start, tape, end, out

    bar = progress_bar(2 * len(starts), "checkpointed rollout", "segment") if progress else None

    # forward: untaped, keep the state at the start of every segment; the last segment, the first the backward
    # pass needs, is taped right away instead of being simulated twice (a rollout of one segment runs once)
    checkpoints = []
    current = state
    for first in starts[:-1]:
        checkpoints.append(current.clone(requires_grad=False))
        current = advance(current, first, min(first + seg, steps), requires_grad=False, out=out)
        if bar is not None:
            bar.update()
    last = taped(current, len(starts) - 1, out)  # its loss terms go to ``out`` too, in the order of one pass
    final = last[2]
    value = float(out.numpy()[0])
    if bar is not None:
        bar.update()

    # backward: re-simulate each segment on its own tape, last first, chaining the state adjoints. A segment's first
    # step may also read arrays of the step before the segment, whose adjoints go to the previous segment's end:
    # the lagged wind normals' positions (particle_x_previous) and BDF2's previous state (particle_x_last/_v_last).
    adj_x = wp.zeros_like(final.particle_x)
    adj_v = wp.zeros_like(final.particle_v)
    adj_x_previous = adj_x_last = adj_v_last = None
    handed_on = None  # the adjoint solve of the first step of the segment after this one
    for k in reversed(range(len(starts))):
        if k == len(starts) - 1:
            (start, tape, end, out), last = last, None
        else:
            start, tape, end, out = taped(checkpoints.pop(), k, wp.zeros_like(out, requires_grad=True))
        if handed_on is not None and end.solve_adjoint is not None:
            # the first guess of this segment's last adjoint solve, as on one tape over the whole rollout: the
            # gradients then equal the full tape's bitwise
            wp.copy(end.solve_adjoint, handed_on)
        seeds = {out: wp.ones_like(out), end.particle_x: adj_x, end.particle_v: adj_v}
        if adj_x_previous is not None:
            if end.particle_x_previous is end.particle_x:  # after a collision response: the current positions
                seeds[end.particle_x] = _sum(adj_x, adj_x_previous)
            else:  # the last step's start positions: never another seed
                seeds[end.particle_x_previous] = adj_x_previous
        if adj_x_last is not None:
            seeds[end.particle_x_last] = adj_x_last
            seeds[end.particle_v_last] = adj_v_last
        tape.backward(grads=seeds)
        handed_on = start.solve_adjoint
        adj_x, adj_v = start.particle_x.grad, start.particle_v.grad
        adj_x_previous = adj_x_last = adj_v_last = None
        if start.particle_x_last is not None:  # it holds the lagged normals' adjoint too where they are the same
            adj_x_last, adj_v_last = start.particle_x_last.grad, start.particle_v_last.grad
        if start.particle_x_previous is not None and start.particle_x_previous is not start.particle_x \
                and start.particle_x_previous is not start.particle_x_last:
            adj_x_previous = start.particle_x_previous.grad
        del tape
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    for arr, adj in ((state.particle_x, adj_x), (state.particle_v, adj_v), (state.particle_x_previous, adj_x_previous),
                     (state.particle_x_last, adj_x_last), (state.particle_v_last, adj_v_last)):
        if arr is not None and adj is not None and arr.requires_grad:  # one host round trip per rollout
            arr.grad.assign(arr.grad.numpy() + adj.numpy())
    return value, final


def _sum(a: wp.array, b: wp.array) -> wp.array:
    """a + b as a new array (host arithmetic: once per segment)."""
    return wp.array(a.numpy() + b.numpy(), dtype=a.dtype, device=a.device)
