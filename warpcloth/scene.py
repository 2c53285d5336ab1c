"""Scenes: small TOML files that describe one cloth, its material, handles, pins, forces, obstacles and collisions.

Schema (every key is checked: an unknown key or a wrong type is a ``ValueError`` naming the key path)::

    name = "hanging-wind"              # required
    description = "..."                # optional
    gravity = [0.0, 0.0, -9.8]         # optional [m/s^2], default (0, 0, -9.8); Z is up

    [sim]                              # required
    dt = 0.02                          # time step [s], > 0
    steps = 50                         # number of steps, >= 1

    [solver]                           # optional: fields of warpcloth.solver.SolverOptions
    preset = "balanced"                # optional: start from a preset (warpcloth.solver.presets; its max_dt must not
                                       #   be below sim.dt); the other keys override single fields
    cg_tol = 1e-5
    collision = { rounds = 50 }        # optional: fields of warpcloth.solver.CollisionOptions

    [cloth]                            # required; exactly one of grid / mesh
    grid = { res = [16, 16], size = [1.0, 1.0] }    # cells, metres; corner at the origin, in the local XY plane
    # mesh = "cloth.obj"  or  mesh = { path = "cloth.obj", scale = 1.0 }   # .obj/.usd*, relative to the scene file
    rot_deg = [90.0, 0.0, 90.0]        # optional rotation, degrees about world X, then Y, then Z (R = Rz Ry Rx)
    pos = [0.0, -0.5, -0.5]            # optional translation [m], applied after the rotation
    vel = [0.0, 0.0, 0.0]              # optional initial velocity [m/s]
    material = "gray-interlock"        # a preset name, or a table (below)
    thicken = 2.0                      # optional, default 1 (ARCSim's thicken; the seed demos use 2)

    # material tables:
    #   { mean = ["gray-interlock", "11oz-black-denim"] }                    element-wise mean of presets
    #   { file = "mat.json", stretching_mult = 1.0, bending_mult = 1.0 }     ARCSim JSON (relative to the scene)
    #   { density = 0.2, stretching = [[...] x6], bending = [[...] x3] }    raw tables (see warpcloth.materials)
    #   { density = 0.2, stretch_stiffness = 50.0, shear_stiffness = 10.0,
    #     poisson_coupling = 0.0, bend_stiffness = 1e-5 }                    Material.isotropic

    [[handles]]                        # soft penalty springs; any number
    grid_vertex = [0, -1]              # selector, exactly one of: particle = i | grid_vertex = [i, j] |
                                       #   grid_row = j | grid_column = i   (grid_* need a grid cloth;
                                       #   negative values count from the end, as in Python)
    stiffness = 1000.0                 # optional [N/m], default 1e3 (ARCSim)
    motion = [[0.0, [0, 0, 0]], [1.0, [0, 0, 0.2]]]   # optional keyframes (time [s], offset [m])

    [[pins]]                           # hard pins; same selectors and motion, no stiffness
    particle = 0

    [wind]                             # optional
    velocity = [5.0, 0.0, 0.0]         # [m/s], required in the table
    density = 1.0                      # optional, default 1 (ARCSim)
    drag = 0.0                         # optional, default 0

    [damping]                          # optional Rayleigh damping
    mass = 0.0                         # alpha [1/s]
    stiffness = 0.0                    # beta [s]

    [[obstacles]]                      # rigid obstacles; any number; each turns on cloth-obstacle collisions
    shape = "sphere"                   # exactly one of shape / mesh; shape parameters by shape:
    radius = 0.3                       #   "plane":  size = [sx, sy] (default [1, 1]), res = [nx, ny] (default [1, 1])
    subdivisions = 3                   #   "box":    half_extents = [hx, hy, hz] (required)
                                       #   "sphere": radius (required), subdivisions (default 3)
                                       #   "funnel": none (the seed's contain.obj)
    # mesh = "bowl.obj"  or  mesh = { path = "bowl.usda", scale = 1.0, prim_path = "/World/Bowl" }
    #                                  # .obj/.usd*, relative to the scene file; prim_path only for USD
    name = "ball"                      # optional, a valid USD identifier, unique; default "obstacle<k>"
    rot_deg = [0.0, 0.0, 0.0]          # optional base rotation, degrees, as for the cloth (R = Rz Ry Rx)
    pos = [0.0, 0.0, 0.0]              # optional base position [m], applied after the rotation
    motion = [[0.0, [0, 0, 0], [0, 0, 0, 1]], [1.0, [0, 0, 0.1], [0, 0, 0, 1]]]
                                       # optional rigid keyframes [time [s], translation [m], quaternion (x,y,z,w)],
                                       #   applied on top of the base placement (warpcloth.obstacles)

    [collision]                        # optional
    self_collision = false             # cloth-cloth collisions, default false
    thickness = 5e-4                   # impact-zone collision thickness [m], > 0, default 5e-4
    repulsion_thickness = 5e-3         # proximity repulsion thickness [m], > 0, default 5e-3 (ARCSim)
    repulsion_stiffness = 1e6          # repulsion stiffness per m^2 of rest area [N/m^3], >= 0 (0: off)
    friction = 0.6                     # cloth-cloth Coulomb friction, >= 0
    obstacle_friction = 0.3            # cloth-obstacle Coulomb friction, >= 0

A scene may carry its task, run by ``warpcloth control SCENE`` / ``warpcloth estimate SCENE`` (and
``ControlTask.from_scene`` / ``EstimationTask.from_scene`` in ``warpcloth.tasks``)::

    [control]                          # optional: find pushes that move the cloth where the loss says
    grid_vertices = [[0, 0], [-1, 0]]  # the pushed particles, exactly one of: particles = [i, ...] |
                                       #   grid_vertices = [[i, j], ...] (a grid cloth; negative values from the end)
    interval = 1.0                     # [s] per push, a whole number of sim.dt steps
    intervals = 3                      # pushes per particle: the first intervals * interval seconds are controlled
    steps = 700                        # optional horizon [steps], default sim.steps
    loss = { com = [0.0, 0.0, -0.7] }  # 1/2 |centre of mass - com|^2 (mass-weighted) at the horizon [m^2], or
                                       #   { positions = "target.obj" }: 1/2 mean_i |x_i - target_i|^2, an OBJ with
                                       #   the cloth's vertex count, in world coordinates (relative to the scene file)
    regularizer = 0.0                  # optional: adds regularizer * 1/2 |pushes|^2 [pushes in m/s^2]
    controller = "open-loop"           # optional: "open-loop" (default) or "mlp" (a PyTorch MLP of the state)
    optimizer = "gauss-newton"         # optional: "gauss-newton" (default with com; for the MLP, without a
                                       #   regularizer), else "lbfgs" (open loop) or "adam" (MLP); open loop, a
                                       #   global search over worlds: "multistart" (local runs from random starts in
                                       #   lockstep), "cmaes" (CMA-ES, then the local default) or "smoothed" (Adam
                                       #   on the Gaussian-smoothed loss, then the local default); see search
    iters = 50                         # optional: simulations spent (default 50 open-loop, 100 mlp)
    search = { population = 8, sigma = 5.0, seed = 0 }
                                       # optional, with a global search, every key optional: multistart: starts
                                       #   (8) and their spread [m/s^2] (5); cmaes: points per generation (one
                                       #   simulation each, run as worlds of one batch; default 4 + 3 ln n), initial
                                       #   spread (5) and refine = simulations left to the local optimiser (a fifth
                                       #   of iters); smoothed: copies a step (8), their spread (5), refine
                                       #   as cmaes's; random seed (0)
    warm_start = 20                    # optional, the MLP only: first optimise the pushes themselves with this many
                                       #   simulations and fit the network's output layer to them (default 0: none)

    [estimate]                         # optional: fit the cloth's material to a trajectory
    targets = "frames"                 # optional: a directory of OBJ frames (frame 0 = the start), relative to the
                                       #   scene file; default: the scene simulated with cloth.material (a known truth)
    frame_stride = 2                   # optional: steps per target frame, default 1
    steps = 50                         # optional: steps compared, default sim.steps
    start = "gray-interlock"           # optional material (the forms above); default the mean of 8 fabrics (the seed's)
    free = ["density", "stretching", "bending"]   # optional: what is fitted (default all); the rest stays at start
    optimizer = "lbfgs"                # optional: "lbfgs" (default), "adam", "seed-sgd", or a global search with a
                                       #   search table as [control]'s, sigma in the log-scale parameters' units:
                                       #   "cmaes" (then L-BFGS; sigma 0.5), "multistart" (L-BFGS runs, one after
                                       #   another; sigma 0.5) or "smoothed" (then L-BFGS; sigma 0.05)
    iters = 100                        # optional: forward + backward evaluations, default 100

A push is a constant force ``(M / k) p`` on each of the k pushed particles over its interval (M the cloth's mass),
so ``p`` [m/s^2] is the acceleration k equal pushes give the whole cloth.

A ``grid_row``/``grid_column`` selector adds one handle (or pin) per vertex of that row/column, all with the same
stiffness and motion. Particle indices are those of the cloth (the scene's only one). Embedded scenes live in
``warpcloth/scenes/*.toml``; their names are :data:`SCENE_NAMES`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from warpcloth import materials as _materials
from warpcloth import mesh_io
from warpcloth.builder import DEFAULT_HANDLE_STIFFNESS
from warpcloth.geometry.transforms import QUAT_UNIT_TOL

__all__ = ["DEFAULT_SCENE", "SCENE_NAMES", "ControlSpec", "EstimateSpec", "Scene", "SearchSpec", "load_scene",
           "scene_from_toml"]

DEFAULT_SCENE = "hanging-wind"
"""The scene ``warpcloth simulate`` runs when none is named."""

SCENE_NAMES: tuple[str, ...] = tuple(
    sorted(p.name[: -len(".toml")] for p in resources.files("warpcloth.scenes").iterdir() if p.name.endswith(".toml"))
)
"""Names of the embedded scenes."""

_DEFAULT_GRAVITY = (0.0, 0.0, -9.8)
_PLAIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")


@dataclass(frozen=True)
class SearchSpec:
    """A global search's settings (a ``search`` table in ``[control]`` or ``[estimate]``). A control task's search
    simulates its candidates as worlds of one batch; an estimation's one after another (``estimate_material(...,
    batch=True)`` batches them: slower on the CPU). ``optimizer = "cmaes"``: CMA-ES over the task's parameters (its
    generations forward only), then the task's local optimiser from the best point found
    (``warpcloth.tasks.optim.cmaes``). ``optimizer = "multistart"``: local runs from random starts (in lockstep when
    batched). ``optimizer = "smoothed"``: Adam on the Gaussian-smoothed loss
    (``warpcloth.tasks.optim.smoothed_descent``), then the local optimiser.

    Attributes:
        population: CMA-ES's points per generation, each one simulation (default 4 + floor(3 ln n), n parameters);
            the multistart's starts (default 8); the smoothed search's copies a step (default 8, even).
        sigma: CMA-ES's initial standard deviation, the multistart's spread of starts, the smoothing's, in the
            parameters' units (default: the task's; for control, pushes 5 m/s^2, also smoothed; for estimation, 0.5
            of the material's log-scale parameters and 0.05 smoothed).
        refine: CMA-ES and the smoothed search: simulations left to the local optimiser (default a fifth of the
            budget).
        seed: Seed of the search's random numbers.
    """

    population: int | None = None
    sigma: float | None = None
    refine: int | None = None
    seed: int = 0


@dataclass
class ControlSpec:
    """A scene's ``[control]`` table, checked (``warpcloth.tasks.control.ControlTask.from_scene`` runs it).

    Attributes:
        particles: The pushed particles (model indices), in the order of the pushes.
        interval_steps: Steps per push: each particle gets one push (a constant acceleration [m/s^2]) per interval.
        intervals: Pushes per particle; the first ``intervals * interval_steps`` steps are controlled.
        steps: The horizon [steps].
        target_com: The centre of mass's target [m], or None.
        target_positions: Every particle's target position [m] (particle_count, 3), or None; exactly one of the two.
        regularizer: Weight of ``1/2 |pushes|^2`` in the loss.
        controller: ``"open-loop"`` or ``"mlp"``.
        optimizer: The controller's optimiser (``CONTROL_OPTIMIZERS``): ``"gauss-newton"`` (a centre-of-mass target
            only; for the MLP, without a regulariser), ``"lbfgs"`` (open loop), ``"multistart"``, ``"cmaes"`` or
            ``"smoothed"`` (open loop: global searches, the last two then the local default) or ``"adam"`` (MLP).
        iters: Simulations the optimisation may spend.
        search: The global stage's settings (``optimizer = "multistart"``, ``"cmaes"`` or ``"smoothed"``).
        warm_start: The MLP's warm start: simulations of the open-loop optimisation it is first fitted to (0: none).
    """

    particles: tuple[int, ...]
    interval_steps: int
    intervals: int
    steps: int
    target_com: tuple[float, float, float] | None
    target_positions: np.ndarray | None
    regularizer: float
    controller: str
    optimizer: str
    iters: int
    search: SearchSpec = SearchSpec()
    warm_start: int = 0


@dataclass
class EstimateSpec:
    """A scene's ``[estimate]`` table, checked (``warpcloth.tasks.estimation.EstimationTask.from_scene`` runs it).

    Attributes:
        targets: The target frames (particle_count, 3) [m], frame 0 the start; None: the scene simulated with its own
            cloth material (a known truth).
        targets_source: Where the targets came from (the directory), or None.
        frame_stride: Steps per target frame.
        steps: Steps compared.
        start: The material the fit starts from.
        free: The material parameters fitted (of ``"density"``, ``"stretching"``, ``"bending"``); the others stay at
            ``start``'s.
        optimizer: ``"lbfgs"``, ``"adam"``, ``"seed-sgd"`` or ``"cmaes"`` (global search, then L-BFGS).
        iters: Forward + backward evaluations (a global search's forward-only simulations count one each).
        search: The global stage's settings (``optimizer = "cmaes"``).
    """

    targets: list[np.ndarray] | None
    targets_source: str | None
    frame_stride: int
    steps: int
    start: _materials.Material
    free: tuple[str, ...]
    optimizer: str
    iters: int
    search: SearchSpec = SearchSpec()


@dataclass
class Scene:
    """A loaded scene: its builder (already holding the cloth, handles and forces) and run settings.

    Attributes:
        name: Scene name.
        description: One-line description.
        dt: Time step [s].
        steps: Number of steps to simulate.
        model_builder: A ``ModelBuilder`` with everything added; ``build`` finalises it.
        solver_options: ``SolverOptions`` for the simulator.
        source: Where the scene came from (file path, or ``embedded:<name>``).
        grid_res: (cells_x, cells_y) of a grid cloth, else None; grid vertex (i, j) is particle
            ``j * (cells_x + 1) + i``.
        max_dt: the solver preset's time-step ceiling [s], else None (:meth:`set_dt` keeps to it).
        cloth_material: The cloth's material.
        control: The scene's control task (its ``[control]`` table), else None.
        estimate: The scene's estimation task (its ``[estimate]`` table), else None.
    """

    name: str
    description: str
    dt: float
    steps: int
    model_builder: Any
    solver_options: Any
    source: str = "<string>"
    grid_res: tuple[int, int] | None = None
    max_dt: float | None = None
    cloth_material: _materials.Material | None = None
    control: ControlSpec | None = None
    estimate: EstimateSpec | None = None

    MAX_FRAME_BYTES = 4 * 2**30
    """Most memory the frames of one ``warpcloth simulate`` run may take (they are kept until the USD is written)."""

    def set_dt(self, dt: float) -> None:
        """Change the time step; raises ValueError for a dt that is not finite and > 0, or above the preset's
        ceiling (the one the scene file's own sim.dt is held to)."""
        if not (isinstance(dt, (int, float)) and 0.0 < dt < math.inf):
            raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
        if self.max_dt is not None and dt > self.max_dt * (1.0 + 1e-9):
            raise ValueError(f"scene {self.name!r} uses a solver preset that steps at most {self.max_dt:g} s, "
                             f"got {dt:g} s")
        self.dt = float(dt)

    def check_frame_memory(self) -> None:
        """Raise ValueError if keeping every frame of ``steps`` steps would take more than MAX_FRAME_BYTES (8 bytes
        per coordinate: write_usd holds the frames in float64 while it writes them)."""
        need = (self.steps + 1) * self.model_builder.particle_count * 3 * 8
        if need > self.MAX_FRAME_BYTES:
            most = self.MAX_FRAME_BYTES // (self.model_builder.particle_count * 3 * 8) - 1
            raise ValueError(f"{self.steps} steps of {self.model_builder.particle_count} particles keep "
                             f"{need / 2**30:.1f} GiB of frames, more than {self.MAX_FRAME_BYTES / 2**30:g} GiB; "
                             f"simulate at most {most} steps per run")

    @property
    def tasks(self) -> tuple[str, ...]:
        """The tasks the scene carries: ``"control"``, ``"estimate"``, both or none."""
        return tuple(k for k in ("control", "estimate") if getattr(self, k) is not None)

    def build(self, device=None, requires_grad: bool = False, dtype=None):
        """Finalises the model and creates its simulator.

        Args:
            device: Warp device; Warp's default when None.
            requires_grad: Allocate gradient arrays in the model.
            dtype: ``wp.float32`` (default) or ``wp.float64``.

        Returns:
            ``(model, sim)``: the ``Model`` and a ``Simulator`` with this scene's ``dt`` and solver options.
        """
        from warpcloth.solver.simulator import Simulator

        model = self.finalize(device=device, requires_grad=requires_grad, dtype=dtype)
        sim = Simulator(model, dt=self.dt, options=self.solver_options)
        return model, sim


    def finalize(self, device=None, requires_grad: bool = False, dtype=None):
        """The scene's ``Model`` (``ModelBuilder.finalize``; float32 when ``dtype`` is None)."""
        if dtype is None:
            return self.model_builder.finalize(device=device, requires_grad=requires_grad)
        return self.model_builder.finalize(device=device, requires_grad=requires_grad, dtype=dtype)


def load_scene(name_or_path: str | os.PathLike) -> Scene:
    """Loads an embedded scene by name, or a scene file by path.

    Args:
        name_or_path: One of :data:`SCENE_NAMES`, or a path to a ``.toml`` file.

    Raises:
        ValueError: for an unknown name (listing the embedded ones) or an invalid scene (naming the key path).
        FileNotFoundError: when a path does not exist.
    """
    if isinstance(name_or_path, str) and name_or_path in SCENE_NAMES:
        resource = resources.files("warpcloth.scenes").joinpath(f"{name_or_path}.toml")
        base = Path(str(resources.files("warpcloth.scenes")))
        return scene_from_toml(resource.read_text(encoding="utf-8"), source=f"embedded:{name_or_path}", base_dir=base)
    path = Path(name_or_path)
    if path.suffix != ".toml" and not path.exists():
        raise ValueError(
            f"unknown scene {os.fspath(name_or_path)!r}; embedded scenes: {', '.join(SCENE_NAMES)} "
            "(or give the path of a .toml scene file)"
        )
    text = path.read_text(encoding="utf-8")
    return scene_from_toml(text, source=os.fspath(path), base_dir=path.resolve().parent)


def scene_from_toml(text: str, *, source: str = "<string>", base_dir: str | os.PathLike | None = None) -> Scene:
    """Parses a scene from TOML text (schema in this module's docstring).

    Args:
        text: TOML document.
        source: Name used in error messages.
        base_dir: Directory against which relative mesh and material paths are resolved (the current directory
            when None).

    Raises:
        ValueError: ``"<source>: <key path>: <problem>"`` for invalid TOML, an unknown key, a missing key, a wrong
            type or an invalid value.
    """
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{source}: invalid TOML: {exc}") from None
    try:
        return _parse(data, source=source, base_dir=Path(base_dir) if base_dir is not None else Path.cwd())
    except _SceneError as exc:
        raise ValueError(f"{source}: {exc}") from None


# ----------------------------------------------------------------------------------------------------------------------
# Parsing helpers. Each takes the key path of the value it checks, so every error names it.


class _SceneError(ValueError):
    pass


def _err(path: str, message: str) -> _SceneError:
    return _SceneError(f"{path}: {message}" if path else message)


def _type_name(value: Any) -> str:
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array", dict: "table"}.get(
        type(value), type(value).__name__
    )


def _table(value: Any, path: str) -> dict:
    if not isinstance(value, dict):
        raise _err(path, f"expected a table, got {_type_name(value)}")
    return value


def _check_keys(table: dict, path: str, allowed: tuple[str, ...], required: tuple[str, ...] = ()) -> None:
    for key in table:
        if key not in allowed:
            full = f"{path}.{key}" if path else key
            raise _err(full, f"unknown key; allowed here: {', '.join(allowed)}")
    for key in required:
        if key not in table:
            full = f"{path}.{key}" if path else key
            raise _err(full, "missing required key")


def _float(value: Any, path: str, *, min_value: float | None = None, strict: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _err(path, f"expected a number, got {_type_name(value)}")
    x = float(value)
    if not math.isfinite(x):
        raise _err(path, f"must be finite, got {x}")
    if min_value is not None and (x < min_value or (strict and x == min_value)):
        raise _err(path, f"must be {'>' if strict else '>='} {min_value}, got {x}")
    return x


def _int(value: Any, path: str, *, min_value: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _err(path, f"expected an integer, got {_type_name(value)}")
    if min_value is not None and value < min_value:
        raise _err(path, f"must be >= {min_value}, got {value}")
    return value


def _str(value: Any, path: str) -> str:
    if not isinstance(value, str):
        raise _err(path, f"expected a string, got {_type_name(value)}")
    return value


def _vector(value: Any, path: str, n: int = 3) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != n:
        got = f"an array of {len(value)}" if isinstance(value, list) else _type_name(value)
        raise _err(path, f"expected an array of {n} numbers, got {got}")
    return tuple(_float(v, f"{path}[{i}]") for i, v in enumerate(value))


def _cos_sin_deg(angle: float) -> tuple[float, float]:
    """cos and sin of an angle in degrees, exact at multiples of 90 (np.cos(pi/2) is 6e-17: a sheet turned upright
    would lean by that much)."""
    quarter, rest = divmod(angle, 90.0)
    if rest == 0.0:
        return ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))[int(quarter) % 4]
    a = math.radians(angle)
    return math.cos(a), math.sin(a)


def _rotation_xyz_deg(angles: tuple[float, float, float]) -> np.ndarray:
    """Rotation by angles[0] about X, then angles[1] about Y, then angles[2] about Z (fixed axes)."""
    (cx, sx), (cy, sy), (cz, sz) = (_cos_sin_deg(a) for a in angles)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def _existing_file(base_dir: Path, value: Any, key: str, context: str) -> Path:
    """``base_dir / value`` (a string at ``key``), which must be a file: a ValueError under ``context`` otherwise."""
    file = base_dir / _str(value, key)
    if not file.is_file():
        raise _err(context, f"file not found: {file}")
    return file


class _Context:
    """Re-raises a ValueError from library code (materials, mesh loading, builder) under a key path."""

    def __init__(self, path: str):
        self.path = path

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None and issubclass(exc_type, ValueError) and not isinstance(exc, _SceneError):
            raise _err(self.path, str(exc)) from None
        return False


# ----------------------------------------------------------------------------------------------------------------------


def _parse(data: dict, *, source: str, base_dir: Path) -> Scene:
    from warpcloth.builder import ModelBuilder

    _check_keys(
        data,
        "",
        (
            "name", "description", "gravity", "sim", "solver", "cloth", "handles", "pins", "wind", "damping",
            "obstacles", "collision", "control", "estimate",
        ),
        required=("name", "sim", "cloth"),
    )
    name = _str(data["name"], "name")
    if not _PLAIN_NAME.fullmatch(name):
        raise _err("name", f"{name!r} must be a plain file name (letters, digits, '_', '-', '.', not starting with "
                           "'.' or '-'): it names the default output <name>.usda")
    description = _str(data.get("description", ""), "description")
    gravity = _vector(data["gravity"], "gravity") if "gravity" in data else _DEFAULT_GRAVITY

    sim = _table(data["sim"], "sim")
    _check_keys(sim, "sim", ("dt", "steps"), required=("dt", "steps"))
    dt = _float(sim["dt"], "sim.dt", min_value=0.0, strict=True)
    steps = _int(sim["steps"], "sim.steps", min_value=1)

    solver_options, max_dt = _parse_solver(data.get("solver", {}), dt)

    builder = ModelBuilder(gravity=gravity)
    first, grid_res, count, cloth_material = _parse_cloth(builder, _table(data["cloth"], "cloth"), base_dir)

    attached: dict[int, str] = {}  # particle -> the entry that holds it, to name both entries in a conflict
    for kind in ("handles", "pins"):
        entries = data.get(kind, [])
        if not isinstance(entries, list):
            raise _err(kind, f"expected an array of tables ([[{kind}]]), got {_type_name(entries)}")
        for k, entry in enumerate(entries):
            path = f"{kind}[{k}]"
            _parse_attachment(builder, kind, path, _table(entry, path), first, count, grid_res, attached)

    if "wind" in data:
        wind = _table(data["wind"], "wind")
        _check_keys(wind, "wind", ("velocity", "density", "drag"), required=("velocity",))
        velocity = _vector(wind["velocity"], "wind.velocity")
        density = _float(wind.get("density", 1.0), "wind.density", min_value=0.0)
        drag = _float(wind.get("drag", 0.0), "wind.drag", min_value=0.0)
        with _Context("wind"):
            builder.set_wind(velocity, density=density, drag=drag)

    if "damping" in data:
        damping = _table(data["damping"], "damping")
        _check_keys(damping, "damping", ("mass", "stiffness"))
        mass = _float(damping.get("mass", 0.0), "damping.mass", min_value=0.0)
        stiffness = _float(damping.get("stiffness", 0.0), "damping.stiffness", min_value=0.0)
        with _Context("damping"):
            builder.set_damping(mass=mass, stiffness=stiffness)

    entries = data.get("obstacles", [])
    if not isinstance(entries, list):
        raise _err("obstacles", f"expected an array of tables ([[obstacles]]), got {_type_name(entries)}")
    for k, entry in enumerate(entries):
        path = f"obstacles[{k}]"
        _parse_obstacle(builder, path, _table(entry, path), base_dir)

    if "collision" in data:
        collision = _table(data["collision"], "collision")
        positive = ("thickness", "repulsion_thickness")
        non_negative = ("repulsion_stiffness", "friction", "obstacle_friction")
        _check_keys(collision, "collision", ("self_collision",) + positive + non_negative)
        self_collision = collision.get("self_collision", False)
        if not isinstance(self_collision, bool):
            raise _err("collision.self_collision", f"expected a boolean, got {_type_name(self_collision)}")
        kwargs = {"self_collision": self_collision}
        for key in positive + non_negative:
            if key in collision:
                kwargs[key] = _float(collision[key], f"collision.{key}", min_value=0.0, strict=key in positive)
        with _Context("collision"):
            builder.set_collision(**kwargs)

    control = estimate = None
    if "control" in data:
        control = _parse_control(_table(data["control"], "control"), dt, steps, first, count, grid_res, attached,
                                 base_dir)
    if "estimate" in data:
        estimate = _parse_estimate(_table(data["estimate"], "estimate"), steps, count, cloth_material, base_dir)

    return Scene(
        name=name,
        description=description,
        dt=dt,
        steps=steps,
        model_builder=builder,
        solver_options=solver_options,
        source=source,
        grid_res=grid_res,
        max_dt=max_dt,
        cloth_material=cloth_material,
        control=control,
        estimate=estimate,
    )


def _parse_solver(value: Any, dt: float):
    """SolverOptions from the [solver] table: an optional ``preset`` (warpcloth.solver.presets), then single fields,
    each checked against SolverOptions' fields and their defaults' types (and a ``collision`` table of
    CollisionOptions fields). Returns (options, the preset's time-step ceiling or None)."""
    from warpcloth.solver.options import CollisionOptions, SolverOptions
    from warpcloth.solver.presets import PRESET_SOLVER_NAMES, solver_preset

    table = dict(_table(value, "solver"))
    defaults = {f.name: f.default for f in dataclasses.fields(SolverOptions) if f.name != "collision"}
    _check_keys(table, "solver", ("preset", "collision") + tuple(defaults))
    base = SolverOptions()
    max_dt = None
    if "preset" in table:
        name = _str(table.pop("preset"), "solver.preset")
        if name not in PRESET_SOLVER_NAMES:
            raise _err("solver.preset", f"unknown preset {name!r}; one of: {', '.join(PRESET_SOLVER_NAMES)}")
        preset = solver_preset(name)
        if dt > preset.max_dt * (1.0 + 1e-9):
            raise _err("solver.preset", f"the {name!r} preset steps at most {preset.max_dt:g} s but sim.dt is "
                                        f"{dt:g} s; lower sim.dt (and raise sim.steps) or choose another preset")
        base = preset.options
        max_dt = preset.max_dt
    kwargs = _option_fields(table, "solver", defaults)
    with _Context("solver.collision"):
        if "collision" in table:
            collision = _table(table["collision"], "solver.collision")
            fields = {f.name: f.default for f in dataclasses.fields(CollisionOptions)}
            _check_keys(collision, "solver.collision", tuple(fields))
            kwargs["collision"] = dataclasses.replace(base.collision, **_option_fields(collision, "solver.collision",
                                                                                       fields))
    with _Context("solver"):
        return dataclasses.replace(base, **kwargs), max_dt


def _option_fields(table: dict, prefix: str, defaults: dict) -> dict:
    """The entries of an options table, each checked against the type of its field's default."""
    kwargs = {}
    for key, v in table.items():
        if key not in defaults:
            continue
        path = f"{prefix}.{key}"
        default = defaults[key]
        if isinstance(default, bool):
            if not isinstance(v, bool):
                raise _err(path, f"expected a boolean, got {_type_name(v)}")
        elif isinstance(default, int):
            v = _int(v, path)
        elif isinstance(default, float) or default is None:  # None: an optional float (adjoint_cg_tol)
            v = _float(v, path)
        elif isinstance(default, str):
            v = _str(v, path)
        kwargs[key] = v
    return kwargs


def _parse_cloth(builder, cloth: dict, base_dir: Path):
    """Adds the cloth; returns (first particle, grid resolution or None, particle count, material)."""
    allowed = ("grid", "mesh", "pos", "rot_deg", "vel", "material", "thicken")
    _check_keys(cloth, "cloth", allowed, required=("material",))
    if ("grid" in cloth) == ("mesh" in cloth):
        raise _err("cloth", "give exactly one of 'grid' and 'mesh'")
    pos = _vector(cloth["pos"], "cloth.pos") if "pos" in cloth else (0.0, 0.0, 0.0)
    rot = _rotation_xyz_deg(_vector(cloth["rot_deg"], "cloth.rot_deg")) if "rot_deg" in cloth else np.eye(3)
    vel = _vector(cloth["vel"], "cloth.vel") if "vel" in cloth else (0.0, 0.0, 0.0)
    thicken = _float(cloth.get("thicken", 1.0), "cloth.thicken", min_value=0.0, strict=True)
    material = _parse_material(cloth["material"], "cloth.material", thicken, base_dir)

    before = builder.particle_count
    if "grid" in cloth:
        grid = _table(cloth["grid"], "cloth.grid")
        _check_keys(grid, "cloth.grid", ("res", "size"), required=("res", "size"))
        res = grid["res"]
        if not isinstance(res, list) or len(res) != 2:
            raise _err("cloth.grid.res", f"expected an array of 2 integers, got {_type_name(res)}")
        res = tuple(_int(r, f"cloth.grid.res[{i}]", min_value=1) for i, r in enumerate(res))
        size = _vector(grid["size"], "cloth.grid.size", 2)
        for i, s in enumerate(size):
            if s <= 0.0:
                raise _err(f"cloth.grid.size[{i}]", f"must be > 0, got {s}")
        with _Context("cloth"):
            first = builder.add_cloth_grid(res, size, material=material, pos=pos, rot=rot, vel=vel)
        grid_res = res
    else:
        mesh_value = cloth["mesh"]
        if isinstance(mesh_value, str):
            mesh_table = {"path": mesh_value}
        else:
            mesh_table = _table(mesh_value, "cloth.mesh")
        _check_keys(mesh_table, "cloth.mesh", ("path", "scale"), required=("path",))
        mesh_path = _existing_file(base_dir, mesh_table["path"], "cloth.mesh.path", "cloth.mesh")
        scale = _float(mesh_table.get("scale", 1.0), "cloth.mesh.scale", min_value=0.0, strict=True)
        with _Context("cloth.mesh"):
            if mesh_path.suffix.lower() == ".obj":
                mesh = mesh_io.load_obj(mesh_path, scale=scale)
            elif mesh_path.suffix.lower() in (".usd", ".usda", ".usdc"):
                mesh = mesh_io.load_usd_mesh(mesh_path)
                mesh.positions = mesh.positions * scale
                if mesh.tri_uv is not None:
                    mesh.tri_uv = mesh.tri_uv * scale
            else:
                raise ValueError(f"unsupported mesh format {mesh_path.suffix!r} (need .obj, .usd, .usda or .usdc)")
        # ARCSim's transform order: scale (done on load), rotate, translate.
        mesh.positions = mesh.positions @ rot.T + np.asarray(pos)
        with _Context("cloth"):
            first = builder.add_cloth_mesh(mesh, material=material, vel=vel)
        grid_res = None
    return first, grid_res, builder.particle_count - before, material


_MATERIAL_FORMS = (
    "a preset name",
    "{ mean = [names] }",
    "{ file = ..., stretching_mult, bending_mult }",
    "{ density, stretching, bending }",
    "{ density, stretch_stiffness, shear_stiffness, poisson_coupling, bend_stiffness }",
)


def _parse_material(value: Any, path: str, thicken: float, base_dir: Path) -> _materials.Material:
    if isinstance(value, str):
        with _Context(path):
            return _materials.preset(value, thicken=thicken)
    table = _table(value, path) if isinstance(value, dict) else None
    if table is None:
        raise _err(path, f"expected a string or a table, got {_type_name(value)}")
    if "file" in table:
        _check_keys(table, path, ("file", "stretching_mult", "bending_mult"))
        file = _existing_file(base_dir, table["file"], f"{path}.file", path)
        smult = _float(table.get("stretching_mult", 1.0), f"{path}.stretching_mult", min_value=0.0)
        bmult = _float(table.get("bending_mult", 1.0), f"{path}.bending_mult", min_value=0.0)
        with _Context(path):
            return _materials.load_material_json(file, stretching_mult=smult, bending_mult=bmult, thicken=thicken)
    if "mean" in table:
        _check_keys(table, path, ("mean",))
        names = table["mean"]
        if not isinstance(names, list) or not names:
            raise _err(f"{path}.mean", "expected a non-empty array of preset names")
        names = [_str(n, f"{path}.mean[{i}]") for i, n in enumerate(names)]
        with _Context(f"{path}.mean"):
            return _materials.mean_material(names, thicken=thicken)
    if "stretching" in table or "bending" in table:
        required = ("density", "stretching", "bending")
        _check_keys(table, path, required + ("name",), required=required)
        density = _float(table["density"], f"{path}.density")
        tables = {}
        for key, shape in (("stretching", _materials.STRETCHING_SHAPE), ("bending", _materials.BENDING_SHAPE)):
            rows = table[key]
            if not isinstance(rows, list) or len(rows) != shape[0]:
                raise _err(f"{path}.{key}", f"expected {shape[0]} rows of {shape[1]} numbers")
            tables[key] = [_vector(r, f"{path}.{key}[{i}]", shape[1]) for i, r in enumerate(rows)]
        name = _str(table.get("name", "custom"), f"{path}.name")
        with _Context(path):
            return _materials.Material(density=density, thicken=thicken, name=name, **tables)
    if "stretch_stiffness" in table:
        keys = ("density", "stretch_stiffness", "shear_stiffness", "poisson_coupling", "bend_stiffness", "name")
        _check_keys(table, path, keys, required=("density", "stretch_stiffness", "shear_stiffness", "bend_stiffness"))
        kwargs = {k: _float(table[k], f"{path}.{k}") for k in keys[:-1] if k in table}
        name = _str(table.get("name", "isotropic"), f"{path}.name")
        with _Context(path):
            return _materials.Material.isotropic(thicken=thicken, name=name, **kwargs)
    raise _err(path, "unrecognised material table; use one of: " + "; ".join(_MATERIAL_FORMS))


_SELECTORS = ("particle", "grid_vertex", "grid_row", "grid_column")


def _grid_index(value: int, extent: int, path: str) -> int:
    """Python-style index into 0..extent-1."""
    if not -extent <= value < extent:
        raise _err(path, f"index {value} out of range for {extent} vertices")
    return value % extent


def _grid_vertex(value: Any, path: str, grid_res: tuple[int, int]) -> int:
    """The particle of grid vertex ``[i, j]`` (Python-style indices)."""
    if not isinstance(value, list) or len(value) != 2:
        raise _err(path, f"expected an array of 2 integers [i, j], got {_type_name(value)}")
    nx, ny = grid_res[0] + 1, grid_res[1] + 1
    i = _grid_index(_int(value[0], f"{path}[0]"), nx, f"{path}[0]")
    j = _grid_index(_int(value[1], f"{path}[1]"), ny, f"{path}[1]")
    return j * nx + i


def _parse_attachment(
    builder, kind: str, path: str, entry: dict, first: int, count: int, grid_res, attached: dict[int, str]
) -> None:
    allowed = _SELECTORS + (("stiffness", "motion") if kind == "handles" else ("motion",))
    _check_keys(entry, path, allowed)
    given = [s for s in _SELECTORS if s in entry]
    if len(given) != 1:
        raise _err(path, f"give exactly one of {', '.join(_SELECTORS)}")
    selector = given[0]
    if selector != "particle" and grid_res is None:
        raise _err(f"{path}.{selector}", "needs a grid cloth (cloth.grid)")
    nx = grid_res[0] + 1 if grid_res else 0
    ny = grid_res[1] + 1 if grid_res else 0
    sel_path = f"{path}.{selector}"
    value = entry[selector]
    if selector == "particle":
        p = _int(value, sel_path, min_value=0)
        if p >= count:
            raise _err(sel_path, f"particle {p} out of range: the cloth has {count} particles")
        particles = [p]
    elif selector == "grid_vertex":
        particles = [_grid_vertex(value, sel_path, grid_res)]
    elif selector == "grid_row":
        j = _grid_index(_int(value, sel_path), ny, sel_path)
        particles = [j * nx + i for i in range(nx)]
    else:
        i = _grid_index(_int(value, sel_path), nx, sel_path)
        particles = [j * nx + i for j in range(ny)]

    # A particle may carry several soft handles (their springs add up), but a pin excludes any other attachment.
    for p in particles:
        other = attached.get(p)
        if other is not None and (kind == "pins" or other.startswith("pins")):
            verb = "pinned" if other.startswith("pins") else "held"
            raise _err(path, f"particle {p} is also {verb} by {other}; a pinned particle takes no other handle or pin")
        attached.setdefault(p, path)

    motion = None
    if "motion" in entry:
        motion = _parse_motion(entry["motion"], f"{path}.motion")
    stiffness = None
    if kind == "handles":
        stiffness = _float(entry.get("stiffness", DEFAULT_HANDLE_STIFFNESS), f"{path}.stiffness", min_value=0.0)
    with _Context(path):
        for p in particles:
            if kind == "handles":
                builder.add_handle(first + p, stiffness=stiffness, motion=motion)
            else:
                builder.add_pin(first + p, motion=motion)


def _keyframes(value: Any, path: str, form: str, arity: int):
    """Yield (key path, time, key) for a non-empty array of keyframes ``[time, ...]`` (as ``form`` writes them),
    each a list of ``arity`` entries, with increasing times."""
    if not isinstance(value, list) or not value:
        raise _err(path, f"expected a non-empty array of {form} keyframes")
    last = None
    for k, key in enumerate(value):
        kp = f"{path}[{k}]"
        if not isinstance(key, list) or len(key) != arity:
            raise _err(kp, f"expected {form}")
        t = _float(key[0], f"{kp}[0]")
        if last is not None and t <= last:
            raise _err(f"{kp}[0]", f"key times must increase, got {t} after {last}")
        last = t
        yield kp, t, key


def _parse_motion(value: Any, path: str) -> list[tuple[float, tuple[float, float, float]]]:
    return [(t, _vector(key[1], f"{kp}[1]")) for kp, t, key in _keyframes(value, path, "[time, [dx, dy, dz]]", 2)]


_OBSTACLE_SHAPES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    # shape: (parameters, required parameters)
    "plane": (("size", "res"), ()),
    "box": (("half_extents",), ("half_extents",)),
    "sphere": (("radius", "subdivisions"), ("radius",)),
    "funnel": ((), ()),
}
_OBSTACLE_COMMON = ("name", "pos", "rot_deg", "motion")


def _parse_obstacle(builder, path: str, entry: dict, base_dir: Path) -> None:
    shape_params = tuple(dict.fromkeys(p for params, _ in _OBSTACLE_SHAPES.values() for p in params))
    _check_keys(entry, path, ("shape", "mesh") + shape_params + _OBSTACLE_COMMON)
    if ("shape" in entry) == ("mesh" in entry):
        raise _err(path, "give exactly one of 'shape' and 'mesh'")
    options: dict[str, Any] = {}
    if "name" in entry:
        options["name"] = _str(entry["name"], f"{path}.name")
    if "pos" in entry:
        options["pos"] = _vector(entry["pos"], f"{path}.pos")
    if "rot_deg" in entry:
        options["rot"] = _rotation_xyz_deg(_vector(entry["rot_deg"], f"{path}.rot_deg"))
    if "motion" in entry:
        options["motion"] = _parse_rigid_motion(entry["motion"], f"{path}.motion")

    if "shape" in entry:
        shape = _str(entry["shape"], f"{path}.shape")
        if shape not in _OBSTACLE_SHAPES:
            raise _err(f"{path}.shape", f"unknown shape {shape!r}; one of: {', '.join(_OBSTACLE_SHAPES)}")
        params, required = _OBSTACLE_SHAPES[shape]
        for key in shape_params:
            if key in entry and key not in params:
                allowed = ", ".join(params) if params else "none"
                raise _err(f"{path}.{key}", f"not a parameter of shape {shape!r} (its parameters: {allowed})")
        for key in required:
            if key not in entry:
                raise _err(f"{path}.{key}", f"missing required key for shape {shape!r}")
        with _Context(path):
            if shape == "plane":
                size = _vector(entry["size"], f"{path}.size", 2) if "size" in entry else (1.0, 1.0)
                for i, v in enumerate(size):
                    if v <= 0.0:
                        raise _err(f"{path}.size[{i}]", f"must be > 0, got {v}")
                res = (1, 1)
                if "res" in entry:
                    value = entry["res"]
                    if not isinstance(value, list) or len(value) != 2:
                        raise _err(f"{path}.res", f"expected an array of 2 integers, got {_type_name(value)}")
                    res = tuple(_int(r, f"{path}.res[{i}]", min_value=1) for i, r in enumerate(value))
                builder.add_obstacle_plane(size, res, **options)
            elif shape == "box":
                half = _vector(entry["half_extents"], f"{path}.half_extents")
                for i, v in enumerate(half):
                    if v <= 0.0:
                        raise _err(f"{path}.half_extents[{i}]", f"must be > 0, got {v}")
                builder.add_obstacle_box(half, **options)
            elif shape == "sphere":
                radius = _float(entry["radius"], f"{path}.radius", min_value=0.0, strict=True)
                subdivisions = _int(entry.get("subdivisions", 3), f"{path}.subdivisions", min_value=0)
                builder.add_obstacle_sphere(radius, subdivisions, **options)
            else:
                builder.add_obstacle_funnel(**options)
        return

    for key in shape_params:
        if key in entry:
            raise _err(f"{path}.{key}", "a shape parameter, but this obstacle is a mesh (give 'shape' instead)")
    mesh_value = entry["mesh"]
    mesh_table = {"path": mesh_value} if isinstance(mesh_value, str) else _table(mesh_value, f"{path}.mesh")
    _check_keys(mesh_table, f"{path}.mesh", ("path", "scale", "prim_path"), required=("path",))
    mesh_path = _existing_file(base_dir, mesh_table["path"], f"{path}.mesh.path", f"{path}.mesh")
    scale = _float(mesh_table.get("scale", 1.0), f"{path}.mesh.scale", min_value=0.0, strict=True)
    suffix = mesh_path.suffix.lower()
    prim_path = None
    if "prim_path" in mesh_table:
        prim_path = _str(mesh_table["prim_path"], f"{path}.mesh.prim_path")
        if suffix == ".obj":
            raise _err(f"{path}.mesh.prim_path", "only for USD meshes")
    with _Context(f"{path}.mesh"):
        if suffix == ".obj":
            builder.add_obstacle_obj(mesh_path, scale=scale, **options)
        elif suffix in (".usd", ".usda", ".usdc"):
            builder.add_obstacle_usd(mesh_path, prim_path=prim_path, scale=scale, **options)
        else:
            raise ValueError(f"unsupported mesh format {mesh_path.suffix!r} (need .obj, .usd, .usda or .usdc)")


def _parse_rigid_motion(value: Any, path: str) -> list:
    keys = []
    for kp, t, key in _keyframes(value, path, "[time, [tx, ty, tz], [qx, qy, qz, qw]]", 3):
        q = _vector(key[2], f"{kp}[2]", 4)
        norm = math.sqrt(sum(c * c for c in q))
        if abs(norm - 1.0) > QUAT_UNIT_TOL:
            raise _err(
                f"{kp}[2]", f"must be a unit quaternion (x, y, z, w) within {QUAT_UNIT_TOL:g}, norm is {norm:.9g}"
            )
        keys.append((t, _vector(key[1], f"{kp}[1]"), q))
    return keys


# ----------------------------------------------------------------------------------------------------------------------
# Tasks: [control] and [estimate]. Each names its run's choices; the task modules (warpcloth.tasks) run them.

CONTROLLERS = ("open-loop", "mlp")
"""Controllers of a ``[control]`` task."""
CONTROL_OPTIMIZERS = {"open-loop": ("gauss-newton", "lbfgs", "multistart", "cmaes", "smoothed"),
                      "mlp": ("gauss-newton", "adam")}
GLOBAL_OPTIMIZERS = ("multistart", "cmaes", "smoothed")
"""The optimisers that take a ``search`` table."""
"""Optimisers of each controller of a ``[control]`` task (Gauss-Newton needs a centre-of-mass target, and for the MLP
no regulariser)."""


def default_control_optimizer(controller: str, target_com, regularizer: float) -> str:
    """A controller's optimiser where a task names none: Gauss-Newton where it applies, else L-BFGS (open loop) or
    Adam (MLP)."""
    if target_com is not None and (controller == "open-loop" or not regularizer):
        return "gauss-newton"
    return "lbfgs" if controller == "open-loop" else "adam"


def check_control_optimizer(optimizer: str, controller: str, target_com, regularizer: float) -> str | None:
    """Why ``optimizer`` cannot run ``controller`` on this loss, or None where it can."""
    if optimizer not in CONTROL_OPTIMIZERS[controller]:
        return f"unknown value {optimizer!r}; one of: {', '.join(CONTROL_OPTIMIZERS[controller])}"
    if optimizer == "gauss-newton" and target_com is None:
        return ("gauss-newton fits a centre-of-mass target (control.loss.com); use "
                f"{default_control_optimizer(controller, None, regularizer)} with target positions")
    if optimizer == "gauss-newton" and controller == "mlp" and regularizer:
        return "gauss-newton trains the MLP without a regulariser; use adam with control.regularizer"
    return None


ESTIMATION_OPTIMIZERS = ("lbfgs", "adam", "seed-sgd", "cmaes", "multistart", "smoothed")
"""Optimisers of an ``[estimate]`` task."""
MATERIAL_PARTS = ("density", "stretching", "bending")
"""The parts of a material an ``[estimate]`` task may free."""


def _choice(value: Any, path: str, choices: tuple[str, ...]) -> str:
    value = _str(value, path)
    if value not in choices:
        raise _err(path, f"unknown value {value!r}; one of: {', '.join(choices)}")
    return value


def _steps_within(table: dict, path: str, sim_steps: int) -> int:
    return _int(table.get("steps", sim_steps), f"{path}.steps", min_value=1)


def _parse_control(table: dict, dt: float, sim_steps: int, first: int, count: int, grid_res, attached: dict[int, str],
                   base_dir: Path) -> ControlSpec:
    keys = ("particles", "grid_vertices", "interval", "intervals", "steps", "loss", "regularizer", "controller",
            "optimizer", "iters", "search", "warm_start")
    _check_keys(table, "control", keys, required=("interval", "intervals", "loss"))
    if ("particles" in table) == ("grid_vertices" in table):
        raise _err("control", "give exactly one of 'particles' and 'grid_vertices' (the pushed particles)")
    key = "particles" if "particles" in table else "grid_vertices"
    values = table[key]
    if not isinstance(values, list) or not values:
        raise _err(f"control.{key}", f"expected a non-empty array, got {_type_name(values)}")
    particles = []
    for k, value in enumerate(values):
        item = f"control.{key}[{k}]"
        if key == "particles":
            p = _int(value, item, min_value=0)
            if p >= count:
                raise _err(item, f"particle {p} out of range: the cloth has {count} particles")
        else:
            if grid_res is None:
                raise _err(f"control.{key}", "needs a grid cloth (cloth.grid)")
            p = _grid_vertex(value, item, grid_res)
        if p in particles:
            raise _err(item, f"particle {p} is pushed twice")
        if attached.get(p, "").startswith("pins"):
            raise _err(item, f"particle {p} is pinned by {attached[p]}: a push on it would do nothing")
        particles.append(p)

    interval = _float(table["interval"], "control.interval", min_value=0.0, strict=True)
    interval_steps = round(interval / dt)
    if interval_steps < 1 or abs(interval_steps * dt - interval) > 1e-9 * interval:
        raise _err("control.interval", f"{interval:g} s is not a whole number of sim.dt = {dt:g} s steps")
    intervals = _int(table["intervals"], "control.intervals", min_value=1)
    steps = _steps_within(table, "control", sim_steps)
    if intervals * interval_steps > steps:
        raise _err("control.intervals", f"{intervals} pushes of {interval_steps} steps outlast the horizon of "
                                        f"{steps} steps")

    loss = _table(table["loss"], "control.loss")
    _check_keys(loss, "control.loss", ("com", "positions"))
    if len(loss) != 1:
        raise _err("control.loss", "give exactly one of 'com' (a centre-of-mass target [m]) and 'positions' (an OBJ "
                                   "file of every particle's target)")
    target_com = target_positions = None
    if "com" in loss:
        target_com = _vector(loss["com"], "control.loss.com")
    else:
        file = _existing_file(base_dir, loss["positions"], "control.loss.positions", "control.loss.positions")
        with _Context("control.loss.positions"):
            target_positions = mesh_io.load_obj(file, validate=False).positions
        if len(target_positions) != count:
            raise _err("control.loss.positions", f"{file.name} has {len(target_positions)} vertices, the cloth has "
                                                 f"{count}")
        if not np.all(np.isfinite(target_positions)):
            raise _err("control.loss.positions", f"{file.name} has non-finite positions")
    regularizer = _float(table.get("regularizer", 0.0), "control.regularizer", min_value=0.0)
    controller = _choice(table.get("controller", "open-loop"), "control.controller", CONTROLLERS)
    optimizer = _str(table.get("optimizer", default_control_optimizer(controller, target_com, regularizer)),
                     "control.optimizer")
    problem = check_control_optimizer(optimizer, controller, target_com, regularizer)
    if problem:
        raise _err("control.optimizer", problem)
    iters = _int(table.get("iters", 50 if controller == "open-loop" else 100), "control.iters", min_value=1)
    search = _parse_search(table, "control", optimizer, iters)
    warm_start = 0
    if "warm_start" in table:
        if controller != "mlp":
            raise _err("control.warm_start", f"warm-starts the MLP controller, not {controller!r}")
        warm_start = _int(table["warm_start"], "control.warm_start", min_value=0)
        if warm_start >= iters:
            raise _err("control.warm_start", f"{warm_start} simulations leave nothing of control.iters = {iters} to "
                                             "the MLP")
    return ControlSpec(particles=tuple(first + p for p in particles), interval_steps=interval_steps,
                       intervals=intervals, steps=steps, target_com=target_com, target_positions=target_positions,
                       regularizer=regularizer, controller=controller, optimizer=optimizer, iters=iters, search=search,
                       warm_start=warm_start)


def _parse_search(table: dict, path: str, optimizer: str, iters: int) -> SearchSpec:
    """The ``search`` table of a ``[control]`` or ``[estimate]`` task (only with ``optimizer = "cmaes"``)."""
    if "search" not in table:
        return SearchSpec()
    if optimizer not in GLOBAL_OPTIMIZERS:
        raise _err(f"{path}.search", f"configures a global search ({' or '.join(GLOBAL_OPTIMIZERS)}), not optimizer = "
                                     f"{optimizer!r}")
    search = _table(table["search"], f"{path}.search")
    refine_key = ("refine",) if optimizer != "multistart" else ()  # the multistart has no local stage of its own
    _check_keys(search, f"{path}.search", ("population", "sigma", "seed") + refine_key)
    population = sigma = refine = None
    if "population" in search:
        population = _int(search["population"], f"{path}.search.population", min_value=2)
        if optimizer == "multistart" and population > iters:
            raise _err(f"{path}.search.population", f"{population} starts for {path}.iters = {iters} simulations: "
                                                    "each start needs one at least")
    if "sigma" in search:
        sigma = _float(search["sigma"], f"{path}.search.sigma", min_value=0.0, strict=True)
    if "refine" in search:
        refine = _int(search["refine"], f"{path}.search.refine", min_value=0)
        if refine >= iters:
            raise _err(f"{path}.search.refine", f"{refine} simulations leave nothing of {path}.iters = {iters} to "
                                                "the global search")
    seed = _int(search.get("seed", 0), f"{path}.search.seed", min_value=0)
    return SearchSpec(population=population, sigma=sigma, refine=refine, seed=seed)


def _parse_estimate(table: dict, sim_steps: int, count: int, cloth_material: _materials.Material,
                    base_dir: Path) -> EstimateSpec:
    keys = ("targets", "frame_stride", "steps", "start", "free", "optimizer", "iters", "search")
    _check_keys(table, "estimate", keys)
    frame_stride = _int(table.get("frame_stride", 1), "estimate.frame_stride", min_value=1)
    steps = _steps_within(table, "estimate", sim_steps)
    if steps % frame_stride:
        raise _err("estimate.frame_stride", f"the {steps} steps compared are not a whole number of frames of "
                                            f"{frame_stride} steps")
    targets = source = None
    if "targets" in table:
        directory = base_dir / _str(table["targets"], "estimate.targets")
        with _Context("estimate.targets"):
            targets = mesh_io.load_obj_sequence(mesh_io.obj_sequence_files(directory))
        source = str(directory)
        if targets[0].shape[0] != count:
            raise _err("estimate.targets", f"its frames have {targets[0].shape[0]} vertices, the cloth has {count}")
        need = steps // frame_stride + 1
        if len(targets) < need:
            raise _err("estimate.targets", f"{steps} steps compare {need} frames (frame 0 included) every "
                                           f"{frame_stride} steps, but {directory} holds {len(targets)}")
    thicken = cloth_material.thicken
    if "start" in table:
        start = _parse_material(table["start"], "estimate.start", thicken, base_dir)
    else:  # the seed's start: the mean of 8 measured fabrics
        start = _materials.mean_material(_materials.SEED_INITIAL_GUESS_NAMES, thicken=thicken)
    free = table.get("free", list(MATERIAL_PARTS))
    if not isinstance(free, list) or not free:
        raise _err("estimate.free", f"expected a non-empty array of {', '.join(MATERIAL_PARTS)}")
    free = tuple(_choice(v, f"estimate.free[{k}]", MATERIAL_PARTS) for k, v in enumerate(free))
    if len(set(free)) != len(free):
        k = next(k for k in range(len(free)) if free[k] in free[:k])
        raise _err(f"estimate.free[{k}]", f"names {free[k]!r} a second time")
    optimizer = _choice(table.get("optimizer", "lbfgs"), "estimate.optimizer", ESTIMATION_OPTIMIZERS)
    if optimizer == "seed-sgd" and set(free) != set(MATERIAL_PARTS):
        raise _err("estimate.optimizer", "seed-sgd fits the whole material; use lbfgs or adam to free only some of it")
    iters = _int(table.get("iters", 100), "estimate.iters", min_value=1)
    search = _parse_search(table, "estimate", optimizer, iters)
    return EstimateSpec(targets=targets, targets_source=source, frame_stride=frame_stride, steps=steps, start=start,
                        free=free, optimizer=optimizer, iters=iters, search=search)
