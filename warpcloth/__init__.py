"""warpcloth: differentiable implicit cloth simulation in NVIDIA Warp (Liang, Lin and Koltun, NeurIPS 2019)."""

from warpcloth.builder import ModelBuilder
from warpcloth.materials import PRESET_NAMES, Material, mean_material, preset
from warpcloth.mesh_io import TriangleMesh, load_obj, load_usd_mesh
from warpcloth.model import Control, Model, State
from warpcloth.rollout import rollout
from warpcloth.simulator import SimulationError, Simulator, SolverOptions

__all__ = [
    "Control",
    "Material",
    "Model",
    "ModelBuilder",
    "PRESET_NAMES",
    "SimulationError",
    "Simulator",
    "SolverOptions",
    "State",
    "TriangleMesh",
    "load_obj",
    "load_usd_mesh",
    "mean_material",
    "preset",
    "rollout",
]
