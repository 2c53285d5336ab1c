"""The collision stage of a step: detect, project x̂ onto every contact so far, repeat; then v += (z − x̂)/dt. A failed
world retries keeping start gaps, then falls back on :mod:`warpcloth.collision.failsafe`. Method:
docs/concepts/contact.md; why the rounds run on the host: docs/decisions.md, "Collision rounds on the host"."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warpcloth.collision.contact import gather_nodes
from warpcloth.collision.detection import STRAINED, ContactDetector
from warpcloth.collision.diagnostics import rounds_error, strain_error, timed
from warpcloth.collision.failsafe import FailSafeReport, RigidImpactZones
from warpcloth.collision.projection import DeviceBackend
from warpcloth.collision.reference.backend import ZoneBackend
from warpcloth.errors import CollisionError, ContactCapacityError
from warpcloth.kernels.contact import WORLD_SKIPPED, contact_kernels
from warpcloth.kernels.projection import device_round_kernels, expect_found
from warpcloth.kernels.status import RECORD_SIZE
from warpcloth.model import Model, State
from warpcloth.tape import active_tape, capturing, record_adjoint


@dataclass
class CollisionReport:
    """What the collision stage did in one step (the return value of :meth:`CollisionStage.resolve`)."""

    solver: str
    """The projection backend that ran (``CollisionOptions.solver``)."""
    rounds: int = 0
    """Projections run (one per detection round that found contacts)."""
    contacts: int = 0
    """Contacts of the step (those the fail-safe was handed, where it ran)."""
    kept_start_gaps: str | None = None
    """Why the full-thickness try failed, where the second try (keeping start gaps) resolved the step; else None."""
    found: list[int] = field(default_factory=list)
    """Contacts each detection round found in the try that resolved the step (a captured step's plan)."""
    zones: list[dict] = field(default_factory=list)
    """The NumPy backend's per-zone records of its last round (the adjoint's too, after a backward pass)."""
    projections: list = field(default_factory=list)
    """The NumPy backend's (ProjectionResult, z) of each round; ``z.grad`` holds dL/dz after a backward pass."""
    device: dict | None = None
    """The device backend's last solve: MPRGP ``iterations`` and final ``violation`` [m]."""
    fail_safe: FailSafeReport | None = None
    """What the fail-safe did, where the projection gave up; else None."""
    start_gap_worlds: list[int] = field(default_factory=list)
    """The worlds whose step the second try resolved (keeping start gaps)."""
    fail_safe_worlds: list[int] = field(default_factory=list)
    """The worlds whose step the fail-safe resolved."""
    x_hat: wp.array | None = field(default=None, repr=False)
    """Positions before the stage."""
    z: wp.array | None = field(default=None, repr=False)
    """Positions after it."""

    def moved(self) -> np.ndarray:
        """Indices of the cloth particles whose positions the stage changed (reads the positions back)."""
        if self.z is None:
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(np.any(self.z.numpy() != self.x_hat.numpy(), axis=1))


class CollisionStage:
    """The contact detector, projection backends and round loop of one Simulator whose scene has collisions."""

    def __init__(self, model: Model, dt: float, options):
        settings = model.collision
        self.model = model
        self.dt = float(dt)
        self.options = options
        self.device = model.device
        self.thickness = float(settings.thickness)
        n = model.particle_count
        obstacles = settings.obstacles and model.obstacle_count > 0
        V = model.obstacle_vertex_count if obstacles else 0
        capacity = options.collision.contact_capacity or 16 * (n + V)
        self.detector = ContactDetector(model, thickness=self.thickness, capacity=capacity, obstacles=obstacles,
                                        self_collision=settings.self_collision,
                                        rebuild_bvh=options.collision.bvh == "rebuild")
        if obstacles:
            self.detector.check_start_outside(model)
        self.phase_seconds = dict.fromkeys(("detection", "geometry", "projection", "adjoint", "fail_safe"), 0.0)
        """Wall time [s] per phase, summed over steps and (``adjoint``) backward passes."""
        self.backends = {"device": DeviceBackend(model, self.detector, self.phase_seconds, n + V),
                         "numpy": ZoneBackend(model, self.detector, self.phase_seconds)}
        self.fail_safe = RigidImpactZones(model, self.detector)
        self.fail_safe_steps = 0
        """Steps resolved by the fail-safe over this stage's life."""
        self.start_gap_steps = 0
        """Steps resolved by the second try, which keeps start gaps, over this stage's life."""
        self.last: CollisionReport | None = None
        """The report of the last step."""
        self.speculative = False
        """Whether steps follow :attr:`plan` without reading the device (while ``wc.CapturedRollout`` captures)."""
        self.plan: list[int] = []
        """The contacts each round of a speculative step expects ([]: none), the step's last
        :attr:`CollisionReport.found`; other counts or a failed projection raise :attr:`mismatch`."""
        self.mismatch = wp.zeros(1, dtype=wp.int32, device=self.device)
        """The flag of a speculative step that did not keep to its plan (zeroed at the step's start)."""
        self._full_thickness = np.zeros(model.world_count, dtype=np.int32)  # every world's detection mode
        self.record = wp.zeros(RECORD_SIZE, dtype=wp.int32, device=self.device)
        """The failure record (kernels/status.py) the result's divergence guard latches into (the Simulator's)."""
        # every triangle's three edges and their rest lengths (material space): the projection-strain guard
        tris = model.triangles_np
        dm = np.linalg.inv(model.tri_inv_dm.numpy().astype(np.float64))  # columns: rest edges x1 - x0, x2 - x0
        self._edge_ends = np.concatenate([tris[:, [0, 1]], tris[:, [0, 2]], tris[:, [1, 2]]]).astype(np.int32)
        self._edge_rest = np.concatenate([np.linalg.norm(dm[:, :, 0], axis=1), np.linalg.norm(dm[:, :, 1], axis=1),
                                          np.linalg.norm(dm[:, :, 1] - dm[:, :, 0], axis=1)])
        self._edge_ends_device = wp.array(self._edge_ends, dtype=wp.int32, device=self.device)
        self._edge_rest_device = wp.array(self._edge_rest, dtype=wp.float64, device=self.device)
        # The node positions detection reads (untaped, the stage's own, reused by every step): the step's start, its
        # unprojected end (round 0, and the side of pairs touching at the start in every round) and a later round's
        # end. A round that finds contacts gathers its start and end again, taped, into arrays of the step's own
        # (the tape's contact geometry reads them in the backward pass); a round that finds none costs no taped
        # launch and no allocation.
        vec3 = model.types.vec3
        self._start, self._reference, self._end = (wp.zeros(n + V, dtype=vec3, device=self.device) for _ in range(3))

    @property
    def backward_seconds(self) -> float:
        """Wall time spent in the projection's adjoint (accumulates over backward passes)."""
        return self.phase_seconds["adjoint"]

    def resolve(self, state_in: State, x_hat: wp.array, v_hat: wp.array, obstacle_start: wp.array,
                obstacle_end: wp.array, state_out: State, step: int, mass: wp.array | Callable[[], wp.array],
                implicit_dt: float | None = None) -> CollisionReport:
        """Write the step's collision-free positions and velocities into ``state_out``; returns the report.
        ``obstacle_start``, ``obstacle_end``: obstacle vertices (empty without); ``mass``: the lumped masses (the
        adjoint adds to ``mass.grad``) or a function making them where needed; ``implicit_dt``: the implicit step's
        length where not ``dt`` (BDF2: 2/3 dt), x̂ = start + implicit_dt v̂ and v changes by (z − x̂) / implicit_dt."""
        model = self.model
        recording = active_tape() is not None and model.requires_grad
        opt = self.options.collision
        mass = functools.cache(mass if callable(mass) else (lambda masses=mass: masses))  # made once, if at all
        backend = self.backends[opt.solver]
        report = CollisionReport(solver=opt.solver, x_hat=x_hat)
        # the step's start nodes and its unprojected end (every try's round 0), for detection: one launch
        start = self._start
        wp.launch(contact_kernels(model.scalar).gather_two, start.shape[0], device=self.device,
                  inputs=[state_in.particle_x, obstacle_start, x_hat, obstacle_end, model.particle_count],
                  outputs=[start, self._reference], record_tape=False)
        if self.speculative:
            self.mismatch.zero_()
        if self.speculative and not self.plan:
            # a step being captured (wc.CapturedRollout) assumes no contact: detection runs without its read, x̂ is
            # kept, and the replay reads the check afterwards (mismatch), running the step again where it found
            # some
            self.detector.set_world_modes(self._full_thickness)
            self.detector.detect_on_device(start, self._reference, self._reference, expected=0)
            wp.launch(expect_found, 1, device=self.device, inputs=[self.detector.flags, 0, 0, self.mismatch],
                      record_tape=False)
            z = x_hat
        elif self.speculative:
            z = self._planned_rounds(report, state_in, start, x_hat, obstacle_start, obstacle_end, step, mass,
                                     recording)
        elif capturing(self.device):
            raise RuntimeError("a step with a collision stage reads the device, so it cannot be captured as it is; "
                               "wc.CapturedRollout captures such steps speculatively")
        else:
            z = self._tries(backend, report, state_in, start, x_hat, obstacle_start, obstacle_end, step, mass,
                            recording)
        kernels = contact_kernels(model.scalar)
        report.z = z
        inv_dt = model.scalar(1.0 / (self.dt if implicit_dt is None else implicit_dt))
        unmoved = z is x_hat and recording  # no contact in any world, on a tape
        wp.launch(kernels.apply_projection, model.particle_count, device=self.device,
                  inputs=[x_hat, v_hat, z, inv_dt, model.scalar(self.options.max_speed), step],
                  outputs=[state_out.particle_x, state_out.particle_v, self.record], record_tape=not unmoved)
        if unmoved:
            # No contact: the adjoint is that of z, a copy of x̂, projected by apply_projection (a world without
            # contacts among worlds with some passes dL/dz on to dL/dx̂ so: position_gradients), in one hand-written
            # kernel with the same arithmetic (kernels/contact.py unmoved_adjoint): no copy, no array for z.
            def adjoint():
                wp.launch(kernels.unmoved_adjoint, model.particle_count, device=self.device,
                          inputs=[state_out.particle_x.grad, state_out.particle_v.grad, inv_dt],
                          outputs=[x_hat.grad, v_hat.grad], record_tape=False)

            record_adjoint(adjoint, arrays=[state_out.particle_x, state_out.particle_v])
        self.last = report
        return report

    def check_adjoints(self) -> None:
        """Warn where a projection's adjoint replayed from a graph did not converge (one read)."""
        self.backends["device"].check_adjoints()

    def _planned_rounds(self, report: CollisionReport, state_in: State, start: wp.array, x_hat: wp.array,
                        obstacle_start: wp.array, obstacle_end: wp.array, step: int, mass: Callable[[], wp.array],
                        recording: bool) -> wp.array:
        """The device round loop of a captured step, sized by :attr:`plan`, with no read (checks: :attr:`mismatch`)."""
        model = self.model
        backend = self.backends["device"]
        taped_start = functools.cache(lambda: gather_nodes(model, state_in.particle_x, obstacle_start, True))
        self.detector.set_world_modes(self._full_thickness)
        backend.mismatch = self.mismatch
        try:
            backend.begin(x_hat, obstacle_end, mass, recording)
            z = self._rounds(backend, start, taped_start, x_hat, obstacle_end, step, report, recording,
                             plan=self.plan)
        finally:
            backend.mismatch = None
        report.contacts = backend.count
        report.device = backend.solver_stats
        return z

    def _tries(self, backend, report: CollisionReport, state_in: State, start: wp.array, x_hat: wp.array,
               obstacle_start: wp.array, obstacle_end: wp.array, step: int, mass: Callable[[], wp.array],
               recording: bool) -> wp.array:
        """Each world's tries (full thickness, keeping start gaps, the fail-safe), filling ``report``; returns z."""
        model, opt = self.model, self.options.collision
        # the step's start nodes taped, made at the first round that finds contacts (shared by the step's tries)
        taped_start = functools.cache(lambda: gather_nodes(model, state_in.particle_x, obstacle_start, True))
        # Each world's way through the step: the full thickness; where that fails, the second try keeping start
        # gaps; where that fails too, the fail-safe. A failure names its worlds, so only they move on: the others
        # redo their tries unchanged (worlds never interact), and each world ends as it would alone.
        W = model.world_count
        tries = np.zeros(W, dtype=np.int32)  # 0 full thickness, 1 keeping start gaps, 2 left to the fail-safe
        reasons: list[list[str]] = [[] for _ in range(W)]
        fail_safe_rows = []  # the contacts of the worlds left to the fail-safe, as their last try found them
        z = x_hat
        while not np.all(tries == 2):
            self.detector.set_world_modes(np.where(tries == 2, WORLD_SKIPPED, tries))
            backend.begin(x_hat, obstacle_end, mass, recording)
            report.rounds = 0
            try:
                z = self._rounds(backend, start, taped_start, x_hat, obstacle_end, step, report, recording)
                report.contacts = backend.count
                break
            except ContactCapacityError:
                raise
            except CollisionError as err:
                failed = [w for w in (range(W) if err.worlds is None else err.worlds) if tries[w] < 2]
                if not failed:  # a failure of worlds already left to the fail-safe cannot happen: they are skipped
                    raise
                rows = backend.contact_nodes()
                row_world = self.detector.node_world_host[rows[:, 0]] if len(rows) else np.zeros(0, dtype=np.int32)
                for w in failed:
                    reasons[w].append(str(err))
                    tries[w] = 2 if tries[w] == 1 or opt.rounds == 0 else 1  # no projection at all: the fail-safe
                    if tries[w] == 2:
                        fail_safe_rows.append(rows[row_world == w])
        report.start_gap_worlds = np.flatnonzero(tries == 1).tolist()
        report.fail_safe_worlds = np.flatnonzero(tries == 2).tolist()
        if report.fail_safe_worlds:  # rigid impact zones, on those worlds alone, from the others' projected positions
            self.detector.set_world_modes(np.where(tries == 2, 0, WORLD_SKIPPED))
            rows = np.concatenate(fail_safe_rows)
            reason = " | ".join(_world_reason(model, w, reasons[w]) for w in report.fail_safe_worlds)
            with timed(self.phase_seconds, "fail_safe"):
                z, report.fail_safe = self.fail_safe.resolve(state_in.particle_x, z, obstacle_start, obstacle_end,
                                                             mass(), rows, recording, reason, step)
            report.contacts += len(rows)
            self.fail_safe_steps += 1
        if report.start_gap_worlds:
            report.kept_start_gaps = " | ".join(_world_reason(model, w, reasons[w][:1])
                                                for w in report.start_gap_worlds)
            self.start_gap_steps += 1
        if isinstance(backend, ZoneBackend):
            report.zones, report.projections = backend.zones, backend.projections
        else:
            report.device = backend.solver_stats
        return z

    def _rounds(self, backend, start: wp.array, taped_start: Callable[[], wp.array], x_hat: wp.array,
                obstacle_end: wp.array, step: int, report: CollisionReport, recording: bool,
                plan: list[int] | None = None) -> wp.array:
        """Detect, add, project x̂ until detection finds nothing new; returns z. ``taped_start`` makes ``start`` taped;
        ``plan``: each round's count, expected without a read."""
        opt = self.options.collision
        phases = self.phase_seconds
        z = x_hat
        reference = self._reference  # the unprojected end: the side of pairs touching at the start
        report.found = []
        for round_index in range(opt.rounds + 1):
            with timed(phases, "detection"):
                if round_index == 0:
                    end = reference  # gathered with the start (resolve)
                else:
                    end = gather_nodes(self.model, z, obstacle_end, recording, out=self._end)
                if plan is None:
                    found = backend.detect(start, end, reference)
                else:
                    last = round_index >= len(plan)
                    found = backend.detect(start, end, reference, expected=0 if last else plan[round_index],
                                           last=last)
            if found == 0:
                break
            report.found.append(found)
            if opt.rounds == 0:
                raise CollisionError(f"step {step}: CollisionOptions.rounds is 0: no projection, {found} contacts",
                                     worlds=backend.found_worlds())
            if round_index == opt.rounds:
                raise rounds_error(step, opt.rounds, found, backend.count + found, *backend.first_found(), start,
                                   self.thickness, backend.found_worlds())
            with timed(phases, "geometry"):
                if recording:  # the contacts' geometry is taped: its positions, the step's own
                    backend.add_found(taped_start(), gather_nodes(self.model, z, obstacle_end, True), step)
                else:
                    backend.add_found(start, end, step)
            with timed(phases, "projection"):
                z = backend.project(step, opt)
                self._test_strain(x_hat, z)
            report.rounds = round_index + 1
        if plan is None and backend.count and self.detector.last_flags[STRAINED]:  # as the last read saw it
            self._strain_error(x_hat, z, step)
        return z

    def _test_strain(self, x_hat: wp.array, z: wp.array) -> None:
        """Raise the detector's STRAINED flag where z stretches an edge past ``max_projection_strain``."""
        limit = self.options.collision.max_projection_strain
        self.detector.strained.zero_()
        wp.launch(device_round_kernels(self.model.scalar).largest_strain, len(self._edge_rest), device=self.device,
                  inputs=[x_hat, z, self._edge_ends_device, self._edge_rest_device, wp.float64(limit)],
                  outputs=[self.detector.strained], record_tape=False)

    def _strain_error(self, x_hat: wp.array, z: wp.array, step: int) -> None:
        limit = self.options.collision.max_projection_strain
        error = strain_error(step, x_hat.numpy().astype(np.float64), z.numpy().astype(np.float64),
                             self._edge_ends, self._edge_rest, limit, self.detector.node_world_host)
        if error is not None:
            raise error


def _world_reason(model: Model, world: int, reasons: list[str]) -> str:
    """Why a world's tries failed, in one line ("; keeping start gaps: " between its first and second try)."""
    text = "; keeping start gaps: ".join(reasons)
    return text if model.world_count == 1 else f"world {world}: {text}"
