"""Progress bars: tqdm, with Warp's module-load log lines (which break a bar) silenced while a bar is open."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import warp as wp
from tqdm import tqdm

_forward: Callable[[int], None] | None = None


class _QuietBar(tqdm):
    def __init__(self, *args, **kwargs):
        self._warp_log_level = wp.config.log_level
        wp.config.log_level = max(self._warp_log_level, wp.LOG_WARNING)
        super().__init__(*args, **kwargs)

    def close(self):
        if hasattr(self, "_warp_log_level"):
            wp.config.log_level = self._warp_log_level
            del self._warp_log_level
        super().close()


class _ForwardingBar(tqdm):
    def __init__(self, total: int, sink: Callable[[int], None]):
        super().__init__(total=total, disable=True)
        self._sink = sink

    def update(self, n=1):
        self._sink(n)


def progress_bar(total: int, desc: str, unit: str) -> tqdm:
    """An open tqdm bar of ``total`` units; close it (or use it as a context manager) to restore Warp's output.
    Inside :func:`forward_progress` the bar draws nothing and passes its updates on."""
    if _forward is not None:
        return _ForwardingBar(total, _forward)
    return _QuietBar(total=total, desc=desc, unit=unit)


@contextmanager
def forward_progress(sink: Callable[[int], None]) -> Iterator[None]:
    """While open, every bar :func:`progress_bar` opens, in any thread, calls ``sink(n)`` for each update of ``n``
    units instead of drawing itself: how one job's simulations advance a bar over many (warpcloth.tasks.jobs)."""
    global _forward
    lock = threading.Lock()

    def locked(n: int) -> None:
        with lock:
            sink(n)

    previous, _forward = _forward, locked
    try:
        yield
    finally:
        _forward = previous
