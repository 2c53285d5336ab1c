"""The one place that touches Warp's internals: its tape, its CPU allocator and CPU captures' memory operations."""

import ctypes
import gc
import weakref
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
    """Launches inside are not recorded on the active tape (for library code such as ``warp.optim.linear.cg``)."""
    runtime = wp._src.context.runtime
    tape, runtime.tape = runtime.tape, None
    try:
        yield
    finally:
        runtime.tape = tape


@contextmanager
def paused_gc():
    """Python's cyclic garbage collector off inside (as it was after): a tape's records are many objects, and
    rollouts make no cycles. Why: docs/decisions.md, "Garbage collector paused during rollouts"."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def capturing(device) -> bool:
    """Whether a graph is being captured on ``device``: launches are recorded, not run; nothing may read back."""
    device = wp.get_device(device)
    if device.is_cuda:
        return device.is_capturing
    return wp._src.context.runtime._apic_capture is not None


@contextmanager
def arrays_kept(keep: list):
    """Append every Warp array made inside to ``keep``: a graph captured inside uses them at every replay but holds
    no reference to them (Warp 1.19)."""
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
    """The arrays a step makes for itself: new, with a gradient, where a tape records; otherwise one per name for
    every step, grown to the largest size asked. A name must not be asked for twice while the first is read."""

    def __init__(self, device):
        self.device = device
        self._arrays: dict[str, wp.array] = {}
        # the arrays grown ones replaced, kept alive: a graph captured before the growth still writes them
        self._retired: list[wp.array] = []

    def empty(self, name: str, n: int, dtype, recording: bool) -> wp.array:
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
        if recording:
            return wp.zeros(n, dtype=dtype, device=self.device, requires_grad=True)
        array = self.empty(name, n, dtype, recording)
        array.zero_()
        return array


class _CpuAllocator:
    """An allocator for Warp's CPU device (Warp 1.19's allocator protocol) over the device's own."""

    deallocate_requires_context_guard = False

    def __init__(self, device):
        device = wp.get_device(device)
        if not device.is_cpu:
            raise ValueError(f"{type(self).__name__}: only on the CPU, not {device}")
        self.device = device
        self._inner = device.default_allocator
        self.memory_kind = self._inner.memory_kind

    def rewind(self) -> None:
        """Where the next allocation starts (an Arena's first block; nothing otherwise)."""


class Arena(_CpuAllocator):
    """Memory for graphs that never run at the same time: inside :func:`allocating_from`, the n-th allocation since
    the last rewind gets the n-th block (grown where asked for more), so graphs captured after different rewinds
    share memory. Freeing is a no-op: the blocks live as long as the arena."""

    def __init__(self, device):
        super().__init__(device)
        self._blocks: list[tuple[int, int]] = []  # (pointer, bytes), in allocation order
        self._outgrown: list[tuple[int, int]] = []  # blocks replaced by larger ones, still read by earlier graphs
        self._cursor = 0

    @property
    def nbytes(self) -> int:
        return sum(size for _, size in self._blocks + self._outgrown)

    def rewind(self) -> None:
        """The next allocation gets the first block again."""
        self._cursor = 0

    def owns(self, ptr: int | None) -> bool:
        """Whether ``ptr`` points into one of this arena's blocks."""
        return ptr is not None and any(start <= ptr < start + max(size, 1)
                                       for start, size in self._blocks + self._outgrown)

    def allocate(self, size_in_bytes: int) -> int:
        i = self._cursor
        self._cursor += 1
        if i == len(self._blocks) or self._blocks[i][1] < size_in_bytes:
            block = (self._inner.allocate(max(size_in_bytes, 1)), size_in_bytes)
            if i == len(self._blocks):
                self._blocks.append(block)
            else:
                self._outgrown.append(self._blocks[i])
                self._blocks[i] = block
        return self._blocks[i][0]

    def deallocate(self, ptr, size_in_bytes) -> None:
        pass  # the arena owns its blocks

    def __del__(self):
        for ptr, size in getattr(self, "_blocks", []) + getattr(self, "_outgrown", []):
            self._inner.deallocate(ptr, size)


class Tally(_CpuAllocator):
    """The CPU device's own allocator, counting the bytes of the arrays made inside :func:`allocating_from`."""

    def __init__(self, device):
        super().__init__(device)
        self.nbytes = 0
        """The bytes held now."""

    def allocate(self, size_in_bytes: int) -> int:
        self.nbytes += size_in_bytes
        return self._inner.allocate(size_in_bytes)

    def deallocate(self, ptr, size_in_bytes) -> None:
        self.nbytes -= size_in_bytes
        self._inner.deallocate(ptr, size_in_bytes)


@contextmanager
def allocating_from(arena: Arena | Tally | None, *, rewind: bool = True):
    """Every Warp array made on the arena's device inside takes its memory from ``arena`` (rewound first where
    ``rewind``); None: the device's own allocator."""
    if arena is None:
        yield
        return
    if rewind:
        arena.rewind()
    device = arena.device
    original, device.default_allocator = device.default_allocator, arena
    try:
        yield
    finally:
        device.default_allocator = original


def gradient_owners(tape: wp.Tape) -> list:
    """Weak references to the arrays whose gradients ``tape.zero()`` zeroes, for :func:`zero_gradients`."""
    return [weakref.ref(a) for a in tape.gradients if isinstance(a, wp.array)]


def zero_gradients(owners: list) -> None:
    """Zero the gradients of the arrays of ``owners`` (from :func:`gradient_owners`) still alive."""
    for ref in owners:
        array = ref()
        if array is not None and array.grad is not None:
            array.grad.zero_()


@contextmanager
def memory_ops_as_kernels(device):
    """Inside a CPU graph capture, Warp's memsets, fills (of 1, 2, 4 or 8 bytes) and host copies launch kernels; no
    effect on CUDA. Why: docs/decisions.md, "Memory operations as kernels in CPU captures"."""
    device = wp.get_device(device)
    if not device.is_cpu:
        yield
        return
    from warpcloth.kernels import memory as km  # noqa: PLC0415 - only captures need these kernels

    wp.load_module(km, device=device)  # loaded now: a capture records launches, it does not load modules
    core = wp._src.context.runtime.core
    memset, memtile, memcpy = device.memset, device.memtile, core.wp_memcpy_h2h

    fills = ((wp.uint64, 8, km.fill_u64), (wp.uint32, 4, km.fill_u32), (wp.uint8, 1, km.fill_u8))
    copies = ((wp.uint64, 8, km.copy_u64), (wp.uint32, 4, km.copy_u32), (wp.uint8, 1, km.copy_u8))

    def view(ptr: int, dtype, count: int) -> wp.array:
        return wp.array(ptr=ptr, dtype=dtype, shape=(count,), device=device)

    def fill(dst: int, pattern: bytes, nbytes: int) -> bool:
        """``nbytes`` bytes at ``dst`` <- ``pattern`` repeated, in the widest words that hold whole patterns."""
        for dtype, size, kernel in fills:
            if size % len(pattern) == 0 and dst % size == 0 and nbytes % size == 0:
                value = int.from_bytes(pattern * (size // len(pattern)), "little")
                wp.launch(kernel, nbytes // size, inputs=[view(dst, dtype, nbytes // size), dtype(value)],
                          device=device, record_tape=False)
                return True
        return False

    def kernel_memset(dst, value, nbytes):
        return True if not nbytes else fill(int(dst), bytes([int(value) & 0xFF]), int(nbytes))

    def kernel_memtile(dst, src, srcsize, count):
        if count and not fill(int(dst), ctypes.string_at(src, srcsize), int(srcsize) * int(count)):
            memtile(dst, src, srcsize, count)  # a pattern of another length: Warp's, with its snapshot

    def kernel_memcpy(dst, src, nbytes):
        dst, src, nbytes = int(dst), int(src), int(nbytes)
        for dtype, size, kernel in copies:
            if nbytes and dst % size == 0 and src % size == 0 and nbytes % size == 0:
                count = nbytes // size
                wp.launch(kernel, count, inputs=[view(dst, dtype, count), view(src, dtype, count)], device=device,
                          record_tape=False)
                break
        return True

    device.memset, device.memtile, core.wp_memcpy_h2h = kernel_memset, kernel_memtile, kernel_memcpy
    try:
        yield
    finally:
        device.memset, device.memtile, core.wp_memcpy_h2h = memset, memtile, memcpy
