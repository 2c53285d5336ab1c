"""Where output goes: one rule for every output path, checked before any work starts.

A path must end in one of its kind's suffixes and must not be an existing directory; missing parent directories are
created. An existing file of the right kind is overwritten. The CLI checks all its output flags this way before it
simulates anything, so a long run is never lost to a bad path at its end.
"""

from __future__ import annotations

import os
from pathlib import Path

USD_SUFFIXES = (".usd", ".usda", ".usdc")
"""What warpcloth.usd.write_usd writes (.usdz packages are not written)."""
JSON_SUFFIXES = (".json",)
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
PREVIEW_SUFFIXES = (".gif", ".mp4", ".png")
"""What warpcloth.preview.write_preview writes: an animation, a video (with ffmpeg) or a contact sheet."""


def prepare_output_path(path: str | os.PathLike, what: str, suffixes: tuple[str, ...]) -> Path:
    """Check an output path and create its missing parent directories.

    Args:
        path: the file to write.
        what: how to name it in an error (a CLI flag such as ``"--usd"``, or a function's name).
        suffixes: accepted file name endings (lower case).

    Returns:
        The path as a ``Path``.

    Raises:
        ValueError: a suffix not in ``suffixes``, an existing directory, or a parent that is a file.
    """
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{what} {str(path)!r} is a directory; give a file name ending in {' or '.join(suffixes)}")
    if p.suffix.lower() not in suffixes:
        raise ValueError(f"{what} {str(path)!r}: expected a file ending in {' or '.join(suffixes)}")
    for parent in reversed(p.parents):
        if parent.exists() and not parent.is_dir():
            raise ValueError(f"{what} {str(path)!r}: {str(parent)!r} is a file, not a directory")
    p.parent.mkdir(parents=True, exist_ok=True)
    return p
