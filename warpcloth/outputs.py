"""Where output goes: one rule for every output path, checked before any work starts.

A path must end in one of its kind's suffixes and must not be an existing directory; missing parent directories are
created. An existing file of the right kind is overwritten. The CLI checks all its output flags this way before it
simulates anything, so a long run is never lost to a bad path at its end.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

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


def check_frames(frames, what: str) -> list[np.ndarray]:
    """``frames`` (a sequence of (N, 3) positions) as float64 arrays; ValueError naming ``what``, the frame and the
    vertex where one is empty, of another shape or not finite (USD and preview output)."""
    frames = [np.asarray(f, dtype=np.float64) for f in frames]
    if not frames:
        raise ValueError(f"{what}: frames is empty")
    shape = frames[0].shape
    if len(shape) != 2 or shape[1] != 3:
        raise ValueError(f"{what}: frame 0 must have shape (N, 3), got {shape}")
    for k, f in enumerate(frames):
        if f.shape != shape:
            raise ValueError(f"{what}: frame {k} has shape {f.shape}, frame 0 has {shape}")
        bad = np.flatnonzero(~np.all(np.isfinite(f), axis=1))
        if len(bad):
            raise ValueError(f"{what}: frame {k} vertex {int(bad[0])} is not finite: {f[bad[0]].tolist()}")
    return frames


def check_triangles(triangles, vertex_count: int, what: str) -> np.ndarray:
    """``triangles`` (T, 3) as int32; ValueError naming ``what`` and the triangle where one is out of range."""
    tris = np.asarray(triangles)
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise ValueError(f"{what}: triangles must have shape (T, 3), got {tris.shape}")
    if tris.size and not np.issubdtype(tris.dtype, np.integer):
        raise ValueError(f"{what}: triangles must hold integers, got dtype {tris.dtype}")
    bad = np.argwhere((tris < 0) | (tris >= vertex_count))
    if len(bad):
        t = int(bad[0][0])
        raise ValueError(f"{what}: triangle {t} {tris[t].tolist()} has an index out of range [0, {vertex_count})")
    return tris.astype(np.int32)
