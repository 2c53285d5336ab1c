"""Progress bars: tqdm, with Warp's module-load lines silenced while a bar is open.

Warp logs a line at info level whenever it loads a module (the first launch of a kernel set); printed between a
bar's redraws, those lines break the bar into pieces. A bar from :func:`progress_bar` raises ``wp.config.log_level``
to warnings until it is closed, then restores the caller's setting.
"""

from __future__ import annotations

import warp as wp
from tqdm import tqdm


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


def progress_bar(total: int, desc: str, unit: str) -> tqdm:
    """An open tqdm bar of ``total`` units; close it (or use it as a context manager) to restore Warp's output."""
    return _QuietBar(total=total, desc=desc, unit=unit)
