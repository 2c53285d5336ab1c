"""Motion control: throw a cloth over a wall into a basket by pushing its corners (SPEC §5(c)).

The control is the seed's: for each of the first 3 seconds, one push per corner (36 numbers), applied every step as
a force on the 4 corner particles. The seed adds a velocity increment to each corner every step (a corner
acceleration); here the push is a force ``F = (M / 4) p``, with M the cloth's mass, so ``p`` [m/s^2] is the
acceleration four such pushes would give the whole cloth: ``p = (0, 0, 9.8)`` on every corner holds it up. This is a
fixed linear rescaling of the seed's control (corner acceleration = ``M p / (4 m_corner)``, about 95 p here) that
puts the parameters on the scale of gravity. The loss is ``1/2 |com_T - (0, 0, -0.7)|^2`` on the centre of mass
(vertex mean) after 700 steps of 0.01 s, with the cloth colliding with the basket and the wall (the scene:
``warpcloth.tasks.scenes.basket_scene``, also importable from here). Gradients come from a checkpointed rollout
(``wc.checkpointed_backward``), so the 700 steps back-propagate with O(sqrt(T)) stored states.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

import warpcloth as wc
from warpcloth.kernels.losses import loss_kernels
from warpcloth.progress import progress_bar

# the scene (warpcloth.tasks.scenes), importable from here too
from warpcloth.tasks.scenes import THROW_CORNERS as CORNERS
from warpcloth.tasks.scenes import basket_scene

DT = 0.01
STEPS = 700
SECONDS_CONTROLLED = 3
STEPS_PER_SECOND = 100
TARGET = (0.0, 0.0, -0.7)
"""Bottom centre of the basket [m]."""
N_PARAMS = SECONDS_CONTROLLED * len(CORNERS) * 3


def error_pct(com_final: np.ndarray, com_initial: np.ndarray) -> float:
    """|com_T - target| / |com_0 - target| x 100: 100 % ends as far from the target as it started. Not "no
    better than doing nothing": with no pushes the cloth drops straight down outside the wall, with no floor to stop
    it, to z = -238 m after the 7 s (5508 %)."""
    target = np.asarray(TARGET)
    return 100.0 * float(np.linalg.norm(com_final - target) / np.linalg.norm(com_initial - target))


class ThrowTask:
    """The throw: loss, gradient and trajectory as functions of the 36 corner pushes ``a[second, corner, xyz]``."""

    def __init__(self, model: wc.Model | None = None, *, steps: int = STEPS, options: wc.SolverOptions | None = None,
                 segment_steps: int | None = None):
        self.model = model or basket_scene()
        self.steps = steps
        self.segment_steps = segment_steps
        # hard throws pile the cloth into the basket's corners: allow more projection rounds than the default
        self.sim = wc.Simulator(self.model, DT, options=options or wc.SolverOptions(
            cg_tol=1e-6, collision=wc.CollisionOptions(rounds=50)))
        self._kernels = loss_kernels(self.model.scalar)
        device = self.model.device
        self.corners = wp.array(CORNERS, dtype=wp.int32, device=device)
        self.quarter_mass = float(self.model.particle_mass().sum()) / len(CORNERS)
        self.target = self.model.types.vec3(*TARGET)
        self.com_initial = self.model.particle_x0.numpy().mean(axis=0)
        self.simulations = 0
        self.seconds = 0.0

    def _forces(self, accel: wp.array) -> list[wp.array]:
        forces = []
        for s in range(SECONDS_CONTROLLED):
            f = wp.zeros(self.model.particle_count, dtype=self.model.types.vec3, device=self.model.device,
                         requires_grad=True)
            wp.launch(self._kernels.corner_forces, len(CORNERS),
                      inputs=[accel, s, self.corners, self.model.scalar(self.quarter_mass)], outputs=[f],
                      device=self.model.device)
            forces.append(f)
        return forces

    def _control_fn(self, forces: list[wp.array]):
        base = self.model.control(requires_grad=False)
        controls = [wc.Control(f, base.handle_target, base.pin_target, obstacle_transform=base.obstacle_transform)
                    for f in forces]

        def control(i: int) -> wc.Control:
            s = i // STEPS_PER_SECOND
            return controls[s] if s < SECONDS_CONTROLLED else base

        return control

    def _accel_array(self, params: np.ndarray) -> wp.array:
        params = np.asarray(params, dtype=np.float64).reshape(-1)
        if params.shape != (N_PARAMS,) or not np.all(np.isfinite(params)):
            raise ValueError(f"control parameters must be {N_PARAMS} finite numbers, got shape {params.shape}")
        return wp.array(params.reshape(-1, 3), dtype=self.model.types.vec3, device=self.model.device,
                        requires_grad=True)

    def _loss_fn(self, component: int | None = None):
        model = self.model
        com = wp.zeros(1, dtype=model.types.vec3, device=model.device, requires_grad=True)

        def loss(i: int, state: wc.State, out: wp.array) -> None:
            if i == self.steps:  # the loss squares the mean: accumulate the mean first, then square it
                com.zero_()
                wp.launch(self._kernels.centre_of_mass, model.particle_count,
                          inputs=[state.particle_x, model.scalar(1.0 / model.particle_count)], outputs=[com])
                if component is None:
                    wp.launch(self._kernels.point_squared_distance, 1, inputs=[com, self.target, model.scalar(0.5)],
                              outputs=[out])
                else:
                    wp.launch(self._kernels.add_component, 1, inputs=[com, component], outputs=[out])

        return loss, com

    def loss_and_grad(self, params: np.ndarray, *, component: int | None = None
                      ) -> tuple[float, np.ndarray, np.ndarray]:
        """(loss [m^2], d loss / d params (36,), final centre of mass (3,)); one simulation. With ``component``
        (0, 1, 2) the "loss" is that coordinate of the final centre of mass instead."""
        t0 = time.perf_counter()
        accel = self._accel_array(params)
        tape = wp.Tape()
        with tape:
            forces = self._forces(accel)
        loss_fn, com = self._loss_fn(component)
        value, _ = wc.checkpointed_backward(self.sim, self.model.state(requires_grad=False), self._control_fn(forces),
                                            steps=self.steps, loss=loss_fn, segment_steps=self.segment_steps)
        tape.backward(grads={f: f.grad for f in forces})
        self.simulations += 1
        self.seconds += time.perf_counter() - t0
        return value, accel.grad.numpy().astype(np.float64).reshape(-1), com.numpy()[0].astype(np.float64)

    def trajectory(self, params: np.ndarray) -> list[np.ndarray]:
        """Positions (n, 3) of every step, from a forward pass only."""
        control = self._control_fn(self._forces(self._accel_array(params)))
        state = self.model.state(requires_grad=False)
        frames = [state.particle_x.numpy()]
        for i in range(self.steps):
            nxt = self.model.empty_state(requires_grad=False)
            self.sim.step(state, nxt, control(i))
            state = nxt
            frames.append(state.particle_x.numpy())
        return frames


@dataclass
class ControlResult:
    params: np.ndarray
    """Corner pushes [m/s^2], shape (3 seconds, 4 corners, 3) (see the module docstring)."""
    losses: list[float] = field(default_factory=list)
    errors_pct: list[float] = field(default_factory=list)
    simulations: int = 0
    """Forward + backward simulations until the best result."""
    error_pct: float = math.nan
    seconds: float = 0.0
    failed_trials: list[str] = field(default_factory=list)
    """Messages of trial steps whose simulation raised (a CollisionError or a SimulationError): each is rejected as a
    bad step, counted as a simulation, and the run goes on."""

    def trajectory(self, task: ThrowTask) -> list[np.ndarray]:
        """Positions of every step with the best pushes (forward only; the MLP's pushes replayed open-loop)."""
        return task.trajectory(self.params.reshape(-1))


def optimize_open_loop(task: ThrowTask, *, iters: int = 50, max_step: float = 20.0, damping: float = 1e-3,
                       start: np.ndarray | None = None, progress: bool = False, callback=None) -> ControlResult:
    """Damped Gauss-Newton on the 36 corner pushes, from zero (the seed's start) or ``start`` (36 pushes [m/s^2]).
    ``iters`` bounds the simulations (forward + backward) spent; returns the best iterate and the simulations spent
    to reach it. A start whose simulation raises is halved towards zero until one runs.

    The loss is 1/2 |r|^2 with r = com_T - target (3 numbers). Without contact the mass-weighted centre moves
    affinely with the pushes (they are external forces) and the vertex mean (the seed's com) nearly so, so a
    Gauss-Newton step (the least-norm push change that zeroes r in the linearisation) makes most of the way where
    first-order methods crawl; contacts make it nonlinear, and a step is halved until the loss drops. Each point
    costs three simulations (one reverse pass per coordinate of com_T: the 3x36 Jacobian), cut short when its loss
    is worse. ``max_step`` [m/s^2] bounds how far one step moves any push.
    """
    result = ControlResult(params=np.zeros((SECONDS_CONTROLLED, len(CORNERS), 3)))
    bar = progress_bar(iters, "control (open-loop)", "sim") if progress else None
    t0 = time.perf_counter()
    target = np.asarray(TARGET)

    def record(params, com) -> float:
        r = com - target
        loss = 0.5 * float(r @ r)
        err = error_pct(com, task.com_initial)
        result.losses.append(loss)
        result.errors_pct.append(err)
        k = len(result.losses)
        if not err >= result.error_pct:  # the first recorded point (error_pct is NaN until then) or a better one
            result.params = params.reshape(SECONDS_CONTROLLED, len(CORNERS), 3).copy()
            result.simulations, result.error_pct = k, err
        if bar is not None:
            bar.update()
            bar.set_postfix(loss=f"{loss:.3e}", err=f"{err:.1f}%")
        if callback is not None:
            callback(k, loss, err, params)
        return loss

    def evaluate(params: np.ndarray) -> tuple[float, np.ndarray | None, np.ndarray | None]:
        """Loss, com_T and the Jacobian at params: three simulations (one reverse pass per coordinate); stops early
        at a worse loss. A simulation that raises (CollisionError, SimulationError) counts as an infinite loss: the
        step is rejected and halved."""
        jac = np.zeros((3, N_PARAMS))
        com = None
        for k in range(3):
            if len(result.losses) >= iters:
                return math.inf, None, None
            try:
                _, jac[k], com_k = task.loss_and_grad(params, component=k)
            except (wc.CollisionError, wc.SimulationError) as exc:
                result.failed_trials.append(f"{type(exc).__name__}: {exc}")
                result.losses.append(math.inf)
                result.errors_pct.append(math.inf)
                return math.inf, None, None
            if k == 0:
                com = com_k
                trial_loss = record(params, com)
                if trial_loss >= best_loss:
                    return trial_loss, None, None
            else:  # the same point again: keep the per-simulation history aligned
                result.losses.append(result.losses[-1])
                result.errors_pct.append(result.errors_pct[-1])
                if bar is not None:
                    bar.update()
        return trial_loss, com, jac

    params = np.zeros(N_PARAMS) if start is None else np.array(start, dtype=np.float64).reshape(N_PARAMS)
    best_loss = math.inf
    best_loss, com, jac = evaluate(params)
    while com is None and result.failed_trials and len(result.losses) < iters:  # the start raised: pull it in
        params = 0.5 * params
        best_loss, com, jac = evaluate(params)
    step = None
    while com is not None and len(result.losses) < iters:
        if step is None:
            r = com - target
            gram = jac @ jac.T
            step = -jac.T @ np.linalg.solve(gram + damping * np.trace(gram) / 3 * np.eye(3), r)
            step *= min(1.0, max_step / max(np.abs(step).max(), 1e-30))
        trial_loss, trial_com, trial_jac = evaluate(params + step)
        if trial_com is not None:  # accepted: a lower loss with its Jacobian
            params, best_loss, com, jac, step = params + step, trial_loss, trial_com, trial_jac, None
        else:
            step = 0.5 * step
    if bar is not None:
        bar.close()
    result.seconds = time.perf_counter() - t0
    return result


SEED_PUBLISHED = {
    "open-loop": {"error_pct": 17.0, "simulations": 53, "target_error_pct": 10.0, "target_simulations": 50},
    "mlp": {"error_pct": 39.0, "simulations": 108, "target_error_pct": 20.0, "target_simulations": 100},
}
"""The seed's Table 3 ("Ours" and "Ours + FC"; talk slides) and this project's targets."""


def _push_to_force(push, quarter_mass: float, n: int):
    """(4, 3) torch pushes -> (n, 3) particle forces on the corners (differentiable)."""
    import torch

    force = torch.zeros((n, 3), dtype=push.dtype, device=push.device)
    return force.index_put((torch.tensor(CORNERS, device=push.device),), quarter_mass * push)


def train_mlp(task: ThrowTask, *, iters: int = 100, lr: float = 1e-3, hidden: int = 200, seed: int = 0,
              zero_start: bool = True, progress: bool = False) -> ControlResult:
    """Train a PyTorch MLP controller through the simulator (warpcloth.torch): every second of the first three, the
    MLP maps the cloth's state (positions relative to the target and velocities of all particles) to the 4 corner
    pushes, applied for that second (the seed's "Ours + FC": Linear -> ReLU -> Linear). Adam on the weights; each
    iteration is one forward + backward simulation of the whole throw. A simulation that raises (CollisionError,
    SimulationError) is a rejected step: the weights go back to the last ones that simulated and the learning rate
    halves (``ControlResult.failed_trials``); the run goes on.

    The network and every tensor take the model's torch device and dtype (``warpcloth.torch.torch_device`` and
    ``torch_dtype``); the initial weights are drawn on the CPU in float32 whatever they are, so a seed gives the same
    start on every device and precision.

    Args:
        task: The throw (its model, simulator and horizon).
        iters: Training iterations (one forward + backward simulation each).
        lr: Adam's learning rate.
        hidden: Width of the hidden layer.
        seed: Seed of torch's generator for the initial weights.
        zero_start: Zero the output layer, so training starts from no pushes (as the open loop does); else it keeps
            PyTorch's random initialisation (a random start).
        progress: Show a progress bar (tqdm).

    Returns:
        The pushes of the best iteration (replayed open-loop by ``ControlResult.trajectory``) and the history.

    Raises:
        ImportError: When PyTorch is not installed.
    """
    import torch

    from warpcloth.torch import simulate, torch_device, torch_dtype

    torch.manual_seed(seed)
    model = task.model
    device, dtype = torch_device(model), torch_dtype(model)
    n = model.particle_count
    net = torch.nn.Sequential(torch.nn.Linear(6 * n, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, 12))
    if zero_start:
        with torch.no_grad():  # start from "no push", as the open-loop optimisation does
            net[2].weight.zero_()
            net[2].bias.zero_()
    net = net.to(device=device, dtype=dtype)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    x0 = torch.tensor(model.particle_x0.numpy(), dtype=dtype, device=device)
    v0 = torch.tensor(model.particle_v0.numpy(), dtype=dtype, device=device)
    target = torch.tensor(TARGET, dtype=dtype, device=device)
    push_scale = 10.0  # network outputs of order one -> pushes of order gravity [m/s^2]

    def policy(x, v):
        features = torch.cat([(x - target).reshape(-1), 0.1 * v.reshape(-1)])
        return push_scale * net(features).reshape(len(CORNERS), 3)

    result = ControlResult(params=np.zeros((SECONDS_CONTROLLED, len(CORNERS), 3)))
    best = math.inf
    bar = progress_bar(iters, "control (mlp)", "sim") if progress else None
    t0 = time.perf_counter()
    last_good = copy.deepcopy(net.state_dict())  # the weights of the last simulation that ran through
    for k in range(1, iters + 1):
        x, v = x0, v0
        pushes = []
        try:
            for s in range(SECONDS_CONTROLLED):
                push = policy(x, v)
                pushes.append(push)
                xs, vs = simulate(task.sim, x, v, steps=STEPS_PER_SECOND, time=s * STEPS_PER_SECOND * DT,
                                  particle_force=_push_to_force(push, task.quarter_mass, n))
                x, v = xs[-1], vs[-1]
            rest = task.steps - SECONDS_CONTROLLED * STEPS_PER_SECOND
            if rest > 0:
                xs, vs = simulate(task.sim, x, v, steps=rest, time=SECONDS_CONTROLLED * STEPS_PER_SECOND * DT)
                x = xs[-1]
            com = x.mean(dim=0)
            loss = 0.5 * ((com - target) ** 2).sum()
            opt.zero_grad()
            loss.backward()
        except (wc.CollisionError, wc.SimulationError) as exc:
            # a rejected step: back to the last weights that simulated, with half the learning rate
            task.simulations += 1
            result.failed_trials.append(f"{type(exc).__name__}: {exc}")
            result.losses.append(math.inf)
            result.errors_pct.append(math.inf)
            net.load_state_dict(last_good)
            for group in opt.param_groups:
                group["lr"] *= 0.5
            if bar is not None:
                bar.update()
            continue
        last_good = copy.deepcopy(net.state_dict())
        opt.step()
        task.simulations += 1
        err = error_pct(com.detach().cpu().numpy().astype(np.float64), task.com_initial)
        result.losses.append(float(loss.detach()))
        result.errors_pct.append(err)
        if err < best:
            best = err
            result.params = torch.stack(pushes).detach().cpu().numpy().astype(np.float64)
            result.simulations, result.error_pct = k, err
        if bar is not None:
            bar.update()
            bar.set_postfix(loss=f"{float(loss):.3e}", err=f"{err:.1f}%")
    if bar is not None:
        bar.close()
    result.seconds = time.perf_counter() - t0
    return result
