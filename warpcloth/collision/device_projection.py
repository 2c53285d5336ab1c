"""The collision projection and its adjoint as Warp kernels over all contacts at once (kernels/projection.py has
the method), the default solver of the collision stage (``CollisionOptions.solver="device"``). Same problem, same
tolerance and same adjoint formulas as the NumPy zone solver (:mod:`warpcloth.collision.qp`), the oracle of these
kernels' tests. The host-side :meth:`DeviceProjection.adjoint` and :meth:`DeviceProjection.backward` serve those
tests; the stage uses :meth:`DeviceProjection.adjoint_on_device` and the kernels of kernels/projection.py."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warpcloth.collision.adjoint import push_onto_contacts
from warpcloth.collision.detection import RowSort
from warpcloth.kernels import projection as kp
from warpcloth.kernels.geometry import world_starts

ADJOINT_WARN = 1.0e-8
"""An adjoint CG that ends above this relative residual warns (it aims at 1e-13)."""
QP_BLOCK_DIM = 128
"""Threads of the block that solves a world's QP and its adjoint on CUDA (on the CPU a block is one thread). Not
yet tuned on a GPU: a world's contacts number from a few to thousands."""


@dataclass
class DeviceSolution:
    """What :meth:`DeviceProjection.project` found (device arrays, valid until the next call, unless it kept its
    own). The solver's status is read from the device when first asked for (``world_status`` and the figures
    after it): a caller that reads only the failure flag of the solve reads nothing else."""

    z: wp.array
    """Positions of every node (cloth particles, then obstacle vertices) [m], vec3d."""
    lam: wp.array
    """Multiplier of every contact, in the caller's order (the raw masses' scale) [kg m], float64."""
    rows: object
    """The contacts as the kernels read them, sorted by world (kernels/projection.py Rows)."""
    sorted_lam: wp.array
    """``lam`` in the order of ``rows``."""
    info: wp.array
    """Each world's [status, iterations, KKT residual, a bound on ||Hs||, violation] (kernels/projection.py solve),
    float64."""
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
        """The KKT test's residual at the end [m]: largest violation, and |c_j| where λ_j > 0 (largest over
        worlds)."""
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
    """The collision stage's device backend's adjoint work arrays for ``node_count`` nodes and up to ``capacity``
    contacts (one set per DeviceProjection, reused by every step's adjoint: they run one at a time)."""

    def __init__(self, device, node_count: int, capacity: int):
        f64 = wp.float64
        self.d_z = wp.zeros(node_count, dtype=wp.vec3d, device=device)
        self.d_z_in = wp.zeros(node_count, dtype=wp.vec3d, device=device)
        self.grad_const = wp.zeros(node_count, dtype=wp.vec3d, device=device)
        self.grad_w = wp.zeros(capacity, dtype=wp.vec4d, device=device)
        self.grad_n = wp.zeros(capacity, dtype=wp.vec3d, device=device)
        self.grad_target = wp.zeros(capacity, dtype=f64, device=device)
        self.sinks: dict = {}
        """Gradient arrays for inputs that have none (their gradient is dropped), by (shape, dtype)."""

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
    """Buffers and launches of the device projection for up to ``capacity`` contacts among ``node_count`` nodes,
    the nodes in ``world_count`` worlds (each world's contacts are its own QP, solved by its own thread block).

    Args:
        device: Warp device.
        node_count: cloth particles plus obstacle vertices.
        capacity: most contacts one call may hold.
        node_world: the world of every node, (node_count,) int32 on the device (default: one world).
        world_count: number of worlds.
        block_dim: threads of the block that solves a world on CUDA.
    """

    def __init__(self, device, node_count: int, capacity: int, node_world: wp.array | None = None,
                 world_count: int = 1, block_dim: int = QP_BLOCK_DIM):
        self.device = device
        if not 1 <= int(block_dim) <= 1024 or int(block_dim) & (int(block_dim) - 1):
            raise ValueError(f"DeviceProjection block_dim must be a power of two up to 1024, got {block_dim!r}")
        self.block_dim = int(block_dim)
        """Threads of the block that solves a world (QP_BLOCK_DIM unless given; on the CPU a block is one thread)."""
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
        """Work arrays of a caller's adjoint (the collision stage's device backend), sized for this capacity."""

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
        """Project ``positions`` (every node; the free ones are x̂) onto the ``count`` contacts, each world's
        contacts on their own.

        Args:
            positions: (node_count,) vec3d: x̂ for free particles, the constant position of every other node.
            free: (node_count,) int32, 1 for a free particle.
            inv_mass: (node_count,) float64, 1/m for free particles (0 elsewhere).
            nodes, weights, normals: the contacts, (>= count, 4) int32, vec4d, vec3d.
            count: number of contacts.
            thickness: δ [m], or each contact's target gap (>= count, float64).
            lam_init: warm start, or None (zeros); it may be this object's last solution's ``lam``.
            warm: how many leading entries of ``lam_init`` to use (default ``count``); the rest start at 0.
            resume: a later round of the same step: the first ``warm`` contacts are the last call's, and a world
                with no contact after them keeps the last call's solution without solving again (so each world
                runs the rounds it would run alone).
            tol: KKT tolerance [m] (violation, and |c_j| where λ_j > 0).
            max_iters: most MPRGP iterations (each one product with the dual matrix).
            stall: stop (not converged) when the KKT residual has not halved in this many iterations.
            keep: return arrays of its own (for a later :meth:`adjoint`), not this object's buffers.
            failed: a flag (an int32 array, its entry 0) this call zeroes and the solve sets to 1 where a world
                did not converge; default: one of this object's.
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
        """In place on the device: ``d_z`` (node_count,) vec3d holds W⁻¹ ∂L/∂z on entry (0 for constant nodes) and
        W⁻¹(∂L/∂z − G_Aᵀd_λ) on return; returns the kernels' d_λ (count,) in the caller's order (the negative of
        :mod:`warpcloth.collision.adjoint`'s), in this object's buffer: valid until the next call. The CG's
        residual is read back, and warned of above ADJOINT_WARN; with ``worst`` (a (1,) float64 array, for a
        graph's capture) it is not read but kept there, the largest of the calls."""
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
        """(d_z (node_count, 3), d_λ (count,)) of ``solution`` for ∂L/∂z (node_count, 3), on the host, in
        :mod:`warpcloth.collision.adjoint`'s convention (d_z = W⁻¹(ḡ − G_Aᵀd_λ) with its G = −g, so its d_λ is the
        negative of the kernels'); d_z is W⁻¹ḡ for free particles in no active contact, 0 for constant nodes."""
        inv_mass = solution.rows.inv_mass.numpy()
        d_z = wp.array(np.asarray(grad_z, dtype=np.float64) * inv_mass[:, None], dtype=wp.vec3d, device=self.device)
        d_lam = self.adjoint_on_device(solution, d_z)
        return d_z.numpy(), -d_lam.numpy()[:solution.rows.count]  # a copy: d_lam is this object's buffer

    def backward(self, solution: DeviceSolution, grad_z: np.ndarray, *, x_hat: np.ndarray, mass: np.ndarray,
                 fixed: np.ndarray, obstacle_x: np.ndarray, nodes: np.ndarray, weights: np.ndarray,
                 normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(∂L/∂x̂ (n, 3), ∂L/∂weights (m, 4), ∂L/∂normals (m, 3), ∂L/∂obstacle_x (V, 3), ∂L/∂thickness (m,)) for
        ∂L/∂z (n, 3) of the cloth particles, as :func:`warpcloth.collision.adjoint.backward` returns them (the
        arguments: the problem :meth:`project` solved, on the host)."""
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
