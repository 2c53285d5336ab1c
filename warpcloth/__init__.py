"""warpcloth: differentiable implicit cloth simulation in NVIDIA Warp (Liang, Lin and Koltun, NeurIPS 2019)."""

from warpcloth.builder import ModelBuilder
from warpcloth.materials import PRESET_NAMES, Material, load_material_json, mean_material, preset
from warpcloth.mesh_io import TriangleMesh, grid_mesh, load_obj, load_usd_mesh
from warpcloth.model import CollisionSettings, Control, Model, State
from warpcloth.obstacles import (
    Obstacle,
    RigidMotion,
    box_mesh,
    funnel_mesh,
    obstacle_meshes_numpy,
    obstacle_points,
    obstacle_points_numpy,
    plane_mesh,
    sphere_mesh,
)
from warpcloth.presets import PRESET_SOLVER_NAMES, SolverPreset, solver_preset
from warpcloth.rollout import rollout
from warpcloth.scene import SCENE_NAMES, Scene, load_scene
from warpcloth.simulator import SimulationError, Simulator, SolverOptions
from warpcloth.usd import read_usd_points, write_usd

__all__ = [
    "CollisionSettings",
    "Control",
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
    "Simulator",
    "SolverOptions",
    "SolverPreset",
    "State",
    "TriangleMesh",
    "box_mesh",
    "funnel_mesh",
    "grid_mesh",
    "load_material_json",
    "load_obj",
    "load_scene",
    "load_usd_mesh",
    "mean_material",
    "obstacle_meshes_numpy",
    "obstacle_points",
    "obstacle_points_numpy",
    "plane_mesh",
    "preset",
    "read_usd_points",
    "rollout",
    "solver_preset",
    "sphere_mesh",
    "write_usd",
]
