"""PyTorch bridge: a simulator rollout as a differentiable torch function (``pip install warpcloth[torch]``); only
``import warpcloth.torch`` imports torch."""

from __future__ import annotations

import contextlib
import weakref

try:
    import torch
except ImportError as exc:  # pragma: no cover - exercised in a subprocess by the tests
    raise ImportError(
        "warpcloth.torch needs PyTorch, which is an optional extra: pip install warpcloth[torch]"
    ) from exc

import numpy as np
import warp as wp

from warpcloth.kernels.losses import loss_kernels
from warpcloth.materials import check_material_values
from warpcloth.model import Control, Model, State
from warpcloth.solver.capture import CapturedRollout
from warpcloth.solver.gradients import GraphCache, plan_gradient
from warpcloth.solver.simulator import Simulator

__all__ = ["MAX_CAPTURES", "simulate"]


def torch_dtype(model: Model) -> torch.dtype:
    """The torch dtype of the model's float arrays (torch.float32 or torch.float64)."""
    return wp.dtype_to_torch(model.scalar)


def torch_device(model: Model) -> torch.device:
    return torch.device(wp.device_to_torch(model.device))


def simulate(
    sim: Simulator,
    x0: torch.Tensor,
    v0: torch.Tensor,
    *,
    steps: int,
    particle_force: torch.Tensor | None = None,
    density: torch.Tensor | None = None,
    stretching: torch.Tensor | None = None,
    bending: torch.Tensor | None = None,
    time: float = 0.0,
    capture: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Simulate ``steps`` (>= 0) steps from positions x0 [m] and velocities v0 [m/s], (n, 3); returns the trajectory
    ``(x, v)``, each (steps+1, n, 3), row 0 the initial state. Gradients flow to x0, v0, ``particle_force`` and the
    material tensors; ``sim``'s model must have been built with ``requires_grad=True`` for them.

    ``particle_force`` [N]: (n, 3) for every step, (steps, n, 3) one a step, or None. ``density``, ``stretching``,
    ``bending``: raw tables before thicken, (material_count,), (material_count, 6, 4), (material_count, 3, 5), written
    into the model's arrays (they stay there; the backward uses this call's values); None: the model's, without
    gradient. ``time`` [s]: the simulated time of x0, to which scripted motion is keyed. A model of W worlds of m
    particles takes x0, v0 (W, m, 3) and forces (W, m, 3) or (W, steps, m, 3), and returns (W, steps+1, m, 3) each.

    ``capture`` replays the rollout from graphs (``wc.CapturedRollout``) from the second call with this Simulator,
    ``steps``, ``time`` and form of ``particle_force`` on, with the uncaptured call's results and gradients (bitwise
    on the CPU); the Simulator keeps its last ``MAX_CAPTURES``. Why: docs/concepts/torch.md. Backward runs again only
    with ``retain_graph=True``; there is no double backward.

    Raises:
        ValueError: naming the argument for a tensor of another shape, dtype or device, or invalid material values;
            a gradient asked of a model without one; ``capture`` where the steps cannot be captured.
        TypeError: ``sim`` is not a Simulator, or an argument is not a tensor."""
    if not isinstance(sim, Simulator):
        raise TypeError(f"sim must be a warpcloth.Simulator, got {type(sim).__name__}")
    if isinstance(steps, bool) or int(steps) != steps or steps < 0:
        raise ValueError(f"steps must be a non-negative integer, got {steps!r}")
    steps = int(steps)
    model = sim.model
    if isinstance(x0, torch.Tensor) and x0.dim() == 3:
        return _simulate_batch(sim, x0, v0, steps, particle_force, density, stretching, bending, time, capture)
    n = model.particle_count
    _check_tensor("x0", x0, model, [(n, 3)])
    _check_tensor("v0", v0, model, [(n, 3)])
    if particle_force is not None:
        _check_tensor("particle_force", particle_force, model, [(n, 3), (steps, n, 3)])
    materials = {"density": density, "stretching": stretching, "bending": bending}
    for name, t in materials.items():
        if t is not None:
            _check_tensor(name, t, model, [tuple(getattr(model, f"material_{name}").shape)])
    # before anything is written into the model: a rejected call leaves its materials as they were
    check_material_values("simulate", **{k: t.detach().cpu().numpy() for k, t in materials.items() if t is not None})
    needs_grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad for t in (x0, v0, particle_force, density, stretching, bending)
    )
    if needs_grad and not model.requires_grad:
        raise ValueError("simulate: a gradient was asked for but the model has none; build it with "
                         "ModelBuilder.finalize(..., requires_grad=True)")
    if capture:
        reason = CapturedRollout.unsupported(sim)
        if reason is not None:
            raise ValueError(f"simulate: capture=True, but {reason}")
    config = _Config(sim, steps, float(time), bool(capture))
    return _Rollout.apply(config, x0, v0, particle_force, density, stretching, bending)


def _simulate_batch(sim, x0, v0, steps, particle_force, density, stretching, bending, time, capture):
    """``simulate`` with a leading world dimension, through the model's contiguous particle order."""
    model = sim.model
    sizes = set(np.diff(model.world_particle_start).tolist())
    if len(sizes) != 1:
        raise ValueError(f"simulate: a batch dimension needs worlds of one size; this model's worlds have "
                         f"{sorted(sizes)} particles (pass (particle_count, 3) tensors instead)")
    W, m = model.world_count, sizes.pop()
    _check_tensor("x0", x0, model, [(W, m, 3)])
    _check_tensor("v0", v0, model, [(W, m, 3)])
    force = particle_force
    if force is not None:
        _check_tensor("particle_force", force, model, [(W, m, 3), (W, steps, m, 3)])
        force = force.reshape(-1, 3) if force.dim() == 3 else force.transpose(0, 1).reshape(steps, W * m, 3)
    x, v = simulate(sim, x0.reshape(-1, 3), v0.reshape(-1, 3), steps=steps, particle_force=force, density=density,
                    stretching=stretching, bending=bending, time=time, capture=capture)
    return (x.reshape(steps + 1, W, m, 3).transpose(0, 1), v.reshape(steps + 1, W, m, 3).transpose(0, 1))


def _check_tensor(name: str, t, model: Model, shapes: list[tuple[int, ...]]) -> None:
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    dtype, device = torch_dtype(model), torch_device(model)
    got = f"got shape {tuple(t.shape)}, dtype {t.dtype}, device {t.device}"
    expected = " or ".join(str(s) for s in shapes)
    if t.device != device:
        raise ValueError(f"{name} must be on the model's device {device} (warp {model.device}); {got}")
    if t.dtype != dtype:
        raise ValueError(f"{name} must have the model's dtype {dtype} (warp {model.scalar.__name__}); {got}")
    if tuple(t.shape) not in shapes:
        raise ValueError(f"{name} must have shape {expected}; {got}")


class _Config:

    def __init__(self, sim: Simulator, steps: int, time: float, capture: bool):
        self.sim, self.steps, self.time, self.capture = sim, steps, time, capture


_MATERIALS = ("density", "stretching", "bending")

MAX_CAPTURES = 32
"""How many captured calls (``simulate(capture=True)``) a Simulator keeps; the least recently used is dropped."""


class _Recording:
    """What the backward needs from the forward: the tape and its buffers, or the replay and its inputs. Released
    when torch frees the node's saved tensors."""

    def __init__(self, tape, grads, material_values, keep, replay=None):
        self.tape = tape
        self.grads = grads  # torch gradient buffers the Warp views write: x, v (steps+1, n, 3) and force, or None
        self.material_values = material_values  # this call's model material values (wp arrays, no grad)
        self.keep = keep  # uncaptured: arrays the tape's launches alias; captured: the inputs (x0, v0, force)
        self.replay = replay

    def release(self):
        self.tape = self.grads = self.material_values = self.keep = self.replay = None


class _Replay:
    """One call of ``simulate`` captured over arrays of its own (inputs copied in, trajectory out); with gradients
    its "loss" is the trajectory gathered into (steps+1, n) arrays, whose gradients torch's seed."""

    def __init__(self, sim: Simulator, steps: int, time: float, force_form: str | None, x0, v0, force):
        model = sim.model
        vec3, n, grad = model.types.vec3, model.particle_count, model.requires_grad
        self.steps, self.vec3 = steps, vec3
        self.state = model.state(requires_grad=grad)
        self.state.time = time
        self.force = None
        if force_form is None:
            controls = _controls(model, steps, None)
        elif force_form == "shared":
            self.force = wp.zeros(n, dtype=vec3, device=model.device, requires_grad=grad)
            controls = _controls(model, steps, self.force)
        else:
            self.force = wp.zeros((steps, n), dtype=vec3, device=model.device, requires_grad=grad)
            controls = _controls(model, steps, [self.force[i] for i in range(steps)])
        self.store_frame = loss_kernels(model.scalar).store_frame
        self.velocities: wp.array | None = None  # the gathered velocities (the positions are the rollout's loss)
        self.owner: _Recording | None = None  # the call whose forward pass the graphs' arrays hold
        self.load(x0, v0, force)  # the capture's first, ordinary run simulates these inputs
        self.rollout = CapturedRollout(sim, self.state, controls, steps=steps, loss=self._gather if grad else None)

    def _gather(self, trajectory: list[State]) -> wp.array:
        first = trajectory[0].particle_x
        shape = (len(trajectory), first.shape[0])
        xs = wp.empty(shape, dtype=self.vec3, device=first.device, requires_grad=True)
        vs = wp.empty(shape, dtype=self.vec3, device=first.device, requires_grad=True)
        for k, s in enumerate(trajectory):
            wp.launch(self.store_frame, dim=shape[1], inputs=[s.particle_x, s.particle_v, k], outputs=[xs, vs],
                      device=first.device)
        self.velocities = vs
        return xs

    def load(self, x0, v0, force) -> None:
        wp.copy(self.state.particle_x, wp.from_torch(x0.detach().contiguous(), dtype=self.vec3))
        wp.copy(self.state.particle_v, wp.from_torch(v0.detach().contiguous(), dtype=self.vec3))
        if self.force is not None:
            wp.copy(self.force, wp.from_torch(force.detach().contiguous(), dtype=self.vec3))

    def forward(self, x0, v0, force, owner: _Recording | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Replay from these inputs; returns the trajectory as new tensors."""
        self.load(x0, v0, force)
        trajectory = self.rollout.run(backward=False)
        self.owner = owner
        if self.rollout.loss is not None:
            return (wp.to_torch(self.rollout.loss, requires_grad=False).clone(),
                    wp.to_torch(self.velocities, requires_grad=False).clone())
        return (torch.stack([wp.to_torch(s.particle_x, requires_grad=False) for s in trajectory]),
                torch.stack([wp.to_torch(s.particle_v, requires_grad=False) for s in trajectory]))

    def backward(self, grad_x, grad_v) -> None:
        """The recorded backward pass from the trajectory's gradients (None: zero)."""
        seeds = {}
        for array, g in ((self.rollout.loss, grad_x), (self.velocities, grad_v)):
            if g is not None:
                seeds[array] = wp.from_torch(g.contiguous(), dtype=self.vec3)
        self.rollout.backward(seeds)


_graphs: weakref.WeakKeyDictionary[Simulator, GraphCache[_Replay]] = weakref.WeakKeyDictionary()
"""Each Simulator's captured calls, by (steps, time, force form): the second call captures, later ones replay."""


def _controls(model: Model, steps: int, force) -> list[Control]:
    """A Control a step at the model's defaults, with ``force``: None, one array, or a list of one a step."""
    base = model.control(requires_grad=False)

    def control(f):
        return Control(f, base.handle_target, base.pin_target, obstacle_transform=base.obstacle_transform)

    if isinstance(force, list):
        return [control(f) for f in force]
    return [control(force)] * steps


def _vec3_view(t: torch.Tensor, vec3, grad: torch.Tensor | None) -> wp.array:
    """A Warp vec3 array aliasing the (n, 3) tensor ``t``, with ``grad`` as its (aliased) gradient."""
    if grad is None:
        return wp.from_torch(t, dtype=vec3, requires_grad=False)
    return wp.from_torch(t, dtype=vec3, requires_grad=True, grad=grad)


@contextlib.contextmanager
def _materials_of(model: Model, values: dict):
    """The model's material arrays hold one call's ``values`` inside the block (its launches read them), their
    current values after it."""
    arrays = {name: getattr(model, f"material_{name}") for name in _MATERIALS}
    current = {name: wp.clone(a, requires_grad=False) for name, a in arrays.items()}
    try:
        for name, a in arrays.items():
            wp.copy(a, values[name])
        yield arrays
    finally:
        for name, a in arrays.items():
            wp.copy(a, current[name])


class _Rollout(torch.autograd.Function):
    @staticmethod
    def forward(ctx, cfg: _Config, x0, v0, force, density, stretching, bending):
        sim, steps = cfg.sim, cfg.steps
        model = sim.model
        recording = any(ctx.needs_input_grad[1:]) and model.requires_grad
        ctx.set_materialize_grads(False)

        # the simulator reads the materials from the model's arrays: write the given ones there
        for name, value in zip(_MATERIALS, (density, stretching, bending)):
            if value is not None:
                wp.copy(getattr(model, f"material_{name}"),
                        wp.from_torch(value.detach().contiguous(), dtype=model.scalar, requires_grad=False))

        replay = None
        fd = None if force is None else force.detach().contiguous()
        if cfg.capture and steps > 0 and plan_gradient(sim, steps, backward=model.requires_grad).captured:
            force_form = None if fd is None else "shared" if fd.dim() == 2 else "steps"
            graphs = _graphs.get(sim)
            if graphs is None:
                graphs = _graphs[sim] = GraphCache(after=2, size=MAX_CAPTURES)
            replay = graphs.get((steps, cfg.time, force_form),
                                lambda: _Replay(sim, steps, cfg.time, force_form, x0, v0, fd),
                                lambda r: r.rollout.current())
        if replay is not None:
            rec = _Recording(None, None, _material_values(model), keep=None, replay=replay) if recording else None
            x, v = replay.forward(x0, v0, fd, rec)
            if rec is not None:
                # the inputs to replay this call again (another call of the graphs may run before its backward):
                # the trajectory's first frame (saved below, so torch refuses a backward after an in-place change)
                # and a copy of the forces
                rec.keep = (x.detach()[0], v.detach()[0], None if fd is None else fd.clone())
        else:
            x, v, rec = _run(ctx, cfg, x0, v0, fd, recording)
        if rec is not None:
            token = torch.empty(0)
            ctx.save_for_backward(x, v, token)  # x, v: torch's in-place check; token: lifetime of saved tensors
            weakref.finalize(token, rec.release)
            ctx.rec = rec
            ctx.cfg = cfg
        return x, v

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_x, grad_v):
        try:
            _ = ctx.saved_tensors  # raises if a backward without retain_graph already ran
        except RuntimeError as exc:
            raise RuntimeError(
                "warpcloth.torch.simulate: backward ran a second time through the same rollout, whose Warp tape "
                "was released by the first backward; pass retain_graph=True to the first backward, or simulate again"
            ) from exc
        rec = ctx.rec
        if rec.material_values is None:
            raise RuntimeError("warpcloth.torch.simulate: the rollout's Warp tape was already released")
        needs = ctx.needs_input_grad
        with _materials_of(ctx.cfg.sim.model, rec.material_values) as arrays:
            for a in arrays.values():
                a.grad.zero_()
            if rec.replay is not None:
                force_grad = _replayed_backward(rec, grad_x, grad_v)
                x0_grad, v0_grad = (wp.to_torch(a.grad, requires_grad=False).clone() if need else None
                                    for a, need in ((rec.replay.state.particle_x, needs[1]),
                                                    (rec.replay.state.particle_v, needs[2])))
            else:
                rec.tape.zero()  # a rerun (retain_graph) starts from clean intermediate gradients
                for g in rec.grads.values():
                    if g is not None:
                        g.zero_()
                if grad_x is not None:
                    rec.grads["x"].copy_(grad_x)
                if grad_v is not None:
                    rec.grads["v"].copy_(grad_v)
                rec.tape.backward()
                x0_grad = rec.grads["x"][0].clone() if needs[1] else None
                v0_grad = rec.grads["v"][0].clone() if needs[2] else None
                force_grad = rec.grads["force"]
            result = [None, x0_grad, v0_grad]  # cfg first
            result.append(force_grad.clone() if needs[3] and force_grad is not None else None)
            for i, name in enumerate(_MATERIALS):
                result.append(wp.to_torch(arrays[name].grad, requires_grad=False).clone() if needs[4 + i] else None)
        return tuple(result)


def _material_values(model: Model) -> dict:
    """Copies of the model's material arrays: what this call simulated with."""
    return {name: wp.clone(getattr(model, f"material_{name}"), requires_grad=False) for name in _MATERIALS}


def _run(ctx, cfg: _Config, x0, v0, fd, recording: bool):
    """An uncaptured call into States aliasing the trajectory, taped when recording: (x, v, _Recording or None)."""
    sim, steps = cfg.sim, cfg.steps
    model = sim.model
    vec3, n = model.types.vec3, model.particle_count
    x = torch.empty((steps + 1, n, 3), dtype=x0.dtype, device=x0.device)
    v = torch.empty_like(x)
    x[0].copy_(x0)
    v[0].copy_(v0)
    # Detached aliases share the storage but not the outputs' autograd history: the Warp views (and so the
    # tape) keep the memory alive without a reference cycle through this node.
    xd, vd = x.detach(), v.detach()
    gx = torch.zeros_like(xd) if recording else None
    gv = torch.zeros_like(vd) if recording else None
    states = [
        State(_vec3_view(xd[i], vec3, None if gx is None else gx[i]),
              _vec3_view(vd[i], vec3, None if gv is None else gv[i]))
        for i in range(steps + 1)
    ]
    states[0].time = cfg.time

    gf = None
    if fd is None:
        controls = _controls(model, steps, None)
    else:
        gf = torch.zeros_like(fd) if recording and ctx.needs_input_grad[3] else None
        if fd.dim() == 2:  # one array for every step: Warp's adjoint accumulates the steps' gradients into gf
            controls = _controls(model, steps, _vec3_view(fd, vec3, gf))
        else:
            controls = _controls(model, steps, [_vec3_view(fd[i], vec3, None if gf is None else gf[i])
                                                for i in range(steps)])

    tape = wp.Tape() if recording else None
    with tape if tape is not None else contextlib.nullcontext():
        for i in range(steps):  # wc.rollout's loop, into preallocated States that alias x and v
            sim.step(states[i], states[i + 1], controls[i])
    rec = None
    if recording:
        rec = _Recording(tape, {"x": gx, "v": gv, "force": gf}, _material_values(model),
                         keep=(xd, vd, fd, states, controls))
    return x, v, rec


def _replayed_backward(rec: _Recording, grad_x, grad_v):
    """A captured call's backward (its forward replayed first where another call ran since); the force's gradient."""
    replay = rec.replay
    if not replay.rollout.current():
        raise RuntimeError("warpcloth.torch.simulate: the Simulator's options or a model array were replaced between "
                           "this captured call and its backward pass, and its graphs hold the old ones; simulate "
                           "again")
    if replay.owner is not rec:
        replay.forward(*rec.keep, rec)
    replay.backward(grad_x, grad_v)
    if replay.force is None:
        return None
    return wp.to_torch(replay.force.grad, requires_grad=False)
