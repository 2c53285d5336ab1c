"""The collision stage's fail-safe: rigid impact zones (Provot 1997; Bridson, Fedkiw and Anderson 2002), taped.
The method: docs/concepts/contact.md."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warpcloth.collision.contact import contact_geometry, gather_nodes
from warpcloth.collision.detection import ContactDetector
from warpcloth.collision.reference.zones import components
from warpcloth.errors import CollisionError
from warpcloth.kernels.failsafe import failsafe_kernels

MERGES = 100
"""Most detection passes that merge zones before the fail-safe gives up."""


@dataclass
class FailSafeReport:
    """What the fail-safe did in a step."""

    reason: str
    """Why the projection was given up (its error message)."""
    zones: int
    """Rigid zones in the end."""
    particles: int
    """Particles in them."""
    passes: int
    """Detection passes (each merging zones) until no contact was left outside a zone."""


class RigidImpactZones:
    """Rigid impact zones over a model's cloth particles; ``detector``: the collision stage's."""

    def __init__(self, model, detector: ContactDetector):
        self.model = model
        self.detector = detector
        self.cloth_count = model.particle_count
        self.thickness = float(model.collision.thickness)
        self.free = model.particle_pin.numpy() < 0  # read again at each resolve: the model's pins as they are then
        self.kernels = failsafe_kernels(model.scalar)

    def zones(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(zone of each cloth particle or -1, anchor zones, anchor nodes) of contacts ``rows`` (m, 4): free particles
        that share a contact share a zone; the contacts' constant nodes anchor it."""
        n = self.cloth_count
        rows = np.asarray(rows, dtype=np.int64).reshape(-1, 4)
        free = (rows < n) & self.free[np.where(rows < n, rows, 0)]
        linked = free.any(axis=1)
        rows, free = rows[linked], free[linked]
        first = rows[np.arange(len(rows)), np.argmax(free, axis=1)]  # a free particle of each contact
        label = components(n, np.broadcast_to(first[:, None], rows.shape)[free], rows[free])
        zone = np.full(n, -1, dtype=np.int32)
        members = np.unique(rows[free])
        if members.size:
            zone[members] = np.unique(label[members], return_inverse=True)[1]
        anchors = np.unique(np.stack([np.broadcast_to(zone[first][:, None], rows.shape)[~free], rows[~free]], axis=1),
                            axis=0).astype(np.int32).reshape(-1, 2)
        return zone, anchors[:, 0].copy(), anchors[:, 1].copy()

    def positions(self, x0: wp.array, x_hat: wp.array, mass: wp.array, start: wp.array, end: wp.array,
                  zone: np.ndarray, anchor_zone: np.ndarray, anchor_node: np.ndarray, recording: bool) -> wp.array:
        """The zones' rigid positions (x^ outside them), taped; ``start``, ``end``: every node at the step's ends."""
        model = self.model
        dev = model.device
        scalar, vec3, mat33 = model.scalar, model.types.vec3, model.types.mat33
        k = self.kernels
        n = self.cloth_count
        count_zones = max(int(zone.max()) + 1, 1)
        zone_wp = wp.array(zone, dtype=wp.int32, device=dev)

        def zeros(dtype):
            return wp.zeros(count_zones, dtype=dtype, device=dev, requires_grad=recording)

        total, count = zeros(scalar), zeros(scalar)
        first, moved, turn, shift = zeros(vec3), zeros(vec3), zeros(vec3), zeros(vec3)
        inertia = zeros(mat33)
        wp.launch(k.zone_sums, n, device=dev, inputs=[x0, x_hat, mass, zone_wp], outputs=[total, first, moved])
        wp.launch(k.zone_rotation_sums, n, device=dev, inputs=[x0, x_hat, mass, zone_wp, total, first],
                  outputs=[turn, inertia])
        if len(anchor_zone):
            wp.launch(k.anchor_sums, len(anchor_zone), device=dev,
                      inputs=[start, end, wp.array(anchor_zone, dtype=wp.int32, device=dev),
                              wp.array(anchor_node, dtype=wp.int32, device=dev)], outputs=[shift, count])
        z = wp.empty(n, dtype=vec3, device=dev, requires_grad=recording)
        wp.launch(k.rigid_positions, n, device=dev,
                  inputs=[x0, x_hat, zone_wp, total, first, moved, turn, inertia, shift, count], outputs=[z])
        return z

    def resolve(self, x0: wp.array, x_hat: wp.array, obstacle_start: wp.array, obstacle_end: wp.array,
                mass: wp.array, rows: np.ndarray, recording: bool, reason: str, step: int
                ) -> tuple[wp.array, FailSafeReport]:
        """Positions that leave no contact outside a rigid zone, from the contacts ``rows`` the projection gave up
        on (``reason``: why); raises CollisionError where the zones do not settle in MERGES passes."""
        model = self.model
        self.free = model.particle_pin.numpy() < 0  # the model's pins as they are now
        start = gather_nodes(model, x0, obstacle_start, recording)
        end_anchors = gather_nodes(model, x_hat, obstacle_end, recording)
        rows = np.asarray(rows, dtype=np.int32).reshape(-1, 4)
        held = np.zeros(self.cloth_count, dtype=bool)  # particles whose zone must move with its anchors
        for passes in range(1, MERGES + 1):
            zone, anchor_zone, anchor_node = self.zones(rows)
            anchored = np.zeros(max(int(zone.max()) + 1, 1), dtype=bool)
            anchored[zone[held & (zone >= 0)]] = True
            keep = anchored[anchor_zone] if len(anchor_zone) else np.zeros(0, dtype=bool)
            z = self.positions(x0, x_hat, mass, start, end_anchors, zone, anchor_zone[keep], anchor_node[keep],
                               recording)
            found = self._violated(start, gather_nodes(model, z, obstacle_end, False), step)
            outside, hold = [], []
            for row in found:
                where = self._place(row, zone, anchored)
                if where == "outside":
                    outside.append(row)
                elif where == "hold":
                    hold.append(row)
            if not outside and not hold:
                members = int(np.count_nonzero(zone >= 0))
                return z, FailSafeReport(reason, int(zone.max()) + 1 if members else 0, members, passes)
            for row in hold:  # a free zone that meets an obstacle or a pin: it moves with them from now on
                held[[a for a in row if a < self.cloth_count]] = True
            if outside:
                rows = np.concatenate([rows, np.asarray(outside, dtype=np.int32)])
        raise CollisionError(f"step {step}: the rigid impact zones did not settle in {MERGES} passes after the "
                             f"projection failed ({reason})")

    def _violated(self, start: wp.array, end: wp.array, step: int) -> np.ndarray:
        """The nodes of the contacts detected between ``start`` and ``end`` that the end positions violate."""
        found = self.detector.detect(start, end)
        if len(found) == 0:
            return found.nodes
        normal, weight, target = contact_geometry(self.model, self.detector, start, end, found, False, step)
        x = end.numpy().astype(np.float64)[found.nodes]  # (m, 4, 3)
        gap = np.einsum("ma,mak,mk->m", weight.numpy().astype(np.float64), x, normal.numpy().astype(np.float64))
        return found.nodes[gap < target.numpy() - 1.0e-6 * self.thickness]

    def _place(self, row: np.ndarray, zone: np.ndarray, anchored: np.ndarray) -> str:
        """Where a contact found after the rigid motion lies: "inside" one zone, "hold" (a free zone against an
        obstacle or a pin: it must move with them) or "outside" (particles in no zone or in two: they merge)."""
        n = self.cloth_count
        free = [int(a) for a in row if a < n and self.free[a]]
        if not free:  # only constant nodes: nothing to move
            return "inside"
        if zone[free[0]] < 0 or any(zone[a] != zone[free[0]] for a in free):
            return "outside"
        constants = any(a >= n or not self.free[a] for a in row)
        return "hold" if constants and not anchored[zone[free[0]]] else "inside"
