"""PyTorch bridge: a simulator rollout as a differentiable torch function.

``simulate`` lets a torch model (a network predicting forces or materials, an optimiser over torch parameters)
train through the cloth simulator: the forward runs the Warp steps, the backward runs their Warp tape. The
trajectory tensors share memory with the States the simulator writes, and the per-step forces with the tensor
given, so nothing is copied per step.

Importing ``warpcloth`` never imports torch; only ``import warpcloth.torch`` does (``pip install warpcloth[torch]``).
"""

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

from warpcloth.materials import check_material_values
from warpcloth.model import Control, Model, State
from warpcloth.solver.simulator import Simulator

__all__ = ["simulate"]


def torch_dtype(model: Model) -> torch.dtype:
    """The torch dtype of the model's float arrays (torch.float32 or torch.float64)."""
    return wp.dtype_to_torch(model.scalar)


def torch_device(model: Model) -> torch.device:
    """The torch device of the model's arrays."""
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
) -> tuple[torch.Tensor, torch.Tensor]:
    """Simulate ``steps`` steps from (x0, v0) and return the trajectory ``(x, v)``, each (steps+1, n, 3).

    Row 0 is the initial state, so a loss may weigh every frame. Gradients flow to x0, v0, ``particle_force`` and
    the material tensors.

    The material tensors are written into ``sim.model``'s arrays (``material_density`` (material_count,),
    ``material_stretching`` (material_count, 6, 4), ``material_bending`` (material_count, 3, 5), raw units before
    thicken), which stay overwritten after the call: that is what the simulator reads. None uses the model's
    current values, which then get no gradient. The backward puts this call's values back temporarily, so calls
    with different materials can be chained before one backward.

    Args:
        sim: the Simulator; its model must be built with ``requires_grad=True`` for gradients.
        x0, v0: initial positions [m] and velocities [m/s], (n, 3).
        steps: number of steps (>= 0).
        particle_force: external forces [N]: (n, 3) for every step, or (steps, n, 3) one per step; None for none.
        density, stretching, bending: material tables in the shapes of the model's arrays, or None.
        time: simulated time of x0 [s]; scripted handle, pin and obstacle motion is keyed to it, so a chained call
            continues with ``time = previous start + previous steps * sim.dt``.

    A batch dimension: for a model of W worlds of m particles each (``ModelBuilder.replicate``), x0 and v0 may be
    (W, m, 3), ``particle_force`` then (W, m, 3) or (W, steps, m, 3), and the trajectory comes back as
    (W, steps+1, m, 3) each: world w's is ``x[w]``. The worlds are simulated together, one launch per kernel for
    all of them, and one backward pass gives every world's gradient.

    Every tensor must have the model's float dtype and live on its device (ValueError naming the argument
    otherwise). Each call starts a new trajectory: with ``set_wind(lagged_normals=True)`` its first step uses
    x0's normals. Backward can run again only with ``retain_graph=True``; double backward is not supported.
    """
    if not isinstance(sim, Simulator):
        raise TypeError(f"sim must be a warpcloth.Simulator, got {type(sim).__name__}")
    if isinstance(steps, bool) or int(steps) != steps or steps < 0:
        raise ValueError(f"steps must be a non-negative integer, got {steps!r}")
    steps = int(steps)
    model = sim.model
    if isinstance(x0, torch.Tensor) and x0.dim() == 3:
        return _simulate_batch(sim, x0, v0, steps, particle_force, density, stretching, bending, time)
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
    return _Rollout.apply(_Config(sim, steps, float(time)), x0, v0, particle_force, density, stretching, bending)


def _simulate_batch(sim, x0, v0, steps, particle_force, density, stretching, bending, time):
    """``simulate`` with a leading world dimension: the worlds' tensors flattened into the model's particle order
    (each world's particles are one contiguous range), the trajectory split back into worlds."""
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
                    stretching=stretching, bending=bending, time=time)
    return (x.reshape(steps + 1, W, m, 3).transpose(0, 1), v.reshape(steps + 1, W, m, 3).transpose(0, 1))


def _check_tensor(name: str, t, model: Model, shapes: list[tuple[int, ...]]) -> None:
    """Raise a ValueError that names the argument when a tensor cannot be handed to the model's kernels."""
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
    """The non-tensor arguments of the autograd function."""

    def __init__(self, sim: Simulator, steps: int, time: float):
        self.sim, self.steps, self.time = sim, steps, time


_MATERIALS = ("density", "stretching", "bending")


class _Recording:
    """What the backward pass needs from the forward: the tape and the buffers its launches read and write.

    Released (so the tape's per-step buffers are freed) as soon as torch frees the node's saved tensors: after a
    backward without retain_graph, or when the graph is dropped.
    """

    def __init__(self, tape, grads, material_values, keep):
        self.tape = tape
        self.grads = grads  # torch gradient buffers the Warp views write: x, v (steps+1, n, 3) and force, or None
        self.material_values = material_values  # this call's model material values (wp arrays, no grad)
        self.keep = keep  # arrays the tape's launches alias: trajectory storage, force tensor, states, controls

    def release(self):
        self.tape = self.grads = self.material_values = self.keep = None


def _vec3_view(t: torch.Tensor, vec3, grad: torch.Tensor | None) -> wp.array:
    """A Warp vec3 array aliasing the (n, 3) tensor ``t``, with ``grad`` as its (aliased) gradient."""
    if grad is None:
        return wp.from_torch(t, dtype=vec3, requires_grad=False)
    return wp.from_torch(t, dtype=vec3, requires_grad=True, grad=grad)


class _Rollout(torch.autograd.Function):
    @staticmethod
    def forward(ctx, cfg: _Config, x0, v0, force, density, stretching, bending):
        sim, steps = cfg.sim, cfg.steps
        model = sim.model
        vec3 = model.types.vec3
        n = model.particle_count
        recording = any(ctx.needs_input_grad[1:]) and model.requires_grad
        ctx.set_materialize_grads(False)

        # the simulator reads the materials from the model's arrays: write the given ones there
        for name, value in zip(_MATERIALS, (density, stretching, bending)):
            if value is not None:
                wp.copy(getattr(model, f"material_{name}"),
                        wp.from_torch(value.detach().contiguous(), dtype=model.scalar, requires_grad=False))

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

        base = model.control(requires_grad=False)

        def control(f):
            return Control(f, base.handle_target, base.pin_target, obstacle_transform=base.obstacle_transform)

        gf = None
        fd = None
        if force is None:
            controls = [control(None)] * steps
        else:
            fd = force.detach().contiguous()
            gf = torch.zeros_like(fd) if recording and ctx.needs_input_grad[3] else None
            if fd.dim() == 2:  # one array for every step: Warp's adjoint accumulates the steps' gradients into gf
                controls = [control(_vec3_view(fd, vec3, gf))] * steps
            else:
                controls = [control(_vec3_view(fd[i], vec3, None if gf is None else gf[i])) for i in range(steps)]

        tape = wp.Tape() if recording else None
        with tape if tape is not None else contextlib.nullcontext():
            for i in range(steps):  # wc.rollout's loop, into preallocated States that alias x and v
                sim.step(states[i], states[i + 1], controls[i])

        if recording:
            material_values = {name: wp.clone(getattr(model, f"material_{name}"), requires_grad=False)
                               for name in _MATERIALS}
            rec = _Recording(tape, {"x": gx, "v": gv, "force": gf}, material_values,
                             keep=(xd, vd, fd, states, controls, base))
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
        if rec.tape is None:
            raise RuntimeError("warpcloth.torch.simulate: the rollout's Warp tape was already released")
        model = ctx.cfg.sim.model
        arrays = {name: getattr(model, f"material_{name}") for name in _MATERIALS}
        # another simulate call may have overwritten the model's materials since this forward: the tape's
        # launches read the arrays now, so put this call's values back for the backward, and restore after
        current = {name: wp.clone(a, requires_grad=False) for name, a in arrays.items()}
        try:
            for name, a in arrays.items():
                wp.copy(a, rec.material_values[name])
            rec.tape.zero()  # a rerun (retain_graph) starts from clean intermediate gradients
            for a in arrays.values():
                a.grad.zero_()
            for g in rec.grads.values():
                if g is not None:
                    g.zero_()
            if grad_x is not None:
                rec.grads["x"].copy_(grad_x)
            if grad_v is not None:
                rec.grads["v"].copy_(grad_v)
            rec.tape.backward()
            needs = ctx.needs_input_grad
            result = [None]  # cfg
            result.append(rec.grads["x"][0].clone() if needs[1] else None)
            result.append(rec.grads["v"][0].clone() if needs[2] else None)
            result.append(rec.grads["force"].clone() if needs[3] and rec.grads["force"] is not None else None)
            for i, name in enumerate(_MATERIALS):
                result.append(wp.to_torch(arrays[name].grad, requires_grad=False).clone() if needs[4 + i] else None)
        finally:
            for name, a in arrays.items():
                wp.copy(a, current[name])
        return tuple(result)
