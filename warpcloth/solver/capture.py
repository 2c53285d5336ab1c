"""A rollout recorded once as graphs and replayed. Why: docs/decisions.md, "Rollouts replayed as graphs"."""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable

import warp as wp

from warpcloth.model import State
from warpcloth.solver.rollout import ControlSchedule, check_schedule, control_at, rollout
from warpcloth.solver.simulator import Simulator, model_arrays
from warpcloth.tape import (
    Arena,
    Tally,
    allocating_from,
    arrays_kept,
    gradient_owners,
    memory_ops_as_kernels,
    paused_gc,
    zero_gradients,
)


class CapturedRollout:
    """``steps`` steps from ``state`` recorded as graphs; :meth:`run` replays them.

    Construction runs the rollout once, then captures it; results are the uncaptured rollout's (bitwise on the CPU).
    A scene with contact is captured a step at a time, each following its last uncaptured run's contacts; a step
    that leaves that plan runs again uncaptured (:attr:`rerun_steps`). On CUDA a loss's rollout runs uncaptured.

    Args:
        state: the initial State, whose arrays the graph reads: assign new values into them between replays.
        control: as for :func:`~warpcloth.rollout`; its arrays, like the model's, are read in place at every replay.
        loss: optional ``loss(trajectory) -> wp.array`` launching kernels on the trajectory; each replay then
            back-propagates the sum of its entries into the zeroed ``.grad`` of the arrays it depends on.
        segment_steps: with a loss, back-propagate in segments of this many steps, as
            :func:`~warpcloth.checkpointed_backward` does: one segment's taped arrays are held (:attr:`taped_bytes`)
            for one more forward pass, bitwise the same gradients. CPU only.

    Raises:
        ValueError: ``steps`` or ``segment_steps`` not a positive integer, a loss on a model finalized without
            ``requires_grad``, or steps that cannot be captured (:meth:`unsupported`, :meth:`segments_unsupported`)."""

    def __init__(self, sim: Simulator, state: State, control: ControlSchedule = None, *, steps: int,
                 loss: Callable[[list[State]], wp.array] | None = None, segment_steps: int | None = None):
        if int(steps) != steps or steps < 1:
            raise ValueError(f"steps must be a positive integer, got {steps!r}")
        check_schedule(control, steps)
        reason = self.unsupported(sim)
        if reason is not None:
            raise ValueError(f"CapturedRollout: {reason}; use wc.rollout")
        if loss is not None and not sim.model.requires_grad:
            raise ValueError("CapturedRollout: a loss needs a model finalized with requires_grad=True")
        segment = _segment(sim, steps, loss, segment_steps)
        self.sim, self.state, self.control, self.steps, self._loss_fn = sim, state, control, int(steps), loss
        # what the graph baked in: the options (kernel arguments) and the model's arrays (pointers)
        self._captured_with = (sim.options, model_arrays(sim.model))
        self.trajectory: list[State] = []
        """The states of the last replay, ``[state, s1, ..., s_steps]`` (the same arrays at every replay)."""
        self.loss: wp.array | None = None
        """The loss array the graph writes (None without a loss)."""
        self.tape: wp.Tape | None = None
        self.rerun_steps: list[int] = []
        """The steps (0-based) of the last run that ran uncaptured (scenes with contact only)."""
        self.graphs: list = []
        """The graphs a replay launches in turn (empty where the rollout is captured a step at a time, or not)."""
        self._steps = None
        self._kept: list[wp.array] = []  # the arrays made during the captures (tape.py arrays_kept says why)
        self._tally = Tally(sim.device) if sim.device.is_cpu else None  # their bytes (taped_bytes)
        if segment is not None or _stepwise(sim) and not (sim.device.is_cuda and loss is not None):
            self._steps = _StepGraphs(sim, state, control, self.steps, loss, segment)
            self.trajectory = self._steps.states
            return
        self._record_forward()  # an ordinary run: loads modules, builds the solver's lazily made buffers
        warmup = self.tape
        if warmup is not None:
            self._backward()
            warmup.zero()
        device = sim.device
        if device.is_cuda and warmup is not None:
            # run, not replayed: docs/decisions.md, "Loss rollouts not captured on CUDA"
            warnings.warn("CapturedRollout: a rollout with a loss is not captured on CUDA yet (its graph did not "
                          "instantiate with Warp 1.19); each run() records and differentiates it afresh",
                          RuntimeWarning, stacklevel=2)
        elif warmup is None:  # the forward pass alone: one graph
            with _capture(device, self._kept, self._tally) as capture:
                self._record_forward()
            self.graphs = [capture.graph]
        else:
            # three graphs, so that a run without its backward pass, and a backward pass from other seeds
            # (backward()), replay only their parts; the gradients are zeroed after the forward pass, whose graph
            # (on CUDA) owns the memory of the arrays it makes
            with _capture(device, self._kept, self._tally) as capture:
                self._record_forward()
            forward = capture.graph
            with _capture(device, self._kept, self._tally) as capture:
                self._backward()
            backward = capture.graph
            with _capture(device, self._kept, self._tally) as capture:
                self.tape.zero()
            self.graphs = [forward, capture.graph, backward]

    @staticmethod
    def unsupported(sim: Simulator) -> str | None:
        """Why ``sim``'s steps cannot be captured, or None if they can."""
        if sim.linear_solver.backend == "warp" and sim.device.is_cpu:
            return ("the warp CG backend tests its convergence on the host on the CPU; use cg_backend 'sequential' "
                    "or 'tiled' there")
        return None

    @staticmethod
    def segments_unsupported(sim: Simulator) -> str | None:
        """Why ``sim``'s rollouts with a loss cannot be captured in segments (``segment_steps``), or None."""
        if not sim.device.is_cpu:
            return (f"segment_steps on {sim.device}: a rollout's backward pass is captured on the CPU only; use "
                    "wc.checkpointed_backward there")
        if sim.options.integrator == "bdf2" and sim.collision is not None:
            return ("segment_steps with the BDF2 integrator in a scene with a collision stage (a step after a "
                    "collision response hands the next one BDF2 history arrays of its own); use "
                    "wc.checkpointed_backward")
        return CapturedRollout.unsupported(sim)

    @property
    def taped_bytes(self) -> int | None:
        """Bytes of the arrays the graphs hold (with ``segment_steps``, one segment's); None on CUDA."""
        if self._steps is not None:
            return self._steps.taped_bytes
        return None if self._tally is None else self._tally.nbytes

    @property
    def pair_budgets(self) -> list[int]:
        """Each step's budget of proximity pairs in its graph (0: no pair kernel runs); empty without contact."""
        return [] if self._steps is None else list(self._steps.pair_budget)

    @property
    def flag_reads(self) -> int:
        """How often the last run read whether its replayed steps kept to their contact plans; 0 without contact."""
        return 0 if self._steps is None else self._steps.flag_reads

    @property
    def contact_plans(self) -> list[list[int]]:
        """Each step's contact plan: the contacts each detection round is to find; empty without contact."""
        return [] if self._steps is None else [list(p) for p in self._steps.plans]

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
        self.tape.backward(grads={self.loss: self._seed})

    def current(self) -> bool:
        """Whether the graphs still hold the Simulator's options and the model's arrays (else :meth:`run` raises)."""
        options, arrays = self._captured_with
        return self.sim.options is options and model_arrays(self.sim.model) == arrays

    def run(self, *, backward: bool = True) -> list[State]:
        """Replay the rollout (and, with a loss and ``backward``, the backward pass); returns the trajectory.

        Raises:
            ValueError: the Simulator's options were replaced or a model array rebound since the capture.
            SimulationError: a step diverged or (``on_cg_failure="raise"``) a solve failed."""
        self._check_current("run")
        taped = self._loss_fn is not None
        if self._steps is not None:  # one speculative graph a step
            self.rerun_steps = self._steps.run(backward=backward)
            self.loss = self._steps.loss
        elif not self.graphs:  # not captured (CUDA with a loss): the ordinary forward and backward passes
            self.tape.zero()
            self._record_forward()
            if backward:
                self._backward()
                self.sim.check()  # the adjoint solves' failures
        else:
            for graph in self.graphs[:2] if taped and not backward else self.graphs:  # zeroed either way
                wp.capture_launch(graph)
            self.sim._count_replayed(self.steps)  # noqa: SLF001 - the solver package's own bookkeeping
        self.sim.check(self.trajectory)
        return self.trajectory

    def backward(self, grads: dict) -> None:
        """The last run's backward pass again, all gradients zeroed first, from ``grads``: the loss, or an array the
        loss function made, to its gradient's values (the loss's zero unless given). Rows of a Jacobian, for one."""
        self._check_current("backward")
        if self._loss_fn is None or self.loss is None:
            raise ValueError("CapturedRollout.backward needs a loss and a run before it")
        if self._steps is not None:
            self._steps.backward(grads)
        else:
            if self.graphs:
                wp.capture_launch(self.graphs[1])  # the zeroing
            else:
                self.tape.zero()
            _write_seeds(self._seed, self.loss, grads)
            if self.graphs:
                wp.capture_launch(self.graphs[2])
            else:
                self._backward()
        self.sim.check()

    def _check_current(self, name: str) -> None:
        options, arrays = self._captured_with
        if self.sim.options is not options:
            raise ValueError(f"CapturedRollout.{name}: the Simulator's options changed since the capture, and the "
                             "graph holds the old ones; make a new CapturedRollout")
        if model_arrays(self.sim.model) != arrays:
            raise ValueError(f"CapturedRollout.{name}: an array of the model was rebound since the capture, and the "
                             "graph reads the old one; assign values in place instead, or make a new "
                             "CapturedRollout")


def _write_seeds(seed: wp.array, loss: wp.array, grads: dict) -> None:
    """``seed`` (copied into the loss's gradient) from ``grads[loss]`` or zero; other arrays' gradients from theirs."""
    seed.zero_()
    for array, values in grads.items():
        target = seed if array is loss else array.grad
        if target is None:
            raise ValueError("CapturedRollout.backward: an array of grads has no gradient (requires_grad=False)")
        target.assign(values)


@contextlib.contextmanager
def _capture(device, kept: list, arena: Arena | Tally | None = None, *, rewind: bool = True):
    """A graph capture on ``device``; its new arrays go to ``kept`` and take their memory from ``arena``, if given."""
    with allocating_from(arena, rewind=rewind), memory_ops_as_kernels(device), arrays_kept(kept), \
            wp.ScopedCapture(device=device) as capture:
        yield capture


def _segment(sim: Simulator, steps: int, loss, segment_steps: int | None) -> int | None:
    """The steps per re-simulated segment of a CapturedRollout (None: the whole rollout's taped arrays kept)."""
    if segment_steps is None:
        return None
    if isinstance(segment_steps, bool) or int(segment_steps) != segment_steps or segment_steps < 1:
        raise ValueError(f"CapturedRollout: segment_steps must be a positive integer, got {segment_steps!r}")
    if loss is None:
        raise ValueError("CapturedRollout: segment_steps needs a loss (a rollout without one keeps no taped arrays)")
    if segment_steps >= steps:
        return None  # one segment: the whole rollout's taped arrays
    reason = CapturedRollout.segments_unsupported(sim)
    if reason is not None:
        raise ValueError(f"CapturedRollout: {reason}")
    return int(segment_steps)


def _stepwise(sim: Simulator) -> bool:
    return sim.collision is not None or sim.proximity is not None


def _handed_on(state: State) -> tuple:
    """The arrays of a step's input State that the step before chose (a graph reads those it was captured with)."""
    return state.particle_x_previous, state.particle_x_last, state.particle_v_last


NO_MISS = 2**31 - 1  # first_miss when no replayed step left its plan
MAX_MISSES = 2  # a step whose graph left its plan this many times runs uncaptured from then on


class _StepGraphs:
    """A contact scene's rollout as one graph per step, each following a plan of contacts and proximity pairs.
    Why: docs/decisions.md, "Contact rollouts captured a step at a time"."""

    def __init__(self, sim: Simulator, state: State, control: ControlSchedule, steps: int,
                 loss: Callable[[list[State]], wp.array] | None, segment: int | None = None):
        self.sim, self.loss_fn = sim, loss
        self.segment = segment  # steps per re-simulated segment; None: every step's taped arrays are kept
        # segment mode: one arena per place in a segment, shared by the steps at that place (tape.py Arena)
        self.arenas = None if segment is None else [Arena(sim.device) for _ in range(min(segment, steps))]
        self._live: int | None = None  # the segment whose taped arrays the arenas and re-run tapes hold now
        self._dropped: list = []  # the gradient owners of the re-run tapes dropped since the last zeroing
        self._handed = None  # a segment's end State's adjoint first guess, kept while the segment is re-simulated
        self.tally = Tally(sim.device) if sim.device.is_cpu else None  # the bytes the captures hold besides
        self.states = [state] + [sim.model.empty_state() for _ in range(steps)]
        self.controls = [control_at(control, k) for k in range(steps)]
        # the arrays made during each capture (tape.py arrays_kept says why), released with its graph
        self.kept: dict = {}
        self.motions: dict = {}  # the obstacles' motions the graphs read, one array a time
        self.reruns: dict[int, wp.Tape | None] = {}  # the last run's uncaptured steps (their tapes, with a loss)
        self.uncaptured: set[int] = set()  # the steps the next run runs uncaptured at once, without their graphs
        # (contacts a graph cannot follow, or a graph that left its plan MAX_MISSES times)
        self.pair_budget = [0] * steps  # each step's graph's budget of proximity pairs
        self.plans: list[list[int]] = [[] for _ in range(steps)]  # each step's graph's contact plan
        self.misses = [0] * steps  # how often each step's graph left its plan
        self.handed = [()] * steps  # what each graph read of its input State that the step before chose (_handed_on)
        self.first_miss = wp.full(1, NO_MISS, dtype=wp.int32, device=sim.device)  # _note_plan_miss's
        self.flag_reads = 0  # how often the last run read first_miss
        self.loss: wp.array | None = None
        taped = loss is not None
        self.tapes = [None] * steps  # what each graph's step recorded
        self.forward = [None] * steps  # each step's speculative graph
        self.backward_graphs = [None] * steps  # each step's recorded adjoint
        self.loss_graphs, self._zero = [], None
        with paused_gc(), sim._keeping_motions(self.motions):  # noqa: SLF001 - the solver package's own
            for k in range(steps):
                self.reruns[k] = self._rerun(k)
                self._note(k, set())
            self._forward_done()
            if taped:
                first = wp.Tape()
                with wp.ScopedDevice(sim.device), first:
                    self.loss = loss(self.states)
                first.backward(grads={self.loss: wp.ones_like(self.loss, requires_grad=False)})
                self._backward_steps()
                first.zero()
            for k in range(steps):
                self._capture_step(k)
            if taped:
                self._capture_loss()
                self._capture_zero()
                self._zero_reruns()
                wp.capture_launch(self._zero)
            self._check_arenas()

    def _note(self, k: int, changed: set) -> None:
        """After step k ran uncaptured: mark it ``changed`` (new plan, more pairs) or ``uncaptured`` (unplannable)."""
        sim = self.sim
        plan = sim._contact_plan()  # noqa: SLF001
        if plan is None or self.misses[k] >= MAX_MISSES:
            self.uncaptured.add(k)
            return
        pairs = sim._pairs_needed()  # noqa: SLF001
        if pairs > self.pair_budget[k]:
            self.pair_budget[k] = 1 << max(4, (2 * pairs - 1).bit_length())  # a power of two >= 2 pairs, >= 16
            changed.add(k)
        if plan != self.plans[k]:
            self.plans[k] = plan
            changed.add(k)

    def _capture_step(self, k: int) -> None:
        sim, device = self.sim, self.sim.device
        kept = self.kept[k] = []
        self.handed[k] = _handed_on(self.states[k])
        tape = self.tapes[k] = wp.Tape() if self.loss_fn is not None else None
        arena = self.tally if self.arenas is None else self.arenas[k % self.segment]
        self._live = None  # a capture may write scratch
        report = None if sim.collision is None else sim.collision.last
        speculating = sim._speculating(self.pair_budget[k], self.plans[k])  # noqa: SLF001
        with speculating, _capture(device, kept, arena) as capture:
            with tape if tape is not None else contextlib.nullcontext():
                sim.step(self.states[k], self.states[k + 1], self.controls[k])
            sim._note_plan_miss(k, self.first_miss)  # noqa: SLF001
        if sim.collision is not None:  # the last step run keeps its report; a captured one has not run
            sim.collision.last = report
        self.forward[k] = capture.graph
        if tape is not None:
            with _capture(device, kept, arena, rewind=False) as capture:
                tape.backward()
            self.backward_graphs[k] = capture.graph

    def _capture_loss(self) -> None:
        """Capture the loss and its backward pass (its seed: ones at every run; backward() writes others)."""
        sim, kept = self.sim, self.kept.setdefault("loss", [])
        self._loss_tape = wp.Tape()
        with _capture(sim.device, kept, self.tally) as capture:
            with wp.ScopedDevice(sim.device), self._loss_tape:
                self.loss = self.loss_fn(self.states)
            self._seed = wp.ones_like(self.loss, requires_grad=False)
        self.loss_graphs.append(capture.graph)
        with _capture(sim.device, kept, self.tally) as capture:
            self._loss_tape.backward(grads={self.loss: self._seed})
        self.loss_graphs.append(capture.graph)

    def _capture_zero(self) -> None:
        self.kept["zero"] = []
        with _capture(self.sim.device, self.kept["zero"], self.tally) as capture:
            for tape in [*self.tapes, self._loss_tape]:
                tape.zero()
        self._zero = capture.graph

    def run(self, backward: bool = True) -> list[int]:
        """One run (with a loss and ``backward``, the backward pass too); returns the steps that ran uncaptured."""
        sim = self.sim
        with paused_gc():
            self._zero_all()
            self.reruns = {}
            predicted, self.uncaptured = self.uncaptured, set()
            changed = set()
            self._forward(predicted, changed)
            sim._count_replayed(len(self.forward) - len(self.reruns))  # noqa: SLF001
            if self.loss_fn is not None:
                sim.check(self.states)  # a diverged forward pass raises before its backward pass runs
                wp.capture_launch(self.loss_graphs[0])  # the loss (its seed: ones)
                if backward:
                    self._backward()
                    sim._check_replayed_adjoints()  # noqa: SLF001
            if changed:  # the steps whose plans changed, captured again (this run's re-run tapes kept), and after
                # them those whose input they changed (_handed_on)
                with sim._keeping_motions(self.motions):  # noqa: SLF001
                    for k in range(min(changed), len(self.forward)):
                        if k not in self.uncaptured and (k in changed or not self._current(k)):
                            self._capture_step(k)
                if self.loss_fn is not None:
                    self._capture_zero()
                self._check_arenas()
        return sorted(self.reruns)

    def _forward(self, predicted: set, changed: set) -> None:
        """The graphs in turn, reading every ``sync_every`` steps for a step that left its plan; from it, uncaptured."""
        sim, steps = self.sim, len(self.forward)
        every = sim.options.sync_every or steps
        self.flag_reads = 0
        self.first_miss.fill_(NO_MISS)  # a run that raised may have left a step's miss unread
        k, unchecked = 0, 0  # the next step, the replayed steps since the last read
        while k < steps:
            if k not in predicted and self._current(k):
                wp.capture_launch(self.forward[k])
                k, unchecked = k + 1, unchecked + 1
                if k < steps and k not in predicted and self._current(k) and unchecked < every:
                    continue
                unchecked, missed = 0, self._first_miss()
                if missed is None:
                    continue
                self.misses[missed] += 1
                sim._discard_failures_from(self.states[missed].step + 1, self.states)  # noqa: SLF001
                k, every = missed, 1
            elif k not in predicted:  # the step before, run uncaptured, handed it other arrays than its graph reads
                self.misses[k] += 1
                changed.add(k)
            self.reruns[k] = self._rerun(k)
            self._note(k, changed)
            k += 1
        self._forward_done()

    def _current(self, k: int) -> bool:
        return all(a is b for a, b in zip(_handed_on(self.states[k]), self.handed[k], strict=True))

    def _first_miss(self) -> int | None:
        """The first step replayed since the last call that left its plan, or None (a read of the device)."""
        self.flag_reads += 1
        first = int(self.first_miss.numpy()[0])
        if first == NO_MISS:
            return None
        self.first_miss.fill_(NO_MISS)
        return first

    def backward(self, grads: dict) -> None:
        with paused_gc():
            self._zero_all()
            _write_seeds(self._seed, self.loss, grads)
            self._backward()
            self.sim._check_replayed_adjoints()  # noqa: SLF001

    def _zero_all(self) -> None:
        if self._zero is not None:
            self._zero_reruns()
            wp.capture_launch(self._zero)

    def _rerun(self, k: int, *, keep: bool = False) -> wp.Tape | None:
        """Step k uncaptured, on its own tape with a loss (dropped outside the last segment unless ``keep``)."""
        tape = wp.Tape() if self.loss_fn is not None else None
        with tape if tape is not None else contextlib.nullcontext():
            self.sim.step(self.states[k], self.states[k + 1], self.controls[k])
        if not keep and self.segment is not None and k // self.segment != self._last_segment:
            return None
        return tape

    @property
    def _last_segment(self) -> int:
        return (len(self.forward) - 1) // self.segment

    @property
    def taped_bytes(self) -> int | None:
        if self.tally is None:
            return None
        return self.tally.nbytes + sum(arena.nbytes for arena in self.arenas or ())

    def _forward_done(self) -> None:  # in segment mode the arenas hold the last segment's arrays
        if self.segment is not None:
            self._live = self._last_segment

    def _resimulate(self, first: int, last: int) -> None:
        """Steps ``first`` to ``last - 1`` again for their backward passes, keeping their end State's adjoint guess."""
        handed = self.states[last].solve_adjoint
        if handed is not None:
            if self._handed is None or self._handed.shape != handed.shape or self._handed.dtype != handed.dtype:
                self._handed = wp.empty_like(handed)
            wp.copy(self._handed, handed)
        for k in range(first, last):
            if k in self.reruns:
                self.reruns[k] = self._rerun(k, keep=True)
            else:
                wp.capture_launch(self.forward[k])
        if handed is not None:
            wp.copy(self.states[last].solve_adjoint, self._handed)
        self._live = first // self.segment

    def _check_arenas(self) -> None:
        """Raise RuntimeError where an array that outlives its step lies in an arena the steps share (a bug)."""
        if self.arenas is None:
            return
        for path, array in _persistent_arrays({"sim": self.sim, "states": self.states, "controls": self.controls}):
            for a in (array, array.grad):
                if a is not None and any(arena.owns(a.ptr) for arena in self.arenas):
                    raise RuntimeError(f"CapturedRollout: {path} was made during a step's capture in memory that "
                                       "the steps of the segments share (an internal error; please report it)")

    def _backward(self) -> None:
        wp.capture_launch(self.loss_graphs[1])
        self._backward_steps()

    def _backward_steps(self) -> None:
        """The steps' backward passes, last first (in segment mode a segment at a time, re-simulated first)."""
        steps = len(self.forward)
        seg = self.segment or steps
        for first in reversed(range(0, steps, seg)):
            last = min(first + seg, steps)
            if self.segment is not None and self._live != first // seg:
                self._resimulate(first, last)
            for k in reversed(range(first, last)):
                if k in self.reruns:
                    self.reruns[k].backward()
                else:
                    wp.capture_launch(self.backward_graphs[k])
            if self.segment is not None:
                for k in range(first, last):
                    if self.reruns.get(k) is not None:
                        self._dropped += gradient_owners(self.reruns[k])
                        self.reruns[k] = None
                self._live = None

    def _zero_reruns(self) -> None:
        """Zero the gradients the last run's re-run steps reached, dropped tapes' included."""
        for tape in self.reruns.values():
            if tape is not None:
                tape.zero()
        zero_gradients(self._dropped)
        self._dropped = []


def _persistent_arrays(root, path: str = "", seen: set | None = None):
    """(path, array) for every Warp array reachable from ``root`` through warpcloth's objects, but STEP_LOCAL ones."""
    seen = set() if seen is None else seen
    if id(root) in seen:
        return
    seen.add(id(root))
    if isinstance(root, wp.array):
        yield path, root
    elif type(root) is dict:  # not a subclass: one may read the device lazily (backends.py _SolverStats)
        for key, value in root.items():
            yield from _persistent_arrays(value, f"{path}[{key!r}]" if path else str(key), seen)
    elif type(root) in (list, tuple):
        for i, value in enumerate(root):
            yield from _persistent_arrays(value, f"{path}[{i}]", seen)
    elif type(root).__module__.startswith("warpcloth") and hasattr(root, "__dict__"):
        step_local = getattr(type(root), "STEP_LOCAL", frozenset())  # one step's arrays, not read by the next
        for name, value in vars(root).items():
            if name not in step_local:
                yield from _persistent_arrays(value, f"{path}.{name}", seen)
