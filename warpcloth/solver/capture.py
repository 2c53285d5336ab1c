"""A rollout recorded once as a graph and replayed: a CUDA graph on the GPU, Warp's API capture on the CPU.

Replaying a graph skips Python and the launch overhead of every kernel (on CUDA 17.8 us a launch against a few us
a graph node; on the CPU 25 us against 0.25 us for a small kernel, issue #37), and on CUDA the CG loop runs as a
conditional node, so the host never waits for the device inside a rollout. With a loss, the graph holds the
forward pass, the loss and the whole backward pass, as Newton's differentiable-simulation examples capture them.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import warp as wp

from warpcloth.model import State
from warpcloth.solver.rollout import ControlSchedule, check_schedule, rollout
from warpcloth.solver.simulator import Simulator, model_arrays


class CapturedRollout:
    """``steps`` steps from ``state`` recorded as one graph; :meth:`run` replays it.

    Args:
        sim: the Simulator (a scene without a collision stage or proximity forces: those still read the device
            inside a step, so they cannot be captured yet).
        state: the initial State. Its arrays are the graph's input: assign new values into them (``assign``,
            ``wp.copy``) between replays; rebinding them has no effect on the graph.
        control: as for :func:`~warpcloth.rollout` (one Control, one per step, or a function of the step index);
            its arrays, the model's and ``state``'s are read in place at every replay.
        steps: number of steps.
        loss: optional ``loss(trajectory) -> wp.array`` that launches kernels on the trajectory. With it, each
            replay also runs the backward pass (of the sum of the loss array's entries, e.g. one loss per world):
            gradients land in the ``.grad`` of the model's, the control's and ``state``'s arrays (zeroed at the
            start of each replay), and :attr:`loss` holds the value.

    The first run is an ordinary one (it loads the kernels and makes the arrays the step keeps), then the same
    rollout is captured (on the CPU with its backward pass as a graph of its own); each :meth:`run` replays it and
    then reads the failure record once (:meth:`Simulator.check`), so a diverged particle or failed solve still
    raises, naming its step. Results are the uncaptured rollout's: bitwise on the CPU (the same kernels in the same
    order); on CUDA to rounding, as any two runs there (the assembly adds blocks with atomics).
    """

    def __init__(self, sim: Simulator, state: State, control: ControlSchedule = None, *, steps: int,
                 loss: Callable[[list[State]], wp.array] | None = None):
        if int(steps) != steps or steps < 1:
            raise ValueError(f"steps must be a positive integer, got {steps!r}")
        check_schedule(control, steps)
        reason = self.unsupported(sim)
        if reason is not None:
            raise ValueError(f"CapturedRollout: {reason}; use wc.rollout")
        if loss is not None and not sim.model.requires_grad:
            raise ValueError("CapturedRollout: a loss needs a model finalized with requires_grad=True")
        self.sim, self.state, self.control, self.steps, self._loss_fn = sim, state, control, int(steps), loss
        # what the graph baked in: the options (kernel arguments) and the model's arrays (pointers)
        self._captured_with = (sim.options, model_arrays(sim.model))
        self.trajectory: list[State] = []
        """The states of the last replay, ``[state, s1, ..., s_steps]`` (the same arrays at every replay; new ones at
        every run where the rollout is not captured, on CUDA with a loss)."""
        self.loss: wp.array | None = None
        """The loss array the graph writes (None without a loss)."""
        self.tape: wp.Tape | None = None
        self._record_forward()  # an ordinary run: loads modules, builds the solver's lazily made buffers
        warmup = self.tape
        if warmup is not None:
            self._backward()
            warmup.zero()
        device = sim.device
        self.graphs: list = []
        """The graphs a replay launches in turn (empty where the rollout is not captured: see below)."""
        if device.is_cuda and warmup is not None:
            # On an H200 (Warp 1.19) a graph holding the taped forward pass and its backward pass failed to
            # instantiate ("invalid argument"), and as separate graphs the backward one crashed on replay
            # (benchmarks/results/gpu/): until that is understood, such a rollout is run, not replayed.
            warnings.warn("CapturedRollout: a rollout with a loss is not captured on CUDA yet (its graph did not "
                          "instantiate with Warp 1.19); each run() records and differentiates it afresh",
                          RuntimeWarning, stacklevel=2)
        elif warmup is None:  # the forward pass alone: one graph
            with wp.ScopedCapture(device=device) as capture:
                self._record_forward()
            self.graphs = [capture.graph]
        else:
            # On the CPU (Warp 1.19) a graph holding both a recorded forward pass and the element adjoints'
            # launches crashed on replay; the forward pass, the backward pass and the zeroing of the gradients as
            # three graphs replay correctly.
            with wp.ScopedCapture(device=device) as capture:
                self._record_forward()
            forward = capture.graph
            with wp.ScopedCapture(device=device) as capture:
                self._backward()
            backward = capture.graph
            with wp.ScopedCapture(device=device) as capture:
                self.tape.zero()
            self.graphs = [capture.graph, forward, backward]

    @staticmethod
    def unsupported(sim: Simulator) -> str | None:
        """Why ``sim``'s steps cannot be captured, or None if they can."""
        if sim.collision is not None or sim.proximity is not None:
            return ("this scene has a collision stage or proximity forces, which still read the device inside a "
                    "step and cannot be captured yet")
        if sim.linear_solver.backend == "warp" and sim.device.is_cpu:
            return ("the warp CG backend tests its convergence on the host on the CPU; use cg_backend 'sequential' "
                    "or 'tiled' there")
        return None

    def _record_forward(self) -> None:
        sim = self.sim
        if self._loss_fn is None:
            self.trajectory = rollout(sim, self.state, self.control, steps=self.steps)
            return
        self.tape = wp.Tape()
        with wp.ScopedDevice(sim.device), self.tape:
            self.trajectory = rollout(sim, self.state, self.control, steps=self.steps)
            self.loss = self._loss_fn(self.trajectory)
            self._seed = wp.ones_like(self.loss, requires_grad=False)

    def _backward(self) -> None:
        """The recording tape's backward pass of the loss's sum (its seed: ones, made in the loss's recording)."""
        self.tape.backward(grads={self.loss: self._seed})

    def run(self) -> list[State]:
        """Replay the rollout (and, with a loss, the backward pass); returns the trajectory. Raises ValueError where
        the Simulator's options were replaced or an array of the model rebound since the capture: the graph would
        still use the old ones (change values in place, or capture again)."""
        options, arrays = self._captured_with
        if self.sim.options is not options:
            raise ValueError("CapturedRollout.run: the Simulator's options changed since the capture, and the graph "
                             "holds the old ones; make a new CapturedRollout")
        if model_arrays(self.sim.model) != arrays:
            raise ValueError("CapturedRollout.run: an array of the model was rebound since the capture, and the "
                             "graph reads the old one; assign values in place instead, or make a new "
                             "CapturedRollout")
        if not self.graphs:  # not captured (CUDA with a loss): the ordinary forward and backward passes
            self.tape.zero()
            self._record_forward()
            self._backward()
            self.sim.check()  # the adjoint solves' failures
        for graph in self.graphs:
            wp.capture_launch(graph)
        if self.graphs:
            self.sim._count_replayed(self.steps)  # noqa: SLF001 - the solver package's own bookkeeping
        self.sim.check(self.trajectory)
        return self.trajectory
