"""The seed's scenes (Liang, Lin and Koltun 2019) as models built in code, the tasks owning their time steps: the
hanging cloth in the wind, other motions of a fabric (a shake, a drop, a tensile test) and the throw's basket."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import warp as wp

import warpcloth as wc
from warpcloth.builder import DEFAULT_HANDLE_STIFFNESS

__all__ = [
    "DEFAULT_HANDLE_STIFFNESS",
    "DROP_OFFSET",
    "GRAVITY",
    "GRID_RES",
    "GRID_TO_YZ",
    "SEED_HANDLES",
    "THICKEN",
    "WIND",
    "basket_scene",
    "cloth_dropped_on_sphere",
    "hanging_cloth",
    "hanging_cloth_builder",
    "shaken_cloth",
    "stretched_cloth",
]

GRAVITY = (0.0, 0.0, -9.8)
"""Gravity [m/s^2] of every seed demo."""
THICKEN = 2.0
"""ARCSim thicken of every seed demo."""

# -- the hanging cloth (material estimation) -------------------------------------------------------------------------
WIND = (5.0, 0.0, 0.0)
"""Wind velocity [m/s] of the seed's material-estimation scene (density 1, drag 0: ARCSim's defaults)."""
GRID_RES = 16
"""Cells per side of the hanging cloth made in code (the resolution of demo_wind.obj)."""
GRID_TO_YZ = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""Grid x -> world y, grid y -> world z: a vertical sheet in the YZ plane whose normal is +x, the wind's direction."""
SEED_HANDLES = (2, 3)
"""The handled vertices (top corners) of the seed's demo_wind.obj."""


def hanging_cloth(material: wc.Material, *, res: int = GRID_RES, mesh_path: str | Path | None = None,
                  handles: Sequence[int] | None = None, lagged_normals: bool = False, self_collision: bool = False,
                  device=None, dtype=wp.float32, requires_grad: bool = True) -> wc.Model:
    """The seed's material-estimation scene: a 1 m cloth at rest held at its top corners by soft handles, under gravity
    and a 5 m/s wind along +x; a flat ``res`` x ``res``-cell square in the x = 0 plane, or the shape of ``mesh_path``
    (an OBJ with ``vt`` material coordinates, default handles ``SEED_HANDLES``, velocities ignored). ``lagged_normals``:
    ARCSim's one-step lag of the wind's face normals; ``self_collision``: cloth-cloth collisions. Why at rest:
    docs/decisions.md, "The hanging cloth starts at rest"."""
    return hanging_cloth_builder(material, res=res, mesh_path=mesh_path, handles=handles,
                                 lagged_normals=lagged_normals, self_collision=self_collision).finalize(
        device, requires_grad=requires_grad, dtype=dtype)


def hanging_cloth_builder(material: wc.Material, *, res: int = GRID_RES, mesh_path: str | Path | None = None,
                          handles: Sequence[int] | None = None, lagged_normals: bool = False,
                          self_collision: bool = False) -> wc.ModelBuilder:
    """The ModelBuilder of :func:`hanging_cloth` (same arguments), to batch worlds."""
    b = wc.ModelBuilder(gravity=GRAVITY)
    if mesh_path is None:
        b.add_cloth_grid((res, res), (1.0, 1.0), material=material, rot=GRID_TO_YZ, pos=(0.0, -0.5, -0.5))
        top = res * (res + 1)  # vertex (i, j) = j * (res + 1) + i; top row j = res
        handles = (top, top + res) if handles is None else handles
    else:
        b.add_cloth_obj(mesh_path, material=material, vel=(0.0, 0.0, 0.0))
        handles = SEED_HANDLES if handles is None else handles
    for p in handles:
        b.add_handle(int(p), stiffness=DEFAULT_HANDLE_STIFFNESS)
    b.set_wind(WIND, density=1.0, drag=0.0, lagged_normals=lagged_normals)
    if self_collision:
        b.set_collision(self_collision=True)
    return b


# -- other motions of a fabric (material estimation: what one motion leaves undetermined) ---------------------------
DROP_OFFSET = (0.07, 0.04)
"""Where :func:`cloth_dropped_on_sphere`'s cloth centre lands off the sphere's top [m]. Why: docs/decisions.md,
"The drop lands off the sphere's top"."""
def cloth_dropped_on_sphere(material: wc.Material, *, res: int = GRID_RES, device=None, dtype=wp.float32,
                            requires_grad: bool = True) -> wc.Model:
    """A flat 1 m square dropped from 10 cm onto a 0.3 m sphere (repulsion, friction), ``DROP_OFFSET`` off its top."""
    b = wc.ModelBuilder(gravity=GRAVITY)
    b.add_cloth_grid((res, res), (1.0, 1.0), material=material,
                     pos=(-0.5 + DROP_OFFSET[0], -0.5 + DROP_OFFSET[1], 0.4))
    b.add_obstacle_sphere(0.3)
    b.set_collision()
    return b.finalize(device, requires_grad=requires_grad, dtype=dtype)


SHAKE = ((0.0, (0.0, 0.0, 0.0)), (0.125, (0.15, 0.0, 0.0)), (0.375, (-0.15, 0.0, 0.0)), (0.625, (0.15, 0.0, 0.0)),
         (0.875, (-0.15, 0.0, 0.0)), (1.0, (0.0, 0.0, 0.0)))
"""The handles' offsets of :func:`shaken_cloth` [(s, m)]: 15 cm across the sheet and back, twice a second."""


def shaken_cloth(material: wc.Material, *, res: int = GRID_RES, device=None, dtype=wp.float32,
                 requires_grad: bool = True) -> wc.Model:
    """The hanging cloth of :func:`hanging_cloth` without wind, its two handles shaken across the sheet (``SHAKE``)."""
    b = wc.ModelBuilder(gravity=GRAVITY)
    b.add_cloth_grid((res, res), (1.0, 1.0), material=material, rot=GRID_TO_YZ, pos=(0.0, -0.5, -0.5))
    top = res * (res + 1)
    for p in (top, top + res):
        b.add_handle(p, stiffness=DEFAULT_HANDLE_STIFFNESS, motion=list(SHAKE))
    return b.finalize(device, requires_grad=requires_grad, dtype=dtype)


STRETCH = 1.2
"""Peak stretch of :func:`stretched_cloth`, past the 7/6 at which the stretching table's rows 1-5 are sampled."""
STRETCH_ANGLES = (0.0, 22.5, 45.0, 67.5, 90.0)
"""Directions [degrees from the warp] of :func:`stretched_cloth`'s pulls: the five angles of the table's rows 1-5."""
STRETCH_PERIOD = 0.2
"""Seconds per pull of :func:`stretched_cloth` (out to ``STRETCH`` in half of it, back to rest in the other half)."""
STRETCH_HANDLE_STIFFNESS = 50.0
"""Stiffness [N/m] of :func:`stretched_cloth`'s border handles: soft, so the sheet's shape depends on the fabric."""


def stretched_cloth(material: wc.Material, *, res: int = GRID_RES, device=None, dtype=wp.float32,
                    requires_grad: bool = True) -> wc.Model:
    """A tensile test under gravity: a flat, horizontal 1 m square whose border handles stretch it uniaxially to
    ``STRETCH`` and back along each of ``STRETCH_ANGLES`` in turn, ``STRETCH_PERIOD`` each."""
    b = wc.ModelBuilder(gravity=GRAVITY)
    b.add_cloth_grid((res, res), (1.0, 1.0), material=material, pos=(-0.5, -0.5, 0.0))
    n = res + 1
    times, maps = [0.0], [np.eye(3)]
    for k, angle in enumerate(STRETCH_ANGLES):
        d = np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle)), 0.0])
        times += [STRETCH_PERIOD * (k + 0.5), STRETCH_PERIOD * (k + 1)]
        maps += [np.eye(3) + (STRETCH - 1.0) * np.outer(d, d), np.eye(3)]
    for j in range(n):
        for i in range(n):
            if i in (0, res) or j in (0, res):
                rest = np.array([i / res - 0.5, j / res - 0.5, 0.0])  # from the sheet's centre
                offsets = [(t, tuple((A - np.eye(3)) @ rest)) for t, A in zip(times, maps)]
                b.add_handle(j * n + i, stiffness=STRETCH_HANDLE_STIFFNESS, motion=offsets)
    return b.finalize(device, requires_grad=requires_grad, dtype=dtype)


# -- the throw into a basket (motion control) ------------------------------------------------------------------------
def basket_scene(device=None, *, dtype=wp.float32, requires_grad: bool = True) -> wc.Model:
    """The embedded scene ``basket-throw``'s model: a 0.7 m gray-interlock cloth flat at z = 2 under gravity, the
    seed's basket (an open-top box 0.98 m wide centred at the origin) and the wall before it (``basket``, ``wall``)."""
    return wc.load_scene("basket-throw").finalize(device, requires_grad=requires_grad, dtype=dtype)
