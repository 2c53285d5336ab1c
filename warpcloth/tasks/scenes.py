"""The seed's scenes (Liang, Lin and Koltun 2019), built once for the tasks, examples, benchmarks and command line.

* ``hanging_cloth``: material estimation (SPEC §5(b)), a 1 m cloth held at its two top corners by soft handles in a
  5 m/s wind, either a flat grid made in code or the seed's demo_wind.obj (or any OBJ with material coordinates).
* ``shaken_cloth``, ``cloth_dropped_on_sphere``, ``stretched_cloth``: other motions of a fabric, for fits to several
  motions at once and for predictions (a shake by the handles, a drop onto a sphere, a tensile test).
* ``basket_scene``: motion control (SPEC §5(c)), a 0.7 m cloth flat above the ground, the seed's basket and the wall
  in front of it (the embedded scene ``basket-throw``, whose ``[control]`` table is the task).

Time steps and horizons belong to the tasks (``warpcloth.tasks.estimation``, ``warpcloth.tasks.throw``).
"""

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
    """The seed's material-estimation scene: a 1 m cloth held at its two top corners by soft handles
    (``DEFAULT_HANDLE_STIFFNESS``, ARCSim's), gravity, a 5 m/s wind along +x, starting at rest.

    Without ``mesh_path`` the cloth is a flat ``res`` x ``res``-cell square made in code, hanging in the x = 0 plane
    (the seed's demo_wind.obj is the 16x16 grid already draped, top corners 0.8 m apart). With ``mesh_path`` (an OBJ
    with ``vt`` material coordinates, such as demo_wind.obj or frame 0 of a target sequence) the cloth starts in that
    shape, at rest: the seed's targets match a start from rest to 1e-6 m after one frame, not the ``nv`` velocities
    stored in demo_wind.obj (0.1 mm off).

    Self-collision is off by default: a cloth hanging in a steady wind barely touches itself (the seed's targets were
    made with it on, and with ARCSim's proximity repulsion and friction, which ``self_collision`` turns on).

    Args:
        material: The cloth's material (the seed's fabrics: ``wc.preset(name, thicken=THICKEN)``).
        res: Cells per side of the grid made in code; ignored with ``mesh_path``.
        mesh_path: An OBJ to start from instead of the flat grid.
        handles: The handled particles; default: the top corners of the grid, or ``SEED_HANDLES`` with
            ``mesh_path``.
        lagged_normals: Reproduce ARCSim's one-step lag of the wind's face normals.
        self_collision: Cloth-cloth collisions with ARCSim's repulsion and friction (``set_collision`` defaults).
        device: Warp device (default: Warp's default device).
        dtype: ``wp.float32`` or ``wp.float64``.
        requires_grad: Build the model's arrays with gradients.

    Returns:
        The finalized model (:func:`hanging_cloth_builder` gives its builder, to batch worlds).
    """
    return hanging_cloth_builder(material, res=res, mesh_path=mesh_path, handles=handles,
                                 lagged_normals=lagged_normals, self_collision=self_collision).finalize(
        device, requires_grad=requires_grad, dtype=dtype)


def hanging_cloth_builder(material: wc.Material, *, res: int = GRID_RES, mesh_path: str | Path | None = None,
                          handles: Sequence[int] | None = None, lagged_normals: bool = False,
                          self_collision: bool = False) -> wc.ModelBuilder:
    """The ModelBuilder of :func:`hanging_cloth` (same arguments), for a model of several worlds
    (``ModelBuilder.add_world``): a fabric library fitted in one batch (``estimation.estimate_materials``)."""
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
"""Where :func:`cloth_dropped_on_sphere`'s cloth centre lands off the sphere's top [m]. Dropped centred, the centre
particle lands on the top, where rounding decides which way it slides off: materials 1e-4 apart (relative) ended
2.5 cm apart after 100 steps and the loss jumped, so a fit to the drop stalled (README, Material estimation)."""
def cloth_dropped_on_sphere(material: wc.Material, *, res: int = GRID_RES, device=None, dtype=wp.float32,
                            requires_grad: bool = True) -> wc.Model:
    """A flat 1 m square of ``material`` dropped from 10 cm onto a 0.3 m sphere (repulsion and friction on), its
    centre ``DROP_OFFSET`` off the sphere's top."""
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
"""Peak stretch of :func:`stretched_cloth`'s border along each direction: principal stretch 1.2 is past the 7/6 at
which the stretching table's rows 1-5 are sampled (SPEC §1.2), so the motion reaches them."""
STRETCH_ANGLES = (0.0, 22.5, 45.0, 67.5, 90.0)
"""Directions [degrees from the warp] of :func:`stretched_cloth`'s pulls: the five angles of the table's rows 1-5."""
STRETCH_PERIOD = 0.2
"""Seconds per pull of :func:`stretched_cloth` (out to ``STRETCH`` in half of it, back to rest in the other half)."""
STRETCH_HANDLE_STIFFNESS = 50.0
"""Stiffness [N/m] of each of :func:`stretched_cloth`'s border handles. Soft on purpose: the handles are the test's
force gauge. As stiff as the default handles (1e3 N/m each, 64 of them) they would hold the border to the prescribed
stretch whatever the fabric, and a homogeneous sheet whose border is stretched affinely rests in the same shape for
any stiffness, so the motion would say little about the material."""


def stretched_cloth(material: wc.Material, *, res: int = GRID_RES, device=None, dtype=wp.float32,
                    requires_grad: bool = True) -> wc.Model:
    """A tensile test: a flat, horizontal 1 m square held by soft handles (``STRETCH_HANDLE_STIFFNESS``) on every
    border vertex, whose targets stretch the sheet uniaxially to ``STRETCH`` and back along each of
    ``STRETCH_ANGLES`` in turn (``STRETCH_PERIOD`` each: 1 s in all), under gravity.

    The seed's hanging cloth strains its sheet by about 1 %, so its motion barely depends on the stretching table's
    rows 1-5 (sampled at 1/6 strain) and a fit leaves them where it started (README, Material estimation); this
    motion reaches them in every direction the table samples.
    """
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
    """The seed's throw scene, the embedded scene ``basket-throw``: a 0.7 m gray-interlock cloth (8x8 cells,
    thicken 2) flat at z = 2 over x in [-3.7, -3], y in [0, 0.7]; the seed's basket (an open-top box 0.98 x 0.98 m
    centred at the origin, z in [-0.7, 0.7]) and the wall in front of it (a plate at x = -0.562); gravity; no wind,
    no handles.

    Args:
        device: Warp device (default: Warp's default device).
        dtype: ``wp.float32`` or ``wp.float64``.
        requires_grad: Build the model's arrays with gradients.

    Returns:
        The finalized model (obstacles ``basket`` and ``wall``).
    """
    return wc.load_scene("basket-throw").finalize(device, requires_grad=requires_grad, dtype=dtype)
