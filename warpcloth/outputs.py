"""Output paths, checked before any work starts: a suffix of their kind, not a directory; parents created."""

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
    """``path`` as a Path, its missing parents created; ValueError naming ``what`` (a flag or function) for a suffix
    not in ``suffixes`` (lower case), an existing directory, or a parent that is a file."""
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
    """``frames`` ((N, 3) positions each) as float64 arrays; ValueError naming ``what``, frame and vertex for an
    empty list, another shape or a non-finite value."""
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


def check_geometry(triangles, frames, obstacles, what: str, *, static: bool = False):
    """The cloth's checked triangles, ``frames``, and each obstacle ``(name, vertices, triangles)`` checked as
    ``(vertices, triangles)``: vertices (M, 3), or (F, M, 3) one per frame unless ``static``. ValueError naming
    ``what`` and the obstacle."""
    tris = check_triangles(triangles, frames[0].shape[0], f"{what} cloth")
    checked = []
    for k, obstacle in enumerate(obstacles):
        if len(obstacle) != 3:
            raise ValueError(f"{what}: obstacle {k} must be (name, vertices, triangles)")
        name, verts, otris = obstacle
        verts = np.asarray(verts, dtype=np.float64)
        if verts.ndim not in (2, 3) or verts.shape[-1] != 3 or (static and verts.ndim != 2):
            shapes = "(M, 3)" if static else "(M, 3) or (F, M, 3)"
            raise ValueError(f"{what}: obstacle {name!r} vertices must have shape {shapes}, got {verts.shape}")
        if verts.ndim == 3 and verts.shape[0] != len(frames):
            raise ValueError(f"{what}: obstacle {name!r} has {verts.shape[0]} frames of vertices, the cloth "
                             f"has {len(frames)}; time-sampled obstacles need one per cloth frame")
        if not np.all(np.isfinite(verts)):
            raise ValueError(f"{what}: obstacle {name!r} has non-finite vertices")
        checked.append((verts, check_triangles(otris, verts.shape[-2], f"{what} obstacle {name!r}")))
    return tris, frames, checked
