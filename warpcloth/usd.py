"""Time-sampled USD output of cloth trajectories (viewable in usdview, Omniverse, Blender)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from warpcloth.outputs import USD_SUFFIXES, check_frames, check_triangles, prepare_output_path

__all__ = ["read_usd_points", "write_usd"]


def _import_pxr():
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, Vt
    except ImportError as exc:  # pragma: no cover - usd-core is a dependency
        raise ImportError("USD output needs the 'usd-core' package (pip install usd-core)") from exc
    return Gf, Sdf, Usd, UsdGeom, Vt


def _define_mesh(stage, UsdGeom, path: str, triangles: np.ndarray):
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateFaceVertexCountsAttr(np.full(len(triangles), 3, dtype=np.int32).tolist())
    mesh.CreateFaceVertexIndicesAttr(triangles.reshape(-1).tolist())
    # Cloth is thin: show both sides, and keep viewers from subdividing the triangles (USD's default is catmullClark).
    mesh.CreateDoubleSidedAttr(True)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    return mesh


def write_usd(
    path: str | os.PathLike,
    *,
    triangles: np.ndarray,
    frames: Sequence[np.ndarray] | np.ndarray,
    fps: float,
    obstacles: Sequence[tuple[str, np.ndarray, np.ndarray]] = (),
    up_axis: str = "Z",
    cloth_prim: str = "/World/Cloth",
) -> None:
    """Writes a cloth trajectory to ``path`` (.usd, .usda text, .usdc; overwritten, parents created) as a USD stage.

    ``frames``: cloth positions [m], (N, 3) arrays or an (F, N, 3) array, stored as float32 points of the mesh
    ``cloth_prim`` (vertex indices ``triangles`` (T, 3)) at time codes 0, 1, ..., ``fps`` (> 0) of them a second.
    ``obstacles``: ``(name, vertices [m], triangles (K, 3))`` each, vertices (M, 3) static or (F, M, 3) a frame
    (:func:`~warpcloth.obstacle_meshes_numpy` builds the list), written under ``/World/Obstacles/<name>``.
    ``up_axis``: ``"Z"`` (warpcloth's) or ``"Y"``; ``metersPerUnit`` is 1.

    Raises:
        ImportError: when ``pxr`` is missing.
        ValueError: for a bad path, frames (naming frame and vertex), index, ``fps``, ``up_axis``, prim path or
            obstacle name, or obstacle frames other than the cloth's."""
    Gf, Sdf, Usd, UsdGeom, Vt = _import_pxr()

    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"write_usd: fps must be a finite number > 0, got {fps!r}")
    axes = {"Z": UsdGeom.Tokens.z, "Y": UsdGeom.Tokens.y}
    if up_axis not in axes:
        raise ValueError(f"write_usd: up_axis must be 'Z' or 'Y', got {up_axis!r}")
    if not Sdf.Path.IsValidPathString(cloth_prim) or not Sdf.Path(cloth_prim).IsAbsolutePath():
        raise ValueError(f"write_usd: cloth_prim must be an absolute prim path, got {cloth_prim!r}")

    frame_list = check_frames(frames, "write_usd")
    shape = frame_list[0].shape
    tris = check_triangles(triangles, shape[0], "write_usd cloth")

    checked_obstacles = []
    seen: set[str] = set()
    for k, obstacle in enumerate(obstacles):
        if len(obstacle) != 3:
            raise ValueError(f"write_usd: obstacle {k} must be (name, vertices, triangles)")
        name, verts, otris = obstacle
        if not isinstance(name, str) or not Sdf.Path.IsValidIdentifier(name):
            raise ValueError(f"write_usd: obstacle {k} name {name!r} is not a valid USD identifier")
        if name in seen:
            raise ValueError(f"write_usd: obstacle name {name!r} is used twice")
        seen.add(name)
        verts = np.asarray(verts, dtype=np.float64)
        if verts.ndim not in (2, 3) or verts.shape[-1] != 3:
            raise ValueError(
                f"write_usd: obstacle {name!r} vertices must have shape (M, 3) or (F, M, 3), got {verts.shape}"
            )
        if verts.ndim == 3 and verts.shape[0] != len(frame_list):
            raise ValueError(
                f"write_usd: obstacle {name!r} has {verts.shape[0]} frames of vertices, the cloth has "
                f"{len(frame_list)}; time-sampled obstacles need one per cloth frame"
            )
        if not np.all(np.isfinite(verts)):
            raise ValueError(f"write_usd: obstacle {name!r} has non-finite vertices")
        checked_obstacles.append(
            (name, verts, check_triangles(otris, verts.shape[-2], f"write_usd obstacle {name!r}"))
        )

    path = prepare_output_path(path, "write_usd: path", USD_SUFFIXES)
    # Build in memory and export: Usd.Stage.CreateNew refuses a path whose layer is already open in this process.
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, axes[up_axis])
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(len(frame_list) - 1)
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())

    cloth = _define_mesh(stage, UsdGeom, cloth_prim, tris)
    points_attr = cloth.CreatePointsAttr()
    extent_attr = cloth.CreateExtentAttr()
    for k, f in enumerate(frame_list):
        pts = f.astype(np.float32)
        points_attr.Set(Vt.Vec3fArray.FromNumpy(pts), Usd.TimeCode(k))
        extent_attr.Set(Vt.Vec3fArray.FromNumpy(np.stack([pts.min(axis=0), pts.max(axis=0)])), Usd.TimeCode(k))

    if checked_obstacles:
        UsdGeom.Scope.Define(stage, "/World/Obstacles")
    for name, verts, otris in checked_obstacles:
        mesh = _define_mesh(stage, UsdGeom, f"/World/Obstacles/{name}", otris)
        if verts.ndim == 2:
            pts = verts.astype(np.float32)
            mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
            mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([pts.min(axis=0), pts.max(axis=0)])))
        else:
            o_points, o_extent = mesh.CreatePointsAttr(), mesh.CreateExtentAttr()
            for k, frame in enumerate(verts):
                pts = frame.astype(np.float32)
                o_points.Set(Vt.Vec3fArray.FromNumpy(pts), Usd.TimeCode(k))
                o_extent.Set(Vt.Vec3fArray.FromNumpy(np.stack([pts.min(axis=0), pts.max(axis=0)])), Usd.TimeCode(k))

    if not stage.GetRootLayer().Export(os.fspath(path)):
        raise OSError(f"write_usd: could not write {os.fspath(path)!r}")
    # A stage still open on this file elsewhere in the process would otherwise keep serving the old content.
    open_layer = Sdf.Layer.Find(os.fspath(path))
    if open_layer is not None:
        open_layer.Reload(force=True)


def read_usd_points(path: str | os.PathLike, prim: str = "/World/Cloth") -> np.ndarray:
    """The points [m] of mesh ``prim`` at every time sample (else its default value), shape (F, N, 3), float64;
    ValueError when the file cannot be opened or the prim has no points."""
    _, _, Usd, UsdGeom, _ = _import_pxr()
    stage = Usd.Stage.Open(os.fspath(path))
    if stage is None:
        raise ValueError(f"{path}: cannot open as a USD stage")
    p = stage.GetPrimAtPath(prim)
    if not p.IsValid():
        raise ValueError(f"{path}: no prim at {prim!r}")
    attr = UsdGeom.PointBased(p).GetPointsAttr()
    times = attr.GetTimeSamples()
    values = [attr.Get(Usd.TimeCode(t)) for t in times] if times else [attr.Get()]
    if not values or values[0] is None:
        raise ValueError(f"{path}: prim {prim!r} has no points")
    return np.stack([np.array(v, dtype=np.float64).reshape(-1, 3) for v in values])
