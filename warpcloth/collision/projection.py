"""The device projection (``CollisionOptions.solver="device"``, the default): each world's QP by MPRGP on the dual on
its own thread block, its adjoint by CG on the active set, as :mod:`warpcloth.collision.reference` poses them.
Why MPRGP: docs/decisions.md, "MPRGP for the collision QP"."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warpcloth.collision.contact import degenerate_error, geometry_arrays
from warpcloth.collision.detection import DEGENERATE, FAILED, ContactDetector, RowSort
from warpcloth.collision.diagnostics import timed, worlds_suffix
from warpcloth.collision.reference.adjoint import push_onto_contacts
from warpcloth.errors import CollisionError
from warpcloth.kernels import projection as kp
from warpcloth.kernels.contact import contact_kernels
from warpcloth.kernels.geometry import world_starts
from warpcloth.kernels.projection import device_round_kernels
from warpcloth.model import Model
from warpcloth.tape import capturing, record_adjoint

ADJOINT_WARN = 1.0e-8
"""An adjoint CG that ends above this relative residual warns (it aims at 1e-13)."""
QP_BLOCK_DIM = 128
"""Threads of the block that solves a world's QP and its adjoint on CUDA (on the CPU a block is one thread)."""


@dataclass
class DeviceSolution:
    """:meth:`DeviceProjection.project`'s result: its buffers (valid until its next call) unless ``keep``."""

    z: wp.array
    """Positions of every node (cloth particles, then obstacle vertices) [m], vec3d."""
    lam: wp.array
    """Multiplier of every contact, in the caller's order (the raw masses' scale) [kg m], float64."""
    rows: object
    """The contacts as the kernels read them, sorted by world (kernels/projection.py Rows)."""
    sorted_lam: wp.array
    """``lam`` in the order of ``rows``."""
    info: wp.array
    """Each world's [status, iterations, KKT residual, a bound on ||Hs||, violation], float64."""
    _read: np.ndarray | None = field(default=None, repr=False)

    def _info(self) -> np.ndarray:
        if self._read is None:
            self._read = self.info.numpy().copy()
        return self._read

    @property
    def world_status(self) -> np.ndarray:
        """Each world's solver status (kernels/projection.py CONVERGED, NOT_CONVERGED, UNBOUNDED)."""
        info = self._info()
        return np.where(np.isfinite(info[:, 2]), info[:, 0], kp.NOT_CONVERGED).astype(np.int64)

    @property
    def iterations(self) -> int:
        """MPRGP iterations taken (the most any world took)."""
        return int(self._info()[:, 1].max())

    @property
    def residual(self) -> float:
        """The KKT residual at the end [m]: largest violation and |c_j| where λ_j > 0, over all worlds."""
        return float(self._info()[:, 2].max())

    @property
    def violation(self) -> float:
        """Largest violation of a contact at the end [m]."""
        return float(self._info()[:, 4].max())

    @property
    def converged(self) -> bool:
        return bool(np.all(self.world_status == kp.CONVERGED))

    @property
    def unbounded(self) -> bool:
        """The dual fell without bound in some world: no positions satisfy its contacts."""
        return bool(np.any(self.world_status == kp.UNBOUNDED))

    def failed_worlds(self) -> list[int]:
        return np.flatnonzero(self.world_status != kp.CONVERGED).tolist()


class AdjointWork:
    """Adjoint work arrays for ``node_count`` nodes and ``capacity`` contacts, shared by every step's adjoint."""

    def __init__(self, device, node_count: int, capacity: int):
        f64 = wp.float64
        self.d_z = wp.zeros(node_count, dtype=wp.vec3d, device=device)
        self.d_z_in = wp.zeros(node_count, dtype=wp.vec3d, device=device)
        self.grad_const = wp.zeros(node_count, dtype=wp.vec3d, device=device)
        self.grad_w = wp.zeros(capacity, dtype=wp.vec4d, device=device)
        self.grad_n = wp.zeros(capacity, dtype=wp.vec3d, device=device)
        self.grad_target = wp.zeros(capacity, dtype=f64, device=device)
        self.sinks: dict = {}

    def sink(self, count: int, dtype, device) -> wp.array:
        """An array of ``count`` zeros of ``dtype`` to write a dropped gradient into (zeroed at each call)."""
        key = (count, dtype)
        array = self.sinks.get(key)
        if array is None:
            array = self.sinks[key] = wp.zeros(count, dtype=dtype, device=device)
        else:
            array.zero_()
        return array


class DeviceProjection:
    """Up to ``capacity`` contacts among ``node_count`` nodes (cloth, then obstacle vertices) in ``world_count`` worlds
    (``node_world``: each node's, int32; None: one), a world's QP on ``block_dim`` CUDA threads (2^k ≤ 1024)."""

    def __init__(self, device, node_count: int, capacity: int, node_world: wp.array | None = None,
                 world_count: int = 1, block_dim: int = QP_BLOCK_DIM):
        self.device = device
        if not 1 <= int(block_dim) <= 1024 or int(block_dim) & (int(block_dim) - 1):
            raise ValueError(f"DeviceProjection block_dim must be a power of two up to 1024, got {block_dim!r}")
        self.block_dim = int(block_dim)
        self.node_count = int(node_count)
        self.capacity = int(capacity)
        self.world_count = int(world_count)
        f64 = wp.float64
        m, N = max(self.capacity, 1), max(self.node_count, 1)
        self.node_world = node_world if node_world is not None else wp.zeros(N, dtype=wp.int32, device=device)
        self._fw = wp.zeros(m, dtype=wp.vec4d, device=device)
        self._h = wp.zeros(m, dtype=f64, device=device)
        self._diag = wp.zeros(m, dtype=f64, device=device)
        self._sorted_nodes = wp.zeros((m, 4), dtype=wp.int32, device=device)
        self._sorted_normals = wp.zeros(m, dtype=wp.vec3d, device=device)
        self._by_world = RowSort(m, self.world_count, device)  # the contacts sorted by world
        # the contacts' node entries grouped by node, for the node sums (kernels/projection.py Rows.entry_row ..)
        self._by_node = RowSort(4 * m, self.world_count * (N + 1), device, what="contacts' nodes")
        self._entry_row, self._run_end, self._run_node = (wp.zeros(4 * m, dtype=wp.int32, device=device)
                                                          for _ in range(3))
        self._entry_weight = wp.zeros(4 * m, dtype=f64, device=device)
        self._order = self._by_world.order
        self._held = wp.zeros(1, dtype=wp.int32, device=device)
        self._start = wp.zeros(self.world_count + 1, dtype=wp.int32, device=device)
        self._solve_world = wp.zeros(self.world_count, dtype=wp.int32, device=device)
        self._lam = wp.zeros(m, dtype=f64, device=device)  # the caller's order
        self._sorted_lam = wp.zeros(m, dtype=f64, device=device)
        self._ones = wp.ones(m, dtype=wp.int32, device=device)
        self._work = [wp.zeros(m, dtype=f64, device=device) for _ in range(5)]
        self._z = wp.zeros(N, dtype=wp.vec3d, device=device)
        self._x_hat = wp.zeros(N, dtype=wp.vec3d, device=device)
        self._scratch = wp.zeros(N, dtype=wp.vec3d, device=device)
        self._info = wp.zeros((self.world_count, 5), dtype=f64, device=device)
        self._failed = wp.zeros(1, dtype=wp.int32, device=device)
        self._rows = None
        # The adjoint's work arrays, reused by every call (a backward pass runs one step's adjoint at a time, and
        # nothing is kept from one call to the next but what the caller copies out of them)
        self._adj_active = wp.zeros(m, dtype=wp.int32, device=device)
        self._adj_sorted_d_lam = wp.zeros(m, dtype=f64, device=device)
        self._adj_work = [wp.zeros(m, dtype=f64, device=device) for _ in range(6)]
        self._adj_info = wp.zeros((self.world_count, 2), dtype=f64, device=device)
        self._adj_d_lam = wp.zeros(m, dtype=f64, device=device)
        self.adjoint_work = AdjointWork(device, N, m)

    def grown(self, capacity: int) -> DeviceProjection:
        """A projection of a larger capacity that resumes this one's step: its multipliers and positions kept."""
        bigger = DeviceProjection(self.device, self.node_count, capacity, self.node_world, self.world_count,
                                  self.block_dim)
        wp.copy(bigger._lam, self._lam, count=min(self.capacity, capacity))
        wp.copy(bigger._z, self._z)
        return bigger

    def project(self, positions: wp.array, free: wp.array, inv_mass: wp.array, nodes: wp.array, weights: wp.array,
                normals: wp.array, count: int, thickness: float | wp.array, *, lam_init: wp.array | None = None,
                warm: int | None = None, resume: bool = False, tol: float = 1.0e-10, max_iters: int = 100000,
                stall: int = 5000, keep: bool = False, failed: wp.array | None = None) -> DeviceSolution:
        """Project ``positions`` onto the ``count`` contacts, each world's on their own.

        Args:
            positions: (node_count,) vec3d: x̂ for free particles, the constant position of every other node.
            free, inv_mass: (node_count,) int32 and float64: 1 and 1/m for a free particle, else 0.
            nodes, weights, normals: the ``count`` contacts, (>= count, 4) int32, vec4d, vec3d.
            thickness: δ [m], or each contact's target gap (>= count, float64).
            lam_init: warm start, or None (zeros); it may be this object's last solution's ``lam``.
            warm: how many leading entries of ``lam_init`` to use (default ``count``); the rest start at 0.
            resume: a later round of the same step: the first ``warm`` contacts are the last call's; a world with
                no new contact keeps the last solution unsolved (each world runs the rounds it would alone).
            tol: KKT tolerance [m] (violation, and |c_j| where λ_j > 0).
            max_iters: most MPRGP iterations.
            stall: stop (not converged) when the KKT residual has not halved in this many iterations.
            keep: return arrays of its own (for a later :meth:`adjoint`), not this object's buffers.
            failed: a (1,) int32 flag, zeroed, then set to 1 where a world did not converge (default: own).
        """
        if count > self.capacity:
            raise ValueError(f"{count} contacts for a device projection of capacity {self.capacity}")
        dev = self.device
        k = 0 if lam_init is None else min(count if warm is None else int(warm), count)
        if k and lam_init is not self._lam:
            wp.copy(self._lam, lam_init, count=k)
        self._lam[k:].zero_()
        if not resume:
            wp.copy(self._z, positions)
        wp.copy(self._x_hat, positions)
        self._solve_world.zero_()
        wp.launch(kp.world_keys, max(count, 1), device=dev,
                  inputs=[nodes, self.node_world, count, k if resume else 0, self.world_count],
                  outputs=[self._by_world.keys, self._by_world.values, self._held, self._start, self._solve_world],
                  record_tape=False)
        if self.world_count > 1:
            self._by_world.sort(count)
            wp.launch(world_starts, self.world_count + 1, device=dev, inputs=[self._by_world.keys, self._held, 1],
                      outputs=[self._start], record_tape=False)
        r = kp.Rows()
        r.count, r.nodes, r.fw, r.normal, r.h, r.diag, r.inv_mass = (count, self._sorted_nodes, self._fw,
                                                                      self._sorted_normals, self._h, self._diag,
                                                                      inv_mass)
        r.order, r.start = self._order, self._start
        r.entry_row, r.entry_weight, r.run_end, r.run_node = (self._entry_row, self._entry_weight, self._run_end,
                                                              self._run_node)
        self._rows = r
        if not isinstance(thickness, wp.array):
            thickness = wp.full(max(count, 1), float(thickness), dtype=wp.float64, device=dev)
        if count:
            by_node = self._by_node
            wp.launch(kp.prepare_rows, count, device=dev,
                      inputs=[nodes, weights, normals, positions, free, inv_mass, thickness, self._order,
                              self.node_world, max(self.node_count, 1)],
                      outputs=[self._sorted_nodes, self._sorted_normals, self._fw, self._h, self._diag, by_node.keys,
                               by_node.values], record_tape=False)
            wp.launch(kp.gather, count, device=dev, inputs=[self._lam, self._order], outputs=[self._sorted_lam],
                      record_tape=False)
            by_node.sort(4 * count)
            wp.launch(kp.incidence_runs, 4 * count, device=dev,
                      inputs=[by_node.keys, by_node.order, 4 * count, max(self.node_count, 1), self._sorted_nodes,
                              self._fw, inv_mass],
                      outputs=[self._entry_row, self._entry_weight, self._run_end, self._run_node], record_tape=False)
        x, g, p, hp, tmp = self._work
        failed = self._failed if failed is None else failed
        failed.zero_()
        wp.launch_tiled(kp.solve, dim=[self.world_count], block_dim=self.block_dim, device=dev,
                        inputs=[r, self._x_hat, wp.float64(tol), int(max_iters), int(stall), self._ones,
                                self._solve_world],
                        outputs=[self._sorted_lam, self._z, x, g, p, hp, tmp, self._scratch, self._info, failed],
                        record_tape=False)
        if count:
            wp.launch(kp.scatter, count, device=dev, inputs=[self._sorted_lam, self._order], outputs=[self._lam],
                      record_tape=False)
        z, lam, sorted_lam, info = self._z, self._lam, self._sorted_lam, self._info
        if keep:
            kept = kp.Rows()
            kept.count = count
            m = max(count, 1)  # the buffers hold up to their capacity: keep the first count rows
            kept.nodes, kept.fw = wp.clone(self._sorted_nodes[:m]), wp.clone(self._fw[:m])
            kept.normal, kept.h = wp.clone(self._sorted_normals[:m]), wp.clone(self._h[:m])
            kept.diag, kept.inv_mass = wp.clone(self._diag[:m]), wp.clone(inv_mass)
            kept.order, kept.start = wp.clone(self._order[:m]), wp.clone(self._start)
            kept.entry_row, kept.entry_weight, kept.run_end, kept.run_node = (
                wp.clone(a[:4 * m]) for a in (self._entry_row, self._entry_weight, self._run_end, self._run_node))
            r, z, lam, sorted_lam = kept, wp.clone(z), wp.clone(lam[:m]), wp.clone(sorted_lam[:m])
            info = wp.clone(info)
        return DeviceSolution(z=z, lam=lam, rows=r, sorted_lam=sorted_lam, info=info)

    @property
    def lam(self) -> wp.array:
        """The last solve's multipliers (this object's buffer: a warm start for the next, larger solve)."""
        return self._lam

    def adjoint_on_device(self, solution: DeviceSolution, d_z: wp.array, *, active_tol: float = 1.0e-9,
                          rtol: float = 1.0e-13, worst: wp.array | None = None) -> wp.array:
        """In place: ``d_z`` (node_count,) vec3d holds W⁻¹ ∂L/∂z on entry (0 for constant nodes), W⁻¹(∂L/∂z − G_Aᵀd_λ)
        on return; returns d_λ (count,) in the caller's order, the reference's negated, in this object's buffer.
        Warns where the CG ends above ADJOINT_WARN, or with ``worst`` ((1,) float64) keeps the largest there."""
        r = solution.rows
        dev = self.device
        m = max(r.count, 1)
        if m > self.capacity:
            raise ValueError(f"{r.count} contacts for a device projection of capacity {self.capacity}")
        # this object's work arrays, their first m entries zeroed (as new arrays of m zeros would be)
        active, sorted_d_lam, d_lam = (a[:m] for a in (self._adj_active, self._adj_sorted_d_lam, self._adj_d_lam))
        rhs, res, p, q, correction, remainder = (a[:m] for a in self._adj_work)
        info = self._adj_info
        for a in (active, sorted_d_lam, rhs, res, p, q, correction, remainder, info, d_lam):
            a.zero_()
        if r.count:
            wp.launch(kp.active_set, r.count, device=dev,
                      inputs=[r, solution.z, solution.sorted_lam, wp.float64(active_tol)], outputs=[active],
                      record_tape=False)
        wp.launch_tiled(kp.adjoint, dim=[self.world_count], block_dim=self.block_dim, device=dev,
                        inputs=[r, active, wp.float64(rtol)],
                        outputs=[sorted_d_lam, d_z, rhs, res, p, q, correction, remainder, self._scratch, info],
                        record_tape=False)
        if r.count:
            wp.launch(kp.scatter, r.count, device=dev, inputs=[sorted_d_lam, r.order], outputs=[d_lam],
                      record_tape=False)
        if worst is not None:
            wp.launch(kp.worst_residual, 1, device=dev, inputs=[info, worst], record_tape=False)
            return d_lam
        info = info.numpy()
        world = int(np.argmax(np.where(np.isfinite(info[:, 1]), info[:, 1], np.inf)))
        iterations, residual = info[world]
        if not residual <= ADJOINT_WARN:
            where = f" in world {world}" if self.world_count > 1 else ""
            warnings.warn(f"the device projection's adjoint CG stopped at relative residual {residual:.2e} after "
                          f"{int(iterations)} iterations{where} ({r.count} contacts): its gradient is that inexact",
                          RuntimeWarning, stacklevel=3)
        return d_lam

    def adjoint(self, solution: DeviceSolution, grad_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(d_z (node_count, 3), d_λ (count,)) for ∂L/∂z (node_count, 3) on the host, in the convention of
        :mod:`warpcloth.collision.reference.adjoint` (d_λ the kernels' negated; d_z 0 for constant nodes)."""
        inv_mass = solution.rows.inv_mass.numpy()
        d_z = wp.array(np.asarray(grad_z, dtype=np.float64) * inv_mass[:, None], dtype=wp.vec3d, device=self.device)
        d_lam = self.adjoint_on_device(solution, d_z)
        return d_z.numpy(), -d_lam.numpy()[:solution.rows.count]  # a copy: d_lam is this object's buffer

    def backward(self, solution: DeviceSolution, grad_z: np.ndarray, *, x_hat: np.ndarray, mass: np.ndarray,
                 fixed: np.ndarray, obstacle_x: np.ndarray, nodes: np.ndarray, weights: np.ndarray,
                 normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:func:`warpcloth.collision.reference.adjoint.backward`'s gradients, for the problem :meth:`project` solved
        (given on the host) and ∂L/∂z (n, 3) of the cloth particles."""
        n = x_hat.shape[0]
        V = obstacle_x.shape[0]
        grad_z = np.asarray(grad_z, dtype=np.float64)
        d_z, d_lam = self.adjoint(solution, np.concatenate([grad_z, np.zeros((V, 3))]))
        movable = ~fixed
        grad_x = grad_z.copy()
        grad_x[movable] = d_z[:n][movable] * mass[movable, None]
        d_ext = np.zeros((n + V, 3))
        d_ext[:n][movable] = d_z[:n][movable]
        z = np.where(movable[:, None], solution.z.numpy()[:n], x_hat)
        lam = solution.lam.numpy()[:solution.rows.count]
        grad_w, grad_n, grad_ext = push_onto_contacts(nodes, weights, normals, fixed, z, obstacle_x, d_ext, d_lam, lam)
        grad_x += grad_ext[:n]
        return grad_x, grad_w, grad_n, grad_ext[n:].copy(), -d_lam


class DeviceBackend:
    """The device projection round by round, each solve warm-started from the last. ``timings``: the stage's phase
    totals (the adjoint adds to ``"adjoint"``); ``node_count``: cloth particles plus the colliding obstacle vertices."""

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
        self._untaped_geometry = geometry_arrays(model, max(detector.capacity, 1), False)
        self._retired = []  # the solvers and contact lists that grown ones replaced: a captured step's graph may
        # still read them
        self.mismatch: wp.array | None = None
        """A planned (captured) step's flag, raised on the device where it leaves its plan (set by the stage)."""
        self.adjoint_residual = wp.zeros(1, dtype=wp.float64, device=dev)  # read by check_adjoints
        self.begin(None, None, None, False)

    STEP_LOCAL = frozenset({"_x_hat", "_obstacle_end", "_mass", "_rounds", "_solution", "_constants", "solver_stats"})
    """The attributes that hold one step's arrays, set anew by :meth:`begin` and never read by a later step."""

    def begin(self, x_hat: wp.array | None, obstacle_end: wp.array | None, mass: wp.array | None,
              recording: bool) -> None:
        """Start a try at a step that projects ``x_hat`` (``mass()`` makes the lumped masses at its first call)."""
        self._x_hat, self._obstacle_end, self._mass, self._recording = x_hat, obstacle_end, mass, recording
        self._total = 0  # contacts in the lists
        self._found = 0  # contacts the last detection found (in the detector's buffers)
        self._rounds = []  # (offset, count, normal, weight, target) of each round's contacts
        self._solution = None
        self._constants = None  # (positions, free, inverse masses) of the step, once it has contacts
        self.solver_stats: dict | None = None

    @property
    def count(self) -> int:
        """Contacts in the step's projection so far."""
        return self._total

    def detect(self, start: wp.array, end: wp.array, reference: wp.array, expected: int | None = None,
               last: bool = False) -> int:
        """Detect the contacts between ``start`` and ``end``; returns how many. A planned step (``expected``: the
        plan's count; ``last``: must find none) reads nothing: it checks into :attr:`mismatch`, returns ``expected``."""
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
        """(nodes, mode) of the first contact the last detection found."""
        return self.detector.nodes.numpy()[0], int(self.detector.mode.numpy()[0])

    def found_worlds(self) -> list[int]:
        return np.unique(self.detector.node_world_host[self.detector.nodes.numpy()[:self._found, 0]]).tolist()

    def contact_nodes(self) -> np.ndarray:
        """The nodes (m, 4) of every contact the step found so far, the last detection's included."""
        parts = [self._nodes.numpy()[:self._total]] if self._total else []
        parts.append(self.detector.nodes.numpy()[:self._found])
        return np.concatenate(parts)

    def add_found(self, start: wp.array, end: wp.array, step: int) -> None:
        """Evaluate the geometry of the contacts just found and add them to the step's projection."""
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
            normal, weight, target = geometry_arrays(model, found, True)
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
        """Project x̂ onto every contact so far with the CollisionOptions ``opt``; record its adjoint."""
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
            raise degenerate_error(step, self.detector.nodes.numpy()[j], self.detector)
        if not flags[FAILED]:
            return self._positions(solution)
        failed = solution.failed_worlds()
        where = worlds_suffix(model, failed)
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
        """Warn where an adjoint CG replayed from a graph stopped above ADJOINT_WARN (one read); reset the largest."""
        residual = float(self.adjoint_residual.numpy()[0])
        if not residual <= ADJOINT_WARN:
            warnings.warn(f"the device projection's adjoint CG of a replayed step stopped at relative residual "
                          f"{residual:.2e}: its gradient is that inexact", RuntimeWarning, stacklevel=3)
        self.adjoint_residual.zero_()


class _SolverStats(dict):
    """``solver_stats`` (``iterations``, ``violation``), read when first looked at (untaped: before the next step)."""

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
