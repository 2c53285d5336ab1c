"""Pictures of a simulation without a USD viewer: the cloth and its obstacles ray cast with Warp (each pixel shows
the nearest surface along its ray), shaded, with shadows, from one fixed camera; written as a ``.gif`` animation at
the simulation's speed, an ``.mp4`` video (needs ``ffmpeg``) or a ``.png`` contact sheet of panels with their times.
Drawn off screen (matplotlib's Agg canvas writes the titles), without touching pyplot's state. The cloth and
closed obstacles are opaque; an open obstacle (a plate, a basket, a target cloth) is translucent.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np
import warp as wp

from warpcloth.kernels.render import ray_cast
from warpcloth.outputs import PREVIEW_SUFFIXES, check_frames, check_geometry, prepare_output_path

__all__ = ["PREVIEW_FRAMES", "Camera", "check_preview_path", "preview_frame_indices", "render_frame", "write_preview"]

PREVIEW_FRAMES = {".gif": 36, ".mp4": 36, ".png": 9}
"""Frames drawn by default for each kind of file."""

CLOTH_COLOR = (0.85, 0.38, 0.18)  # the cloth's front, the side its triangles' winding faces
CLOTH_BACK_COLOR = (0.93, 0.74, 0.38)
OBSTACLE_COLORS = ((0.50, 0.58, 0.72), (0.62, 0.64, 0.60), (0.56, 0.66, 0.58))  # obstacle k: k % 3
OPEN_ALPHA = 0.55  # opacity of an obstacle that is an open surface (a plate, a basket, a target cloth)
BACKGROUND = ((0.97, 0.97, 0.98), (0.84, 0.86, 0.89))  # top and bottom of a vertical gradient
MAX_ASPECT = 4.0
"""The framed box's longest side in multiples of its middle one: a longer axis is squeezed (the title says so)."""
_HALF_FOV = math.radians(10.0)
_MIN_GIF_FRAME_MS = 20  # browsers play a GIF frame shorter than 20 ms at 100 ms


def _corner_normals(points: np.ndarray, tris: np.ndarray, crease: float = 0.7) -> np.ndarray:
    # per corner: the vertex's area-weighted normal within the crease angle of the face's, else the face's
    face = np.cross(points[tris[:, 1]] - points[tris[:, 0]], points[tris[:, 2]] - points[tris[:, 0]])
    vertex = np.stack([np.bincount(tris.ravel(), np.repeat(face[:, k], 3), minlength=len(points))
                       for k in range(3)], axis=1)
    vertex /= np.maximum(np.linalg.norm(vertex, axis=1, keepdims=True), 1e-30)
    face /= np.maximum(np.linalg.norm(face, axis=1, keepdims=True), 1e-30)
    corner = vertex[tris]
    smooth = np.einsum("tkc,tc->tk", corner, face) > crease
    return np.where(smooth[..., None], corner, face[:, None, :]).reshape(-1, 3)


def _closed(tris: np.ndarray) -> bool:
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    return len(tris) > 0 and bool(np.all(np.unique(edges, axis=0, return_counts=True)[1] == 2))


class Camera:
    """A pinhole camera at ``eye`` [m] looking along the unit vector ``forward``, ``right`` and ``up`` (unit) spanning
    its image; ``window`` is ``(left, right, bottom, top)`` of the ``width`` x ``height`` pixel image on the plane one
    unit ahead of the eye."""

    def __init__(self, eye, forward, right, up, window, width: int, height: int):
        self.eye, self.forward = np.asarray(eye, dtype=np.float64), np.asarray(forward, dtype=np.float64)
        self.right, self.up = np.asarray(right, dtype=np.float64), np.asarray(up, dtype=np.float64)
        self.window = tuple(float(v) for v in window)
        self.width, self.height = int(width), int(height)

    @classmethod
    def framing(cls, points, width: int, height: int, view: tuple[float, float] = (20.0, -60.0),
                margin: float = 0.04) -> Camera:
        """The camera at ``view`` (elevation and azimuth [degrees], matplotlib's ``view_init``: azimuth 0 looks
        along -x, elevation 90 straight down) whose picture holds every point of ``points`` (P, 3) [m], with
        ``margin`` (a fraction of the picture) left around them."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        elev, azim = np.radians(view)
        back = np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)])
        forward = -back
        right = np.cross(forward, [0.0, 0.0, 1.0])
        if np.linalg.norm(right) < 1e-9:  # straight down or up: keep azimuth's direction as the image's up
            right = np.cross(forward, [-np.cos(azim), -np.sin(azim), 0.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        lo, hi = points.min(axis=0), points.max(axis=0)
        centre, size = 0.5 * (lo + hi), max(float(np.linalg.norm(hi - lo)), 1e-6)
        rel = points - centre
        x, y, z = rel @ right, rel @ up, rel @ forward
        tan = math.tan(_HALF_FOV)
        distance = max(float(np.max(np.maximum(np.abs(x), np.abs(y)) / tan - z)), float(np.max(-z)) + 0.1 * size)
        u, v = x / (distance + z), y / (distance + z)  # on the plane one unit ahead
        aspect = width / height
        half_w = max(np.ptp(u), np.ptp(v) * aspect, 1e-6) / (2.0 * (1.0 - 2.0 * margin))
        mid_u, mid_v = 0.5 * (u.min() + u.max()), 0.5 * (v.min() + v.max())
        window = (mid_u - half_w, mid_u + half_w, mid_v - half_w / aspect, mid_v + half_w / aspect)
        return cls(centre - distance * forward, forward, right, up, window, width, height)

    def pixel(self, points) -> np.ndarray:
        """Where points (..., 3) [m] in front of the camera land: (row, column) in pixels, shape (..., 2); pixel
        ``(i, j)`` covers rows ``[i, i + 1)`` and columns ``[j, j + 1)``."""
        rel = np.asarray(points, dtype=np.float64) - self.eye
        depth = rel @ self.forward
        u, v = (rel @ self.right) / depth, (rel @ self.up) / depth
        left, right, bottom, top = self.window
        return np.stack([(top - v) / (top - bottom) * self.height, (u - left) / (right - left) * self.width], axis=-1)

    def _light(self) -> np.ndarray:
        # the unit direction towards the lamp: above, behind and left of the camera
        d = -0.5 * self.forward - 0.5 * self.right + np.array([0.0, 0.0, 0.6])
        return d / np.linalg.norm(d)


class _Renderer:
    # one wp.Mesh of the cloth's and the obstacles' triangles, refit for each frame

    def __init__(self, tris, vertex_count, obstacles, device=None):
        self.device = wp.get_device(device)
        parts, offset = [tris], vertex_count
        objects = [np.zeros(len(tris), dtype=np.int32)]
        for k, (verts, otris) in enumerate(obstacles):
            parts.append(otris + offset)
            objects.append(np.full(len(otris), k + 1, dtype=np.int32))
            offset += verts.shape[-2]
        self.tris = np.concatenate(parts).astype(np.int32)
        self.obstacles = obstacles
        self.mesh = None
        if len(self.tris):
            self.points = wp.zeros(offset, dtype=wp.vec3, device=self.device)
            self.mesh = wp.Mesh(points=self.points, indices=wp.array(self.tris.ravel(), dtype=wp.int32,
                                                                     device=self.device))
        self.face_object = wp.array(np.concatenate(objects), dtype=wp.int32, device=self.device)
        colors = [CLOTH_BACK_COLOR, CLOTH_COLOR] + [OBSTACLE_COLORS[k % len(OBSTACLE_COLORS)]
                                                    for k in range(len(obstacles))]
        self.palette = wp.array(np.array(colors), dtype=wp.vec3, device=self.device)
        alpha = [1.0] + [1.0 if _closed(otris) else OPEN_ALPHA for _, otris in obstacles]
        self.alpha = wp.array(np.array(alpha), dtype=float, device=self.device)

    def points_at(self, cloth: np.ndarray, i: int) -> np.ndarray:
        return np.concatenate([cloth] + [v if v.ndim == 2 else v[i] for v, _ in self.obstacles])

    def render(self, points: np.ndarray, camera: Camera, samples: int = 1) -> tuple[np.ndarray, np.ndarray]:
        w, h = camera.width * samples, camera.height * samples
        rows = np.linspace(BACKGROUND[0], BACKGROUND[1], num=h)
        image = np.broadcast_to(rows[:, None, :], (h, w, 3)).astype(np.float32)
        ids = np.full((h, w), -1, dtype=np.int32)
        if self.mesh is not None:
            self.points.assign(points.astype(np.float32))
            self.mesh.refit()
            rgb = wp.array(image, dtype=wp.vec3, device=self.device)
            id_map = wp.array(ids, dtype=wp.int32, device=self.device)
            normals = wp.array(_corner_normals(points, self.tris), dtype=wp.vec3, device=self.device)
            eps = 1e-5 * max(float(np.ptp(points, axis=0).max()), 1e-3)
            wp.launch(ray_cast, dim=(h, w), device=self.device, record_tape=False,
                      inputs=[self.mesh.id, wp.vec3(camera.eye), wp.vec3(camera.forward), wp.vec3(camera.right),
                              wp.vec3(camera.up), wp.vec4(camera.window), wp.vec3(camera._light()), eps,
                              self.face_object, normals, self.palette, self.alpha],
                      outputs=[rgb, id_map])
            image, ids = rgb.numpy(), id_map.numpy()
        if samples > 1:
            image = image.reshape(camera.height, samples, camera.width, samples, 3).mean(axis=(1, 3))
            ids = ids[samples // 2::samples, samples // 2::samples]
        return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8), ids


def render_frame(triangles: np.ndarray, positions: np.ndarray,
                 obstacles: Sequence[tuple[str, np.ndarray, np.ndarray]] = (), *, width: int = 400,
                 height: int = 400, view: tuple[float, float] = (20.0, -60.0), camera: Camera | None = None,
                 samples: int = 1, device=None) -> tuple[np.ndarray, np.ndarray]:
    """Ray cast one frame: per pixel, the nearest of the cloth's and the obstacles' surfaces along its ray.

    Args:
        triangles: Cloth vertex indices, shape (T, 3).
        positions: Cloth positions [m], shape (N, 3).
        obstacles: ``(name, vertices (M, 3), triangles (K, 3))`` per obstacle.
        width, height: Image size [pixels] when ``camera`` is None.
        view: Camera elevation and azimuth [degrees] for :meth:`Camera.framing` around the cloth and the obstacles.
        camera: The camera to use instead (its own size).
        samples: Rays per pixel along each side, averaged (anti-aliasing).
        device: Warp device that casts the rays; default Warp's default device.

    Returns:
        ``(rgb, ids)``: uint8 (height, width, 3), and int32 (height, width) saying what each pixel shows: -1
        nothing, 0 the cloth, ``k + 1`` obstacle ``k``.

    Raises:
        ValueError: naming the bad position, triangle, obstacle (vertices not (M, 3)) or ``samples``.
    """
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise ValueError(f"render_frame: samples must be an integer >= 1, got {samples!r}")
    frames = check_frames([positions], "render_frame")
    tris, frames, checked = check_geometry(triangles, frames, obstacles, "render_frame", static=True)
    renderer = _Renderer(tris, len(frames[0]), checked, device)
    points = renderer.points_at(frames[0], 0)
    if camera is None:
        camera = Camera.framing(points, width, height, view)
    return renderer.render(points, camera, int(samples))


def _ffmpeg_available() -> bool:
    from matplotlib import animation

    return animation.writers.is_available("ffmpeg")


def check_preview_path(path: str | os.PathLike, what: str = "write_preview: path") -> str:
    """Check a preview path before any work (``warpcloth/outputs.py``'s rule) and return its kind, the lower-case
    suffix; ValueError naming ``what`` and the path for a suffix not .gif, .mp4 or .png, a directory, or an .mp4
    without ffmpeg."""
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
    tris, frames, checked = check_geometry(triangles, frames, obstacles, "write_preview")
    return tris, frames, checked, int(max_frames)


POINT_COLOUR = (200, 30, 30)
"""The colour (RGB) of the recorded points :func:`write_preview` draws over the cloth."""


def _checked_points(points, frame_count: int, what: str):
    # one (P, 3) array or None per frame; ValueError naming the frame and point
    if points is None:
        return None
    points = list(points)
    if len(points) != frame_count:
        raise ValueError(f"{what}: points has {len(points)} frames, the cloth {frame_count}")
    out = []
    for k, p in enumerate(points):
        if p is None:
            out.append(None)
            continue
        p = np.asarray(p, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"{what}: points of frame {k} must be (P, 3) or None, got shape {p.shape}")
        bad = np.flatnonzero(~np.isfinite(p).all(axis=1))
        if bad.size:
            raise ValueError(f"{what}: points of frame {k}, point {bad[0]}: not finite")
        out.append(p)
    return out


class _Scene:
    # the drawn frames, squeezed to MAX_ASPECT, and one camera for all of them

    def __init__(self, tris, frames, obstacles, indices, dots=None):
        self.frames, self.indices, self.dots = frames, indices, dots  # dots: drawn over, not framed
        self.renderer = _Renderer(tris, frames[0].shape[0], obstacles)
        points = [frames[i] for i in indices]
        points += [v if v.ndim == 2 else v[indices].reshape(-1, 3) for v, _ in obstacles]
        points = np.concatenate(points)
        lo, hi = points.min(axis=0), points.max(axis=0)
        extent = hi - lo
        # a flat side still gets a depth, from the middle extent (the longest would pad a long fall's width by metres)
        pad = np.maximum(0.05 * extent, 0.02 * max(float(np.sort(extent)[1]), 1e-3))
        box = extent + 2.0 * pad
        aspect = np.minimum(box, MAX_ASPECT * np.sort(box)[1])
        self.squeezed = [axis for axis, a, b in zip("xyz", aspect, box) if a < b]  # drawn shorter than in metres
        self.centre, self.scale = 0.5 * (lo + hi), aspect / box
        self.framed, self.cameras = self._squeeze(points), {}

    def _squeeze(self, points):
        return self.centre + (points - self.centre) * self.scale

    def image(self, i: int, width: int, height: int, view, samples: int = 1) -> np.ndarray:
        key = (width, height, tuple(view))
        if key not in self.cameras:
            self.cameras[key] = Camera.framing(self.framed, width, height, view)
        camera = self.cameras[key]
        points = self._squeeze(self.renderer.points_at(self.frames[i], i))
        rgb = self.renderer.render(points, camera, samples)[0]
        if self.dots is not None and self.dots[i] is not None:  # drawn over the cloth, 2x2 pixels each
            rgb = rgb.copy()
            dots = self._squeeze(self.dots[i])
            dots = dots[(dots - camera.eye) @ camera.forward > 0.0]  # in front of the camera
            rows, cols = np.floor(camera.pixel(dots)).astype(int).T
            for dr in (0, 1):
                for dc in (0, 1):
                    r, c = rows + dr, cols + dc
                    inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
                    rgb[r[inside], c[inside]] = POINT_COLOUR
        return rgb


def _fontsize(text: str, width: int, dpi: int, largest: float) -> float:
    # points at which ``text`` fits ``width`` pixels (a character about 0.6 of the size wide)
    return max(4.0, min(largest, 0.95 * width * 72.0 / (0.6 * max(len(text), 1) * dpi)))


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
    points: Sequence[np.ndarray | None] | None = None,
) -> np.ndarray:
    """Draws a cloth trajectory and its obstacles (:func:`render_frame`): an animated GIF, an MP4 or a PNG sheet.

    Takes what :func:`warpcloth.usd.write_usd` takes. One camera frames every drawn frame, in metres on every axis
    but one squeezed to :data:`MAX_ASPECT`.

    Args:
        path: Output file, ``.gif``, ``.mp4`` (needs ffmpeg) or ``.png``; overwritten if it exists.
        triangles: Cloth vertex indices, shape (T, 3).
        frames: Cloth positions [m] per frame: a sequence of (N, 3) arrays or an (F, N, 3) array.
        fps: Frames per second of ``frames`` (> 0), e.g. ``1 / dt``: the times shown and the animation's speed.
        obstacles: ``(name, vertices, triangles (K, 3))`` per obstacle, vertices (M, 3) (static) or (F, M, 3) (one
            per cloth frame), as :func:`warpcloth.obstacles.obstacle_meshes_numpy` builds them.
        max_frames: Most frames drawn (:func:`preview_frame_indices`); default :data:`PREVIEW_FRAMES` of the kind.
        title: Text above the picture (e.g. the scene's name); each frame's time follows it.
        view: Camera elevation and azimuth [degrees] (:meth:`Camera.framing`).
        size: Width and height of one frame [inches]; ``size * dpi`` pixels with ``dpi`` pixels per inch.
        points: Per cloth frame, recorded points (P, 3) [m] or None, drawn as dots of :data:`POINT_COLOUR` over the
            cloth (a point cloud against the cloth fitted to it); the camera frames the cloth and obstacles only, so
            far points (a background) fall outside the picture.

    Returns:
        The indices of the frames drawn, shape (min(F, max_frames),).

    Raises:
        ValueError: naming what is wrong: the path (:func:`check_preview_path`), ``fps``, ``max_frames``, no
            frames, frames of different shapes, a non-finite position, a triangle index, obstacle vertices, points
            of another count of frames, shape or a non-finite point.
    """
    kind = check_preview_path(path)
    tris, frames, checked, max_frames = _checked(triangles, frames, fps, obstacles, max_frames, kind)
    dots = _checked_points(points, len(frames), "write_preview")
    indices = preview_frame_indices(len(frames), max_frames)
    scene = _Scene(tris, frames, checked, indices, dots)
    if scene.squeezed:  # say where metres are not metres
        title = f"{title or ''} ({', '.join(scene.squeezed)} not to scale)".strip()
    prefix = f"{title}: " if title else ""

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    side = round(size * dpi)
    band = min(round(0.28 * dpi), side // 4)  # a line of 9-point text above each picture
    if kind == ".png":
        cols = math.ceil(math.sqrt(len(indices)))
        rows = math.ceil(len(indices) / cols)
        top = round(0.3 * dpi) if title else 0
        fig = Figure(figsize=(size * cols, size * rows + top / dpi), dpi=dpi)
        FigureCanvasAgg(fig)
        height = round(fig.get_figheight() * dpi)
        for k, i in enumerate(indices):
            x0, y0 = (k % cols) * side, top + (k // cols) * side  # the panel's top left, from the figure's top
            fig.figimage(scene.image(i, side, side - band, view), xo=x0, yo=height - y0 - side)
            fig.text((x0 + 0.5 * side) / (side * cols), 1.0 - (y0 + 0.5 * band) / height, f"t = {i / fps:.3g} s",
                     ha="center", va="center", fontsize=9)
        if title:
            fig.text(0.5, 1.0 - 0.5 * top / height, title, ha="center", va="center",
                     fontsize=_fontsize(title, side * cols, dpi, 11))
        fig.savefig(os.fspath(path), dpi=dpi)
        return indices

    fig = Figure(figsize=(size, size), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    picture = fig.figimage(np.zeros((side - band, side, 3), dtype=np.uint8), xo=0, yo=0)
    heading = fig.text(0.5, 1.0 - 0.5 * band / side, "", ha="center", va="center",
                       fontsize=_fontsize(f"{prefix}t = {indices[-1] / fps:.3g} s", side, dpi, 9))
    stride = (indices[-1] - indices[0]) / max(len(indices) - 1, 1) if len(indices) > 1 else 1.0
    playback_fps = fps / stride  # real time

    def render(i):
        picture.set_data(scene.image(i, side, side - band, view))
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
