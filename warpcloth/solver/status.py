"""The step's failure record: what the divergence guard and the CG solves latched on the device, read at syncs."""

from __future__ import annotations

from typing import NamedTuple

import warp as wp

from warpcloth.kernels import status as ks


class Failure(NamedTuple):
    """One latched failure."""

    step: int
    kind: int
    """kernels/status.py: DIVERGED, CG_NON_FINITE or CG_UNCONVERGED (+ ADJOINT for the adjoint solve)."""
    index: int
    """The particle (DIVERGED) or the world (a CG solve)."""
    iterations: int
    """The CG solve's iterations (0 for DIVERGED)."""
    residual: float
    """The CG solve's relative residual (nan for DIVERGED)."""
    count: int = 1
    """How many failures of this slot were latched since the last read (warnings only; 1 for an error)."""

    @property
    def diverged(self) -> bool:
        return self.kind == ks.DIVERGED

    @property
    def adjoint(self) -> bool:
        return self.kind in (ks.CG_NON_FINITE + ks.ADJOINT, ks.CG_UNCONVERGED + ks.ADJOINT)

    @property
    def non_finite(self) -> bool:
        return self.kind in (ks.CG_NON_FINITE, ks.CG_NON_FINITE + ks.ADJOINT)


class StepStatus:

    def __init__(self, device):
        self.device = device
        self.record = wp.zeros(ks.RECORD_SIZE, dtype=wp.int32, device=device)
        """The failure record (kernels/status.py layout)."""
        self.detail = wp.zeros(4, dtype=wp.float64, device=device)
        """Iterations and relative residual of the latched error and warning."""
        self.totals = wp.zeros(2, dtype=wp.float64, device=device)
        """CG iterations over all solves so far: [forward, adjoint] (the most of any world, per solve)."""
        cpu = wp.get_device(device).is_cpu
        # on the CPU a host view shares memory: reading it costs no copy and no launch
        self._views = (self.record.numpy(), self.detail.numpy(), self.totals.numpy()) if cpu else None

    def take(self) -> tuple[Failure | None, Failure | None, int]:
        """Clear and return (error, warning, skipped): Failures or None, and the step of the first forward solve
        that took no iteration (0: none)."""
        record = self._views[0] if self._views is not None else self.record.numpy()
        skipped = int(record[ks.SKIPPED])
        if record[ks.ERROR] or record[ks.WARNING]:
            detail = self._views[1] if self._views is not None else self.detail.numpy()
        error = warning = None
        if record[ks.ERROR]:
            error = Failure(int(record[ks.ERROR + 1]), int(record[ks.ERROR + 2]), int(record[ks.ERROR + 3]),
                            int(detail[0]), float(detail[1]) if record[ks.ERROR + 2] != ks.DIVERGED else float("nan"))
        if record[ks.WARNING]:
            warning = Failure(int(record[ks.WARNING + 1]), int(record[ks.WARNING + 2]), int(record[ks.WARNING + 3]),
                              int(detail[2]), float(detail[3]), int(record[ks.WARNING_COUNT]))
        if error is not None or warning is not None or skipped:
            self.clear()
        return error, warning, skipped

    def clear(self) -> None:
        """Forget what was latched (a memset: capturable)."""
        if self._views is not None:
            self._views[0][:] = 0
        else:
            self.record.zero_()

    def iterations(self) -> tuple[int, int]:
        """(forward, adjoint) CG iterations over every solve so far."""
        totals = self._views[2] if self._views is not None else self.totals.numpy()
        return int(totals[0]), int(totals[1])
