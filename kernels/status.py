"""The step's failure record on the device: kernels latch the first failure (its step, kind and particle or world)
so that no step has to read the device back to notice one (warpcloth/solver/status.py reads it when asked).

Layout of ``record`` (int32, RECORD_SIZE): the error slot [set, step, kind, index], the warning slot
[set, step, kind, index], the number of warnings latched since the last read, then the step of the first forward
solve that took no iteration (0: none; its right-hand side was below cg_atol). ``detail`` (float64, 4): the
error's and the warning's CG iterations and relative residual.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

DIVERGED = wp.constant(1)
"""A particle's position or velocity is non-finite, or it moves faster than SolverOptions.max_speed."""
CG_NON_FINITE = wp.constant(2)
"""A CG solve's residual is non-finite (add ADJOINT for the adjoint solve)."""
CG_UNCONVERGED = wp.constant(3)
"""A CG solve missed its tolerance (add ADJOINT for the adjoint solve)."""
ADJOINT = wp.constant(2)
ERROR = wp.constant(0)
WARNING = wp.constant(4)
WARNING_COUNT = wp.constant(8)
SKIPPED = wp.constant(9)
RECORD_SIZE = 10


@wp.func
def latch(record: wp.array(dtype=wp.int32), slot: int, step: int, kind: int, index: int) -> bool:
    """Claim ``slot`` (ERROR or WARNING) for this failure if it is still free; returns whether it was. The first
    claimant alone writes the fields, so threads racing in one launch leave one consistent entry."""
    if wp.atomic_cas(record, slot, 0, 1) == 0:
        record[slot + 1] = step
        record[slot + 2] = kind
        record[slot + 3] = index
        return True
    return False


@wp.kernel
def account_solve(
    info: wp.array2d(dtype=wp.float64),
    step: int,
    adjoint: int,
    unconverged_raises: int,
    # out:
    record: wp.array(dtype=wp.int32),
    detail: wp.array(dtype=wp.float64),
    totals: wp.array(dtype=wp.float64),
):
    # One thread after each CG solve: adds its iterations (the most of any world) to the totals [forward, adjoint]
    # and latches a failed world: a non-finite residual always as an error, a missed tolerance as an error or, with
    # on_cg_failure="warn", as a warning. info: per world [iterations, relative residual, converged (0/1)].
    most = wp.float64(0.0)
    non_finite = int(-1)
    worst = int(-1)
    for w in range(info.shape[0]):
        most = wp.max(most, info[w, 0])
        if not wp.isfinite(info[w, 1]):
            if non_finite < 0:
                non_finite = w
        elif info[w, 2] == wp.float64(0.0):
            if worst < 0 or info[w, 1] > info[worst, 1]:
                worst = w
    totals[adjoint] = totals[adjoint] + most
    if adjoint == 0 and most == wp.float64(0.0) and record[SKIPPED] == 0:
        record[SKIPPED] = step
    kind_base = adjoint * ADJOINT
    if non_finite >= 0:
        if latch(record, ERROR, step, CG_NON_FINITE + kind_base, non_finite):
            detail[0] = info[non_finite, 0]
            detail[1] = info[non_finite, 1]
    elif worst >= 0:
        if unconverged_raises != 0:
            if latch(record, ERROR, step, CG_UNCONVERGED + kind_base, worst):
                detail[0] = info[worst, 0]
                detail[1] = info[worst, 1]
        else:
            record[WARNING_COUNT] = record[WARNING_COUNT] + 1
            if latch(record, WARNING, step, CG_UNCONVERGED + kind_base, worst):
                detail[2] = info[worst, 0]
                detail[3] = info[worst, 1]


@wp.kernel
def note_plan_miss(collision: wp.array(dtype=wp.int32), pairs: wp.array(dtype=wp.int32), index: int,
                   first: wp.array(dtype=wp.int32)):
    # One thread at the end of a step captured following a plan (wc.CapturedRollout): where the collision stage's
    # check or the proximity pairs' budget raised its flag, keep the smallest such step index of the replay in
    # first[0], so that the host reads one value for any number of replayed steps.
    if (collision[0] != 0 or pairs[0] != 0) and index < first[0]:
        first[0] = index
