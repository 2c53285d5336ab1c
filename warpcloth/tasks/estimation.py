"""Material estimation (SPEC §5(b)): fit a fabric's 40 material numbers (density, 6x4 stretching, 3x5 bending) to a
trajectory (:class:`TrajectoryFit`) through an unconstrained vector (:class:`MaterialParameterization`)."""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import warp as wp

import warpcloth as wc
from warpcloth.materials import (
    BENDING_SHAPE,
    DIFFCLOTH_BENDING_SCALE,
    DIFFCLOTH_STRETCHING_SCALE,
    SEED_INITIAL_GUESS_NAMES,
    STRETCHING_SHAPE,
)
from warpcloth.observations import MarkerFrames, PointCloudFrames, VertexFrames
from warpcloth.progress import progress_bar
from warpcloth.scene import Scene, load_scene
from warpcloth.solver.gradients import GraphCache, plan_gradient
from warpcloth.tasks.lockstep import Lockstep, run_in_lockstep
from warpcloth.tasks.optim import (
    MULTISTART_POPULATION,
    SMOOTHED_COPIES,
    FitSummary,
    adam,
    check_backtracks,
    cmaes,
    lbfgs,
    smoothed_descent,
    smoothed_steps,
)
from warpcloth.tasks.scenes import THICKEN
from warpcloth.tasks.specs import ESTIMATION_OPTIMIZERS, GLOBAL_OPTIMIZERS, MATERIAL_PARTS, SearchSpec

# -- the seed's scene: warpcloth.tasks.scenes.hanging_cloth -----------------------------------------------------------
DT = 0.02
"""Time step [s]."""
STEPS = 50
"""Steps of the seed's longest horizon (1 s)."""
FRAME_STRIDE = 2
"""Steps per compared frame: the seed's targets are saved every 0.04 s."""
CAPTURE_AFTER = 3
"""The evaluation of a horizon that captures its rollout. Why: docs/decisions.md, "Material fits capture at the third
evaluation"."""


def initial_guess() -> wc.Material:
    """The seed's start point: the element-wise mean of 8 of the 10 measured fabrics (SPEC §1.5)."""
    return wc.mean_material(SEED_INITIAL_GUESS_NAMES, thicken=THICKEN)


def start_bending_factor(k: int) -> float:
    """The factor on the bending of start ``k`` of a fit from several: 1, 1/2, 2, 1/4, 4, ... (k = 0, 1, 2, ...).
    ValueError for a negative or non-integer ``k``. Why bending: docs/decisions.md, "A fit from several starts
    varies its bending"."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
        raise ValueError(f"start {k!r}: a start is numbered 0, 1, 2, ...")
    return 2.0 ** ((k + 1) // 2 * (-1 if k % 2 else 1))


def varied_start(m: wc.Material, k: int) -> wc.Material:
    """Start ``k`` of a fit from several: ``m`` with its bending times :func:`start_bending_factor` ``(k)``, named
    for it (start 0 is ``m``)."""
    factor = start_bending_factor(k)
    return m if factor == 1.0 else replace(m, bending=m.bending * factor, name=f"{m.name}, bending x{factor:g}")


# -- parameterisation ------------------------------------------------------------------------------------------------
_POSITIVE_COLUMNS = (0, 2)  # warp and weft stretch: log space; coupling and shear (1, 3): linear
N_PARAMS = 1 + STRETCHING_SHAPE[0] * STRETCHING_SHAPE[1] + BENDING_SHAPE[0] * BENDING_SHAPE[1]


class MaterialParameterization:
    """Maps a Material to an unconstrained vector ``theta`` (N_PARAMS = 40) and back, with the chain rule;
    theta = 0 is the reference. theta = [log(density/ref), stretching, log(bending/ref)], each entry of order one: the
    stretching table's warp and weft columns (``log_mask``) in log space, rows 1-5 relative to row 0; coupling and shear
    linear, (k - ref) / the rms of the reference row. ValueError where the reference's warp/weft stretch or bending is
    not positive. Why: docs/decisions.md, "The material parameterisation"."""

    def __init__(self, reference: wc.Material):
        self.reference = reference
        s = reference.stretching
        self.log_mask = np.zeros(STRETCHING_SHAPE, dtype=bool)
        self.log_mask[:, _POSITIVE_COLUMNS] = True
        if np.any(s[self.log_mask] <= 0.0) or np.any(reference.bending <= 0.0):
            raise ValueError(f"reference material {reference.name!r}: warp/weft stretch and bending must be > 0 "
                             "(they are estimated in log space)")
        self._row_scale = np.broadcast_to(np.sqrt(np.mean(s**2, axis=1, keepdims=True)), STRETCHING_SHAPE)

    def encode(self, m: wc.Material) -> np.ndarray:
        ref = self.reference
        lin = (m.stretching - ref.stretching) / self._row_scale
        with np.errstate(divide="raise"):
            logs = np.log(np.where(self.log_mask, m.stretching, 1.0) / np.where(self.log_mask, ref.stretching, 1.0))
            logs[1:] -= logs[0]  # rows 1-5 relative to row 0
            return np.concatenate([[math.log(m.density / ref.density)],
                                   np.where(self.log_mask, logs, lin).ravel(),
                                   np.log(m.bending / ref.bending).ravel()])

    def split(self, theta: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        theta = np.asarray(theta, dtype=np.float64)
        if theta.shape != (N_PARAMS,):
            raise ValueError(f"theta must have shape ({N_PARAMS},), got {theta.shape}")
        if not np.all(np.isfinite(theta)):
            raise ValueError(f"theta has non-finite entries at {np.flatnonzero(~np.isfinite(theta)).tolist()}")
        ns = STRETCHING_SHAPE[0] * STRETCHING_SHAPE[1]
        return theta[0], theta[1:1 + ns].reshape(STRETCHING_SHAPE), theta[1 + ns:].reshape(BENDING_SHAPE)

    def decode(self, theta: np.ndarray, name: str = "estimate") -> wc.Material:
        ref = self.reference
        td, ts, tb = self.split(theta)
        logs = np.where(self.log_mask, ts, 0.0)
        logs[1:] += logs[0]
        stretching = np.where(self.log_mask, ref.stretching * np.exp(logs), ref.stretching + ts * self._row_scale)
        return wc.Material(density=ref.density * math.exp(td), stretching=stretching,
                           bending=ref.bending * np.exp(tb), thicken=ref.thicken, name=name)

    def chain(self, theta: np.ndarray, g_density: float, g_stretching: np.ndarray, g_bending: np.ndarray) -> np.ndarray:
        """d loss / d theta from the gradients with respect to the material's raw density and tables."""
        m = self.decode(theta)
        gs = np.where(self.log_mask, g_stretching * m.stretching, g_stretching * self._row_scale)
        gs[0] += np.where(self.log_mask[0], gs[1:].sum(axis=0), 0.0)  # row 0's log entry scales its whole column
        return np.concatenate([[g_density * m.density], gs.ravel(), (g_bending * m.bending).ravel()])


SEED_PUBLISHED = {"runtime_s_per_step_iter": 2.03, "density_err_pct": 1.8, "stretch_linear_err_pct": 45.0,
                  "stretch_nonlinear_err_pct": 57.0, "bending_err_pct": 77.0, "sim_err_pct": 1.6}
"""The seed's "Ours" row of Table 2 (mean over 10 fabrics; talk slides, SPEC.md)."""
SEED_BASELINE = {"density_err_pct": 68.0, "stretch_linear_err_pct": 160.0, "stretch_nonlinear_err_pct": 74.0,
                 "bending_err_pct": 70.0, "sim_err_pct": 12.0}
"""The seed's "Baseline" row (the mean-material start)."""
ERROR_LABELS = {"density_err_pct": "density error [%]", "stretch_linear_err_pct": "linear stretching error [%]",
                "stretch_nonlinear_err_pct": "non-linear stretching error [%]", "bending_err_pct": "bending error [%]"}


# -- errors (SPEC.md, published numbers) -------------------------------------------------------------------------------
def parameter_errors(estimate: wc.Material, truth: wc.Material) -> dict[str, float]:
    """Relative Frobenius errors [%]: density, stretching row 0 ("linear"), rows 1-5 ("non-linear"), bending."""

    def rel(a, b):
        return 100.0 * float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(b))

    return {
        "density_err_pct": rel(estimate.density, truth.density),
        "stretch_linear_err_pct": rel(estimate.stretching[0], truth.stretching[0]),
        "stretch_nonlinear_err_pct": rel(estimate.stretching[1:], truth.stretching[1:]),
        "bending_err_pct": rel(estimate.bending, truth.bending),
    }


# -- the fit ---------------------------------------------------------------------------------------------------------

Observation = VertexFrames | MarkerFrames | PointCloudFrames
OBSERVATIONS = (VertexFrames, MarkerFrames, PointCloudFrames)


def _check_vertex_frames(frames_in, steps: int, frames: int, particles: int, what: str) -> None:
    if len(frames_in) < frames + 1:
        raise ValueError(f"{steps} steps compare {frames} frames after frame 0, but the {what} has only "
                         f"{len(frames_in) - 1}")
    for k, x in enumerate(frames_in[: frames + 1]):
        if np.shape(x) != (particles, 3):
            raise ValueError(f"{what} frame {k} has shape {np.shape(x)}, the cloth has {particles} particles")


class TrajectoryFit:
    """Loss and gradient of a material against a recording ``targets``, frame 0 the start, compared every
    ``frame_stride`` steps up to ``steps``: vertex frames (particle_count, 3) [m] (the seed's loss, the mean over
    frames of the mean over vertices of ``|x_sim - x_target|^2`` [m^2]) or an observation of
    :mod:`warpcloth.observations` (markers, point clouds). ``reference``: the true vertex frames, where known, that
    :meth:`simulation_error` measures against (the whole model's, or one world's for every world). A model of equal
    worlds, each with its own material, fits one per world (:meth:`losses`, :meth:`losses_and_grads`). ``options``
    default to a CG tolerance of 1e-6; ``template`` (the one-world builder ``model`` was finalised from) enables
    :meth:`worlds`. ValueError for worlds of different sizes or sharing a material, or a recording short
    of ``steps``."""

    def __init__(self, model: wc.Model, targets: Sequence[np.ndarray] | Observation, *, steps: int = STEPS,
                 frame_stride: int = FRAME_STRIDE, dt: float = DT, options: wc.SolverOptions | None = None,
                 capture: bool = True, template: wc.ModelBuilder | None = None,
                 reference: Sequence[np.ndarray] | None = None):
        worlds = model.world_count
        if model.material_count != worlds:
            raise ValueError(f"TrajectoryFit estimates one material per world; the model has {model.material_count} "
                             f"materials in {worlds} world(s) (worlds built with one Material object share it: give "
                             "each world's builder its own, material.copy())")
        if worlds > 1:
            sizes = np.diff(model.world_particle_start)
            odd = np.flatnonzero(sizes != sizes[0])
            if odd.size:
                raise ValueError(f"TrajectoryFit: world {odd[0]} has {sizes[odd[0]]} particles, world 0 "
                                 f"{sizes[0]}; a batched fit needs worlds of one size")
            tri_world = model.particle_world.numpy()[model.triangles_np[:, 0]]
            odd = np.flatnonzero(model.tri_material.numpy() != tri_world)
            if odd.size:
                raise ValueError(f"TrajectoryFit: triangle {odd[0]} of world {tri_world[odd[0]]} uses material "
                                 f"{model.tri_material.numpy()[odd[0]]}; each world's cloth needs its own material")
        if steps % frame_stride:
            raise ValueError(f"steps ({steps}) must be a multiple of frame_stride ({frame_stride})")
        frames = steps // frame_stride
        observation = targets if isinstance(targets, OBSERVATIONS) else None
        if observation is None:
            _check_vertex_frames(targets, steps, frames, model.particle_count, "target")
            observation = VertexFrames(np.stack([np.asarray(x, dtype=np.float64) for x in targets[: frames + 1]]))
        elif observation.frame_count < frames + 1:
            raise ValueError(f"{steps} steps compare {frames} frames after frame 0, but the recording has only "
                             f"{observation.frame_count - 1}")
        if reference is not None:
            per_world = model.particle_count // worlds
            if worlds > 1 and len(reference) and np.shape(reference[0]) == (per_world, 3):
                reference = [np.tile(np.asarray(x), (worlds, 1)) for x in reference[: frames + 1]]  # every world's
            _check_vertex_frames(reference, steps, frames, model.particle_count, "reference")
            reference = [np.asarray(x, dtype=np.float64) for x in reference[: frames + 1]]
        self.model, self.steps, self.frame_stride = model, steps, frame_stride
        self.observation = observation
        """What the fit compares the simulation with (vertices, markers or point clouds: warpcloth.observations)."""
        self.reference = reference
        """Every vertex's true position in each compared frame, where known: :meth:`simulation_error` measures
        against it (a vertex recording is its own reference)."""
        self._loss = observation.bind(model)
        # sync_every=0: a rollout reads the failure record once, at its end (and the backward pass after it), not
        # at every step: free on the CPU, a device round trip a step on CUDA; errors still name their step
        self.sim = wc.Simulator(model, dt, options=options or wc.SolverOptions(cg_tol=1e-6, sync_every=0))
        self.capture = capture
        """Replay rollouts from graphs (``wc.CapturedRollout``, per horizon and kind, from its CAPTURE_AFTER-th
        evaluation), bitwise the uncaptured results on the CPU; on CUDA the forward losses only."""
        self._graphs: GraphCache[wc.CapturedRollout] = GraphCache(after=CAPTURE_AFTER)  # by horizon and kind
        self.evaluations = 0
        self.seconds = 0.0
        if template is not None and (template.world_count != 1 or template.particle_count != model.particle_count):
            raise ValueError(f"TrajectoryFit: the template has {template.world_count} world(s) of "
                             f"{template.particle_count} particles in all; it must be the one-world builder the "
                             f"model ({worlds} world(s), {model.particle_count} particles) was finalised from")
        self.template = template
        self.control: wc.Control | None = None
        """The control every rollout takes (None: the model's defaults); made where the obstacles' placement is
        free (:meth:`bind_scene`)."""
        self.start_state: wc.State | None = None
        """The start State of the last rollout (its gradient: the start's)."""
        self.scene_parameters: tuple = ()
        """The free scene parameters (:meth:`bind_scene`) whose gradients :meth:`losses_and_grads` reads."""
        self.scene_grads: dict[str, np.ndarray] = {}
        """d loss / d values of each bound scene parameter, of the last :meth:`losses_and_grads`."""
        self._start_free = False
        self._init = {"steps": steps, "frame_stride": frame_stride, "dt": dt, "options": self.sim.options,
                      "capture": capture, "reference": reference}
        self._batched: dict[int, TrajectoryFit] = {}

    @property
    def world_count(self) -> int:
        return self.model.world_count

    def bind_scene(self, names: Sequence[str]) -> list:
        """Free the scene parameters ``names`` (:data:`~warpcloth.tasks.parameters.SCENE_PARAMETERS`): returns them
        (:class:`~warpcloth.tasks.parameters.SceneParameter`), and :meth:`losses_and_grads` reads their gradients
        into :attr:`scene_grads`. ValueError for a fit of several worlds or a parameter the scene lacks."""
        from warpcloth.tasks.parameters import bind_parameters

        if self.world_count != 1:
            raise ValueError(f"free scene parameters need a fit of one world; this one has {self.world_count}")
        params = bind_parameters(self, names)
        if "obstacle_placement" in names and self.control is None:
            self.control = self.model.control()
            self._graphs = GraphCache(after=CAPTURE_AFTER)  # the rollouts take the control from now on
        self._start_free = self._start_free or any(n.startswith("start_") for n in names)
        self.scene_parameters = tuple(params)
        for p in params:
            p.zero_grad()
        return params

    def worlds(self, count: int) -> TrajectoryFit | None:
        """This fit over ``count`` copies of its scene, each with its own material (made once, then kept); None without
        a ``template`` or for several worlds. Each world's loss is bitwise this fit's on the CPU."""
        if self.template is None or self.world_count != 1:
            return None
        if int(count) != count or count < 1:
            raise ValueError(f"TrajectoryFit.worlds: count must be a positive integer, got {count!r}")
        if count not in self._batched:
            builder = wc.ModelBuilder()
            builder.replicate(self.template, count, own_materials=True)
            model = builder.finalize(self.model.device, requires_grad=True, dtype=self.model.scalar)
            init = dict(self._init)  # a one-world reference serves every world
            if init["options"].preconditioner == "multigrid" and self.sim.linear_solver.backend != "sequential":
                init["options"] = replace(init["options"], preconditioner="auto")  # its parallel form: one world
            self._batched[count] = TrajectoryFit(model, self.observation, **init)  # one recording, every world
        return self._batched[count]

    @staticmethod
    def simulate_targets(model: wc.Model, truth: wc.Material | Sequence[wc.Material], *, steps: int = STEPS,
                         frame_stride: int = FRAME_STRIDE, dt: float = DT, options: wc.SolverOptions | None = None
                         ) -> list[np.ndarray]:
        """Every ``frame_stride``-th frame of ``truth``'s rollout (a material or one per world), CG tolerance 1e-8."""
        dummy = [np.zeros((model.particle_count, 3))] * (steps // frame_stride + 1)
        fit = TrajectoryFit(model, dummy, steps=steps, frame_stride=frame_stride, dt=dt,
                            options=replace(options or wc.SolverOptions(), cg_tol=1e-8))
        return fit.trajectory(truth)[::frame_stride]

    def set_material(self, m: wc.Material | Sequence[wc.Material]) -> None:
        """Give every world ``m``, or world w ``m[w]``."""
        model = self.model
        ms = [m] * model.world_count if isinstance(m, wc.Material) else list(m)
        if len(ms) != model.world_count:
            raise ValueError(f"{len(ms)} materials for {model.world_count} world(s)")
        model.material_density.assign(np.array([x.density for x in ms]))
        model.material_stretching.assign(np.stack([x.stretching for x in ms]))
        model.material_bending.assign(np.stack([x.bending for x in ms]))

    def _rollout_loss(self, steps: int, grad: bool) -> tuple[wp.array, wp.Tape | None]:
        model = self.model
        captured = self._capture(steps, grad)
        if captured is not None:
            if self._start_free:  # the graph reads its start state's arrays: the start parameters' values
                wp.copy(captured.state.particle_x, model.particle_x0)
                wp.copy(captured.state.particle_v, model.particle_v0)
            self.start_state = captured.state
            trajectory = captured.run()
            return (captured.loss if grad else self._loss_of(trajectory, steps)), None
        self.start_state = start = model.state()
        if not grad:
            return self._loss_of(wc.rollout(self.sim, start, self.control, steps=steps), steps), None
        tape = wp.Tape()
        with tape:
            loss = self._loss_of(wc.rollout(self.sim, start, self.control, steps=steps), steps)
        tape.backward(grads={loss: wp.ones(model.world_count, dtype=model.types.scalar, device=model.device)})
        self.sim.check()  # the adjoint solves' failures (a rollout checks its forward steps itself)
        return loss, tape

    def _capture(self, steps: int, grad: bool) -> wc.CapturedRollout | None:
        capture = self.capture and self._loss.capturable
        if not plan_gradient(self.sim, steps, segment_steps=steps, backward=grad, capture=capture).captured:
            return None
        loss = (lambda trajectory: self._loss_of(trajectory, steps)) if grad else None
        # options are kernel arguments baked into the graph: a fit with other options asks for other graphs
        return self._graphs.get((steps, grad, id(self.sim.options)),
                                lambda: wc.CapturedRollout(self.sim, self.model.state(), self.control, steps=steps,
                                                                  loss=loss))

    def _loss_of(self, trajectory, steps: int) -> wp.array:
        frames = range(1, steps // self.frame_stride + 1)
        return self._loss([trajectory[k * self.frame_stride].particle_x for k in frames], frames)

    def _one_world(self, what: str) -> None:
        if self.model.world_count != 1:
            raise ValueError(f"TrajectoryFit.{what} fits one world; this fit has {self.model.world_count}: use "
                             f"{what.replace('loss', 'losses').replace('_grad', '_grads')}")

    def loss(self, m: wc.Material, steps: int | None = None) -> float:
        self._one_world("loss")
        return float(self.losses([m], steps)[0])

    def losses(self, materials: Sequence[wc.Material], steps: int | None = None) -> np.ndarray:
        """Each world's loss with its material ``materials[w]``, forward only, (world_count,)."""
        self.set_material(materials)
        t0 = time.perf_counter()
        out = self._rollout_loss(steps or self.steps, grad=False)[0].numpy().astype(np.float64)
        self.seconds += time.perf_counter() - t0
        return out

    def loss_and_grad(self, m: wc.Material, steps: int | None = None) -> tuple[float, float, np.ndarray, np.ndarray]:
        """(loss, d/d density, d/d stretching (6, 4), d/d bending (3, 5)) in raw units."""
        self._one_world("loss_and_grad")
        return self.losses_and_grads([m], steps)[0]

    def losses_and_grads(self, materials: Sequence[wc.Material], steps: int | None = None
                         ) -> list[tuple[float, float, np.ndarray, np.ndarray]]:
        """Each world's :meth:`loss_and_grad` with its material ``materials[w]``: one forward and one backward pass."""
        model = self.model
        self.set_material(materials)
        t0 = time.perf_counter()
        loss, tape = self._rollout_loss(steps or self.steps, grad=True)
        density, stretching, bending = (a.grad.numpy().astype(float) for a in
                                        (model.material_density, model.material_stretching, model.material_bending))
        if self.scene_parameters:
            self.scene_grads = {p.name: p.grad() for p in self.scene_parameters}
            for p in self.scene_parameters:
                p.zero_grad()
        if tape is not None:
            tape.zero()
        for arr in (model.material_density, model.material_stretching, model.material_bending):
            arr.grad.zero_()
        self.seconds += time.perf_counter() - t0
        self.evaluations += 1
        values = loss.numpy()
        return [(float(values[w]), float(density[w]), stretching[w], bending[w]) for w in range(model.world_count)]

    @property
    def has_reference(self) -> bool:
        """Whether :meth:`simulation_error` can be measured: a vertex recording, or a ``reference`` given."""
        return self.reference is not None or isinstance(self.observation, VertexFrames)

    def simulation_error(self, m: wc.Material) -> float:
        """RMS vertex distance to the reference over the compared frames, per metre of cloth side, in %. ValueError
        without a reference (:attr:`has_reference`)."""
        if self.reference is None:
            if not isinstance(self.observation, VertexFrames):
                raise ValueError(f"TrajectoryFit.simulation_error: a {type(self.observation).__name__} recording "
                                 "holds no vertex positions; give the fit a reference trajectory")
            return 100.0 * math.sqrt(self.loss(m))
        self._one_world("simulation_error")
        return self.simulation_errors([m])[0]

    def simulation_errors(self, ms: Sequence[wc.Material]) -> list[float]:
        """Each world's :meth:`simulation_error` with its own material ``ms[w]``, from one rollout of every world.
        ValueError without a ``reference`` or for another count of materials than the worlds."""
        if self.reference is None:
            raise ValueError("TrajectoryFit.simulation_errors measures against a reference trajectory; this fit has "
                             "none")
        if len(ms) != self.model.world_count:
            raise ValueError(f"TrajectoryFit.simulation_errors: {len(ms)} materials for {self.model.world_count} "
                             "worlds")
        trajectory = self.trajectory(list(ms), self.steps)
        frames = range(1, self.steps // self.frame_stride + 1)
        errors = []
        for w in range(self.model.world_count):
            part = self.model.world_slice(w)
            squared = [np.mean(np.sum((trajectory[k * self.frame_stride][part] - self.reference[k][part]) ** 2,
                                      axis=1)) for k in frames]
            errors.append(100.0 * math.sqrt(float(np.mean(squared))))
        return errors

    def trajectory(self, m: wc.Material | Sequence[wc.Material], steps: int | None = None) -> list[np.ndarray]:
        """Positions of every step with ``m`` (one material, or one per world)."""
        self.set_material(m)
        return [s.particle_x.numpy() for s in wc.rollout(self.sim, self.model.state(), self.control,
                                                         steps=steps or self.steps)]


class MultiMotionFit:
    """One material fitted to several motions (a TrajectoryFit each), the loss the mean of theirs. Takes a
    TrajectoryFit's place in :func:`estimate_material`, except with ``seed-sgd``."""

    def __init__(self, fits: Sequence[TrajectoryFit]):
        if not fits:
            raise ValueError("MultiMotionFit needs at least one TrajectoryFit")
        self.fits = list(fits)
        self.steps = sum(f.steps for f in self.fits)

    @property
    def seconds(self) -> float:
        """Wall time of the evaluations so far (forward, and forward + backward)."""
        return sum(f.seconds for f in self.fits)

    def loss(self, m: wc.Material, steps: int | None = None) -> float:
        return sum(f.loss(m) for f in self.fits) / len(self.fits)

    def loss_and_grad(self, m: wc.Material, steps: int | None = None) -> tuple[float, float, np.ndarray, np.ndarray]:
        """As :meth:`TrajectoryFit.loss_and_grad`, of the mean loss over the motions (each over its own horizon)."""
        parts = [f.loss_and_grad(m) for f in self.fits]
        k = len(parts)
        return (sum(p[0] for p in parts) / k, sum(p[1] for p in parts) / k, sum(p[2] for p in parts) / k,
                sum(p[3] for p in parts) / k)

    @property
    def has_reference(self) -> bool:
        return all(f.has_reference for f in self.fits)

    def simulation_error(self, m: wc.Material) -> float:
        """RMS vertex distance over every motion's compared frames (each motion weighted equally), in %."""
        if all(f.reference is None and isinstance(f.observation, VertexFrames) for f in self.fits):
            return 100.0 * math.sqrt(self.loss(m))
        return math.sqrt(sum(f.simulation_error(m) ** 2 for f in self.fits) / len(self.fits))


def free_mask(free: Sequence[str]) -> np.ndarray:
    """Which of the N_PARAMS entries of theta (density, stretching, bending) the named parts free."""
    ns = STRETCHING_SHAPE[0] * STRETCHING_SHAPE[1]
    parts = {"density": [0], "stretching": range(1, 1 + ns), "bending": range(1 + ns, N_PARAMS)}
    mask = np.zeros(N_PARAMS, dtype=bool)
    for name in free:
        mask[list(parts[name])] = True
    return mask


@dataclass
class _Point:  # a material and the values of the free scene parameters
    material: wc.Material
    values: dict[str, np.ndarray]


# theta = the material's (N_PARAMS, MaterialParameterization) then each free scene parameter's (ParameterTransform)
class _FreeParameterization:

    def __init__(self, material: MaterialParameterization, transforms: list):
        self.material, self.transforms = material, transforms
        self.size = N_PARAMS + sum(t.size for t in transforms)

    @property
    def reference(self) -> wc.Material:
        return self.material.reference

    def with_material(self, m: wc.Material) -> _FreeParameterization:
        return _FreeParameterization(MaterialParameterization(m), self.transforms)

    def mask(self, free: Sequence[str]) -> np.ndarray:
        return np.concatenate([free_mask([p for p in free if p in MATERIAL_PARTS]),
                               np.ones(self.size - N_PARAMS, dtype=bool)])

    def _parts(self, theta):
        k = N_PARAMS
        for t in self.transforms:
            yield t, theta[k:k + t.size]
            k += t.size

    def decode(self, theta: np.ndarray, name: str = "estimate") -> _Point:
        theta = np.asarray(theta, dtype=np.float64)
        return _Point(self.material.decode(theta[:N_PARAMS], name),
                      {t.name: t.decode(part) for t, part in self._parts(theta)})

    def chain(self, theta, g_density, g_stretching, g_bending, g_scene: dict) -> np.ndarray:
        theta = np.asarray(theta, dtype=np.float64)
        return np.concatenate([self.material.chain(theta[:N_PARAMS], g_density, g_stretching, g_bending)]
                              + [t.chain(part, g_scene[t.name]) for t, part in self._parts(theta)])


# a one-world TrajectoryFit whose free scene parameters each evaluation writes first (their start values for a bare
# material), in its place for estimate_material; gradients (loss, material's..., {name: d loss / d values})
class _SceneFit:

    def __init__(self, fit: TrajectoryFit, params: list):
        self.fit, self.params = fit, params
        self.steps, self.frame_stride = fit.steps, fit.frame_stride
        self.start = {p.name: p.read() for p in params}

    @property
    def seconds(self) -> float:
        return self.fit.seconds

    @property
    def has_reference(self) -> bool:
        return self.fit.has_reference

    def apply(self, point: _Point | wc.Material) -> wc.Material:
        values = point.values if isinstance(point, _Point) else self.start
        for p in self.params:
            p.write(values[p.name])
        return point.material if isinstance(point, _Point) else point

    def loss(self, point, steps: int | None = None) -> float:
        return self.fit.loss(self.apply(point), steps)

    def loss_and_grad(self, point, steps: int | None = None):
        out = self.fit.loss_and_grad(self.apply(point), steps)
        return (*out, dict(self.fit.scene_grads))

    def simulation_error(self, point) -> float:
        return self.fit.simulation_error(self.apply(point))


# -- one estimation --------------------------------------------------------------------------------------------------
OPTIMIZERS = ESTIMATION_OPTIMIZERS

START_SCAN = {"density": (0.5, 2.0**-0.5, 1.0, 2.0**0.5, 2.0), "stretch": tuple(2.0**k for k in range(-2, 6))}
"""Factors tried on the start before a fit, every pair of them: on its density and on its warp and weft stretch.
Why: docs/decisions.md, "A fit scans its start"."""

CURRICULUM = ((0.4, 2.0), (0.7, 2.0), (1.0, 3.0))
"""L-BFGS's stages of (fraction of the fit's steps, share of the evaluations), each from where the last ended. Why:
docs/decisions.md, "Material fits grow their horizon"."""

SEARCH_SIGMA = 0.5
"""The global searches' default spread (``SearchSpec.sigma``) in the parameterization's units."""
SMOOTHED_SIGMA = 0.05
"""The smoothed optimiser's default spread (``SearchSpec.sigma``) in the parameterization's units."""
SMOOTHED_STEP_FRACTION = 4.0
"""The smoothed optimiser's Adam step is its spread divided by this."""


@dataclass
class EstimationResult(FitSummary):
    """A material fit's result: the estimate (``material``), where it started, and every evaluation's loss, summed up
    by :class:`~warpcloth.tasks.optim.FitSummary`."""

    material: wc.Material
    initial: wc.Material
    """The material the fit started from (before the start scan)."""
    losses: list[float] = field(default_factory=list)
    """Loss [m^2] of every evaluation, in order, over its ``horizons`` entry (infinite for a diverged trial)."""
    horizons: list[int] = field(default_factory=list)
    """Steps simulated by each evaluation (the seed's curriculum grows them)."""
    seconds: float = 0.0
    """Wall time of the evaluations [s]; in a batch, this fit's share of each batch's."""
    simulation_error_pct: float = math.nan
    initial_simulation_error_pct: float = math.nan
    diverged: list[str] = field(default_factory=list)
    """Messages of trial materials whose simulation diverged (rejected, each counted as an evaluation)."""
    scan: list[tuple[float, float, float]] = field(default_factory=list)
    """(density factor, stretch factor, loss) of each material of the start scan."""
    scan_factors: dict[str, float] = field(default_factory=dict)
    """The factors of the scan's best material, where the fit started (empty without a scan)."""
    parameters: dict[str, np.ndarray] = field(default_factory=dict)
    """The fitted values of every free parameter by name: the material's parts (``density`` (1,) [kg/m^2],
    ``stretching`` (6, 4) [N/m], ``bending`` (3, 5) [N*m]) and the scene's (``SCENE_PARAMETERS``' shapes, flat)."""
    initial_parameters: dict[str, np.ndarray] = field(default_factory=dict)
    """The free parameters' values at the start (``initial``'s, before the start scan), by name, as ``parameters``."""

    @property
    def seconds_per_step_iter(self) -> float:
        return self.seconds / max(sum(self.horizons), 1)


def estimate_material(fit: TrajectoryFit | MultiMotionFit, *, initial: wc.Material | None = None,
                      optimizer: str = "lbfgs", iters: int = 60, free: Sequence[str] = MATERIAL_PARTS,
                      scan: dict[str, Sequence[float]] | None = START_SCAN, search: SearchSpec | None = None,
                      curriculum: Sequence[tuple[float, float]] | None = CURRICULUM, batch: bool = False,
                      progress: bool = False, bounds: Mapping[str, Sequence] | None = None,
                      scales: Mapping[str, float | Sequence[float]] | None = None,
                      backtracks: int | None = None) -> EstimationResult:
    """Fit the model's material to ``fit``'s targets; returns the estimate and the history.

    Args:
        initial: The start (default :func:`initial_guess`).
        optimizer: ``"lbfgs"`` (stages of growing horizon, ``curriculum``), ``"adam"``, ``"seed-sgd"`` (the seed's
            SGD, momentum 0.9 in its scaled units, the horizon growing by 2 steps whenever the loss drops under 1e-4
            m^2), or a global search then L-BFGS from its best point for ``search.refine`` evaluations (default a
            fifth): ``"cmaes"`` (spread ``search.sigma``, default :data:`SEARCH_SIGMA`), ``"multistart"`` (L-BFGS from
            the start and ``search.population - 1`` normal random points around it, equal shares) or ``"smoothed"``
            (Adam on the Gaussian-smoothed loss, ``search.population`` copies a step, default :data:`SMOOTHED_SIGMA`).
        iters: Evaluations to spend; each scanned material, search point, copy and line-search trial counts.
        free: The parameters fitted: the material's parts (``"density"``, ``"stretching"``, ``"bending"``; the
            others keep ``initial``'s) and scene parameters (:data:`~warpcloth.tasks.parameters.SCENE_PARAMETERS`,
            from the model's current values, for a one-world TrajectoryFit; the model keeps the fitted ones).
        scan: ``{"density": factors, "stretch": factors}`` (default :data:`START_SCAN`): before ``lbfgs`` or ``adam``,
            start from the best of ``initial`` with its density and warp and weft stretch scaled by every pair of
            factors (of the free parts); skipped with None, ``seed-sgd`` or an ``iters`` under twice the pairs.
        curriculum: L-BFGS's stages (default :data:`CURRICULUM`); None, or a MultiMotionFit: one stage.
        batch: Simulate a global search's trials as worlds of one batch (a TrajectoryFit with a ``template``), bitwise
            the same search on the CPU. Why off: docs/decisions.md, "Material searches run unbatched by default".
        bounds: ``{name: [low, high]}`` for free scene parameters (each a number or one per entry, None for none):
            the fit stays inside (:class:`~warpcloth.tasks.parameters.ParameterTransform`).
        scales: ``{name: scale}`` replacing a free scene parameter's default scale (``SCENE_PARAMETERS``).
        backtracks: ``lbfgs`` only: where a stage's line search shrinks its step this many times without a decrease,
            it starts again from steepest descent, and the stage ends when that fails too, its unspent evaluations
            passing to the next stage (the last stage's are not spent: ``result.evaluations`` may end under
            ``iters``). None (default): the line search shrinks its step until a decrease or the stage's end. Why:
            docs/decisions.md, "A stalled line search may end its stage".

    Raises:
        ValueError: For an unknown optimiser or part, a batch without a global search or template, or a budget that
            makes no generation, step or start; a scene parameter the scene lacks, or bounds or scales that do not
            fit it, named.
        SimulationError: When the first evaluation fails; a later trial that fails is rejected (an infinite loss).
    """
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    check_backtracks(backtracks)
    if optimizer == "seed-sgd" and isinstance(fit, MultiMotionFit):
        raise ValueError("the seed-sgd optimiser grows one motion's horizon; use lbfgs or adam with a MultiMotionFit")
    if batch and optimizer not in GLOBAL_OPTIMIZERS:
        raise ValueError(f"batch=True simulates a global search's trials as worlds ({', '.join(GLOBAL_OPTIMIZERS)}); "
                         f"{optimizer} has none")
    if batch and (not isinstance(fit, TrajectoryFit) or fit.template is None or fit.world_count != 1):
        raise ValueError("batch=True needs a TrajectoryFit of one world made with its scene's builder "
                         "(TrajectoryFit(..., template=builder)), whose copies the trials run on")
    from warpcloth.tasks.parameters import check_names, check_options

    free = tuple(free)
    if not free:
        raise ValueError(f"free must name some of {', '.join(MATERIAL_PARTS)} or of the scene parameters, got []")
    check_names(free, MATERIAL_PARTS)
    scene_free = [p for p in free if p not in MATERIAL_PARTS]
    bounds, scales = check_options(free, bounds, "bounds"), check_options(free, scales, "scales")
    if scene_free and (not isinstance(fit, TrajectoryFit) or fit.world_count != 1 or batch):
        raise ValueError(f"free scene parameters ({', '.join(scene_free)}) need a TrajectoryFit of one world, "
                         "unbatched")
    if optimizer == "seed-sgd" and set(free) != set(MATERIAL_PARTS):
        raise ValueError("the seed-sgd optimiser fits the whole material; use lbfgs or adam to free only some of it")
    if int(iters) != iters or iters < 1:
        raise ValueError(f"iters must be a positive integer, got {iters!r}")
    initial = initial or initial_guess()
    param = MaterialParameterization(initial)
    if scene_free:
        transforms = scene_transforms(fit, scene_free, bounds, scales)  # checked before the fit is changed
        fit = _SceneFit(fit, fit.bind_scene(scene_free))
        param = _FreeParameterization(param, transforms)
        mask = param.mask(free)
    else:
        mask = free_mask(free)
    size = mask.size
    result = EstimationResult(material=initial, initial=initial)
    bar = progress_bar(iters, f"estimate ({optimizer})", "iter") if progress else None

    def record(loss: float, steps: int) -> None:
        result.losses.append(loss)
        result.horizons.append(steps)
        if bar is not None:
            bar.update()
            bar.set_postfix(loss=f"{loss:.3e}", steps=steps)

    best = [math.inf, None]  # the free parameters of least loss evaluated after the scan (the global searches')

    def objective(theta: np.ndarray, steps: int | None = None) -> tuple[float, np.ndarray]:
        steps = steps or fit.steps
        try:
            loss, *grads = fit.loss_and_grad(param.decode(theta), steps)
        except wc.SimulationError as exc:  # a trial material that diverges: an infinite loss, so the step is rejected
            if not result.losses:
                raise
            result.diverged.append(str(exc))
            record(math.inf, steps)
            return math.inf, np.zeros(size)
        record(loss, steps)
        if loss < best[0] and steps == fit.steps:
            best[:] = [loss, theta[mask].copy()]
        return loss, param.chain(theta, *grads)

    def full(theta_free: np.ndarray) -> np.ndarray:
        theta = np.zeros(size)  # theta = 0 (the start) where fixed
        theta[mask] = theta_free
        return theta

    def objective_free(theta_free: np.ndarray, steps: int | None = None) -> tuple[float, np.ndarray]:
        loss, g = objective(full(theta_free), steps)
        return loss, g[mask]

    batched_seconds = [0.0]

    def points_batch(count: int):  # a global search's batch of count worlds, or None: one after another
        return _BatchFit(fit.worlds(count), None) if batch else None

    def evaluate_points(points: list[np.ndarray], grad: bool, batch_fit: _BatchFit) -> list:  # one simulation
        t0 = time.perf_counter()
        answers = batch_fit._evaluate({k: (param.decode(full(q)), grad, fit.steps) for k, q in enumerate(points)})
        batched_seconds[0] += time.perf_counter() - t0
        out = []
        for k, q in enumerate(points):
            answer = answers[k]
            if isinstance(answer, BaseException):
                if not result.losses:  # the first evaluation of all: as objective's
                    raise answer
                result.diverged.append(str(answer))
                record(math.inf, fit.steps)
                out.append(answer)
                continue
            loss = answer[0] if grad else answer
            record(loss, fit.steps)
            if loss < best[0]:
                best[:] = [loss, np.array(q, dtype=float)]
            out.append(_Evaluated(loss, param.chain(full(q), *answer[1:])[mask]) if grad else loss)
        return out

    def copies(requests: list) -> list:  # the smoothed gradient's copies: (loss, gradient) or the divergence
        points = [point for point, _ in requests]
        copies_batch = points_batch(len(points))
        if copies_batch is not None:
            return evaluate_points(points, True, copies_batch)
        out = []
        for point in points:
            loss, g = objective_free(point)
            out.append(_Evaluated(loss, g) if math.isfinite(loss) else wc.SimulationError(result.diverged[-1]))
        return out

    def population_losses(points: list) -> list[float]:
        population_batch = points_batch(len(points))
        if population_batch is None:
            return [loss_free(q) for q in points]
        return [math.inf if isinstance(a, BaseException) else a
                for a in evaluate_points(points, False, population_batch)]

    def multistart(starts: list[np.ndarray], shares: list[int]) -> None:  # L-BFGS runs, in lockstep where batched
        if points_batch(len(starts)) is None:
            for start, share in zip(starts, shares):
                lbfgs(objective_free, start, iters=share)
            return

        def evaluate(requests: dict) -> dict:  # the runs still going: a batch of as many worlds
            answers = evaluate_points(list(requests.values()), True, points_batch(len(requests)))
            return {run: (math.inf, np.zeros(int(mask.sum()))) if isinstance(a, BaseException) else (a.loss, a.grad)
                    for run, a in zip(requests, answers)}

        lock = Lockstep(len(starts), evaluate)
        outcomes = run_in_lockstep(lock, len(starts), lambda run: lbfgs(
            lambda t: lock.ask(run, t), starts[run], iters=shares[run]))
        failed = [r for r in outcomes if isinstance(r, BaseException)]
        if failed:
            raise failed[0]

    def loss_free(theta_free: np.ndarray) -> float:
        try:
            loss = fit.loss(param.decode(full(theta_free)))
        except wc.SimulationError as exc:  # a diverging trial: an infinite loss
            result.diverged.append(str(exc))
            loss = math.inf
        record(loss, fit.steps)
        return loss

    seconds0 = fit.seconds
    scan = dict(scan or {})
    unknown = set(scan) - {"density", "stretch"}
    if unknown:
        raise ValueError(f"scan: unknown part(s) {sorted(unknown)}; scan takes density and stretch")
    densities = tuple(scan.get("density", (1.0,))) if "density" in free else (1.0,)
    stretches = tuple(scan.get("stretch", (1.0,))) if "stretching" in free else (1.0,)
    cost = len(densities) * len(stretches)
    scanning = cost > 1 and optimizer != "seed-sgd" and iters >= 2 * cost
    theta0 = np.zeros(int(mask.sum()))
    search = search or SearchSpec()
    budget = iters - cost if scanning else iters
    refine = budget // 5 if search.refine is None else min(search.refine, budget)
    if optimizer == "cmaes":  # the searches' budgets, checked before any simulation
        population = search.population or 4 + int(3 * math.log(theta0.size))
        generations = (budget - refine) // population
        if not generations:
            raise ValueError(f"cmaes: {budget} evaluations, {refine} of them left to L-BFGS, make no generation of "
                             f"{population} points; raise iters or lower search.population/refine")
    elif optimizer == "smoothed":
        population = search.population or SMOOTHED_COPIES
        adam_steps = smoothed_steps(budget, refine, population, unit="evaluations", local="L-BFGS")
    elif optimizer == "multistart":
        population = search.population or MULTISTART_POPULATION
        if population > budget:
            raise ValueError(f"multistart: {population} starts for {budget} evaluations; each start needs one at "
                             "least")
    stages = _stages(fit, curriculum, budget) if optimizer == "lbfgs" else None  # checked before any simulation
    if scanning:
        initial = _scan_start(fit, initial, densities, stretches, result, record)
        param = param.with_material(initial) if scene_free else MaterialParameterization(initial)
        iters -= cost
    if optimizer == "lbfgs":
        theta_free, unspent = theta0, 0
        for steps, evaluations in stages:  # L-BFGS starts afresh at each horizon
            before = len(result.losses)
            theta_free = lbfgs(lambda t, steps=steps: objective_free(t, steps), theta_free,
                               iters=evaluations + unspent, backtracks=backtracks)
            unspent += evaluations - (len(result.losses) - before)
        theta = np.zeros(size)
        theta[mask] = theta_free
    elif optimizer == "adam":
        theta = np.zeros(size)
        theta[mask] = adam(objective_free, theta0, iters=iters)
    elif optimizer == "multistart":
        rng = np.random.default_rng(search.seed)
        sigma = search.sigma or SEARCH_SIGMA
        starts = [theta0] + [rng.normal(0.0, sigma, theta0.size) for _ in range(population - 1)]
        multistart(starts, [iters // population + (k == 0) * (iters % population) for k in range(population)])
        theta = np.zeros(size)
        theta[mask] = theta0 if best[1] is None else best[1]  # None: every evaluation diverged
    elif optimizer == "smoothed":
        sigma = search.sigma or SMOOTHED_SIGMA
        smoothed_descent(copies, theta0, sigma=sigma, step=sigma / SMOOTHED_STEP_FRACTION, copies=population,
                         steps=adam_steps, rng=np.random.default_rng(search.seed))
        remaining = iters - adam_steps * population
        start = theta0 if best[1] is None else best[1]  # None: every copy diverged
        theta = np.zeros(size)
        theta[mask] = lbfgs(objective_free, start, iters=remaining) if remaining else start
    elif optimizer == "cmaes":
        start = cmaes(population_losses, theta0, sigma=search.sigma or SEARCH_SIGMA,
                      generations=generations, rng=np.random.default_rng(search.seed), popsize=population)
        remaining = iters - generations * population
        theta = np.zeros(size)
        theta[mask] = lbfgs(objective_free, start, iters=remaining) if remaining else start
    else:
        theta = _seed_sgd(fit, param, objective, iters)
    result.seconds += fit.seconds - seconds0 + batched_seconds[0]
    if bar is not None:
        bar.close()
    fitted = param.decode(theta, name=f"estimate ({optimizer})")
    result.material = fitted.material if scene_free else fitted
    result.parameters = _values(free, result.material, fitted.values if scene_free else {})
    result.initial_parameters = _values(free, result.initial, fit.start if scene_free else {})
    if fit.has_reference:
        result.simulation_error_pct = fit.simulation_error(fitted)
        result.initial_simulation_error_pct = fit.simulation_error(result.initial)
    if scene_free:
        fit.apply(fitted)  # the model keeps the fitted scene parameters
    return result


def _values(free: Sequence[str], m: wc.Material, scene: dict) -> dict[str, np.ndarray]:
    material = {"density": np.array([m.density]), "stretching": m.stretching, "bending": m.bending}
    return {p: np.array(material[p] if p in MATERIAL_PARTS else scene[p], dtype=np.float64) for p in free}


def scene_transforms(fit: TrajectoryFit, names: Sequence[str], bounds: Mapping | None = None,
                     scales: Mapping | None = None) -> list:
    """The :class:`~warpcloth.tasks.parameters.ParameterTransform` of each scene parameter ``names`` of ``fit``, at
    the model's current values, with ``bounds`` and ``scales`` by name (defaults: none, the parameter's); ``fit`` is
    left as it was. ValueError naming a parameter the scene lacks or whose bounds or scale do not fit it."""
    from warpcloth.tasks.parameters import ParameterTransform, bind_parameters

    bounds, scales = dict(bounds or {}), dict(scales or {})
    return [ParameterTransform(p.name, p.read(), positive=p.positive, scale=scales.get(p.name, p.scale),
                               bounds=bounds.get(p.name)) for p in bind_parameters(fit, names)]


# (horizon, evaluations) of each curriculum stage: horizons in whole frames, the last the fit's; evaluations by
# share, the remainder to the last stage
def _stages(fit, curriculum: Sequence[tuple[float, float]] | None, iters: int) -> list[tuple[int, int]]:
    stride = getattr(fit, "frame_stride", None)
    if not curriculum or stride is None:
        return [(fit.steps, iters)]
    fractions = [float(f) for f, _ in curriculum]
    shares = np.array([float(w) for _, w in curriculum])
    if any(not 0.0 < f <= 1.0 for f in fractions) or fractions != sorted(fractions) or fractions[-1] != 1.0 \
            or np.any(shares <= 0.0):
        raise ValueError(f"curriculum: growing fractions of the horizon in (0, 1], the last 1, each with a share > 0; "
                         f"got {list(curriculum)}")
    counts = np.floor(iters * shares / shares.sum()).astype(int)
    counts[-1] += iters - counts.sum()
    stages: list[tuple[int, int]] = []
    for f, n in zip(fractions, counts):
        steps = max(stride, int(round(f * fit.steps / stride)) * stride)
        if n > 0 and (not stages or steps > stages[-1][0]):
            stages.append((steps, int(n)))
        elif stages and n > 0:
            stages[-1] = (stages[-1][0], stages[-1][1] + int(n))
    return stages


@dataclass
class _Evaluated:
    loss: float
    grad: np.ndarray


# start with the pair of factors of least loss, forward only (a divergence: an infinite loss)
def _scan_start(fit: TrajectoryFit | MultiMotionFit, start: wc.Material, densities: Sequence[float],
                stretches: Sequence[float], result: EstimationResult, record) -> wc.Material:
    best = (math.inf, start)
    for d in densities:
        for f in stretches:
            stretching = start.stretching.copy()
            stretching[:, list(_POSITIVE_COLUMNS)] *= f
            m = replace(start, density=start.density * d, stretching=stretching,
                        name=f"{start.name}, density x{d:.3g}, stretch x{f:.3g}")
            try:
                loss = fit.loss(m)
            except wc.SimulationError as exc:
                result.diverged.append(str(exc))
                loss = math.inf
            result.scan.append((float(d), float(f), loss))
            record(loss, fit.steps)
            if loss < best[0]:
                best = (loss, m)
                result.scan_factors = {"density": float(d), "stretch": float(f)}
    return best[1]


def estimate_materials(fit: TrajectoryFit, *, initial: wc.Material | Sequence[wc.Material] | None = None,
                       optimizer: str = "lbfgs", iters: int = 60, free: Sequence[str] = MATERIAL_PARTS,
                       scan: dict[str, Sequence[float]] | None = START_SCAN, search: SearchSpec | None = None,
                       curriculum: Sequence[tuple[float, float]] | None = CURRICULUM,
                       progress: bool = False) -> list[EstimationResult]:
    """:func:`estimate_material` for every world of a batched ``fit``, from ``initial`` (one material or one per world),
    in lockstep: each round of evaluations is one simulation, and each world's result is bitwise its fit's alone where
    the solver treats worlds apart (the CPU; on CUDA ``preconditioner="block_jacobi"``).

    Raises:
        ValueError: For ``seed-sgd``, or ``initial`` materials of another count than the worlds.
        SimulationError: When a world's first evaluation fails, naming the world.
    """
    if optimizer == "seed-sgd":
        raise ValueError("estimate_materials runs lbfgs, adam or cmaes in lockstep; seed-sgd grows each fit's "
                         "horizon")
    worlds = fit.world_count
    starts = [initial] * worlds if initial is None or isinstance(initial, wc.Material) else list(initial)
    if len(starts) != worlds:
        raise ValueError(f"initial: {len(starts)} materials for a fit of {worlds} worlds")
    bar = progress_bar(iters, f"estimate {worlds} worlds ({optimizer})", "batch") if progress else None
    batch = _BatchFit(fit, bar)
    outcomes = run_in_lockstep(batch.lockstep, worlds, lambda w: estimate_material(
        _WorldFit(batch, w), initial=starts[w], optimizer=optimizer, iters=iters, free=free, scan=scan,
        search=search, curriculum=curriculum))
    results = [None if isinstance(r, BaseException) else r for r in outcomes]
    errors = {w: r for w, r in enumerate(outcomes) if isinstance(r, BaseException)}
    if bar is not None:
        bar.close()
    if errors:
        w, exc = min(errors.items())
        if isinstance(exc, wc.SimulationError):
            raise wc.SimulationError(f"world {w}'s fit: {exc}", worlds=sorted(errors)) from exc
        raise exc
    if fit.reference is not None:  # a world's loss is no simulation error here: one rollout of every world each
        for r, fitted, start in zip(results, fit.simulation_errors([r.material for r in results]),
                                    fit.simulation_errors([r.initial for r in results])):
            r.simulation_error_pct, r.initial_simulation_error_pct = fitted, start
    return results


# The batch of estimate_materials: every unfinished fit's request (a material, with or without the gradient, and a
# horizon), once all have asked, as one simulation of the worlds; a world without a request simulates its last
# material that did. Answers: a loss, (loss, gradients), or the SimulationError that rejected the request.
class _BatchFit:

    def __init__(self, fit: TrajectoryFit, bar):
        self.fit = fit
        self.lockstep = Lockstep(fit.world_count, self._evaluate, on_batch=bar.update if bar is not None else None)
        self.seconds = [0.0] * fit.world_count
        self.simulated: list[wc.Material | None] = [None] * fit.world_count

    def _evaluate(self, requests: dict[int, tuple[wc.Material, bool, int]]) -> dict[int, object]:
        failed: dict[int, BaseException] = {}
        answers: dict[int, object] = {}
        while True:
            live = [w for w in requests if w not in failed]
            if not live:
                break
            fallback = requests[live[0]][0]
            materials = [requests[w][0] if w in live else self.simulated[w] or fallback
                         for w in range(self.fit.world_count)]
            grad = any(requests[w][1] for w in live)
            steps = {requests[w][2] for w in live}
            if len(steps) > 1:  # the fits run in lockstep with one schedule of horizons: not expected
                raise RuntimeError(f"estimate_materials: one batch asked for horizons {sorted(steps)}")
            steps = steps.pop()
            t0 = time.perf_counter()
            try:
                out = (self.fit.losses_and_grads(materials, steps) if grad else
                       list(self.fit.losses(materials, steps)))
            except wc.SimulationError as exc:
                named = set(live) if exc.worlds is None else set(exc.worlds) & set(live)
                if not named:  # a world simulating a material that simulated before: not expected
                    raise
                for w in named:
                    failed[w] = exc
                continue
            finally:
                share = (time.perf_counter() - t0) / len(live)
                for w in live:
                    self.seconds[w] += share
            for w in live:
                self.simulated[w] = requests[w][0]
                answers[w] = out[w] if requests[w][1] or not grad else out[w][0]
            break
        answers.update(failed)
        return answers


# one world of a _BatchFit, in a TrajectoryFit's place for estimate_material
class _WorldFit:

    def __init__(self, batch: _BatchFit, world: int):
        self.batch, self.world = batch, world
        self.steps, self.frame_stride = batch.fit.steps, batch.fit.frame_stride

    @property
    def seconds(self) -> float:
        return self.batch.seconds[self.world]

    def loss(self, m: wc.Material, steps: int | None = None) -> float:
        return self.batch.lockstep.ask(self.world, (m, False, steps or self.steps))

    def loss_and_grad(self, m: wc.Material, steps: int | None = None) -> tuple[float, float, np.ndarray, np.ndarray]:
        return self.batch.lockstep.ask(self.world, (m, True, steps or self.steps))

    @property
    def has_reference(self) -> bool:
        # a world's simulation error comes from its loss, a vertex recording's; estimate_materials measures the rest
        return self.batch.fit.reference is None and isinstance(self.batch.fit.observation, VertexFrames)

    def simulation_error(self, m: wc.Material) -> float:
        return 100.0 * math.sqrt(self.loss(m))


def registered_start(model: wc.Model, points: np.ndarray) -> np.ndarray:
    """The start positions (particle_count, 3) [m] of a one-world model's cloth on a recorded point cloud ``points``
    (P, 3) [m]: a held cloth (soft handles, pins) deformed from where the scene places it, its held particles kept
    there (:func:`warpcloth.registration.register_nonrigid` with them ``fixed``, both ways); a free one moved
    rigidly from there (not from any placement, so that a square cloth keeps its corners where the scene put them),
    then deformed. ValueError for a model of several worlds or bad points. Why: docs/decisions.md, "A held cloth's
    registration keeps its held particles"."""
    from warpcloth.registration import MAX_POLISH_VERTICES, register_nonrigid, register_rigid

    if model.world_count != 1:
        raise ValueError(f"registered_start places one world's cloth; the model has {model.world_count}")
    x, tris = model.particle_x0.numpy().astype(np.float64), model.triangles_np
    held = [a.numpy() for a in (model.handle_particle, model.pin_particle) if a is not None]
    held = np.unique(np.concatenate(held)) if held else np.zeros(0, dtype=np.int64)
    if len(held):
        return register_nonrigid(x, tris, points, fixed=held, both_ways=True, preserve_lengths=300.0,
                                 polish=30 if len(x) <= MAX_POLISH_VERTICES else 0).positions
    rigid = register_rigid(x, tris, points, init=(np.eye(3), np.zeros(3)))
    polish = 10 if len(x) <= MAX_POLISH_VERTICES else 0
    return register_nonrigid(x, tris, points, rigid=rigid, polish=polish).positions


def place_start(model: wc.Model, positions: np.ndarray) -> None:
    """Start the model's cloth at ``positions`` (particle_count, 3) [m]: its initial positions, and the handles' and
    pins' default targets at their particles' new places."""
    model.particle_x0.assign(np.asarray(positions, dtype=model.particle_x0.numpy().dtype))
    for held, targets in ((model.handle_particle, model.handle_rest_target),
                          (model.pin_particle, model.pin_rest_target)):
        if held is not None:
            targets[:] = positions[held.numpy()]


@dataclass
class EstimationTask:
    """A material estimation: what :meth:`run` fits, from where and how. The fields are :func:`estimate_material`'s
    arguments (``start`` its ``initial``, default :func:`initial_guess`; ``free`` material parts and scene parameters,
    ``bounds`` and ``scales`` the scene parameters'), with ``truth``, the material that simulated the targets (else
    None), and ``source``, where the targets came from, in words."""

    fit: TrajectoryFit | MultiMotionFit
    start: wc.Material = field(default_factory=initial_guess)
    free: tuple[str, ...] = MATERIAL_PARTS
    optimizer: str = "lbfgs"
    iters: int = 100
    search: SearchSpec = field(default_factory=SearchSpec)
    truth: wc.Material | None = None
    source: str = ""
    bounds: dict = field(default_factory=dict)
    scales: dict = field(default_factory=dict)

    @classmethod
    def from_scene(cls, scene: str | os.PathLike | Scene, *, device=None, dtype=None, truth: wc.Material | None = None,
                   steps: int | None = None) -> EstimationTask:
        """The task of a scene's ``[estimate]`` table (a scene name, .toml path or Scene). ``truth`` simulates the
        targets in the cloth's place (a scene without recorded ones); ``steps`` replaces the table's. ValueError for a
        scene without the table, a ``truth`` with recorded targets, or steps the targets do not cover."""
        scene = scene if isinstance(scene, Scene) else load_scene(scene)
        spec = scene.estimate
        if spec is None:
            raise ValueError(f"scene {scene.name!r} ({scene.source}) has no [estimate] table")
        steps = steps or spec.steps
        model = scene.finalize(device=device, requires_grad=True, dtype=dtype)
        if spec.targets is not None:
            if truth is not None:
                raise ValueError(f"scene {scene.name!r} fits recorded targets ({spec.targets_source}); a truth "
                                 "material only makes the targets of a scene without them")
            targets, source = spec.targets, spec.targets_source
        else:
            truth = truth or scene.cloth_material
            if steps % spec.frame_stride:  # checked here too, before simulating the targets
                raise ValueError(f"steps ({steps}) must be a multiple of frame_stride ({spec.frame_stride})")
            targets = TrajectoryFit.simulate_targets(model, truth, steps=steps, frame_stride=spec.frame_stride,
                                                     dt=scene.dt, options=scene.solver_options)
            source = f"{truth.name} simulated by warpcloth"
        template = scene.model_builder
        if spec.start_shape == "registered":
            place_start(model, registered_start(model, targets.points[0]))
            source += ", the start registered to its frame 0"
            template = None  # the builder's copies would start where the scene placed the cloth: no batched worlds
        fit = TrajectoryFit(model, targets, steps=steps, frame_stride=spec.frame_stride, dt=scene.dt,
                            options=scene.solver_options, template=template)
        task = cls(fit, start=spec.start, optimizer=spec.optimizer, iters=spec.iters, search=spec.search, truth=truth,
                   source=source)
        try:
            return task.with_free(spec.free, bounds=spec.bounds, scales=spec.scales)
        except ValueError as exc:
            raise ValueError(f"scene {scene.name!r} ({scene.source}) [estimate]: {exc}") from None

    def with_free(self, free: Sequence[str], *, bounds: Mapping | None = None,
                  scales: Mapping | None = None) -> EstimationTask:
        """This task fitting ``free`` (material parts and scene parameters) with the scene parameters' ``bounds`` and
        ``scales`` by name, checked against the fit's scene before any fit: ValueError naming an unknown parameter,
        one the scene lacks, or bounds or scales that do not fit it."""
        from warpcloth.tasks.parameters import check_names, check_options

        free = tuple(free)
        if not free:
            raise ValueError("free must name at least one parameter")
        check_names(free, MATERIAL_PARTS)
        bounds, scales = check_options(free, bounds, "bounds"), check_options(free, scales, "scales")
        scene_free = [p for p in free if p not in MATERIAL_PARTS]
        if scene_free:
            if not isinstance(self.fit, TrajectoryFit) or self.fit.world_count != 1:
                raise ValueError(f"free scene parameters ({', '.join(scene_free)}) need a TrajectoryFit of one world")
            scene_transforms(self.fit, scene_free, bounds, scales)
        return replace(self, free=free, bounds=bounds, scales=scales)

    def run(self, *, optimizer: str | None = None, iters: int | None = None, batch: bool = False,
            progress: bool = False) -> EstimationResult:
        """Fit: :func:`estimate_material` with the task's settings (``optimizer`` and ``iters`` override them)."""
        return estimate_material(self.fit, initial=self.start, optimizer=optimizer or self.optimizer,
                                 iters=iters or self.iters, free=self.free, search=self.search, batch=batch,
                                 progress=progress, bounds=self.bounds, scales=self.scales)


def _seed_sgd(fit: TrajectoryFit, param: MaterialParameterization, objective, iters: int) -> np.ndarray:
    # The seed optimises density, stretching/1e3 and bending*1e4 directly (its "scaled units", SPEC §1.5).
    ref = param.reference
    scaled = np.concatenate([[ref.density], (ref.stretching / DIFFCLOTH_STRETCHING_SCALE).ravel(),
                             (ref.bending / DIFFCLOTH_BENDING_SCALE).ravel()])
    unit = np.concatenate([[1.0], np.full(24, DIFFCLOTH_STRETCHING_SCALE), np.full(15, DIFFCLOTH_BENDING_SCALE)])
    lr = np.concatenate([[0.1], np.full(24, 0.1), np.full(15, 10.0)])
    velocity = np.zeros(N_PARAMS)
    steps = 2
    theta = np.zeros(N_PARAMS)
    for _ in range(iters):
        raw = scaled * unit
        # plain SGD can step a positive quantity below zero (the seed's code would then simulate a negative
        # stiffness); this keeps the material valid and says so
        floor = np.concatenate([[1e-6], np.where(param.log_mask, 1e-6, -np.inf).ravel(), np.full(15, 1e-12)])
        if np.any(raw < floor):
            bad = np.flatnonzero(raw < floor)
            warnings.warn(f"seed-sgd stepped parameters {bad.tolist()} (0 = density, 1-24 stretching, 25-39 bending) "
                          "below zero; they were raised to a tiny positive value", stacklevel=3)
            raw = np.maximum(raw, floor)
        m = wc.Material(density=raw[0], stretching=raw[1:25].reshape(6, 4), bending=raw[25:].reshape(3, 5),
                     thicken=ref.thicken)
        theta = param.encode(m)
        loss, g_theta = objective(theta, steps)
        # to the seed's scaled units: d/d raw = (d/d theta) / (d raw / d theta), d/d scaled = d/d raw * unit
        draw_dtheta = param.chain(theta, 1.0, np.ones(STRETCHING_SHAPE), np.ones(BENDING_SHAPE))
        g_scaled = g_theta / draw_dtheta * unit
        velocity = 0.9 * velocity + g_scaled
        scaled = scaled - lr * velocity
        if loss < 1e-4 and steps < fit.steps:
            steps = min(fit.steps, steps + 2)
    return theta
