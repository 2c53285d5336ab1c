"""Which ways of capturing a taped rollout and its backward pass replay correctly on a device (issue 37).

On an H200 with Warp 1.19 (2026-11-27) a CUDA graph holding the taped forward pass and the backward pass failed to
instantiate ("invalid argument"), and the forward and backward passes as two graphs crashed on replay (error 719),
so ``wc.CapturedRollout`` with a loss runs uncaptured on CUDA. This probe tries the variants below, each in a
process of its own (a crashed CUDA context poisons the process), and prints whether each replays to the uncaptured
gradient:

    one_graph          forward (taped) + loss + backward in one graph, arrays allocated during the capture
    one_graph_no_gc    the same with Python's garbage collector off during the capture (no frees inside it)
    preallocated       every State allocated before the capture (the step's own per-step buffers still inside)
    two_graphs         forward graph, then backward graph (what CapturedRollout does on the CPU)
    two_graphs_no_gc   the same with the garbage collector off
    one_graph_kept     one_graph, every array made during the capture kept alive (warpcloth.tape.arrays_kept: Warp's
                       graphs hold no reference to them, and on the CPU one freed under a graph was reused)
    two_graphs_kept    two_graphs, the same
    per_step_kept      a graph per step and one per step's backward pass, each step on a tape of its own, then the
                       loss's two graphs, every array kept (what CapturedRollout does for a contact scene on the
                       CPU, _StepGraphs; on CUDA it is not tried for a rollout with a loss until this replays)
    one_graph_slab     one_graph_kept, every array made during the capture taken from one block of device memory
                       reserved before it (Slab), so that the graph holds no memory nodes: the allocations a graph
                       makes and frees itself are the suspects left for error 719 once arrays are kept alive
    two_graphs_slab    two_graphs_kept, the same
    per_step_slab      per_step_kept, the same
    two_graphs_kept_zero_after, per_step_kept_zero_after
                       the zeroing of the gradients replayed after the forward graphs instead of before them. The
                       arrays made in a CUDA capture are the graph's own allocations, backed by memory only once
                       that graph has run: the zeroing graph, replayed first, wrote to the gradients of the forward
                       graph's arrays before it ever ran (the suspect for error 719; wc.CapturedRollout's graphs of a
                       whole rollout replay in this order since 2026-11-29)

On the CPU (Warp 1.19, 2026-11-29) every variant replays exactly. The one_graph variants crashed there too until the
element kernels got a name per use: a CPU graph finds each kernel by its module and name, and the assembly and its
adjoint's "potential" were both "faces", so the replay ran one's code for both (``--debug`` showed the read out of
bounds; tests/test_kernels.py now holds every kernel factory to distinct names). CUDA graphs hold the kernels
themselves, so that was not what failed on the H200.

Usage: python benchmarks/gpu/capture_probe.py [--device cuda:0] [--variant NAME] [--debug]
(without --variant it runs every variant in a subprocess and prints a line each; ``--debug`` compiles the kernels in
Warp's debug mode, bounds-checked, so a fault names the access that failed instead of a bare CUDA error)
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import gc
import subprocess
import sys

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

import warpcloth as wc  # noqa: E402
from warpcloth.tape import arrays_kept  # noqa: E402
from warpcloth.tasks import scenes  # noqa: E402

VARIANTS = ("two_graphs_kept_zero_after", "two_graphs_slab", "per_step_kept_zero_after", "per_step_slab",
            "one_graph_slab", "one_graph", "one_graph_no_gc", "preallocated", "two_graphs", "two_graphs_no_gc",
            "one_graph_kept", "two_graphs_kept", "per_step_kept")
"""The suspects of error 719 first: a part that runs out of time loses the last."""
SLAB_BYTES = 1 << 30
"""The memory a slab variant reserves before its captures (6 steps of a 6x6 cloth take a few MB)."""
STEPS = 6


class Slab:
    """An allocator handing out one block of memory, reserved up front from the device's plain allocator
    (cudaMalloc on CUDA, not the stream-ordered pool), in order; freeing is a no-op. Arrays made during a CUDA capture
    with it are ordinary device memory, not the graph's own allocation nodes."""

    def __init__(self, device, nbytes: int):
        self.device = wp.get_device(device)
        self._inner = self.device.default_allocator
        self.memory_kind = self._inner.memory_kind
        self.deallocate_requires_context_guard = getattr(self._inner, "deallocate_requires_context_guard", False)
        self.base, self.nbytes, self.used = self._inner.allocate(nbytes), nbytes, 0

    def allocate(self, size_in_bytes: int) -> int:
        start = -(-self.used // 256) * 256  # CUDA's allocation alignment
        if start + size_in_bytes > self.nbytes:
            raise RuntimeError(f"Slab: {size_in_bytes} bytes more do not fit in {self.nbytes} ({start} used)")
        self.used = start + size_in_bytes
        return self.base + start

    def deallocate(self, ptr, size_in_bytes) -> None:
        pass  # the slab lives as long as the probe's process

    @contextlib.contextmanager
    def active(self):
        """Every array made inside on the slab's device takes its memory from the slab."""
        if self.device.is_cuda:
            wp.set_device_allocator(self.device, self)
        else:
            original, self.device.default_allocator = self.device.default_allocator, self
        try:
            yield
        finally:
            if self.device.is_cuda:
                wp.set_device_allocator(self.device, None)
            else:
                self.device.default_allocator = original


@wp.kernel
def _height(x: wp.array(dtype=wp.vec3), loss: wp.array(dtype=float)):
    wp.atomic_add(loss, 0, x[wp.tid()][2])


def _problem(device: str):
    model = scenes.hanging_cloth(wc.preset("gray-interlock", thicken=2), res=6, device=device, requires_grad=True)
    return model, wc.Simulator(model, 0.02), model.state()


def _loss(x):
    loss = wp.zeros(1, dtype=float, requires_grad=True)
    wp.launch(_height, x.shape[0], inputs=[x], outputs=[loss])
    return loss


def _forward(sim, state, states=None):
    """A taped rollout and its loss: (tape, loss, kept objects)."""
    tape = wp.Tape()
    with wp.ScopedDevice(sim.device), tape:
        if states is None:
            trajectory = wc.rollout(sim, state, steps=STEPS)
        else:
            trajectory = [state]
            for i in range(STEPS):
                sim.step(trajectory[-1], states[i])
                trajectory.append(states[i])
        loss = _loss(trajectory[-1].particle_x)
    return tape, loss, trajectory


def _per_step_graphs(model, sim, state, kept, keep: list) -> list:
    """The graphs of per_step_kept in the order a replay launches them: the zeroing of the gradients, each step,
    the loss and its backward pass, each step's backward pass from the last."""
    device = sim.device
    states = [state] + [model.empty_state(requires_grad=True) for _ in range(STEPS)]
    tapes, forward, backward = [], [], []
    for k in range(STEPS):
        tape = wp.Tape()
        with kept(), wp.ScopedCapture(device=device) as capture:
            with wp.ScopedDevice(device), tape:
                sim.step(states[k], states[k + 1])
        forward.append(capture.graph)
        with kept(), wp.ScopedCapture(device=device) as capture:
            tape.backward()
        backward.append(capture.graph)
        tapes.append(tape)
    loss_tape = wp.Tape()
    with kept(), wp.ScopedCapture(device=device) as capture:
        with wp.ScopedDevice(device), loss_tape:
            loss = _loss(states[-1].particle_x)
        seed = wp.ones_like(loss, requires_grad=False)
    loss_forward = capture.graph
    with kept(), wp.ScopedCapture(device=device) as capture:
        loss_tape.backward(grads={loss: seed})
    loss_backward = capture.graph
    with kept(), wp.ScopedCapture(device=device) as capture:
        for tape in [*tapes, loss_tape]:
            tape.zero()
    keep += [states, tapes, loss_tape, loss, seed]
    return [capture.graph, *forward, loss_forward, loss_backward, *reversed(backward)]


def run_variant(variant: str, device: str) -> str:
    model, sim, state = _problem(device)
    tape, loss, _ = _forward(sim, state)
    tape.backward(loss)
    expected = model.wind_velocity.grad.numpy().copy()
    tape.zero()
    keep = [tape, loss]
    no_gc = variant.endswith("no_gc")
    if no_gc:
        gc.disable()
    kept = contextlib.nullcontext
    if "kept" in variant:
        kept = functools.partial(arrays_kept, keep)
    elif variant.endswith("slab"):
        slab = Slab(device, SLAB_BYTES)

        @contextlib.contextmanager
        def kept():
            with arrays_kept(keep), slab.active():
                yield
    try:
        if variant.startswith("per_step"):
            graphs = _per_step_graphs(model, sim, state, kept, keep)
        elif variant.startswith("one_graph") or variant == "preallocated":
            states = [model.empty_state(requires_grad=True) for _ in range(STEPS)] if variant == "preallocated" \
                else None
            with kept(), wp.ScopedCapture(device=device) as capture:
                tape.zero()
                tape2, loss2, traj = _forward(sim, state, states)
                tape2.backward(loss2)
            graphs = [capture.graph]
            keep += [tape2, loss2, traj, states]
        else:
            with kept(), wp.ScopedCapture(device=device) as capture:
                tape2, loss2, traj = _forward(sim, state)
            forward = capture.graph
            with kept(), wp.ScopedCapture(device=device) as capture:
                tape2.backward(loss2)
            backward = capture.graph
            with kept(), wp.ScopedCapture(device=device) as capture:
                tape2.zero()
            graphs = [capture.graph, forward, backward]
            keep += [tape2, loss2, traj]
    finally:
        if no_gc:
            gc.enable()
    if variant.endswith("zero_after"):  # the zeroing (first) after the forward graphs, before any backward one
        forward_graphs = STEPS if variant.startswith("per_step") else 1
        graphs = [*graphs[1:forward_graphs + 1], graphs[0], *graphs[forward_graphs + 1:]]
    errors = []
    for _ in range(2):
        for graph in graphs:
            wp.capture_launch(graph)
        wp.synchronize_device(device)
        errors.append(float(np.abs(model.wind_velocity.grad.numpy() - expected).max()))
    return f"replays: gradient off by {errors[0]:.1e}, {errors[1]:.1e} (gradient scale {np.abs(expected).max():.1e})"


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda:0" if wp.is_cuda_available() else "cpu")
    p.add_argument("--variant", choices=VARIANTS)
    p.add_argument("--debug", action="store_true", help="Warp's debug mode: bounds-checked kernels (slow to compile)")
    args = p.parse_args()
    if args.debug:
        wp.config.mode = "debug"
    if args.variant:
        print(run_variant(args.variant, args.device), flush=True)
        return
    for variant in VARIANTS:
        proc = subprocess.run([sys.executable, __file__, "--device", args.device, "--variant", variant,
                               *(["--debug"] if args.debug else [])], capture_output=True, text=True, timeout=600)
        text = proc.stdout.strip().splitlines()[-1:] if proc.returncode == 0 else \
            [f"failed (rc {proc.returncode}): " + " | ".join(
                line for line in proc.stderr.strip().splitlines() if "CUDA driver" not in line)[-300:]]
        print(f"{variant:26s} {text[0] if text else '?'}", flush=True)


if __name__ == "__main__":
    main()
