"""The collision stage of a step: detect, project onto the non-penetrating set, repeat (SPEC.md §3).

After the implicit step has moved the cloth from x0 to x̂, each round
1. detects contacts between the start positions x0 and the current end positions (warpcloth/collision/detection.py:
   BVH broad phase over swept boxes; vertex-face and edge-edge CCD and proximity within the thickness δ:
   kernels/collision.py, not differentiated);
2. evaluates the new contacts at their time of impact, from the positions they were found at: unit normal n and
   weights w (kernels/contact.py, differentiated by Warp, the time of impact included); they stay in later rounds;
3. solves min ½(z − x̂)ᵀW(z − x̂) s.t. Σ_k w_jk n_j·z_k ≥ δ over all contacts so far and records its adjoint on
   the tape: by default on the device (``CollisionOptions.solver="device"``, kernels/projection.py: MPRGP on the
   dual, a CG adjoint on the active set; contacts, geometry and gradients never leave the device, each round reads
   back the contact count and the solver's status), or zone by zone in NumPy (``"numpy"``,
   warpcloth/collision/projection.py, with the QR or dense KKT adjoint).
Rounds repeat until detection finds nothing new; the velocities then take the displacement, v += (z − x̂)/dt.

Gradients reach x̂, the step's start positions x0 and the obstacles' start and end positions (hence the obstacle
transforms of the Control) through n, w and the times of impact, and the masses in W (the Simulator's taped lumped
masses, on to the densities). Deliberately dropped: which contacts exist and which are active (piecewise constant:
the trajectory's piece).
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from warpcloth.collision import projection
from warpcloth.collision.detection import ContactDetector, Contacts
from warpcloth.collision.device_projection import DeviceProjection
from warpcloth.collision.failsafe import RigidImpactZones
from warpcloth.errors import CollisionError, ContactCapacityError
from warpcloth.kernels.contact import contact_kernels
from warpcloth.kernels.geometry import segment_parameters, triangle_barycentric
from warpcloth.kernels.projection import device_round_kernels
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
        # the device solver's buffers (CollisionOptions.solver "device"), made on first use
        self._device = None
        self._contact_nodes = self._contact_normals = self._contact_weights = None
        self._edge_ends_device = self._edge_rest_device = None
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
        self.fail_safe = RigidImpactZones(model, self.fixed)
        """The fail-safe of steps the projection cannot resolve (rigid impact zones)."""
        self.fail_safe_steps = 0
        """Steps resolved by the fail-safe over this stage's life (each also reported in ``last["fail_safe"]``)."""
        self.backward_seconds = 0.0
        """Wall time spent in the projection's adjoint (accumulates over backward passes)."""
        self.phase_seconds = dict.fromkeys(("detection", "geometry", "projection", "adjoint"), 0.0)
        """Wall time per phase, accumulated over steps (forward) and backward passes (``adjoint``): contact detection
        (swept BVH queries; the NumPy solver's also copies the contacts to the host), the contacts' normals and
        weights, the projection, and the projection's adjoint (the same as ``backward_seconds``)."""

    # -- response ------------------------------------------------------------------------------------------------
    def resolve(self, state_in: State, x_hat: wp.array, v_hat: wp.array, obstacle_start: wp.array,
                obstacle_end: wp.array, state_out: State, step: int, mass: wp.array,
                implicit_dt: float | None = None) -> None:
        """Write the collision-free positions and corrected velocities of the step into ``state_out``;
        ``obstacle_start`` and ``obstacle_end`` are the obstacle vertices at the step's start and end (empty without
        obstacles); ``mass``: the particles' lumped masses (the adjoint adds to ``mass.grad``). ``implicit_dt``: the
        length of the implicit step that gave x̂ = start + implicit_dt v̂, where it is not the time step (BDF2: 2/3 dt
        from its blend); the velocity change is (z − x̂) / implicit_dt, so the result keeps that relation."""
        model = self.model
        recording = active_tape() is not None and model.requires_grad
        inv_dt = model.scalar(1.0 / (self.dt if implicit_dt is None else implicit_dt))
        self._rows = []  # the NumPy path's contacts of each round so far (the fail-safe's zones)
        self._device_counts = (0, 0)  # the device path's: contacts in its lists, contacts just found
        self._round = 0  # the detection rounds run so far
        try:
            if self.options.collision.solver == "device":
                z = self._resolve_on_device(state_in, x_hat, obstacle_start, obstacle_end, step, mass, recording)
            else:
                z = self._resolve_zones(state_in, x_hat, obstacle_start, obstacle_end, step, mass, recording)
        except ContactCapacityError:
            raise
        except CollisionError as err:
            rows = self._contacts_so_far()
            z, report = self.fail_safe.resolve(self, state_in.particle_x, x_hat, obstacle_start, obstacle_end, mass,
                                               rows, recording, str(err), step)
            self.last = {"rounds": self._round, "contacts": len(rows), "zones": [], "fail_safe": report}
            self.fail_safe_steps += 1
        wp.launch(self.kernels.apply_projection, self.cloth_count, device=self.device,
                  inputs=[x_hat, v_hat, z, inv_dt], outputs=[state_out.particle_x, state_out.particle_v])

    def _contacts_so_far(self) -> np.ndarray:
        """The nodes of every contact the step's rounds found so far (m, 4), on the host: what the fail-safe
        groups into zones (a contact found twice is harmless)."""
        parts = list(self._rows)
        if self.options.collision.solver == "device":
            known, new = self._device_counts
            if known:
                parts.append(self._contact_nodes.numpy()[:known])
            parts.append(self.detector.nodes.numpy()[:new])
        return np.concatenate(parts) if parts else np.zeros((0, 4), dtype=np.int32)

    def _resolve_zones(self, state_in: State, x_hat: wp.array, obstacle_start: wp.array, obstacle_end: wp.array,
                       step: int, mass: wp.array, recording: bool) -> wp.array:
        """The projected positions z by the NumPy zone solver (``CollisionOptions.solver="numpy"``)."""
        start = self._gather(state_in.particle_x, obstacle_start, recording)
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
            end = self._gather(z, obstacle_end, recording)
            if round_index == 0:
                reference = end  # the unprojected end: the side of pairs touching at the start
            found = self.detector.detect(start, end, reference)
            self._rows.append(found.nodes)
            self._round = round_index + 1
            phases["detection"] += time.perf_counter() - t0
            # Every contact found is new: a pair found again is violated again (the projection leaves resolved
            # pairs exactly at the thickness, which proximity detection does not count), and its new
            # linearisation joins the old one.
            keys.update(row.tobytes() for row in found.nodes)
            if len(found) == 0:
                break
            if round_index == opt.collision.rounds:
                raise _rounds_error(step, opt.collision.rounds, len(found), len(keys), found.nodes[0],
                                    int(found.mode[0]), start, self.thickness)
            t0 = time.perf_counter()
            geometry.append(self._geometry(start, end, found, recording, step))
            t1 = time.perf_counter()
            phases["geometry"] += t1 - t0
            contacts = Contacts.concatenate([contacts, found])
            z, lam = self._project(x_hat, obstacle_end, mass, contacts, geometry, lam, recording, stats, step)
            phases["projection"] += time.perf_counter() - t1
            stats["rounds"] = round_index + 1
        stats["contacts"] = len(contacts)
        self.last = stats
        if len(contacts):
            self._check_projection_strain(x_hat, z, step)
        return z

    def _resolve_on_device(self, state_in: State, x_hat: wp.array, obstacle_start: wp.array, obstacle_end: wp.array,
                           step: int, mass: wp.array, recording: bool) -> wp.array:
        """The projected positions z with ``CollisionOptions(solver="device")``: contacts, their geometry, the
        projection and its adjoint stay on the device; each round reads back the contact count and the solver's
        status."""
        model = self.model
        k = self.kernels
        kr = device_round_kernels(model.scalar)
        vec3 = model.types.vec3
        n, N = self.cloth_count, self.node_count
        dev = self.device
        opt = self.options.collision
        phases = self.phase_seconds

        start = self._gather(state_in.particle_x, obstacle_start, recording)
        z = x_hat
        total = 0
        rounds = []  # (offset, count, normal, weight) of each round's contacts
        solution = None
        stats = {"rounds": 0, "contacts": 0, "zones": []}
        for round_index in range(opt.rounds + 1):
            t0 = time.perf_counter()
            end = self._gather(z, obstacle_end, recording)
            if round_index == 0:
                reference = end  # the unprojected end: the side of pairs touching at the start
            found = self.detector.detect_on_device(start, end, reference)
            self._round = round_index + 1
            self._device_counts = (total, found)
            phases["detection"] += time.perf_counter() - t0
            if found == 0:
                break
            if round_index == opt.rounds:
                raise _rounds_error(step, opt.rounds, found, total + found, self.detector.nodes.numpy()[0],
                                    int(self.detector.mode.numpy()[0]), start, self.thickness)
            t0 = time.perf_counter()
            if total == 0:  # the step's constants, once it has contacts: x^ and the obstacle in float64, masses
                positions = wp.empty(N, dtype=wp.vec3d, device=dev)
                wp.launch(kr.positions64, N, device=dev, inputs=[x_hat, obstacle_end, n], outputs=[positions],
                          record_tape=False)
                free = wp.empty(N, dtype=wp.int32, device=dev)
                inv_mass = wp.empty(N, dtype=wp.float64, device=dev)
                wp.launch(kr.inverse_mass, N, device=dev, inputs=[mass, model.particle_pin, n],
                          outputs=[free, inv_mass], record_tape=False)
            self._grow_contact_lists(total + found)
            normal = wp.empty(found, dtype=vec3, device=dev, requires_grad=recording)
            weight = wp.empty(found, dtype=model.types.vec4, device=dev, requires_grad=recording)
            det = self.detector
            found_arrays = [det.nodes[:found], det.mode[:found], det.t[:found], det.sign[:found]]
            if recording:  # the tape replays this launch after later detections reuse the buffers
                found_arrays = [wp.clone(a) for a in found_arrays]
            wp.launch(k.geometry, found, device=dev, inputs=[start, end, *found_arrays], outputs=[normal, weight])
            wp.copy(self._contact_nodes, det.nodes, dest_offset=4 * total, count=4 * found)
            bad = wp.full(1, found + 1, dtype=wp.int32, device=dev)
            wp.launch(kr.append_geometry, found, device=dev, inputs=[normal, weight, total],
                      outputs=[self._contact_normals, self._contact_weights, bad], record_tape=False)
            j = int(bad.numpy()[0]) - 1
            if j < found:
                raise CollisionError(
                    f"step {step}: a contact between nodes {det.nodes.numpy()[j].tolist()} has a degenerate normal; "
                    "a triangle or edge of the cloth or of an obstacle collapsed")
            rounds.append((total, found, normal, weight))
            t1 = time.perf_counter()
            phases["geometry"] += t1 - t0
            warm = total
            total += found
            if self._device is None or self._device.capacity < total:
                self._device = DeviceProjection(dev, N, max(2 * total, 1024))
                warm = 0  # a new buffer: the previous multipliers are gone
            solution = self._device.project(
                positions, free, inv_mass, self._contact_nodes, self._contact_weights, self._contact_normals, total,
                self.thickness, lam_init=None if solution is None or warm == 0 else self._device.lam, warm=warm,
                tol=opt.qp_tol, keep=recording)
            if solution.unbounded:
                raise CollisionError(
                    f"step {step}: no positions satisfy the {total} contacts of the device projection (its dual is "
                    "unbounded): cloth squeezed between obstacles closer than twice the thickness, or contacts that "
                    "contradict each other")
            if not solution.converged:
                raise CollisionError(
                    f"step {step}: the device projection of {total} contacts did not converge in "
                    f"{solution.iterations} iterations: a contact violated or an active one off by "
                    f"{solution.residual:.3e} m > tol {opt.qp_tol:.1e} (contacts that contradict each other stall it)")
            z = wp.empty(n, dtype=vec3, device=dev, requires_grad=recording)
            wp.launch(kr.cloth_positions, n, device=dev, inputs=[solution.z], outputs=[z], record_tape=False)
            if recording:
                self._record_device_adjoint(solution, x_hat, obstacle_end, mass, positions, free, inv_mass,
                                            list(rounds), z)
            phases["projection"] += time.perf_counter() - t1
            stats["rounds"] = round_index + 1
            stats["device"] = {"iterations": solution.iterations, "violation": solution.violation}
        stats["contacts"] = total
        self.last = stats
        self.last_projections = []
        if total:  # the guard's largest strain is the one value read back; the host names the edge only if it fails
            if self._edge_ends_device is None:
                self._edge_ends_device = wp.array(self._edge_ends.astype(np.int32), dtype=wp.int32, device=dev)
                self._edge_rest_device = wp.array(self._edge_rest, dtype=wp.float64, device=dev)
            largest = wp.full(1, -np.inf, dtype=wp.float64, device=dev)
            wp.launch(kr.largest_strain, len(self._edge_rest), device=dev,
                      inputs=[x_hat, z, self._edge_ends_device, self._edge_rest_device], outputs=[largest],
                      record_tape=False)
            if float(largest.numpy()[0]) > opt.max_projection_strain:
                self._check_projection_strain(x_hat, z, step)
        return z

    def _gather(self, cloth_x: wp.array, obstacle_x: wp.array, recording: bool) -> wp.array:
        """One array of every node's position: cloth particles first, then obstacle vertices."""
        out = wp.empty(self.node_count, dtype=self.model.types.vec3, device=self.device, requires_grad=recording)
        wp.launch(self.kernels.gather_nodes, self.node_count, device=self.device,
                  inputs=[cloth_x, obstacle_x, self.cloth_count], outputs=[out])
        return out

    def _grow_contact_lists(self, count: int) -> None:
        """The step's float64 contact lists (device solver), at least ``count`` long (kept across steps)."""
        have = 0 if self._contact_nodes is None else self._contact_nodes.shape[0]
        if have >= count:
            return
        size = max(2 * count, 1024)
        dev = self.device
        nodes = wp.zeros((size, 4), dtype=wp.int32, device=dev)
        normals = wp.zeros(size, dtype=wp.vec3d, device=dev)
        weights = wp.zeros(size, dtype=wp.vec4d, device=dev)
        if have:  # this step's earlier rounds
            wp.copy(nodes, self._contact_nodes)
            wp.copy(normals, self._contact_normals)
            wp.copy(weights, self._contact_weights)
        self._contact_nodes, self._contact_normals, self._contact_weights = nodes, normals, weights

    def _record_device_adjoint(self, solution, x_hat, obstacle_end, mass, positions, free, inv_mass, rounds,
                               z) -> None:
        """Record the adjoint of one device projection (kernels only): dL/dz -> x^, the contacts' normals and
        weights, the obstacle vertices and the masses."""
        model = self.model
        kr = device_round_kernels(model.scalar)
        n, N = self.cloth_count, self.node_count
        dev = self.device
        count = solution.rows.count
        nodes, normals = solution.rows.nodes, solution.rows.normal  # the solution's own copies
        weights = wp.clone(self._contact_weights[:count])
        device = self._device

        def adjoint():
            t0 = time.perf_counter()
            d_z = wp.empty(N, dtype=wp.vec3d, device=dev)
            wp.launch(kr.scaled_gradient, N, device=dev, inputs=[z.grad, inv_mass, n], outputs=[d_z])
            d_lam = device.adjoint_on_device(solution, d_z)
            grad_w = wp.empty(max(count, 1), dtype=wp.vec4d, device=dev)
            grad_n = wp.empty(max(count, 1), dtype=wp.vec3d, device=dev)
            grad_const = wp.zeros(N, dtype=wp.vec3d, device=dev)
            wp.launch(kr.push_contacts, count, device=dev,
                      inputs=[nodes, weights, normals, free, solution.z, d_z, solution.lam, d_lam],
                      outputs=[grad_w, grad_n, grad_const])
            obstacle_grad = obstacle_end.grad if obstacle_end.grad is not None else wp.zeros(
                max(N - n, 1), dtype=model.types.vec3, device=dev)
            mass_grad = mass.grad if mass.grad is not None else wp.zeros(n, dtype=model.scalar, device=dev)
            wp.launch(kr.position_gradients, N, device=dev,
                      inputs=[z.grad, d_z, inv_mass, grad_const, solution.z, positions, n],
                      outputs=[x_hat.grad, obstacle_grad, mass_grad])
            for offset, found, normal, weight in rounds:
                if normal.grad is not None:
                    wp.launch(kr.geometry_gradients, found, device=dev, inputs=[grad_n, grad_w, offset],
                              outputs=[normal.grad, weight.grad])
            seconds = time.perf_counter() - t0
            self.backward_seconds += seconds
            self.phase_seconds["adjoint"] += seconds

        record_adjoint(adjoint, arrays=[z])

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
        """Normals and weights of new contacts at their time of impact, from the positions they were found
        at (they stay frozen in later rounds, as in ARCSim's impact zones)."""
        model = self.model
        vec3, vec4 = model.types.vec3, model.types.vec4
        dev = self.device
        m = len(contacts)
        normal = wp.empty(m, dtype=vec3, device=dev, requires_grad=recording)
        weight = wp.empty(m, dtype=vec4, device=dev, requires_grad=recording)
        wp.launch(self.kernels.geometry, m, device=dev,
                  inputs=[start, end, wp.array(contacts.nodes, dtype=wp.int32, device=dev),
                          wp.array(contacts.mode, dtype=wp.int32, device=dev),
                          wp.array(contacts.t, dtype=wp.float64, device=dev),
                          wp.array(contacts.sign, dtype=wp.float64, device=dev)],
                  outputs=[normal, weight])
        ok = np.all(np.isfinite(normal.numpy()), axis=1) & np.all(np.isfinite(weight.numpy()), axis=1)
        if not ok.all():
            j = int(np.flatnonzero(~ok)[0])
            raise CollisionError(f"step {step}: a contact between nodes {contacts.nodes[j].tolist()} has a "
                                 "degenerate normal; a triangle or edge of the cloth or of an obstacle collapsed")
        return normal, weight

    def _project(self, x_hat, obstacle_end, mass, contacts: Contacts, geometry, lam, recording, stats, step):
        """Project x̂ onto all contacts found so far; on a tape, record the projection's adjoint.

        ``lam`` are the previous round's multipliers (its contacts come first). Returns z and the multipliers."""
        model = self.model
        normals = np.concatenate([g[0].numpy() for g in geometry]).astype(np.float64)
        weights = np.concatenate([g[1].numpy() for g in geometry]).astype(np.float64)
        try:
            result = projection.project(
                x_hat.numpy().astype(np.float64), mass.numpy().astype(np.float64), self.fixed,
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
                grad_z = z.grad.numpy().astype(np.float64)
                if not np.any(grad_z):  # a round whose z a later round or the fail-safe replaced
                    return
                t0 = time.perf_counter()
                gx, gw, gn, gob = projection.backward(result, grad_z, mode=mode)
                self.backward_seconds += time.perf_counter() - t0
                self.phase_seconds["adjoint"] += time.perf_counter() - t0
                _accumulate(x_hat, gx)
                _accumulate(mass, projection.mass_gradient(result, gx))
                for (normal, weight), lo, hi in zip(geometry, sizes[:-1], sizes[1:]):
                    _accumulate(normal, gn[lo:hi])
                    _accumulate(weight, gw[lo:hi])
                if obstacle_end.shape[0]:
                    _accumulate(obstacle_end, gob)

            record_adjoint(adjoint, arrays=[z])
        return z, result.lam


def _rounds_error(step: int, rounds: int, found: int, total: int, nodes: np.ndarray, mode: int, start: wp.array,
                  thickness: float) -> CollisionError:
    """The round limit's error, naming an unresolved contact; and, where that contact's primitives started the step
    inside the thickness (a cloth laid on an obstacle or on itself), saying so: from there the projection can have
    no consistent side to push them to."""
    gap = round(_start_gap(start.numpy().astype(np.float64)[nodes], mode), 12)  # below a picometre: rounding
    inside = ""
    if gap < thickness:
        inside = (f"; these nodes started the step {gap:.3g} m apart, inside the collision thickness {thickness:g} m, "
                  "where the contact has no consistent side: start the cloth at least the thickness away from "
                  "obstacles and from itself")
    return CollisionError(
        f"step {step}: the collision response did not converge in {rounds} rounds: {found} new contacts (of "
        f"{total}) still found, e.g. nodes {nodes.tolist()}{inside}; raise CollisionOptions.rounds, lower dt, or "
        "check for cloth trapped between obstacles")


def _start_gap(p: np.ndarray, mode: int) -> float:
    """Distance between a contact's primitives (positions p of its 4 nodes): vertex p[0] and triangle p[1:4]
    (mode VF_PLANE), or segments p[0:2] and p[2:4] (the edge-edge modes); the detection's own closest-point
    functions, evaluated on the host (error path only)."""
    a, b, c, d = (wp.vec3d(*row) for row in p)
    if mode == 0:  # VF_PLANE
        u, v, w = triangle_barycentric(a, b, c, d)
        return float(wp.length(a - (u * b + v * c + w * d)))
    s, u = segment_parameters(a, b, c, d, wp.float64(1.0e-12))
    return float(wp.length((a + s * (b - a)) - (c + u * (d - c))))


def _accumulate(array: wp.array, grad: np.ndarray) -> None:
    """array.grad += grad (a host array of the same shape)."""
    if array.grad is None:
        return
    g = array.grad.numpy()
    array.grad.assign((g + grad.reshape(g.shape)).astype(g.dtype))
