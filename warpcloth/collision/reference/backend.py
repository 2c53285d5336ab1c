"""The NumPy backend of the collision stage (``CollisionOptions.solver="numpy"``): each round's contacts projected by
:func:`~warpcloth.collision.reference.qp.project` on the host, its adjoint (``CollisionOptions.adjoint``) taped."""

from __future__ import annotations

import numpy as np
import warp as wp

from warpcloth.collision.contact import contact_geometry
from warpcloth.collision.detection import ContactDetector, Contacts
from warpcloth.collision.diagnostics import timed, worlds_suffix
from warpcloth.collision.reference.adjoint import backward, mass_gradient
from warpcloth.collision.reference.linalg import small_blas
from warpcloth.collision.reference.qp import ProjectionError, project
from warpcloth.collision.reference.zones import ProjectionResult
from warpcloth.errors import CollisionError
from warpcloth.model import Model
from warpcloth.tape import record_adjoint


class ZoneBackend:
    """The NumPy zone solver, round by round; the interface and arguments of
    :class:`~warpcloth.collision.projection.DeviceBackend`. Each round's result is kept in :attr:`projections`."""

    def __init__(self, model: Model, detector: ContactDetector, timings: dict):
        self.model = model
        self.detector = detector
        self.timings = timings
        self.begin(None, None, None, False)

    def begin(self, x_hat: wp.array | None, obstacle_end: wp.array | None, mass: wp.array | None,
              recording: bool) -> None:
        self._x_hat, self._obstacle_end, self._mass, self._recording = x_hat, obstacle_end, mass, recording
        self._contacts = Contacts.empty()  # every contact of the step so far
        self._geometry = []  # (normal, weight, target) of each round's new contacts, evaluated where found
        self._lam = np.zeros(0)  # the last round's multipliers: the next round starts from them
        self._found = Contacts.empty()
        self._fixed = self.model.particle_pin.numpy() >= 0  # read at each step: pins are the model's
        self.projections: list[tuple[ProjectionResult, wp.array]] = []
        self.zones: list[dict] = []

    @property
    def count(self) -> int:
        return len(self._contacts)

    def detect(self, start: wp.array, end: wp.array, reference: wp.array) -> int:
        # Every contact found is new: a pair found again is violated again (the projection leaves resolved pairs
        # exactly at the thickness, which proximity detection does not count), and its new linearisation joins
        # the old one.
        self._found = self.detector.detect(start, end, reference)
        return len(self._found)

    def first_found(self) -> tuple[np.ndarray, int]:
        return self._found.nodes[0], int(self._found.mode[0])

    def found_worlds(self) -> list[int]:
        return np.unique(self.detector.node_world_host[self._found.nodes[:, 0]]).tolist()

    def contact_nodes(self) -> np.ndarray:
        return np.concatenate([self._contacts.nodes, self._found.nodes])

    def add_found(self, start: wp.array, end: wp.array, step: int) -> None:
        self._geometry.append(contact_geometry(self.model, self.detector, start, end, self._found, self._recording,
                                               step))
        self._contacts = Contacts.concatenate([self._contacts, self._found])
        self._found = Contacts.empty()

    def project(self, step: int, opt) -> wp.array:
        x_hat, obstacle_end, mass, geometry = self._x_hat, self._obstacle_end, self._mass(), self._geometry
        normals, weights, targets = (np.concatenate([g[k].numpy() for g in geometry]).astype(np.float64)
                                     for k in range(3))
        unknowns = 3 * np.unique(self._contacts.nodes).size  # the zones' sizes add up to at most this
        try:
            with small_blas(unknowns):
                result = project(
                    x_hat.numpy().astype(np.float64), mass.numpy().astype(np.float64), self._fixed,
                    obstacle_end.numpy().astype(np.float64).reshape(-1, 3), self._contacts.nodes.astype(np.int64),
                    weights, normals, targets, tol=opt.qp_tol,
                    lam_init=np.concatenate([self._lam, np.zeros(len(normals) - len(self._lam))]))
        except ProjectionError as err:
            worlds = None if err.contact is None else \
                [int(self.detector.node_world_host[self._contacts.nodes[err.contact, 0]])]
            raise CollisionError(f"step {step}{worlds_suffix(self.model, worlds)}: {err}", worlds=worlds) from err
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
                gx, gw, gn, gob, gt = backward(result, grad_z, mode=mode)
            _accumulate(x_hat, gx)
            _accumulate(mass, mass_gradient(result, gx))
            for (normal, weight, target), lo, hi in zip(geometry, sizes[:-1], sizes[1:]):
                _accumulate(normal, gn[lo:hi])
                _accumulate(weight, gw[lo:hi])
                _accumulate(target, gt[lo:hi])
            if obstacle_end.shape[0]:
                _accumulate(obstacle_end, gob)

        record_adjoint(adjoint, arrays=[z])


def _accumulate(array: wp.array, grad: np.ndarray) -> None:
    if array.grad is None:
        return
    g = array.grad.numpy()
    array.grad.assign((g + grad.reshape(g.shape)).astype(g.dtype))
