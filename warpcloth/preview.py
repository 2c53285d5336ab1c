"""Pictures of a simulation drawn with matplotlib, for a user without a USD viewer: the cloth and its obstacles as
shaded triangles, seen from one fixed camera whose box holds the whole trajectory.

The file's suffix picks the kind (``warpcloth simulate SCENE --preview PATH`` writes the same):

- ``.gif``: an animation of up to 36 frames evenly spaced through the trajectory, first and last included, played
  at the simulation's speed (as far as a GIF's 20 ms shortest frame allows);
- ``.mp4``: the same animation as H.264 video; needs ``ffmpeg`` on ``PATH`` (or matplotlib's
  ``animation.ffmpeg_path``);
- ``.png``: one contact sheet of up to 9 frames (3 x 3 panels, each with its time).

Everything is drawn off screen (matplotlib's Agg canvas); no display is needed and pyplot's state is not touched.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from warpcloth.outputs import PREVIEW_SUFFIXES, check_frames, check_triangles, prepare_output_path

__all__ = ["PREVIEW_FRAMES", "check_preview_path", "preview_frame_indices", "write_preview"]

PREVIEW_FRAMES = {".gif": 36, ".mp4": 36, ".png": 9}
"""Frames drawn by default for each kind of file."""

CLOTH_COLOR = (0.85, 0.38, 0.18)
OBSTACLE_COLOR = (0.55, 0.58, 0.65)
OBSTACLE_ALPHA = 0.45
MAX_ASPECT = 4.0
"""The drawn box's longest side is at most this many times its middle one: a long fall or a high throw is squeezed
along that axis, and the picture says so ("z not to scale"), instead of being drawn as a thin column."""
_LIGHT = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
_MIN_GIF_FRAME_MS = 20  # browsers play a GIF frame shorter than 20 ms at 100 ms


def _ffmpeg_available() -> bool:
    from matplotlib import animation

    return animation.writers.is_available("ffmpeg")


def check_preview_path(path: str | os.PathLike, what: str = "write_preview: path") -> str:
    """Check a preview file name before any work (``warpcloth/outputs.py``'s rule; missing parent directories are
    created) and return its kind, the lower-case suffix.

    Raises:
        ValueError: naming ``what`` and the path: a suffix other than .gif, .mp4 or .png, an existing directory, or
            an .mp4 without ffmpeg.
    """
    p = prepare_output_path(path, what, PREVIEW_SUFFIXES)
    kind = p.suffix.lower()
    if kind == ".mp4" and not _ffmpeg_available():
        raise ValueError(f"{what} {str(path)!r}: writing MP4 needs ffmpeg on PATH, which was not found; "
                         "write a .gif or .png instead")
    return kind


def preview_frame_indices(frame_count: int, max_frames: int) -> np.ndarray:
    """The frames a preview draws: ``min(frame_count, max_frames)`` indices evenly spaced over
    ``[0, frame_count)``, the first and the last included, increasing and distinct."""
    n = min(frame_count, max_frames)
    if n == 1:
        return np.zeros(1, dtype=np.int64)
    return np.rint(np.linspace(0, frame_count - 1, n)).astype(np.int64)


def _checked(triangles, frames, fps, obstacles, max_frames, kind):
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"write_preview: fps must be a finite number > 0, got {fps!r}")
    if max_frames is None:
        max_frames = PREVIEW_FRAMES[kind]
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 1:
        raise ValueError(f"write_preview: max_frames must be an integer >= 1, got {max_frames!r}")
    frames = check_frames(frames, "write_preview")
    shape = frames[0].shape
    tris = check_triangles(triangles, shape[0], "write_preview cloth")
    checked = []
    for k, obstacle in enumerate(obstacles):
        if len(obstacle) != 3:
            raise ValueError(f"write_preview: obstacle {k} must be (name, vertices, triangles)")
        name, verts, otris = obstacle
        verts = np.asarray(verts, dtype=np.float64)
        if verts.ndim not in (2, 3) or verts.shape[-1] != 3:
            raise ValueError(
                f"write_preview: obstacle {name!r} vertices must have shape (M, 3) or (F, M, 3), got {verts.shape}")
        if verts.ndim == 3 and verts.shape[0] != len(frames):
            raise ValueError(f"write_preview: obstacle {name!r} has {verts.shape[0]} frames of vertices, the cloth "
                             f"has {len(frames)}; time-sampled obstacles need one per cloth frame")
        if not np.all(np.isfinite(verts)):
            raise ValueError(f"write_preview: obstacle {name!r} has non-finite vertices")
        checked.append((verts, check_triangles(otris, verts.shape[-2], f"write_preview obstacle {name!r}")))
    return tris, frames, checked, int(max_frames)


def _shade(polys: np.ndarray, color, alpha: float) -> np.ndarray:
    """RGBA per triangle (T, 3, 3): the base colour lit by a fixed light from either side (cloth is thin)."""
    n = np.cross(polys[:, 1] - polys[:, 0], polys[:, 2] - polys[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    light = 0.35 + 0.65 * np.abs(n @ _LIGHT)
    rgba = np.empty((len(polys), 4))
    rgba[:, :3] = np.clip(np.outer(light, color), 0.0, 1.0)
    rgba[:, 3] = alpha
    return rgba


class _Scene:
    """The triangles of one frame, and the box every frame fits in."""

    def __init__(self, tris, frames, obstacles, indices):
        self.tris, self.frames, self.obstacles = tris, frames, obstacles
        points = [frames[i] for i in indices]
        points += [v if v.ndim == 2 else v[indices].reshape(-1, 3) for v, _ in obstacles]
        points = np.concatenate(points)
        lo, hi = points.min(axis=0), points.max(axis=0)
        extent = hi - lo
        # a flat side still gets a depth, from the middle extent (the longest would pad a long fall's width by metres)
        pad = np.maximum(0.05 * extent, 0.02 * max(float(np.sort(extent)[1]), 1e-3))
        self.lo, self.hi = lo - pad, hi + pad
        box = self.hi - self.lo
        self.aspect = np.minimum(box, MAX_ASPECT * np.sort(box)[1])
        self.squeezed = [axis for axis, a, b in zip("xyz", self.aspect, box) if a < b]
        """The axes drawn shorter than their length in metres (MAX_ASPECT)."""

    def polys(self, i: int):
        cloth = self.frames[i][self.tris]
        polys, colors = [cloth], [_shade(cloth, CLOTH_COLOR, 1.0)]
        for verts, otris in self.obstacles:
            p = (verts if verts.ndim == 2 else verts[i])[otris]
            polys.append(p)
            colors.append(_shade(p, OBSTACLE_COLOR, OBSTACLE_ALPHA))
        return np.concatenate(polys), np.concatenate(colors)

    def axes(self, fig, *args, view):
        ax = fig.add_subplot(*args, projection="3d")
        ax.set_xlim(self.lo[0], self.hi[0])
        ax.set_ylim(self.lo[1], self.hi[1])
        ax.set_zlim(self.lo[2], self.hi[2])
        ax.set_box_aspect(self.aspect, zoom=0.9)  # metres are metres (but MAX_ASPECT); room for the labels
        ax.view_init(elev=view[0], azim=view[1])
        ax.set_xlabel("x [m]", fontsize=7)
        ax.set_ylabel("y [m]", fontsize=7)
        ax.set_zlabel("z [m]", fontsize=7)
        ax.tick_params(labelsize=6, pad=0)
        return ax

    def draw(self, ax, i: int, collection=None):
        """Draw frame ``i`` into ``ax`` (one collection: its triangles are depth-sorted together)."""
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        if collection is not None:
            collection.remove()
        polys, colors = self.polys(i)
        collection = Poly3DCollection(polys, facecolors=colors, edgecolors=(0.0, 0.0, 0.0, 0.12), linewidths=0.2)
        ax.add_collection3d(collection)
        return collection


def write_preview(
    path: str | os.PathLike,
    *,
    triangles: np.ndarray,
    frames: Sequence[np.ndarray] | np.ndarray,
    fps: float,
    obstacles: Sequence[tuple[str, np.ndarray, np.ndarray]] = (),
    max_frames: int | None = None,
    title: str | None = None,
    view: tuple[float, float] = (20.0, -60.0),
    size: float = 4.0,
    dpi: int = 100,
) -> np.ndarray:
    """Draws a cloth trajectory and its obstacles with matplotlib: an animated GIF, an MP4 or a PNG contact sheet.

    Takes what :func:`warpcloth.usd.write_usd` takes, so one trajectory goes to both. The axes are fixed (z up,
    equal scale on every axis) to the box that holds the cloth and the obstacles in every drawn frame; where that box
    is more than :data:`MAX_ASPECT` times as long as it is wide, its long axis is squeezed and the title says so.

    Args:
        path: Output file, ``.gif``, ``.mp4`` (needs ffmpeg) or ``.png``; overwritten if it exists.
        triangles: Cloth vertex indices, shape (T, 3).
        frames: Cloth positions [m] per frame: a sequence of (N, 3) arrays or an (F, N, 3) array.
        fps: Frames per second of ``frames`` (> 0); for one frame per step, ``1 / dt``. Sets the times shown and
            the animation's speed (real time).
        obstacles: ``(name, vertices, triangles (K, 3))`` per obstacle, vertices (M, 3) (static) or (F, M, 3) (one
            per cloth frame), as :func:`warpcloth.obstacles.obstacle_meshes_numpy` builds them.
        max_frames: Most frames drawn (evenly spaced, first and last included, see
            :func:`preview_frame_indices`); default :data:`PREVIEW_FRAMES` of the kind (36 animated, 9 on a sheet).
        title: Text above the picture (e.g. the scene's name); each frame's time follows it.
        view: Camera elevation and azimuth [degrees] (matplotlib's ``view_init``).
        size: Width and height of one frame [inches]; with ``dpi``, ``size * dpi`` pixels.
        dpi: Pixels per inch.

    Returns:
        The indices of the frames drawn, shape (min(F, max_frames),).

    Raises:
        ValueError: naming what is wrong: the path (suffix, a directory, an .mp4 without ffmpeg), ``fps``,
            ``max_frames``, no frames, frames of different shapes, a non-finite position (naming frame and vertex),
            a triangle index out of range, obstacle vertices of the wrong shape or frame count.
    """
    kind = check_preview_path(path)
    tris, frames, checked, max_frames = _checked(triangles, frames, fps, obstacles, max_frames, kind)
    indices = preview_frame_indices(len(frames), max_frames)
    scene = _Scene(tris, frames, checked, indices)
    if scene.squeezed:  # say where metres are not metres
        title = f"{title or ''} ({', '.join(scene.squeezed)} not to scale)".strip()
    prefix = f"{title}: " if title else ""

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if kind == ".png":
        cols = math.ceil(math.sqrt(len(indices)))
        rows = math.ceil(len(indices) / cols)
        fig = Figure(figsize=(size * cols, size * rows + (0.3 if title else 0.0)), dpi=dpi)
        FigureCanvasAgg(fig)
        for k, i in enumerate(indices):
            ax = scene.axes(fig, rows, cols, k + 1, view=view)
            scene.draw(ax, i)
            ax.set_title(f"t = {i / fps:.3g} s", fontsize=9)
        if title:
            fig.suptitle(title, fontsize=11)
        fig.subplots_adjust(left=0.02, right=0.96, bottom=0.03, top=0.92 if title else 0.96, wspace=0.1, hspace=0.15)
        fig.savefig(os.fspath(path), dpi=dpi)
        return indices

    fig = Figure(figsize=(size, size), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = scene.axes(fig, view=view)
    fig.subplots_adjust(left=0.0, right=0.95, bottom=0.04, top=0.93)
    heading = ax.set_title("", fontsize=9)
    stride = (indices[-1] - indices[0]) / max(len(indices) - 1, 1) if len(indices) > 1 else 1.0
    playback_fps = fps / stride  # real time
    collection = None

    def render(i):
        nonlocal collection
        collection = scene.draw(ax, i, collection)
        heading.set_text(f"{prefix}t = {i / fps:.3g} s")

    if kind == ".gif":
        from PIL import Image

        images = []
        for i in indices:
            render(i)
            canvas.draw()
            images.append(Image.fromarray(np.asarray(canvas.buffer_rgba())[..., :3].copy()))
        duration = max(_MIN_GIF_FRAME_MS, round(1000.0 / playback_fps))
        images[0].save(os.fspath(path), save_all=True, append_images=images[1:], duration=duration, loop=0)
    else:  # .mp4, ffmpeg checked above
        from matplotlib.animation import FFMpegWriter

        writer = FFMpegWriter(fps=min(max(playback_fps, 1.0), 60.0), codec="libx264",
                              extra_args=["-pix_fmt", "yuv420p", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2"])
        with writer.saving(fig, os.fspath(path), dpi):
            for i in indices:
                render(i)
                writer.grab_frame()
    return indices
