"""The collision stage's two projection backends (``CollisionOptions.solver``), one round at a time.

The stage (warpcloth/collision/stage.py) runs the rounds: gather the nodes, ``detect``, ``add_found``, ``project``.
A backend owns its buffers and records its own adjoint on the tape:

* :class:`DeviceBackend` (``"device"``, the default): contacts, their geometry, the projection (MPRGP on the dual,
  kernels/projection.py) and its adjoint (CG on the active set) stay on the device; each round reads back the
  detector's flags (detection.py FOUND...) once after its projection: a degenerate normal, a failed solve (the
  solver's figures only then).
* :class:`ZoneBackend` (``"numpy"``): the contacts come to the host and the zone solver of
  :mod:`warpcloth.collision.projection` projects them, with the QR or dense KKT adjoint
  (``CollisionOptions.adjoint``); each round's result is kept for benchmarks (``CollisionReport.projections``).

Both solve the same problem to the same tolerance (the NumPy solver is the device kernels' test oracle).
"""

from __future__ import annotations

import time
import warnings
from contextlib import contextmanager

import numpy as np
import warp as wp

from warpcloth.collision import projection
from warpcloth.collision.detection import DEGENERATE, FAILED, ContactDetector, Contacts
from warpcloth.collision.device_projection import ADJOINT_WARN, DeviceProjection
from warpcloth.collision.linalg import small_blas
from warpcloth.errors import CollisionError
from warpcloth.kernels import projection as kp
from warpcloth.kernels.contact import contact_kernels
from warpcloth.kernels.projection import device_round_kernels
from warpcloth.model import Model
from warpcloth.tape import capturing, record_adjoint


@contextmanager
def timed(totals: dict, phase: str):
    """Add the wall time of the ``with`` block to ``totals[phase]``."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        totals[phase] += time.perf_counter() - t0


def gather_nodes(model: Model, cloth_x: wp.array, obstacle_x: wp.array, recording: bool,
                 out: wp.array | None = None) -> wp.array:
    """One array of every node's position: cloth particles first, then obstacle vertices (taped), in a new array,
    or, untaped, into ``out`` (a buffer the caller owns)."""
    n = model.particle_count
    taped = out is None
    if taped:
        out = wp.empty(n + obstacle_x.shape[0], dtype=model.types.vec3, device=model.device, requires_grad=recording)
    wp.launch(contact_kernels(model.scalar).gather_nodes, out.shape[0], device=model.device,
              inputs=[cloth_x, obstacle_x, n], outputs=[out], record_tape=taped)
    return out


def contact_geometry(model: Model, detector: ContactDetector, start: wp.array, end: wp.array, contacts: Contacts,
                     recording: bool, step: int) -> tuple[wp.array, wp.array, wp.array]:
    """Normals, weights and target gaps of host ``contacts`` at their time of impact, from the node positions they
    were found at (taped; kernels/contact.py geometry; each world's target as ``detector.world_mode`` says); raises
    CollisionError naming a contact whose normal is degenerate."""
    normal, weight, target = _geometry_arrays(model, len(contacts), recording)
    dev = model.device
    wp.launch(contact_kernels(model.scalar).geometry, len(contacts), device=dev,
              inputs=[start, end, wp.array(contacts.nodes, dtype=wp.int32, device=dev),
                      wp.array(contacts.mode, dtype=wp.int32, device=dev),
                      wp.array(contacts.t, dtype=wp.float64, device=dev),
                      wp.array(contacts.sign, dtype=wp.float64, device=dev), model.scalar(model.collision.thickness),
                      detector.world_mode, detector.node_world],
              outputs=[normal, weight, target])
    ok = np.all(np.isfinite(normal.numpy()), axis=1) & np.all(np.isfinite(weight.numpy()), axis=1)
    if not ok.all():
        raise _degenerate(step, contacts.nodes[int(np.flatnonzero(~ok)[0])], detector)
    return normal, weight, target


def _geometry_arrays(model: Model, count: int, recording: bool) -> tuple[wp.array, wp.array, wp.array]:
    """Empty (normal, weight, target) arrays for ``count`` contacts."""
    dev = model.device
    return (wp.empty(count, dtype=model.types.vec3, device=dev, requires_grad=recording),
            wp.empty(count, dtype=model.types.vec4, device=dev, requires_grad=recording),
            wp.empty(count, dtype=model.scalar, device=dev, requires_grad=recording))


def _degenerate(step: int, nodes: np.ndarray, detector: ContactDetector) -> CollisionError:
    world = int(detector.node_world_host[nodes[0]])
    return CollisionError(f"step {step}: a contact between nodes {nodes.tolist()} has a degenerate normal; a triangle "
                          "or edge of the cloth or of an obstacle collapsed", worlds=[world])


class ZoneBackend:
    """The NumPy zone solver, round by round (``CollisionOptions.solver="numpy"``).

    Args:
        model: the Model.
        detector: the stage's contact detector.
        timings: the stage's phase totals; the adjoint adds to ``"adjoint"``.
    """

    def __init__(self, model: Model, detector: ContactDetector, timings: dict):
        self.model = model
        self.detector = detector
        self.timings = timings
        self.begin(None, None, None, False)

    def begin(self, x_hat: wp.array | None, obstacle_end: wp.array | None, mass: wp.array | None,
              recording: bool) -> None:
        """Start a try at a step that projects ``x_hat`` (the obstacle at ``obstacle_end``; the particles' lumped
        masses ``mass()``, a function that makes them at its first call); each world's contacts and targets as the
        detector's ``world_mode`` says (the stage sets it)."""
        self._x_hat, self._obstacle_end, self._mass, self._recording = x_hat, obstacle_end, mass, recording
        self._contacts = Contacts.empty()  # every contact of the step so far
        self._geometry = []  # (normal, weight, target) of each round's new contacts, evaluated where found
        self._lam = np.zeros(0)  # the last round's multipliers: the next round starts from them
        self._found = Contacts.empty()
        self._fixed = self.model.particle_pin.numpy() >= 0  # read at each step: pins are the model's
        self.projections: list[tuple[projection.ProjectionResult, wp.array]] = []
        self.zones: list[dict] = []

    @property
    def count(self) -> int:
        """Contacts in the step's projection so far."""
        return len(self._contacts)

    def detect(self, start: wp.array, end: wp.array, reference: wp.array) -> int:
        """Detect the contacts between node positions ``start`` and ``end``; returns how many."""
        # Every contact found is new: a pair found again is violated again (the projection leaves resolved pairs
        # exactly at the thickness, which proximity detection does not count), and its new linearisation joins
        # the old one.
        self._found = self.detector.detect(start, end, reference)
        return len(self._found)

    def first_found(self) -> tuple[np.ndarray, int]:
        """(nodes, mode) of the first contact the last detection found (error messages)."""
        return self._found.nodes[0], int(self._found.mode[0])

    def found_worlds(self) -> list[int]:
        """The worlds of the contacts the last detection found."""
        return np.unique(self.detector.node_world_host[self._found.nodes[:, 0]]).tolist()

    def contact_nodes(self) -> np.ndarray:
        """The nodes (m, 4) of every contact the step found so far, the last detection's included."""
        return np.concatenate([self._contacts.nodes, self._found.nodes])

    def add_found(self, start: wp.array, end: wp.array, step: int) -> None:
        """Evaluate the geometry of the contacts just found and add them to the step's projection."""
        self._geometry.append(contact_geometry(self.model, self.detector, start, end, self._found, self._recording,
                                               step))
        self._contacts = Contacts.concatenate([self._contacts, self._found])
        self._found = Contacts.empty()

    def project(self, step: int, opt) -> wp.array:
        """Project x̂ onto every contact so far (the previous round's multipliers first) with the CollisionOptions
        ``opt``; record its adjoint."""
        x_hat, obstacle_end, mass, geometry = self._x_hat, self._obstacle_end, self._mass(), self._geometry
        normals, weights, targets = (np.concatenate([g[k].numpy() for g in geometry]).astype(np.float64)
                                     for k in range(3))
        unknowns = 3 * np.unique(self._contacts.nodes).size  # the zones' sizes add up to at most this
        try:
            with small_blas(unknowns):
                result = projection.project(
                    x_hat.numpy().astype(np.float64), mass.numpy().astype(np.float64), self._fixed,
                    obstacle_end.numpy().astype(np.float64).reshape(-1, 3), self._contacts.nodes.astype(np.int64),
                    weights, normals, targets, tol=opt.qp_tol,
                    lam_init=np.concatenate([self._lam, np.zeros(len(normals) - len(self._lam))]))
        except projection.ProjectionError as err:
            worlds = None if err.contact is None else \
                [int(self.detector.node_world_host[self._contacts.nodes[err.contact, 0]])]
            raise CollisionError(f"step {step}{_worlds(self.model, worlds)}: {err}", worlds=worlds) from err
        self._lam = result.lam
        self.zones = result.zones_stats()
        z = wp.array(result.z, dtype=self.model.types.vec3, device=self.model.device,
                     requires_grad=self._recording)
        self.projections.append((result, z))
        if self._recording:
            self._record_adjoint(result, z, list(geometry), opt.adjoint, unknowns)
        return z

    def _record_adjoint(self, result, z, geometry, mode, unknowns: int) -> None:
        x_hat, obstacle_end, mass = self._x_hat, self._obstacle_end, self._mass()
        sizes = np.cumsum([0] + [g[0].shape[0] for g in geometry])

        def adjoint():
            grad_z = z.grad.numpy().astype(np.float64)
            if not np.any(grad_z):  # a round whose z a later round or the fail-safe replaced
                return
            with timed(self.timings, "adjoint"), small_blas(unknowns):
                gx, gw, gn, gob, gt = projection.backward(result, grad_z, mode=mode)
            _accumulate(x_hat, gx)
            _accumulate(mass, projection.mass_gradient(result, gx))
            for (normal, weight, target), lo, hi in zip(geometry, sizes[:-1], sizes[1:]):
                _accumulate(normal, gn[lo:hi])
                _accumulate(weight, gw[lo:hi])
                _accumulate(target, gt[lo:hi])
            if obstacle_end.shape[0]:
                _accumulate(obstacle_end, gob)

        record_adjoint(adjoint, arrays=[z])


class DeviceBackend:
    """The device projection, round by round (``CollisionOptions.solver="device"``): the step's contacts in float64
    lists on the device (kept across steps, grown as needed), one MPRGP solve per round warm-started from the last.

    Args: as :class:`ZoneBackend`, and ``node_count``: cloth particles plus the obstacle vertices that collide.
    """

    def __init__(self, model: Model, detector: ContactDetector, timings: dict, node_count: int):
        self.model = model
        self.detector = detector
        self.timings = timings
        self.thickness = float(model.collision.thickness)
        self.cloth_count = model.particle_count
        self.node_count = node_count
        self._solver: DeviceProjection | None = None  # made on first use, grown as needed
        self._nodes = self._normals = self._weights = self._targets = None  # the step's contact lists (_grow)
        dev = model.device
        # Buffers of untaped steps and of the per-round checks, reused by every step: a taped step's constants and
        # positions are its own instead (its recorded adjoint reads them in the backward pass)
        self._untaped_constants = (wp.zeros(node_count, dtype=wp.vec3d, device=dev),
                                   wp.zeros(node_count, dtype=wp.int32, device=dev),
                                   wp.zeros(node_count, dtype=wp.float64, device=dev))
        self._untaped_z = wp.zeros(self.cloth_count, dtype=model.types.vec3, device=dev)
        self._untaped_geometry = _geometry_arrays(model, max(detector.capacity, 1), False)
        self._retired = []  # the solvers and contact lists that grown ones replaced: a captured step's graph may
        # still read them
        self.mismatch: wp.array | None = None
        """Set by the stage for a planned (captured) step: the flag that the step's checks raise where detection
        finds other counts than the plan's or a projection fails, instead of reading the device."""
        self.adjoint_residual = wp.zeros(1, dtype=wp.float64, device=dev)
        """The largest relative residual of the adjoint CGs recorded while a graph was captured (they cannot read
        theirs back); :meth:`check_adjoints` warns where it is too large."""
        self.begin(None, None, None, False)

    STEP_LOCAL = frozenset({"_x_hat", "_obstacle_end", "_mass", "_rounds", "_solution", "_constants", "solver_stats"})
    """The attributes that hold one step's arrays: set anew by :meth:`begin`, never read by a later step (a
    segmented wc.CapturedRollout lets other steps reuse their memory)."""

    def begin(self, x_hat: wp.array | None, obstacle_end: wp.array | None, mass: wp.array | None,
              recording: bool) -> None:
        """Start a try at a step (as :meth:`ZoneBackend.begin`)."""
        self._x_hat, self._obstacle_end, self._mass, self._recording = x_hat, obstacle_end, mass, recording
        self._total = 0  # contacts in the lists
        self._found = 0  # contacts the last detection found (in the detector's buffers)
        self._rounds = []  # (offset, count, normal, weight, target) of each round's contacts
        self._solution = None
        self._constants = None  # (positions, free, inverse masses) of the step, once it has contacts
        self.solver_stats: dict | None = None

    @property
    def count(self) -> int:
        return self._total

    def detect(self, start: wp.array, end: wp.array, reference: wp.array, expected: int | None = None,
               last: bool = False) -> int:
        """As :meth:`ZoneBackend.detect`; in a planned step (``expected``: the count the plan expects, ``last``: the
        detection that must find none after the step's projections) without a read: the check goes to
        :attr:`mismatch`, and the expected count is returned."""
        if expected is None:
            self._found = self.detector.detect_on_device(start, end, reference)
            return self._found
        self.detector.detect_on_device(start, end, reference, expected=expected)
        wp.launch(kp.expect_found, 1, device=self.model.device,
                  inputs=[self.detector.flags, int(expected), int(last and self._total > 0), self.mismatch],
                  record_tape=False)
        self._found = int(expected)
        return self._found

    def first_found(self) -> tuple[np.ndarray, int]:
        return self.detector.nodes.numpy()[0], int(self.detector.mode.numpy()[0])

    def found_worlds(self) -> list[int]:
        return np.unique(self.detector.node_world_host[self.detector.nodes.numpy()[:self._found, 0]]).tolist()

    def contact_nodes(self) -> np.ndarray:
        parts = [self._nodes.numpy()[:self._total]] if self._total else []
        parts.append(self.detector.nodes.numpy()[:self._found])
        return np.concatenate(parts)

    def add_found(self, start: wp.array, end: wp.array, step: int) -> None:
        model, dev = self.model, self.model.device
        kr = device_round_kernels(model.scalar)
        found, total, N = self._found, self._total, self.node_count
        if self._constants is None:  # x^ and the obstacle in float64, the masses: the step's constants
            if self._recording:
                positions = wp.empty(N, dtype=wp.vec3d, device=dev)
                free = wp.empty(N, dtype=wp.int32, device=dev)
                inv_mass = wp.empty(N, dtype=wp.float64, device=dev)
            else:
                positions, free, inv_mass = self._untaped_constants
            wp.launch(kr.positions64, N, device=dev, inputs=[self._x_hat, self._obstacle_end, self.cloth_count],
                      outputs=[positions], record_tape=False)
            wp.launch(kr.inverse_mass, N, device=dev, inputs=[self._mass(), model.particle_pin, self.cloth_count],
                      outputs=[free, inv_mass], record_tape=False)
            self._constants = (positions, free, inv_mass)
        self._grow(total + found)
        if self._recording:  # the round's own: the tape's geometry launch and the adjoint read them
            normal, weight, target = _geometry_arrays(model, found, True)
        else:  # read at once, into the step's float64 lists
            normal, weight, target = (a[:found] for a in self._untaped_geometry)
        det = self.detector
        found_arrays = [det.nodes[:found], det.mode[:found], det.t[:found], det.sign[:found]]
        if self._recording:  # the tape replays this launch after later detections reuse the buffers
            found_arrays = [wp.clone(a) for a in found_arrays]
        wp.launch(contact_kernels(model.scalar).geometry, found, device=dev,
                  inputs=[start, end, *found_arrays, model.scalar(self.thickness), det.world_mode, det.node_world],
                  outputs=[normal, weight, target])
        wp.copy(self._nodes, det.nodes, dest_offset=4 * total, count=4 * found)
        # the first degenerate contact, if any, lands in the detector's flags: project reads them once, after the
        # solve (a degenerate row makes the solve stop at once as unbounded), and raises for it first
        bad = det.degenerate
        bad.fill_(found + 1)
        wp.launch(kr.append_geometry, found, device=dev, inputs=[normal, weight, target, total],
                  outputs=[self._normals, self._weights, self._targets, bad], record_tape=False)
        self._rounds.append((total, found, normal, weight, target))
        self._total += found
        self._found = 0

    def project(self, step: int, opt) -> wp.array:
        model, dev = self.model, self.model.device
        total = self._total
        warm = self._rounds[-1][0]  # the contacts of earlier rounds, whose multipliers start the solve
        if self._solver is None:
            self._solver = DeviceProjection(dev, self.node_count, max(2 * total, 1024), self.detector.node_world,
                                            model.world_count)
        elif self._solver.capacity < total:  # grown in the step: its multipliers and positions go along
            self._retired.append(self._solver)
            self._solver = self._solver.grown(max(2 * total, 1024))
        positions, free, inv_mass = self._constants
        solution = self._solver.project(
            positions, free, inv_mass, self._nodes, self._weights, self._normals, total, self._targets,
            lam_init=None if self._solution is None else self._solver.lam, warm=warm,
            resume=self._solution is not None, tol=opt.qp_tol, keep=self._recording, failed=self.detector.failed)
        self._solution = solution
        self.solver_stats = _SolverStats(solution)
        found = self._rounds[-1][1]
        if self.mismatch is not None:  # a planned step: checked on the device, read after its replay
            wp.launch(kp.expect_solved, 1, device=dev, inputs=[self.detector.flags, found, self.mismatch],
                      record_tape=False)
            return self._positions(solution)
        # the round's one read: its degenerate contact, if any, and whether a world's solve failed
        flags = self.detector.read_flags()
        j = int(flags[DEGENERATE]) - 1
        if j < found:
            raise _degenerate(step, self.detector.nodes.numpy()[j], self.detector)
        if not flags[FAILED]:
            return self._positions(solution)
        failed = solution.failed_worlds()
        where = _worlds(model, failed)
        if solution.unbounded:
            raise CollisionError(
                f"step {step}{where}: no positions satisfy the {total} contacts of the device projection (its dual is "
                "unbounded): cloth squeezed between obstacles closer than twice the thickness, or contacts that "
                "contradict each other", worlds=failed or None)
        if not solution.converged:
            raise CollisionError(
                f"step {step}{where}: the device projection of {total} contacts did not converge in "
                f"{solution.iterations} iterations: a contact violated or an active one off by "
                f"{solution.residual:.3e} m > tol {opt.qp_tol:.1e} (contacts that contradict each other stall it)",
                worlds=failed or None)
        raise AssertionError("a failed solve with every world converged")  # the flag and the info disagree

    def _positions(self, solution) -> wp.array:
        """The cloth's positions of a solve that succeeded, in the model's precision (its adjoint recorded)."""
        model, dev = self.model, self.model.device
        # a taped round's z is its own (its gradient is this round's); an untaped one's is read before the next
        # round projects again (the next detection gathers it, or the stage writes it into the step's result)
        z = (wp.empty(self.cloth_count, dtype=model.types.vec3, device=dev, requires_grad=True) if self._recording
             else self._untaped_z)
        wp.launch(device_round_kernels(model.scalar).cloth_positions, self.cloth_count, device=dev,
                  inputs=[solution.z], outputs=[z], record_tape=False)
        if self._recording:
            self._record_adjoint(solution, z)
        return z

    def _grow(self, count: int) -> None:
        """The float64 contact lists, at least ``count`` long (this step's earlier rounds kept)."""
        have = 0 if self._nodes is None else self._nodes.shape[0]
        if have >= count:
            return
        size = max(2 * count, 1024)
        dev = self.model.device
        lists = (wp.zeros((size, 4), dtype=wp.int32, device=dev), wp.zeros(size, dtype=wp.vec3d, device=dev),
                 wp.zeros(size, dtype=wp.vec4d, device=dev), wp.zeros(size, dtype=wp.float64, device=dev))
        if have:
            for new, old in zip(lists, (self._nodes, self._normals, self._weights, self._targets)):
                wp.copy(new, old)
            self._retired.append((self._nodes, self._normals, self._weights, self._targets))
        self._nodes, self._normals, self._weights, self._targets = lists

    def _record_adjoint(self, solution, z) -> None:
        """Record the projection's adjoint (kernels only): dL/dz -> x^, the contacts' normals and weights, the
        obstacle vertices and the masses."""
        model, dev = self.model, self.model.device
        kr = device_round_kernels(model.scalar)
        n, N = self.cloth_count, self.node_count
        x_hat, obstacle_end, mass = self._x_hat, self._obstacle_end, self._mass()
        positions, free, inv_mass = self._constants
        rounds = list(self._rounds)
        count = solution.rows.count
        m = max(count, 1)  # the contacts in the step's order (the solution's rows are sorted by world)
        nodes, normals, weights = (wp.clone(a[:m]) for a in (self._nodes, self._normals, self._weights))
        solver = self._solver

        def adjoint():
            with timed(self.timings, "adjoint"):
                # the solver's work arrays (the adjoints of a backward pass run one at a time), at the sizes the
                # kernels were given when these were arrays of their own
                work, m = solver.adjoint_work, max(count, 1)
                d_z, d_z_in, grad_const = work.d_z, work.d_z_in, work.grad_const
                grad_w, grad_n, grad_target = work.grad_w[:m], work.grad_n[:m], work.grad_target[:m]
                wp.launch(kr.scaled_gradient, N, device=dev, inputs=[z.grad, inv_mass, n], outputs=[d_z])
                wp.copy(d_z_in, d_z)
                d_lam = solver.adjoint_on_device(solution, d_z, worst=self.adjoint_residual if capturing(dev) else None)
                grad_const.zero_()
                wp.launch(kr.push_contacts, count, device=dev,
                          inputs=[nodes, weights, normals, free, solution.z, d_z, solution.lam, d_lam],
                          outputs=[grad_w, grad_n, grad_const, grad_target])
                obstacle_grad = obstacle_end.grad if obstacle_end.grad is not None else work.sink(
                    max(N - n, 1), model.types.vec3, dev)
                mass_grad = mass.grad if mass.grad is not None else work.sink(n, model.scalar, dev)
                wp.launch(kr.position_gradients, N, device=dev,
                          inputs=[z.grad, d_z, d_z_in, inv_mass, grad_const, solution.z, positions, n],
                          outputs=[x_hat.grad, obstacle_grad, mass_grad])
                for offset, found, normal, weight, target in rounds:
                    if normal.grad is not None:
                        wp.launch(kr.geometry_gradients, found, device=dev,
                                  inputs=[grad_n, grad_w, grad_target, offset],
                                  outputs=[normal.grad, weight.grad, target.grad])

        record_adjoint(adjoint, arrays=[z])

    def check_adjoints(self) -> None:
        """Warn where an adjoint CG of a backward pass replayed from a graph stopped above ADJOINT_WARN (one read,
        after the pass), and start the record again."""
        residual = float(self.adjoint_residual.numpy()[0])
        if not residual <= ADJOINT_WARN:
            warnings.warn(f"the device projection's adjoint CG of a replayed step stopped at relative residual "
                          f"{residual:.2e}: its gradient is that inexact", RuntimeWarning, stacklevel=3)
        self.adjoint_residual.zero_()


class _SolverStats(dict):
    """The device backend's ``solver_stats`` (``iterations``, ``violation``), read from the solve's info when first
    looked at (diagnostics: no step reads them; an untaped step's solution shares the solver's buffer, so read them
    before the next step)."""

    def __init__(self, solution):
        super().__init__()
        self._solution = solution

    def _fill(self) -> None:
        if self._solution is not None:
            solution, self._solution = self._solution, None
            self.update(iterations=solution.iterations, violation=solution.violation)

    def __getitem__(self, key):
        self._fill()
        return super().__getitem__(key)

    def __contains__(self, key):
        self._fill()
        return super().__contains__(key)

    def __iter__(self):
        self._fill()
        return super().__iter__()

    def __len__(self) -> int:
        self._fill()
        return super().__len__()

    def __repr__(self) -> str:
        self._fill()
        return super().__repr__()

    def __eq__(self, other):
        self._fill()
        return super().__eq__(other)

    __hash__ = None

    def get(self, key, default=None):
        self._fill()
        return super().get(key, default)

    def items(self):
        self._fill()
        return super().items()

    def keys(self):
        self._fill()
        return super().keys()

    def values(self):
        self._fill()
        return super().values()


def _worlds(model: Model, worlds: list[int]) -> str:
    """", world 2" / ", worlds 0, 3" for an error message; "" in a model of one world."""
    if model.world_count == 1 or not worlds:
        return ""
    return f", world{'s' if len(worlds) > 1 else ''} {', '.join(map(str, worlds))}"


def _accumulate(array: wp.array, grad: np.ndarray) -> None:
    """array.grad += grad (a host array of the same shape)."""
    if array.grad is None:
        return
    g = array.grad.numpy()
    array.grad.assign((g + grad.reshape(g.shape)).astype(g.dtype))
