"""The seed's motion control (SPEC §5(c)), the embedded scene ``basket-throw``'s ``[control]`` task: throw a cloth over
a wall into a basket by pushing its corners; the optimisers of :mod:`warpcloth.tasks.controllers` import from here."""

from __future__ import annotations

import functools

import numpy as np

import warpcloth as wc
from warpcloth.scene import load_scene
from warpcloth.tasks.control import ControlTask, scene_task_args

# the optimisers (warpcloth.tasks.controllers), importable from here too
from warpcloth.tasks.controllers import ControlResult, optimize_open_loop, optimize_open_loop_starts, train_mlp

__all__ = ["CORNERS", "DT", "N_PARAMS", "SCENE", "SECONDS_CONTROLLED", "SEED_PUBLISHED", "STEPS", "STEPS_PER_SECOND",
           "TARGET", "ControlResult", "ControlTask", "ThrowTask", "optimize_open_loop", "optimize_open_loop_starts",
           "train_mlp"]

SCENE = "basket-throw"
"""The embedded scene of the throw."""
_SCENE = load_scene(SCENE)
DT = _SCENE.dt
STEPS = _SCENE.control.steps
CORNERS = _SCENE.control.particles
"""The pushed corner particles."""
SECONDS_CONTROLLED = _SCENE.control.intervals
STEPS_PER_SECOND = _SCENE.control.interval_steps
TARGET = _SCENE.control.target_com
"""Bottom centre of the basket [m]."""
N_PARAMS = SECONDS_CONTROLLED * len(CORNERS) * 3

SEED_PUBLISHED = {
    "open-loop": {"error_pct": 17.0, "simulations": 53, "target_error_pct": 10.0, "target_simulations": 50},
    "mlp": {"error_pct": 39.0, "simulations": 108, "target_error_pct": 20.0, "target_simulations": 100},
}
"""The seed's Table 3 ("Ours" and "Ours + FC") and this project's targets."""


class ThrowTask(ControlTask):
    """``ControlTask.from_scene("basket-throw")`` on another ``model`` (default the scene's, float32, on Warp's default
    device), ``steps`` or ``options``. Only the embedded scene's model batches worlds in ``evaluate_many``."""

    def __init__(self, model: wc.Model | None = None, *, steps: int = STEPS, options: wc.SolverOptions | None = None,
                 segment_steps: int | None = None):
        model = model or _SCENE.finalize(requires_grad=True)
        super().__init__(model, **scene_task_args(_SCENE, steps=steps, options=options, segment_steps=segment_steps),
                         template=_SCENE.model_builder if _is_the_scene(model) else None)
        self.name = _SCENE.name


def _is_the_scene(model: wc.Model) -> bool:
    # whether model is one world of the embedded scene, whatever its device and precision
    x0, names = _scene_start()
    return (model.world_count == 1 and model.particle_count == len(x0) and list(model.obstacle_names) == names
            and np.allclose(model.particle_x0.numpy(), x0, rtol=0.0, atol=1e-6))


@functools.cache
def _scene_start() -> tuple[np.ndarray, list[str]]:
    # the embedded scene's start positions and obstacle names (a model finalised once on the CPU)
    model = _SCENE.finalize("cpu", requires_grad=False)
    return model.particle_x0.numpy(), list(model.obstacle_names)
