"""warpcloth: differentiable implicit cloth simulation in NVIDIA Warp (Liang, Lin and Koltun, NeurIPS 2019)."""


# First: from a source checkout, warpcloth.kernels is the checkout's kernels/ (warpcloth/_source_tree.py)
from warpcloth import _source_tree  # noqa: F401
from warpcloth.builder import ModelBuilder
from warpcloth.errors import CollisionError, ContactCapacityError, SimulationError
from warpcloth.geometry.primitives import box_mesh, funnel_mesh, plane_mesh, sphere_mesh
from warpcloth.grippers import Gripper
from warpcloth.materials import PRESET_NAMES, Material, load_material_json, mean_material, preset
from warpcloth.mesh_io import TriangleMesh, grid_mesh, load_obj, load_obj_sequence, load_usd_mesh, obj_sequence_files
from warpcloth.model import CollisionSettings, Control, Model, State
from warpcloth.obstacles import (
    Obstacle,
    RigidMotion,
    obstacle_meshes_numpy,
    obstacle_points,
    obstacle_points_numpy,
)
from warpcloth.preview import write_preview
from warpcloth.scene import SCENE_NAMES, Scene, load_scene
from warpcloth.solver import (
    PRESET_SOLVER_NAMES,
    CapturedRollout,
    CollisionOptions,
    LinearSolver,
    Simulator,
    SolveInfo,
    SolverOptions,
    SolverPreset,
    checkpointed_backward,
    rollout,
    solver_preset,
)
from warpcloth.usd import read_usd_points, write_usd


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("warpcloth")
    except PackageNotFoundError:  # a source tree that was never installed
        return "0+unknown"


__version__ = _version()
"""The installed distribution's version (``importlib.metadata``); ``warpcloth --version`` prints it."""

__all__ = [
    "CapturedRollout",
    "CollisionError",
    "CollisionOptions",
    "CollisionSettings",
    "ContactCapacityError",
    "Control",
    "Gripper",
    "LinearSolver",
    "Material",
    "Model",
    "ModelBuilder",
    "Obstacle",
    "PRESET_NAMES",
    "PRESET_SOLVER_NAMES",
    "RigidMotion",
    "SCENE_NAMES",
    "Scene",
    "SimulationError",
    "SolveInfo",
    "Simulator",
    "SolverOptions",
    "SolverPreset",
    "State",
    "TriangleMesh",
    "box_mesh",
    "checkpointed_backward",
    "funnel_mesh",
    "grid_mesh",
    "load_material_json",
    "load_obj",
    "load_obj_sequence",
    "load_scene",
    "load_usd_mesh",
    "mean_material",
    "obj_sequence_files",
    "obstacle_meshes_numpy",
    "obstacle_points",
    "obstacle_points_numpy",
    "plane_mesh",
    "preset",
    "read_usd_points",
    "rollout",
    "solver_preset",
    "sphere_mesh",
    "write_preview",
    "write_usd",
]
