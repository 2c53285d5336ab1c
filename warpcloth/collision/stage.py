"""The collision stage of a step: detect, project onto the non-penetrating set, repeat (SPEC.md §3).

After the implicit step has moved the cloth from x0 to x̂, each round
1. detects contacts between the start positions x0 and the current end positions (warpcloth/collision/detection.py:
   BVH broad phase over swept boxes; vertex-face and edge-edge CCD and proximity within the thickness δ:
   kernels/collision.py, not differentiated);
2. evaluates the new contacts at their frozen time of impact, from the positions they were found at: unit normal n
   and weights w (kernels/contact.py, differentiated by Warp); they stay frozen in later rounds;
3. solves min ½(z − x̂)ᵀW(z − x̂) s.t. Σ_k w_jk n_j·z_k ≥ δ over impact zones (warpcloth/collision/projection.py,
   NumPy), recording the QR (or dense KKT) adjoint on the tape.
Rounds repeat until detection finds nothing new; the velocities then take the displacement, v += (z − x̂)/dt.

Gradients reach x̂, the step's start positions x0 and the obstacles' start and end positions (hence the obstacle
transforms of the Control) through n and w. Deliberately dropped: the time of impact and the set of contacts
(piecewise constant), and the masses in W (held constant; for a single-material cloth W's normalised masses do not
depend on its density at all).
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from warpcloth.collision import projection
from warpcloth.collision.detection import ContactDetector, Contacts
from warpcloth.collision.device_projection import DeviceProjection
from warpcloth.errors import CollisionError
from warpcloth.kernels.contact import contact_kernels
from warpcloth.model import Model, State
from warpcloth.tape import active_tape, record_adjoint


class CollisionStage:
    """The contact detector and the round loop of one Simulator (built only for scenes with collisions)."""

    def __init__(self, model: Model, dt: float, options):
        settings = model.collision
        self.model = model
        self.dt = float(dt)
        self.options = options
        self.device = model.device
        self.thickness = float(settings.thickness)
        self.kernels = contact_kernels(model.scalar)
        n = model.particle_count
        obstacles = settings.obstacles and model.obstacle_count > 0
        V = model.obstacle_vertex_count if obstacles else 0
        self.cloth_count = n
        self.obstacle_vertex_count = V
        self.node_count = n + V
        self.fixed = model.particle_pin.numpy() >= 0
        self._device = None  # the device projection's buffers (CollisionOptions.solver "device"), made on first use
        capacity = options.collision.contact_capacity or 16 * (n + V)
        self.detector = ContactDetector(model, thickness=self.thickness, capacity=capacity, obstacles=obstacles,
                                        self_collision=settings.self_collision)
        if obstacles:
            self.detector.check_start_outside(model)
        # every triangle's three edges and their rest lengths (material space): the projection-strain guard
        tris = model.triangles_np
        dm = np.linalg.inv(model.tri_inv_dm.numpy().astype(np.float64))  # columns: rest edges x1 - x0, x2 - x0
        self._edge_ends = np.concatenate([tris[:, [0, 1]], tris[:, [0, 2]], tris[:, [1, 2]]])
        self._edge_rest = np.concatenate([np.linalg.norm(dm[:, :, 0], axis=1), np.linalg.norm(dm[:, :, 1], axis=1),
                                          np.linalg.norm(dm[:, :, 1] - dm[:, :, 0], axis=1)])
        self.last = {}
        """Statistics of the last step: rounds, contacts, and the projection's per-zone records."""
        self.last_projections: list[tuple[projection.ProjectionResult, wp.array]] = []
        """(result, z) of each round of the last step (z.grad holds dL/dz after a backward pass): for benchmarks."""
        self.backward_seconds = 0.0
        """Wall time spent in the projection's adjoint (accumulates over backward passes)."""
        self.phase_seconds = dict.fromkeys(("detection", "geometry", "projection", "adjoint"), 0.0)
        """Wall time per phase, accumulated over steps (forward) and backward passes (``adjoint``): contact detection
        (swept BVH queries and the copy to the host), the contacts' normals and weights, the projection (zones and
        QP), and the projection's adjoint (the same as ``backward_seconds``)."""

    # -- response ------------------------------------------------------------------------------------------------
    def resolve(self, state_in: State, x_hat: wp.array, v_hat: wp.array, obstacle_start: wp.array,
                obstacle_end: wp.array, state_out: State, step: int) -> None:
        """Write the collision-free positions and corrected velocities of the step into ``state_out``;
        ``obstacle_start`` and ``obstacle_end`` are the obstacle vertices at the step's start and end (empty without
        obstacles)."""
        model = self.model
        k = self.kernels
        recording = active_tape() is not None and model.requires_grad
        vec3 = model.types.vec3
        n, N = self.cloth_count, self.node_count
        dev = self.device

        def gather(cloth_x, obstacle_x):
            out = wp.empty(N, dtype=vec3, device=dev, requires_grad=recording)
            wp.launch(k.gather_nodes, N, device=dev, inputs=[cloth_x, obstacle_x, n], outputs=[out])
            return out

        start = gather(state_in.particle_x, obstacle_start)
        z = x_hat
        contacts = Contacts.empty()
        lam = np.zeros(0)  # the last round's multipliers: the next round starts from them
        geometry = []  # (normal, weight) arrays of each round's new contacts, evaluated where they were found
        keys: set[bytes] = set()
        stats = {"rounds": 0, "contacts": 0, "zones": []}
        self.last_projections = []
        opt = self.options
        phases = self.phase_seconds
        for round_index in range(opt.collision.rounds + 1):
            t0 = time.perf_counter()
            end = gather(z, obstacle_end)
            found = self.detector.detect(start, end)
            phases["detection"] += time.perf_counter() - t0
            # Every contact found is new: a pair found again is violated again (the projection leaves resolved
            # pairs exactly at the thickness, which proximity detection does not count), and its new
            # linearisation joins the old one.
            keys.update(row.tobytes() for row in found.nodes)
            if len(found) == 0:
                break
            if round_index == opt.collision.rounds:
                raise CollisionError(
                    f"step {step}: the collision response did not converge in {opt.collision.rounds} rounds: "
                    f"{len(found)} new contacts (of {len(keys)}) still found, e.g. nodes "
                    f"{found.nodes[0].tolist()}; raise CollisionOptions.rounds, lower dt, or check "
                    "for cloth trapped between obstacles")
            t0 = time.perf_counter()
            geometry.append(self._geometry(start, end, found, recording, step))
            t1 = time.perf_counter()
            phases["geometry"] += t1 - t0
            contacts = Contacts.concatenate([contacts, found])
            z, lam = self._project(x_hat, obstacle_end, contacts, geometry, lam, recording, stats, step)
            phases["projection"] += time.perf_counter() - t1
            stats["rounds"] = round_index + 1
        stats["contacts"] = len(contacts)
        self.last = stats
        if len(contacts):
            self._check_projection_strain(x_hat, z, step)
        wp.launch(k.apply_projection, n, device=dev, inputs=[x_hat, v_hat, z, model.scalar(1.0 / self.dt)],
                  outputs=[state_out.particle_x, state_out.particle_v])

    def _check_projection_strain(self, x_hat: wp.array, z: wp.array, step: int) -> None:
        """Raise CollisionError if the projection alone lengthened an edge by more than
        ``CollisionOptions.max_projection_strain`` of its rest length.

        The projection moves particles onto the contacts' linearised constraints; when a step carries the cloth
        further than an element past an obstacle's curvature (a coarse cloth wrapping a small sphere at speed),
        neighbours land on different sides, the edges between them are stretched by the projection, and the next
        implicit step turns that stretch into motion that the next projection stretches again: energy grows step
        after step (a 20 m/s impact on a 0.25 m sphere at dt 0.01: 66 J to 2600 J in 12 steps). Well-resolved
        contact stays far below the limit (0.23 at most for that impact at dt 1 ms and a drape at dt 0.01).
        """
        zn, xn = z.numpy().astype(np.float64), x_hat.numpy().astype(np.float64)
        a, b = self._edge_ends[:, 0], self._edge_ends[:, 1]
        # lengthening only: stopping a falling strip's lowest vertices shortens edges, which buckling absorbs
        strain = (np.linalg.norm(zn[a] - zn[b], axis=1) - np.linalg.norm(xn[a] - xn[b], axis=1)) / self._edge_rest
        j = int(np.argmax(strain))
        limit = self.options.collision.max_projection_strain
        if strain[j] > limit:
            raise CollisionError(
                f"step {step}: the collision response stretched the edge between particles {int(a[j])} and "
                f"{int(b[j])} by {strain[j]:.3g} of its rest length in one step "
                f"(CollisionOptions.max_projection_strain "
                f"{limit:g}): the cloth moves too far per step for the contacts' linearisation, which then pumps "
                "energy into it step after step; lower dt")

    def _geometry(self, start, end, contacts: Contacts, recording, step) -> tuple[wp.array, wp.array]:
        """Normals and weights of new contacts at their frozen time of impact, from the positions they were found
        at (they stay frozen in later rounds, as in ARCSim's impact zones)."""
        model = self.model
        scalar, vec3, vec4 = model.scalar, model.types.vec3, model.types.vec4
        dev = self.device
        m = len(contacts)
        normal = wp.empty(m, dtype=vec3, device=dev, requires_grad=recording)
        weight = wp.empty(m, dtype=vec4, device=dev, requires_grad=recording)
        wp.launch(self.kernels.geometry, m, device=dev,
                  inputs=[start, end, wp.array(contacts.nodes, dtype=wp.int32, device=dev),
                          wp.array(contacts.mode, dtype=wp.int32, device=dev),
                          wp.array(contacts.t, dtype=scalar, device=dev),
                          wp.array(contacts.sign, dtype=scalar, device=dev)],
                  outputs=[normal, weight])
        ok = np.all(np.isfinite(normal.numpy()), axis=1) & np.all(np.isfinite(weight.numpy()), axis=1)
        if not ok.all():
            j = int(np.flatnonzero(~ok)[0])
            raise CollisionError(f"step {step}: a contact between nodes {contacts.nodes[j].tolist()} has a "
                                 "degenerate normal; a triangle or edge of the cloth or of an obstacle collapsed")
        return normal, weight

    def _project(self, x_hat, obstacle_end, contacts: Contacts, geometry, lam, recording, stats, step):
        """Project x̂ onto all contacts found so far; on a tape, record the projection's adjoint.

        ``lam`` are the previous round's multipliers (its contacts come first). Returns z and the multipliers."""
        model = self.model
        normals = np.concatenate([g[0].numpy() for g in geometry]).astype(np.float64)
        weights = np.concatenate([g[1].numpy() for g in geometry]).astype(np.float64)
        if self.options.collision.solver == "device":
            return self._project_device(x_hat, obstacle_end, contacts, geometry, normals, weights, lam, recording,
                                        stats, step)
        try:
            result = projection.project(
                x_hat.numpy().astype(np.float64), model.particle_mass(), self.fixed,
                obstacle_end.numpy().astype(np.float64).reshape(-1, 3), contacts.nodes.astype(np.int64),
                weights, normals, self.thickness, tol=self.options.collision.qp_tol,
                lam_init=np.concatenate([lam, np.zeros(len(normals) - len(lam))]))
        except projection.ProjectionError as err:
            raise CollisionError(f"step {step}: {err}") from err
        stats["zones"] = result.zones_stats()
        z = wp.array(result.z, dtype=model.types.vec3, device=self.device, requires_grad=recording)
        self.last_projections.append((result, z))
        if recording:
            mode = self.options.collision.adjoint
            sizes = np.cumsum([0] + [g[0].shape[0] for g in geometry])

            def adjoint():
                t0 = time.perf_counter()
                gx, gw, gn, gob = projection.backward(result, z.grad.numpy().astype(np.float64), mode=mode)
                self.backward_seconds += time.perf_counter() - t0
                self.phase_seconds["adjoint"] += time.perf_counter() - t0
                _accumulate(x_hat, gx)
                self._accumulate_density(projection.mass_gradient(result, gx))
                for (normal, weight), lo, hi in zip(geometry, sizes[:-1], sizes[1:]):
                    _accumulate(normal, gn[lo:hi])
                    _accumulate(weight, gw[lo:hi])
                if obstacle_end.shape[0]:
                    _accumulate(obstacle_end, gob)

            record_adjoint(adjoint, arrays=[z])
        return z, result.lam


    def _project_device(self, x_hat, obstacle_end, contacts, geometry, normals, weights, lam, recording, stats,
                        step):
        """:meth:`_project` by the device kernels (warpcloth/collision/device_projection.py)."""
        model = self.model
        dev = self.device
        n, N = self.cloth_count, self.node_count
        count = len(contacts)
        if self._device is None or self._device.capacity < count:
            self._device = DeviceProjection(dev, N, max(2 * count, 64))
        mass = model.particle_mass()
        xh = x_hat.numpy().astype(np.float64)
        obstacle = obstacle_end.numpy().astype(np.float64).reshape(-1, 3)
        free = np.concatenate([~self.fixed, np.zeros(N - n, dtype=bool)])
        inv_mass = np.zeros(N)
        inv_mass[:n][~self.fixed] = 1.0 / mass[~self.fixed]
        lam_init = np.concatenate([lam, np.zeros(count - len(lam))])
        problem = (wp.array(np.concatenate([xh, obstacle]), dtype=wp.vec3d, device=dev),
                   wp.array(free.astype(np.int32), dtype=wp.int32, device=dev),
                   wp.array(inv_mass, dtype=wp.float64, device=dev),
                   wp.array(contacts.nodes.astype(np.int32), dtype=wp.int32, device=dev),
                   wp.array(weights, dtype=wp.vec4d, device=dev), wp.array(normals, dtype=wp.vec3d, device=dev), count,
                   self.thickness)
        opt = self.options.collision
        solution = self._device.project(*problem, lam_init=wp.array(lam_init, dtype=wp.float64, device=dev),
                                        tol=opt.qp_tol, keep=recording)
        if solution.unbounded:
            raise CollisionError(
                f"step {step}: no positions satisfy the {count} contacts of the device projection (its dual is "
                "unbounded): cloth squeezed between obstacles closer than twice the thickness, or contacts that "
                "contradict each other")
        if not solution.converged:
            raise CollisionError(
                f"step {step}: the device projection of {count} contacts did not converge in {solution.iterations} "
                f"iterations: a contact violated or an active one off by {solution.residual:.3e} m > tol "
                f"{opt.qp_tol:.1e} (contacts that contradict each other stall it)")
        stats["zones"] = []
        stats["device"] = {"iterations": solution.iterations, "violation": solution.violation}
        z_nodes = solution.z.numpy()
        z = wp.array(z_nodes[:n], dtype=model.types.vec3, device=dev, requires_grad=recording)
        lam_out = solution.lam.numpy()[:count].copy()
        if recording:
            sizes = np.cumsum([0] + [g[0].shape[0] for g in geometry])
            nodes = contacts.nodes.astype(np.int64)

            def adjoint():
                t0 = time.perf_counter()
                gx, gw, gn, gob = self._device.backward(
                    solution, z.grad.numpy().astype(np.float64), x_hat=xh, mass=mass, fixed=self.fixed,
                    obstacle_x=obstacle, nodes=nodes, weights=weights, normals=normals)
                seconds = time.perf_counter() - t0
                self.backward_seconds += seconds
                self.phase_seconds["adjoint"] += seconds
                _accumulate(x_hat, gx)
                self._accumulate_density(projection.mass_gradient_of(gx, z_nodes[:n], xh, mass, self.fixed))
                for (normal, weight), lo, hi in zip(geometry, sizes[:-1], sizes[1:]):
                    _accumulate(normal, gn[lo:hi])
                    _accumulate(weight, gw[lo:hi])
                if obstacle_end.shape[0]:
                    _accumulate(obstacle_end, gob)

            record_adjoint(adjoint, arrays=[z])
        return z, lam_out

    def _accumulate_density(self, grad_mass: np.ndarray) -> None:
        """material_density.grad += the chain of ∂L/∂m through m_i = Σ_faces of i density thicken area / 3."""
        model = self.model
        density = model.material_density
        if density.grad is None or not np.any(grad_mass):
            return
        per_face = grad_mass[model.triangles_np].sum(axis=1) * model.tri_area.numpy() / 3.0
        grad = np.bincount(model.tri_material.numpy(), weights=per_face, minlength=density.shape[0])
        _accumulate(density, grad * model.material_thicken.numpy())


def _accumulate(array: wp.array, grad: np.ndarray) -> None:
    """array.grad += grad (a host array of the same shape)."""
    if array.grad is None:
        return
    g = array.grad.numpy()
    array.grad.assign((g + grad.reshape(g.shape)).astype(g.dtype))
