"""Scenes: TOML files that describe one cloth, its material, handles, pins, forces, obstacles and collisions, and may
carry a task (:mod:`warpcloth.tasks.specs`); the embedded ones are ``warpcloth/scenes/*.toml``. Every key is checked;
the schema, with units and defaults: docs/concepts/scenes-and-tasks.md, "The schema"."""

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
from warpcloth._toml_fields import (
    _check_keys,
    _Context,
    _err,
    _existing_file,
    _float,
    _grid_index,
    _grid_vertex,
    _int,
    _parse_material,
    _particle_indices,
    _SceneError,
    _str,
    _table,
    _type_name,
    _vector,
)
from warpcloth.builder import DEFAULT_HANDLE_STIFFNESS
from warpcloth.geometry.transforms import QUAT_UNIT_TOL
from warpcloth.tasks.specs import ControlSpec, EstimateSpec, GripperControlSpec, parse_control, parse_estimate

__all__ = ["DEFAULT_SCENE", "SCENE_NAMES", "Scene", "load_scene", "scene_from_toml"]

DEFAULT_SCENE = "hanging-wind"
"""The scene ``warpcloth simulate`` runs when none is named."""

SCENE_NAMES: tuple[str, ...] = tuple(
    sorted(p.name[: -len(".toml")] for p in resources.files("warpcloth.scenes").iterdir() if p.name.endswith(".toml"))
)
"""Names of the embedded scenes."""

_DEFAULT_GRAVITY = (0.0, 0.0, -9.8)
_PLAIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")


@dataclass
class Scene:
    """A loaded scene: its builder (already holding the cloth, handles and forces) and run settings.

    Attributes:
        dt: Time step [s].
        steps: Steps to simulate.
        model_builder: A ``ModelBuilder`` with everything added; :meth:`build` finalises it.
        source: Where the scene came from (file path, or ``embedded:<name>``).
        grid_res: (cells_x, cells_y) of a grid cloth, else None; vertex (i, j) is particle ``j * (cells_x + 1) + i``.
        max_dt: The solver preset's time-step ceiling [s], else None (:meth:`set_dt` keeps to it).
        control: The checked ``[control]`` table, else None; ``estimate`` likewise.
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
    control: ControlSpec | GripperControlSpec | None = None
    estimate: EstimateSpec | None = None

    MAX_FRAME_BYTES = 4 * 2**30
    """Most memory the frames of one ``warpcloth simulate`` run may take (they are kept until the USD is written)."""

    def set_dt(self, dt: float) -> None:
        """Change the time step; ValueError for a dt not finite and > 0, above the preset's ceiling ``max_dt``, or in
        a scene whose ``[estimate]`` recording is timed by ``frame_rate`` (its frames fall on the file's steps)."""
        if not (isinstance(dt, (int, float)) and 0.0 < dt < math.inf):
            raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
        if self.estimate is not None and self.estimate.frame_rate is not None and dt != self.dt:
            raise ValueError(f"scene {self.name!r}: its recording's frames ({self.estimate.frame_rate:g} a second) "
                             f"fall on its steps of {self.dt:g} s; change dt and frame_rate in the scene file")
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
        """``(model, sim)``: :meth:`finalize`'s model and a ``Simulator`` with the scene's ``dt`` and solver options."""
        from warpcloth.solver.simulator import Simulator

        model = self.finalize(device=device, requires_grad=requires_grad, dtype=dtype)
        sim = Simulator(model, dt=self.dt, options=self.solver_options)
        return model, sim


    def finalize(self, device=None, requires_grad: bool = False, dtype=None):
        """The scene's ``Model`` on ``device`` (Warp's default when None), in ``dtype`` (None: ``wp.float32``)."""
        if dtype is None:
            return self.model_builder.finalize(device=device, requires_grad=requires_grad)
        return self.model_builder.finalize(device=device, requires_grad=requires_grad, dtype=dtype)


def load_scene(name_or_path: str | os.PathLike) -> Scene:
    """Loads an embedded scene by name (one of :data:`SCENE_NAMES`), or a ``.toml`` scene file by path.

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
    """Parses a scene from TOML text (schema: docs/concepts/scenes-and-tasks.md).

    Args:
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
# Parsing. Each check takes the key path of the value it checks, so every error names it (warpcloth/_toml_fields.py).


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



# ----------------------------------------------------------------------------------------------------------------------


def _parse(data: dict, *, source: str, base_dir: Path) -> Scene:
    from warpcloth.builder import ModelBuilder

    _check_keys(
        data,
        "",
        (
            "name", "description", "gravity", "sim", "solver", "cloth", "handles", "pins", "grippers", "wind",
            "damping", "obstacles", "collision", "control", "estimate",
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

    grippers = data.get("grippers", [])
    if not isinstance(grippers, list):
        raise _err("grippers", f"expected an array of tables ([[grippers]]), got {_type_name(grippers)}")
    for k, entry in enumerate(grippers):
        _parse_gripper(builder, f"grippers[{k}]", _table(entry, f"grippers[{k}]"), first, count, grid_res, attached)

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
        control = parse_control(_table(data["control"], "control"), dt, steps, first, count, grid_res, attached,
                                base_dir)
        if isinstance(control, GripperControlSpec) and not grippers:
            raise _err("control.controls", "'grippers' moves the scene's grippers, and it has no [[grippers]] table")
    if "estimate" in data:
        estimate = parse_estimate(_table(data["estimate"], "estimate"), steps, count, cloth_material, base_dir, dt)

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



_SELECTORS = ("particle", "grid_vertex", "grid_row", "grid_column")


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


_GRIPPER_LIMITS = ("max_speed", "max_acceleration", "max_yaw_rate", "max_yaw_acceleration", "stiffness")


def _parse_gripper(builder, path: str, entry: dict, first: int, count: int, grid_res, attached: dict[int, str]) -> None:
    """A ``[[grippers]]`` table: the held particles (one selector), grasp, release, knots and limits."""
    from warpcloth.grippers import Gripper

    selectors = ("particles", "grid_vertices", "grid_row", "grid_column")
    _check_keys(entry, path, ("name", "grasp", "release", "knots") + selectors + _GRIPPER_LIMITS,
                required=("knots",))
    given = [key for key in selectors if key in entry]
    if len(given) != 1:
        raise _err(path, f"give exactly one of {', '.join(selectors)} (the held particles)")
    key = given[0]
    value = entry[key]
    if key != "particles" and grid_res is None:
        raise _err(f"{path}.{key}", "needs a grid cloth (cloth.grid)")
    if key in ("particles", "grid_vertices"):
        particles = _particle_indices(value, f"{path}.{key}", count, grid_res, grid=key == "grid_vertices")
    else:
        nx, ny = grid_res[0] + 1, grid_res[1] + 1
        if key == "grid_row":
            j = _grid_index(_int(value, f"{path}.{key}"), ny, f"{path}.{key}")
            particles = [j * nx + i for i in range(nx)]
        else:
            i = _grid_index(_int(value, f"{path}.{key}"), nx, f"{path}.{key}")
            particles = [j * nx + i for j in range(ny)]
    for p in particles:
        other = attached.get(p)
        if other is not None:
            raise _err(path, f"particle {p} is also held by {other}; a gripper's particles take no other handle or "
                             "pin")
        attached[p] = path
    knots = entry["knots"]
    if not isinstance(knots, list) or len(knots) < 2:
        raise _err(f"{path}.knots", "expected an array of at least 2 tables { t, pos, yaw }")
    times, positions, yaws = [], [], []
    for k, knot in enumerate(knots):
        kp = f"{path}.knots[{k}]"
        knot = _table(knot, kp)
        _check_keys(knot, kp, ("t", "pos", "yaw"), required=("t", "pos"))
        times.append(_float(knot["t"], f"{kp}.t"))
        positions.append(_vector(knot["pos"], f"{kp}.pos"))
        if ("yaw" in knot) != ("yaw" in knots[0]):
            raise _err(f"{kp}.yaw", "give yaw [rad] at every knot of a gripper or at none")
        if "yaw" in knot:
            yaws.append(_float(knot["yaw"], f"{kp}.yaw"))
    options = {name: _float(entry[name], f"{path}.{name}", min_value=0.0, strict=True)
               for name in _GRIPPER_LIMITS if name in entry}
    grasp = _float(entry.get("grasp", times[0]), f"{path}.grasp")
    release = entry.get("release", math.inf)
    release = release if release == math.inf else _float(release, f"{path}.release")
    name = _str(entry.get("name", path), f"{path}.name")
    try:  # the gripper's errors name it (its path, or the path and its name)
        gripper = Gripper(particles=tuple(first + p for p in particles), times=times, positions=positions,
                          yaw=yaws or None, grasp=grasp, release=release, name=name, **options)
        builder.add_gripper(gripper)
    except ValueError as exc:
        raise _SceneError(str(exc) if name == path else f"{path}: {exc}") from None


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
