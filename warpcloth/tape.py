"""The one place that touches Warp's tape internals."""

import gc
from contextlib import contextmanager

import warp as wp


def active_tape() -> wp.Tape | None:
    """The tape recording now, or None (Warp keeps it on its private runtime object, 1.19)."""
    return wp._src.context.runtime.tape


def record_adjoint(backward, *, arrays) -> None:
    """Record a hand-written adjoint on the active tape; ``arrays`` get their gradients zeroed with the tape's."""
    tape = active_tape()
    if tape is not None:
        tape.record_func(backward, arrays=arrays)


@contextmanager
def untaped():
    """Launches inside are not recorded on the active tape (library code that launches its own kernels without a
    ``record_tape`` flag, such as ``warp.optim.linear.cg``, whose adjoint the caller records by hand)."""
    runtime = wp._src.context.runtime
    tape, runtime.tape = runtime.tape, None
    try:
        yield
    finally:
        runtime.tape = tape


@contextmanager
def paused_gc():
    """Python's cyclic garbage collector off inside (as it was after). A rollout makes no reference cycles (one
    evaluation of the throw left 0 unreachable objects), but a tape holds every step's arrays and launch records, and
    each full collection walks all of them: on the throw's forward + backward (700 steps) the collector took 0.4 s
    of 1.46 s (issue 37)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def capturing(device) -> bool:
    """Whether a graph is being captured on ``device`` (CUDA: a stream capture; CPU: Warp's APIC recording): its
    launches are recorded, not run, so nothing may read the device back (1.19)."""
    device = wp.get_device(device)
    if device.is_cuda:
        return device.is_capturing
    return wp._src.context.runtime._apic_capture is not None


@contextmanager
def arrays_kept(keep: list):
    """Append every Warp array made inside to ``keep``. A graph captured inside reads and writes the arrays made
    during its capture at every replay, but Warp's graphs (1.19) hold no reference to them: an array that only the
    step's locals held would be freed and its memory reused under the graph."""
    original = wp.array.__init__

    def init(self, *args, **kwargs):
        original(self, *args, **kwargs)
        keep.append(self)

    wp.array.__init__ = init
    try:
        yield keep
    finally:
        wp.array.__init__ = original


class StepArrays:
    """The arrays a step makes for itself. Where a tape records, each is new, with a gradient (the tape keeps it for
    the backward pass); otherwise one array per name serves every step, grown to the largest size asked, so an
    untaped step allocates nothing once it has seen its sizes. A name must not be asked for twice in one step while
    the first is still read."""

    def __init__(self, device):
        self.device = device
        self._arrays: dict[str, wp.array] = {}
        # the arrays grown ones replaced, kept alive: a graph captured before the growth still writes them
        self._retired: list[wp.array] = []

    def empty(self, name: str, n: int, dtype, recording: bool) -> wp.array:
        """``n`` entries of ``dtype``, uninitialised."""
        if recording:
            return wp.empty(n, dtype=dtype, device=self.device, requires_grad=True)
        array = self._arrays.get(name)
        if array is None or array.shape[0] < n or array.dtype != dtype:
            size = n if array is None or array.dtype != dtype else max(n, 2 * array.shape[0])
            if array is not None:
                self._retired.append(array)
            array = self._arrays[name] = wp.empty(size, dtype=dtype, device=self.device)
        return array if array.shape[0] == n else array[:n]

    def zeros(self, name: str, n: int, dtype, recording: bool) -> wp.array:
        """``n`` zeros of ``dtype``."""
        if recording:
            return wp.zeros(n, dtype=dtype, device=self.device, requires_grad=True)
        array = self.empty(name, n, dtype, recording)
        array.zero_()
        return array
