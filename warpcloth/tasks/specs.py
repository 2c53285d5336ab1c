"""A scene's ``[control]`` and ``[estimate]`` tables, checked, and the optimisers and rules the task modules, the CLI
and the parser share. Keys, units and defaults: docs/concepts/scenes-and-tasks.md, "The schema"."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from warpcloth import materials as _materials
from warpcloth import mesh_io, recordings
from warpcloth._toml_fields import (
    _check_keys,
    _choice,
    _Context,
    _err,
    _existing_file,
    _float,
    _int,
    _parse_material,
    _particle_indices,
    _str,
    _table,
    _type_name,
    _vector,
)
from warpcloth.observations import MarkerFrames, PointCloudFrames
from warpcloth.tasks.parameters import NOT_OFFERED, SCENE_PARAMETERS

__all__ = ["CONTROLLERS", "GRIPPER_LOSSES", "GRIPPER_OPTIMIZERS", "GripperControlSpec",
           "CONTROL_OPTIMIZERS", "DEFAULT_CONTROL_ITERS", "ESTIMATION_OPTIMIZERS", "GLOBAL_OPTIMIZERS",
           "FREE_PARAMETERS", "MATERIAL_PARTS", "ControlSpec", "EstimateSpec", "SearchSpec", "check_control_optimizer",
           "check_waypoints", "default_control_optimizer", "parse_control", "parse_estimate"]


@dataclass(frozen=True)
class SearchSpec:
    """A global search's settings, the ``search`` table of a task whose optimiser is in :data:`GLOBAL_OPTIMIZERS`;
    None takes the task's default.

    Attributes:
        population: CMA-ES's points per generation (default 4 + floor(3 ln n), n parameters); the multistart's starts
            or the smoothed search's copies a step (default 8, even).
        sigma: The initial spread, in the parameters' units (default the task's ``SEARCH_SIGMA`` or ``SMOOTHED_SIGMA``).
        refine: CMA-ES and the smoothed search: simulations left to the local optimiser (default a fifth).
        seed: Seed of the search's random numbers.
    """

    population: int | None = None
    sigma: float | None = None
    refine: int | None = None
    seed: int = 0


@dataclass
class ControlSpec:
    """A scene's ``[control]`` table, checked: the arguments of the same names of
    :class:`~warpcloth.tasks.control.ControlTask` (``ControlTask.from_scene``), ``particles`` as model indices and
    ``interval_steps`` the table's ``interval`` [s] in steps."""

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
    push_bound: float | None = None
    waypoints: tuple = ()


GRIPPER_OPTIMIZERS = ("lbfgs", "adam", "compass", "cmaes", "random")
"""The optimisers of a gripper task: local on the gradient (lbfgs, adam), or forward-only searches."""
GRIPPER_LOSSES = ("coverage", "points", "positions")
"""The goals of a ``[control]`` table with ``controls = "grippers"`` (:mod:`warpcloth.goals`)."""


@dataclass
class GripperControlSpec:
    """A scene's ``[control]`` table with ``controls = "grippers"``, checked (``GripperTask.from_scene``).

    Attributes:
        loss: The goal, ``(kind, arguments)``: ``("coverage", {"table_height", "flat_tolerance"})``,
            ``("points", {"points": (P, 3)})`` or ``("positions", {"positions": (n, 3)})`` [m].
        acceleration_weight, path_weight, optimizer, iters, sigma, seed, tied: ``GripperTask``'s.
    """

    steps: int
    loss: tuple[str, dict]
    acceleration_weight: float = 0.0
    path_weight: float = 0.0
    optimizer: str = "lbfgs"
    iters: int = 50
    sigma: float = 0.05
    seed: int = 0
    tied: bool = False

    def goal(self, model):
        """The goal on ``model`` (ValueError from :mod:`warpcloth.goals`, e.g. coverage without a table)."""
        from warpcloth import goals

        kind, args = self.loss
        if kind == "coverage":
            return goals.Coverage(model, **args)
        if kind == "points":
            return goals.TargetPoints(model, args["points"])
        return goals.TargetPositions(model, args["positions"])


def _parse_gripper_control(table: dict, sim_steps: int, count: int, base_dir: Path) -> GripperControlSpec:
    keys = ("controls", "steps", "loss", "acceleration_weight", "path_weight", "optimizer", "iters", "sigma", "seed",
            "tied")
    _check_keys(table, "control", keys, required=("loss",))
    steps = _steps_within(table, "control", sim_steps)
    loss = _table(table["loss"], "control.loss")
    _check_keys(loss, "control.loss", GRIPPER_LOSSES)
    if len(loss) != 1:
        raise _err("control.loss", f"give exactly one of {', '.join(GRIPPER_LOSSES)}")
    kind = next(iter(loss))
    path = f"control.loss.{kind}"
    if kind == "coverage":
        cov = _table(loss[kind], path)
        _check_keys(cov, path, ("table_height", "flat_tolerance"), required=("table_height",))
        args = {"table_height": _float(cov["table_height"], f"{path}.table_height")}
        if "flat_tolerance" in cov:
            args["flat_tolerance"] = _float(cov["flat_tolerance"], f"{path}.flat_tolerance", min_value=0.0,
                                            strict=True)
    else:
        file = _existing_file(base_dir, loss[kind], path, path)
        with _Context(path):
            if file.suffix.lower() == ".npy":
                points = np.load(file)
            elif file.suffix.lower() == ".obj":
                points = mesh_io.load_obj(file, validate=False).positions
            else:
                raise ValueError(f"{file.name}: expected an .obj or .npy file of points")
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
            raise _err(path, f"{file.name} must hold finite points (P, 3), got shape {points.shape}")
        if kind == "positions" and len(points) != count:
            raise _err(path, f"{file.name} has {len(points)} vertices, the cloth has {count}")
        args = {kind: points}
    weights = {key: _float(table.get(key, 0.0), f"control.{key}", min_value=0.0)
               for key in ("acceleration_weight", "path_weight")}
    optimizer = _choice(table.get("optimizer", "lbfgs"), "control.optimizer", GRIPPER_OPTIMIZERS)
    iters = _int(table.get("iters", 50), "control.iters", min_value=1)
    sigma = _float(table.get("sigma", 0.05), "control.sigma", min_value=0.0, strict=True)
    seed = _int(table.get("seed", 0), "control.seed", min_value=0)
    tied = table.get("tied", False)
    if not isinstance(tied, bool):
        raise _err("control.tied", f"expected true or false, got {tied!r}")
    return GripperControlSpec(steps=steps, loss=(kind, args), optimizer=optimizer, iters=iters, sigma=sigma,
                              seed=seed, tied=tied, **weights)


@dataclass
class EstimateSpec:
    """A scene's ``[estimate]`` table, checked (``EstimationTask.from_scene``; ``start``, ``free``, ``optimizer``,
    ``iters`` and ``search`` as :class:`~warpcloth.tasks.estimation.EstimationTask`'s).

    Attributes:
        targets: The recording: vertex frames (particle_count, 3) [m] (OBJ files), or a
            :class:`~warpcloth.observations.PointCloudFrames` (``.ply``/``.npy`` files) or
            :class:`~warpcloth.observations.MarkerFrames` (``markers``); frame 0 at the start. None: simulated with
            the scene's cloth.
        targets_source: Where the recording came from, or None.
        frame_stride: Steps per target frame.
        steps: Steps compared.
        free: The material parts and scene parameters fitted (``FREE_PARAMETERS``).
        bounds: ``[low, high]`` of free scene parameters by name (``[estimate.bounds]``; each a number, +-inf for
            none, or one per entry).
        scales: The scale of free scene parameters by name (``[estimate.scales]``; a number or one per entry).
        start_shape: ``"scene"`` (the cloth as the scene places it) or ``"registered"`` (the scene's cloth
            registered to frame 0 of a point-cloud recording: :mod:`warpcloth.registration`).
        frame_rate: The recording's frames per second where the table gives it (``frame_stride`` follows from it
            and the scene's dt: :func:`warpcloth.recordings.frame_stride_of`), else None.
    """

    targets: list[np.ndarray] | PointCloudFrames | MarkerFrames | None
    targets_source: str | None
    frame_stride: int
    steps: int
    start: _materials.Material
    free: tuple[str, ...]
    optimizer: str
    iters: int
    search: SearchSpec = SearchSpec()
    bounds: dict = field(default_factory=dict)
    scales: dict = field(default_factory=dict)
    start_shape: str = "scene"
    frame_rate: float | None = None


START_SHAPES = ("scene", "registered")
"""Where a fit's cloth starts: as the scene places it, or registered to the recording's first frame."""
CONTROLLERS = ("open-loop", "mlp")
"""Controllers of a ``[control]`` task."""
CONTROL_OPTIMIZERS = {"open-loop": ("gauss-newton", "lbfgs", "multistart", "cmaes", "smoothed"),
                      "mlp": ("gauss-newton", "adam")}
"""Optimisers of each controller (Gauss-Newton needs a centre-of-mass target, and for the MLP no regulariser)."""
GLOBAL_OPTIMIZERS = ("multistart", "cmaes", "smoothed")
"""The optimisers that take a ``search`` table."""
DEFAULT_CONTROL_ITERS = {"open-loop": 50, "mlp": 100}
"""Simulations a controller spends where its task names none."""


def default_control_optimizer(controller: str, target_com, regularizer: float) -> str:
    """A controller's default optimiser: Gauss-Newton where it applies, else L-BFGS (open loop) or Adam (MLP)."""
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
FREE_PARAMETERS = MATERIAL_PARTS + tuple(SCENE_PARAMETERS)
"""What an ``[estimate]`` task may free: the material's parts and the scene parameters
(:data:`~warpcloth.tasks.parameters.SCENE_PARAMETERS`)."""


def _numbers(value, path: str, *, positive: bool = False) -> float | list[float]:
    # a number or an array of numbers (+-inf allowed unless positive; NaN never)
    items = value if isinstance(value, list) else [value]
    if not items:
        raise _err(path, "expected a number or a non-empty array of numbers")
    for k, v in enumerate(items):
        where = f"{path}[{k}]" if isinstance(value, list) else path
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise _err(where, f"expected a number, got {_type_name(v)}")
        if v != v or (positive and not (0.0 < v < float("inf"))):
            raise _err(where, f"must be {'finite and > 0' if positive else 'a number (+-inf for no bound)'}, got {v}")
    return [float(v) for v in value] if isinstance(value, list) else float(value)


def _parse_parameter_options(table: dict, free: tuple[str, ...]) -> tuple[dict, dict]:
    out = []
    for key in ("bounds", "scales"):
        path = f"estimate.{key}"
        options = _table(table.get(key, {}), path)
        parsed = {}
        for name, value in options.items():
            if name not in SCENE_PARAMETERS or name not in free:
                raise _err(f"{path}.{name}", f"not a free scene parameter (free: {', '.join(free)})")
            if key == "scales":
                parsed[name] = _numbers(value, f"{path}.{name}", positive=True)
                continue
            if not isinstance(value, list) or len(value) != 2:
                raise _err(f"{path}.{name}", "expected [low, high]")
            parsed[name] = [_numbers(v, f"{path}.{name}[{k}]") for k, v in enumerate(value)]
        out.append(parsed)
    return out[0], out[1]


def _steps_within(table: dict, path: str, sim_steps: int) -> int:
    return _int(table.get("steps", sim_steps), f"{path}.steps", min_value=1)


def check_waypoints(waypoints, dt: float, steps: int) -> tuple:
    """Waypoints ``(time [s], (x, y, z) [m], weight >= 0)`` as ``(step, target (3,), weight)``, each time a whole
    step of ``dt`` in (0, ``steps`` dt]; ValueError names the bad waypoint."""
    out = []
    for k, waypoint in enumerate(waypoints):
        try:
            t, target, weight = waypoint
            t, weight = float(t), float(weight)
            target = np.asarray(target, dtype=np.float64).reshape(3)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"waypoint {k}: give (time [s], (x, y, z) [m], weight), got {waypoint!r}") from exc
        step = round(t / dt) if math.isfinite(t) else 0
        if not (1 <= step <= steps and abs(t / dt - step) <= 1e-6 * max(1, step)):
            raise ValueError(f"waypoint {k}: time {t!r} s is not a whole step of dt = {dt} s within the horizon "
                             f"(0, {steps * dt:g}] s")
        if not np.all(np.isfinite(target)):
            raise ValueError(f"waypoint {k}: target must be finite, got {target.tolist()}")
        if not (weight >= 0.0 and math.isfinite(weight)):
            raise ValueError(f"waypoint {k}: weight must be finite and >= 0, got {weight!r}")
        out.append((step, target, weight))
    return tuple(out)


def parse_control(table: dict, dt: float, sim_steps: int, first: int, count: int, grid_res, attached: dict[int, str],
                  base_dir: Path) -> ControlSpec | GripperControlSpec:
    """The ``[control]`` table of a scene of ``sim_steps`` steps of ``dt`` [s] whose cloth has ``count`` particles from
    ``first`` (``grid_res``: its grid cells, None for a mesh; ``attached``: particle -> the entry that holds it; paths
    relative to ``base_dir``). With ``controls = "grippers"``, a :class:`GripperControlSpec`. ValueError names the
    key path of the first bad value."""
    controls = _choice(table.get("controls", "pushes"), "control.controls", ("pushes", "grippers"))
    if controls == "grippers":
        return _parse_gripper_control(table, sim_steps, count, base_dir)
    table = {k: v for k, v in table.items() if k != "controls"}
    keys = ("particles", "grid_vertices", "interval", "intervals", "steps", "loss", "regularizer", "push_bound",
            "waypoints", "controller", "optimizer", "iters", "search", "warm_start")
    _check_keys(table, "control", keys, required=("interval", "intervals", "loss"))
    if ("particles" in table) == ("grid_vertices" in table):
        raise _err("control", "give exactly one of 'particles' and 'grid_vertices' (the pushed particles)")
    key = "particles" if "particles" in table else "grid_vertices"
    particles = []
    indices = _particle_indices(table[key], f"control.{key}", count, grid_res, grid=key == "grid_vertices")
    for k, p in enumerate(indices):
        item = f"control.{key}[{k}]"
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
    push_bound = None
    if "push_bound" in table:
        push_bound = _float(table["push_bound"], "control.push_bound", min_value=0.0, strict=True)
    controller = _choice(table.get("controller", "open-loop"), "control.controller", CONTROLLERS)
    waypoints = _parse_waypoints(table, dt, steps) if "waypoints" in table else ()
    if waypoints and controller != "open-loop":
        raise _err("control.waypoints", "the MLP controller fits the horizon's loss only; use the open loop")
    default = default_control_optimizer(controller, target_com, regularizer)
    if waypoints and default == "gauss-newton":
        default = "lbfgs"
    optimizer = _str(table.get("optimizer", default), "control.optimizer")
    problem = check_control_optimizer(optimizer, controller, target_com, regularizer)
    if problem is None and waypoints and optimizer == "gauss-newton":
        problem = "gauss-newton fits the horizon's centre of mass only; use lbfgs or a search with waypoints"
    if problem:
        raise _err("control.optimizer", problem)
    iters = _int(table.get("iters", DEFAULT_CONTROL_ITERS[controller]), "control.iters", min_value=1)
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
                       warm_start=warm_start, push_bound=push_bound, waypoints=waypoints)


def _parse_waypoints(table: dict, dt: float, steps: int) -> tuple:
    values = table["waypoints"]
    if not isinstance(values, list) or not values:
        raise _err("control.waypoints", f"expected a non-empty array of [time, [x, y, z], weight], got "
                                        f"{_type_name(values)}")
    out = []
    for k, value in enumerate(values):
        item = f"control.waypoints[{k}]"
        if not isinstance(value, list) or len(value) != 3:
            raise _err(item, f"expected [time [s], [x, y, z] [m], weight], got {value!r}")
        out.append((_float(value[0], f"{item}[0]"), _vector(value[1], f"{item}[1]"),
                    _float(value[2], f"{item}[2]", min_value=0.0)))
    try:
        check_waypoints(out, dt, steps)
    except ValueError as exc:
        raise _err("control.waypoints", str(exc)) from None
    return tuple(out)  # as ControlTask takes them: (time [s], target, weight)


def _parse_search(table: dict, path: str, optimizer: str, iters: int) -> SearchSpec:
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


def _parse_recording(table: dict, base_dir: Path, count: int, need: int, frame_stride: int, steps: int):
    """The recording of ``[estimate]``: (observation or vertex frames, its path), or (None, None) without one."""
    if "targets" in table and "markers" in table:
        raise _err("estimate.markers", "a scene fits one recording: give targets or markers, not both")
    for key in ("huber", "trimmed", "both_ways", "frame_count"):
        if key in table and "targets" not in table:
            raise _err(f"estimate.{key}", "applies to a point-cloud recording (estimate.targets)")
    if "markers" in table:
        path = base_dir / _str(table["markers"], "estimate.markers")
        with _Context("estimate.markers"):
            markers = recordings.read_markers(path)
            recording = MarkerFrames(markers.triangles, markers.barycentric, markers.positions)
        frames, source = recording.frame_count, str(path)
    elif "targets" in table:
        directory = base_dir / _str(table["targets"], "estimate.targets")
        source = str(directory)
        if recordings.holds_point_clouds(directory):
            if "huber" in table and "trimmed" in table:
                raise _err("estimate.trimmed", "give huber or trimmed, not both")
            robust = None
            if "huber" in table:
                robust = ("huber", _float(table["huber"], "estimate.huber", min_value=0.0, strict=True))
            elif "trimmed" in table:
                fraction = _float(table["trimmed"], "estimate.trimmed", min_value=0.0, strict=True)
                if fraction >= 1.0:
                    raise _err("estimate.trimmed", f"the fraction of points left out must be below 1, got {fraction:g}")
                robust = ("trimmed", fraction)
            both_ways = table.get("both_ways", False)
            if not isinstance(both_ways, bool):
                raise _err("estimate.both_ways", f"expected true or false, got {both_ways!r}")
            with _Context("estimate.targets"):
                indices, clouds = recordings.read_point_clouds(directory)
            length = int(indices[-1]) + 1
            if "frame_count" in table:  # frames dropped after the last file count as dropped
                declared = _int(table["frame_count"], "estimate.frame_count", min_value=1)
                if declared < length:
                    raise _err("estimate.frame_count", f"{declared} frames, but {directory} holds frame "
                                                       f"{length - 1}")
                length = declared
            with _Context("estimate.targets"):
                points = [None] * length
                for k, cloud in zip(indices, clouds):
                    points[int(k)] = cloud
                recording = PointCloudFrames(points, robust=robust, both_ways=both_ways)
            frames = recording.frame_count
        else:
            for key in ("huber", "trimmed", "both_ways", "frame_count"):
                if key in table:
                    raise _err(f"estimate.{key}", f"applies to a point-cloud recording; {directory} holds OBJ frames")
            with _Context("estimate.targets"):
                recording = mesh_io.load_obj_sequence(mesh_io.obj_sequence_files(directory))
            if recording[0].shape[0] != count:
                raise _err("estimate.targets", f"its frames have {recording[0].shape[0]} vertices, the cloth has "
                                               f"{count}")
            frames = len(recording)
    else:
        return None, None
    if frames < need:
        key = "estimate.markers" if "markers" in table else "estimate.targets"
        raise _err(key, f"{steps} steps compare {need} frames (frame 0 included) every {frame_stride} steps, but "
                        f"{source} holds {frames}")
    return recording, source


def parse_estimate(table: dict, sim_steps: int, count: int, cloth_material: _materials.Material,
                   base_dir: Path, dt: float) -> EstimateSpec:
    """The ``[estimate]`` table of a scene of ``sim_steps`` steps of ``dt`` [s] whose cloth has ``count`` particles
    and ``cloth_material`` (paths relative to ``base_dir``). ValueError names the key path of the first bad value."""
    keys = ("targets", "markers", "huber", "trimmed", "both_ways", "frame_count", "start_shape", "frame_stride",
            "frame_rate", "steps", "start", "free", "optimizer", "iters", "search", "bounds", "scales")
    _check_keys(table, "estimate", keys)
    frame_stride = _int(table.get("frame_stride", 1), "estimate.frame_stride", min_value=1)
    rate = None
    if "frame_rate" in table:
        rate = _float(table["frame_rate"], "estimate.frame_rate", min_value=0.0, strict=True)
        try:
            by_rate = recordings.frame_stride_of(rate, dt)
        except ValueError as exc:
            raise _err("estimate.frame_rate", str(exc)) from None
        if "frame_stride" in table and frame_stride != by_rate:
            raise _err("estimate.frame_stride", f"{frame_stride} steps a frame, but frame_rate {rate:g} at dt {dt:g} s "
                                                f"is {by_rate}; give one of them")
        frame_stride = by_rate
    steps = _steps_within(table, "estimate", sim_steps)
    if steps % frame_stride:
        raise _err("estimate.frame_stride" if rate is None else "estimate.frame_rate",
                   f"the {steps} steps compared are not a whole number of frames of {frame_stride} steps")
    targets, source = _parse_recording(table, base_dir, count, steps // frame_stride + 1, frame_stride, steps)
    start_shape = _choice(table.get("start_shape", "scene"), "estimate.start_shape", START_SHAPES)
    if start_shape == "registered" and not isinstance(targets, PointCloudFrames):
        raise _err("estimate.start_shape", "'registered' places the cloth on frame 0 of a point-cloud recording "
                                           "(estimate.targets of .ply or .npy files)")
    if start_shape == "registered" and targets.points[0] is None:
        raise _err("estimate.start_shape", f"'registered' needs frame 0, which {source} does not hold")
    thicken = cloth_material.thicken
    if "start" in table:
        start = _parse_material(table["start"], "estimate.start", thicken, base_dir)
    else:  # the seed's start: the mean of 8 measured fabrics
        start = _materials.mean_material(_materials.SEED_INITIAL_GUESS_NAMES, thicken=thicken)
    free = table.get("free", list(MATERIAL_PARTS))
    if not isinstance(free, list) or not free:
        raise _err("estimate.free", f"expected a non-empty array of {', '.join(MATERIAL_PARTS)} or scene parameters "
                                    f"({', '.join(SCENE_PARAMETERS)})")
    for k, v in enumerate(free):
        if isinstance(v, str) and v in NOT_OFFERED:
            raise _err(f"estimate.free[{k}]", f"{v!r} names no one parameter: {NOT_OFFERED[v]}")
    free = tuple(_choice(v, f"estimate.free[{k}]", FREE_PARAMETERS) for k, v in enumerate(free))
    if len(set(free)) != len(free):
        k = next(k for k in range(len(free)) if free[k] in free[:k])
        raise _err(f"estimate.free[{k}]", f"names {free[k]!r} a second time")
    optimizer = _choice(table.get("optimizer", "lbfgs"), "estimate.optimizer", ESTIMATION_OPTIMIZERS)
    if optimizer == "seed-sgd" and set(free) != set(MATERIAL_PARTS):
        raise _err("estimate.optimizer", "seed-sgd fits the whole material; use lbfgs or adam to free only some of it")
    iters = _int(table.get("iters", 100), "estimate.iters", min_value=1)
    search = _parse_search(table, "estimate", optimizer, iters)
    bounds, scales = _parse_parameter_options(table, free)
    return EstimateSpec(targets=targets, targets_source=source, frame_stride=frame_stride, steps=steps, start=start,
                        free=free, optimizer=optimizer, iters=iters, search=search, bounds=bounds, scales=scales,
                        start_shape=start_shape, frame_rate=rate)
