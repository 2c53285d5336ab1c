"""Proximity repulsion and friction as forces of the implicit step (the model: kernels/proximity.py)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warpcloth.collision.detection import PrimitiveSet, RowSort, node_worlds
from warpcloth.errors import ContactCapacityError
from warpcloth.kernels.geometry import world_starts
from warpcloth.kernels.proximity import FRICTION_SWEEPS, proximity_kernels
from warpcloth.model import Model, State
from warpcloth.tape import StepArrays, active_tape, record_adjoint


@dataclass
class ProximityPairs:
    """The pairs of one step, as the linear solver applies them: A_ij += weight_i weight_j stiffness."""

    count: int
    """The pair kernels' launch size (host): the number of pairs, or a captured step's budget."""
    nodes: wp.array
    """Node ids of each pair, (>= count, 4) int32 (cloth particles, then obstacle vertices)."""
    weights: wp.array
    """Weight of each node, 0 where it is not a free cloth particle, (>= count,) vec4."""
    stiffness: wp.array
    """The pair's 3x3 block K (dt^2 h n n^T) [kg], (>= count,) mat33."""
    world_start: wp.array
    """First pair of each world, and the count, (world_count + 1,) int32 (pairs sorted by world)."""
    held: wp.array
    """The number of pairs, (1,) int32 on the device."""
    inputs: object = None
    """What the pair kernels read (kernels/proximity.py PairInputs); None without pairs."""


class ProximityForces:
    """Adds the repulsion and friction of the pairs within twice the repulsion thickness at a step's start (taped:
    a fixed pair set) to its system. Why matrix-free: docs/decisions.md, "Proximity cross blocks matrix-free".

    Args:
        capacity: most pairs one step may have (0: 8 per cloth particle and obstacle vertex).
        rebuild_bvh: rebuild the BVHs at each detection, else refit them (CollisionOptions.bvh)."""

    def __init__(self, model: Model, dt: float, *, capacity: int = 0, rebuild_bvh: bool = True):
        settings = model.collision
        self.model = model
        self.dt = float(dt)
        self.device = dev = model.device
        self.kernels = proximity_kernels(model.scalar)
        self.thickness = float(settings.repulsion_thickness)
        n = model.particle_count
        obstacles = settings.obstacles and model.obstacle_count > 0
        V = model.obstacle_vertex_count if obstacles else 0
        self.cloth_count, self.node_count = n, n + V
        self.capacity = int(capacity or 8 * (n + V))
        scalar = model.scalar
        worlds = node_worlds(model, obstacles)
        self._node_world = wp.array(worlds, dtype=wp.int32, device=dev)
        self.pair_world_start = wp.zeros(model.world_count + 1, dtype=wp.int32, device=dev)
        """First pair of each world of the last detection, and the count, (world_count + 1,) int32."""
        cloth_tris = PrimitiveSet(model.triangles_np, dev, worlds, rebuild=rebuild_bvh)
        cloth_edges = PrimitiveSet(model.edge_indices.numpy(), dev, worlds, rebuild=rebuild_bvh)
        cloth_vertices = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=dev)
        # the primitives' areas, for the pairs' stiffness (kernels/proximity.py): the cloth's rest areas; obstacles
        # count as infinite, so a pair takes its cloth primitive's area (docs/decisions.md, "Repulsion stiffness
        # from the cloth's area")
        tri_area = model.tri_area.numpy().astype(np.float64)
        node_area = wp.array(np.concatenate([model.particle_area.numpy(), np.full(V, np.inf)]), dtype=scalar,
                                   device=dev)
        tri_area_wp = wp.array(tri_area, dtype=scalar, device=dev)
        cloth_edge_area = wp.array(_edge_area(model.triangles_np, tri_area, model.edge_indices.numpy()),
                                   dtype=scalar, device=dev)
        # (query rows, target set, kind, row areas, target areas, same set): query rows are node ids (VF, rows'
        # areas by node id) or edges (EE)
        self._queries = []
        if obstacles:
            obstacle_tris = PrimitiveSet(model.obstacle_tri_indices.numpy() + n, dev, worlds, rebuild=rebuild_bvh)
            obstacle_edges = PrimitiveSet(model.obstacle_edge_indices.numpy() + n, dev, worlds, rebuild=rebuild_bvh)
            infinite = wp.array(np.full(max(obstacle_tris.count, obstacle_edges.count), np.inf), dtype=scalar,
                                device=dev)
            self._queries += [
                (cloth_vertices, obstacle_tris, "vf", node_area, infinite, 0),
                (wp.array(np.arange(n, n + V, dtype=np.int32), dtype=wp.int32, device=dev), cloth_tris, "vf",
                 node_area, tri_area_wp, 0),
                (cloth_edges.indices, obstacle_edges, "ee", cloth_edge_area, infinite, 0),
            ]
        if settings.self_collision:
            self._queries += [(cloth_vertices, cloth_tris, "vf", node_area, tri_area_wp, 0),
                              (cloth_edges.indices, cloth_edges, "ee", cloth_edge_area, cloth_edge_area, 1)]
        self._targets = list({id(q[1]): q[1] for q in self._queries}.values())  # each BVH refitted once a step
        # the targets' boxes in one launch: their rows of three corners (an edge's padded by repeating its last:
        # the same box), each target's boxes a view into the one array of them
        rows = [np.pad(t.indices.numpy(), ((0, 0), (0, 3 - t.corners)), mode="edge") for t in self._targets]
        self._target_rows = wp.array(np.concatenate(rows) if rows else np.zeros((0, 3), dtype=np.int32),
                                     dtype=wp.int32, device=dev)
        size = max(self._target_rows.shape[0], 1)
        self._lowers, self._uppers = (wp.zeros(size, dtype=wp.vec3, device=dev) for _ in range(2))
        ends = [int(e) for e in np.cumsum([0] + [t.count for t in self._targets])]
        for t, lo, hi in zip(self._targets, ends[:-1], ends[1:]):
            t.lowers, t.uppers = self._lowers[lo:hi], self._uppers[lo:hi]
        self._count = wp.zeros(1, dtype=wp.int32, device=dev)  # pairs found (may pass the capacity)
        self._count_host = self._count.numpy() if dev.is_cpu else None
        self._held = wp.zeros(1, dtype=wp.int32, device=dev)  # pairs held (hold_pairs)
        self._arrays = StepArrays(dev)  # the positions, velocities and friction terms of a step
        self.spill = wp.zeros(1, dtype=wp.int32, device=dev)
        """Raised (1) by a captured step that found more pairs than its budget."""
        # the pairs as found, and sorted by their keys (world, query row, target: RowSort), or a taped step's own
        # copies: each world's pairs in one order on both devices, those a model of that world alone finds
        self._nodes = wp.zeros((self.capacity, 4), dtype=wp.int32, device=dev)
        self._kind = wp.zeros(self.capacity, dtype=wp.int32, device=dev)
        self._pair_area = wp.zeros(self.capacity, dtype=scalar, device=dev)
        self._row_starts = [int(r) for r in np.cumsum([0] + [q[0].shape[0] for q in self._queries])]
        self._target_count = max([q[1].count for q in self._queries] + [1])
        self._world_span = max(self._row_starts[-1], 1) * self._target_count  # the keys of one world
        self._sort = RowSort(self.capacity, model.world_count * self._world_span, dev,
                             "proximity pairs (worlds x query rows x target primitives)")
        self._sorted = (wp.zeros((self.capacity, 4), dtype=wp.int32, device=dev),
                        wp.zeros(self.capacity, dtype=wp.int32, device=dev),
                        wp.zeros(self.capacity, dtype=scalar, device=dev))
        self._weights = wp.empty(self.capacity, dtype=model.types.vec4, device=dev)
        self._stiffness = wp.empty(self.capacity, dtype=model.types.mat33, device=dev)
        free = np.zeros(n + V, dtype=np.int32)
        free[:n] = model.particle_pin.numpy() < 0
        self._free = wp.array(free, dtype=wp.int32, device=dev)
        self.last_count = 0
        """Pairs found in the last uncaptured step."""
        self.budget: int | None = None
        """None: a step reads its pair count; an int (while captured): it holds up to this many pairs (0: no pair
        kernel runs), and :attr:`spill` tells whether it found more."""
        self._per_node = wp.zeros(n + V, dtype=wp.int32, device=dev)

    @property
    def friction(self) -> bool:
        """Whether steps apply friction: on a differentiable model always, else where a coefficient is > 0 now."""
        return self.model.requires_grad or bool(np.any(self.model.contact_friction.numpy() > 0.0))

    @staticmethod
    def needed(model: Model) -> bool:
        """Whether a model's repulsion or friction can act (an absent term costs nothing)."""
        if model.collision is None:
            return False
        return bool(np.any(model.contact_repulsion_stiffness.numpy() > 0.0))

    def detect(self, x: wp.array) -> int:
        """Find the pairs among node positions ``x`` (cloth particles, then obstacle vertices), sorted by world;
        returns the pair kernels' launch size (:attr:`ProximityPairs.count`).

        Raises:
            ContactCapacityError: more pairs than the capacity."""
        k = self.kernels
        m = self.model
        radius = 2.0 * self.thickness
        if self._target_rows.shape[0]:
            wp.launch(k.primitive_boxes, self._target_rows.shape[0], device=self.device,
                      inputs=[x, self._target_rows, radius], outputs=[self._lowers, self._uppers], record_tape=False)
        for prims in self._targets:
            if prims.count:
                prims.update_bvh()
        self._count.zero_()
        search = k.PairSearch()
        search.offsets, search.columns, search.cloth_count = m.bsr_offsets, m.bsr_columns, self.cloth_count
        search.radius = m.scalar(radius)
        search.count, search.pair_nodes, search.pair_kind = self._count, self._nodes, self._kind
        search.pair_area = self._pair_area
        search.node_world, search.grouped = self._node_world, int(m.world_count > 1)
        search.keys, search.slot_of = self._sort.keys, self._sort.values
        search.row_count, search.target_count = self._row_starts[-1], self._target_count
        for (rows, target, kind, row_area, target_area, same), first in zip(self._queries, self._row_starts):
            if rows.shape[0] == 0 or target.count == 0:
                continue
            if kind == "vf":
                wp.launch(k.vertex_face_pairs, rows.shape[0], device=self.device,
                          inputs=[target.bvh.id, x, rows, target.indices, row_area, target_area, search, first],
                          record_tape=False)
            else:
                wp.launch(k.edge_edge_pairs, rows.shape[0], device=self.device,
                          inputs=[target.bvh.id, x, rows, target.indices, row_area, target_area, same, search,
                                  first],
                          record_tape=False)
        if self.budget is not None:  # a captured step: no read; sort_pairs raises spill where it found more
            size = self.budget
        else:
            size = self._read_count()
            if size > self.capacity:
                raise ContactCapacityError(
                    f"proximity pair buffer overflow: {size} pairs found but the capacity is {self.capacity}; "
                    f"raise CollisionOptions.contact_capacity to at least {size}")
            self.last_count = size
        # the pairs held, sorted by key (a world's pairs are those a model of that world alone finds, in the same
        # order, on either device), and each world's first pair (each world's CG reads its own range)
        wp.launch(k.hold_pairs, max(size, 1), device=self.device, inputs=[self._count, size, m.world_count],
                  outputs=[self._sort.keys, self._sort.values, self._held, self.spill, self.pair_world_start],
                  record_tape=False)
        self._sort.sort(size)
        if m.world_count > 1:
            wp.launch(world_starts, m.world_count + 1, device=self.device,
                      inputs=[self._sort.keys, self._held, self._world_span], outputs=[self.pair_world_start],
                      record_tape=False)
        return size

    def _read_count(self) -> int:
        return int((self._count_host if self._count_host is not None else self._count.numpy())[0])

    def assemble(self, state_in: State, obstacle_start: wp.array, obstacle_end: wp.array, pin_dv: wp.array,
                 dv: wp.array, values: wp.array, rhs: wp.array, recording: bool,
                 implicit_dt: float | None = None) -> ProximityPairs:
        """Find the step's pairs, add their terms to ``values`` (diagonal blocks) and ``rhs`` (taped: with their
        adjoint) and return them for the cross blocks. ``obstacle_start``, ``obstacle_end``: the obstacle vertices at
        the step's start and end; ``implicit_dt``: the implicit step where it is not ``dt`` (BDF2: 2/3 dt)."""
        model = self.model
        k = self.kernels
        dev = self.device
        n, N = self.cloth_count, self.node_count
        vec3 = model.types.vec3
        x = self._arrays.empty("x", N, vec3, recording)
        velocity = self._arrays.empty("velocity", N, vec3, recording)
        wp.launch(k.node_state, N, device=dev,
                  inputs=[state_in.particle_x, state_in.particle_v, pin_dv, model.particle_pin, obstacle_start,
                          obstacle_end, model.scalar(1.0 / self.dt), n],
                  outputs=[x, velocity])
        count = self.detect(x)
        nodes, kind, area = self._nodes, self._kind, self._pair_area
        weights, stiffness = self._weights, self._stiffness
        world_start, held = self.pair_world_start, self._held
        if count == 0:
            return ProximityPairs(0, nodes, weights, stiffness, world_start, held)
        if recording:  # the backward pass reads this step's pairs: arrays that later steps do not overwrite
            nodes = wp.empty((count, 4), dtype=wp.int32, device=dev)
            kind = wp.empty(count, dtype=wp.int32, device=dev)
            area = wp.empty(count, dtype=model.scalar, device=dev)
            weights = wp.empty(count, dtype=model.types.vec4, device=dev)
            stiffness = wp.empty(count, dtype=model.types.mat33, device=dev)
            world_start, held = wp.clone(world_start), wp.clone(held)
        else:
            nodes, kind, area = self._sorted
        wp.launch(k.gather_pairs, count, device=dev, inputs=[self._sort.order, held, self._nodes, self._kind,
                                                             self._pair_area],
                  outputs=[nodes, kind, area], record_tape=False)
        pairs = ProximityPairs(count, nodes, weights, stiffness, world_start, held)
        inputs = self.pair_inputs(x, velocity, nodes, kind, area, held, implicit_dt)
        pairs.inputs = inputs
        wp.launch(k.assemble_pairs, count, device=dev, inputs=[inputs, model.particle_diag_slot],
                  outputs=[values, rhs, weights, stiffness], record_tape=False)
        if recording:
            # made when recorded, held by the closure (a captured backward pass replays these launches), and the
            # recording tape's adjoint struct, so that tape.zero() zeroes the gradients it reaches
            phi = wp.zeros(1, dtype=model.scalar, device=dev)
            seed = wp.ones(1, dtype=model.scalar, device=dev)
            adj_inputs = active_tape().get_adjoint(inputs)

            def adjoint():
                wp.launch(k.pairs_potential, count, device=dev, inputs=[inputs, rhs.grad, dv], outputs=[phi],
                          adj_inputs=[adj_inputs, None, None], adj_outputs=[seed],
                          adjoint=True, record_tape=False)

            record_adjoint(adjoint, arrays=[rhs, dv])
        return pairs

    def apply_friction(self, pairs: ProximityPairs, dv: wp.array, mass: wp.array, recording: bool) -> wp.array:
        """The solve's velocity change ``dv`` plus the pairs' friction, as a new array; ``mass``: the lumped masses.
        Taped: gradients reach dv, the pairs' positions and velocities, the masses, μ and the repulsion stiffness."""
        model = self.model
        k = self.kernels
        dev = self.device
        n, N = self.cloth_count, self.node_count
        scalar, vec3 = model.scalar, model.types.vec3
        count, p = pairs.count, pairs.inputs
        arrays = self._arrays
        inv_mass = arrays.empty("inv_mass", N, scalar, recording)
        wp.launch(k.inverse_mass, N, device=dev, inputs=[mass, self._free, n], outputs=[inv_mass])
        against_obstacles = arrays.zeros("against_obstacles", n, vec3, recording)
        if self.node_count > n:
            load = arrays.zeros("load", n, scalar, recording)
            push, motion = (arrays.zeros(name, n, vec3, recording) for name in ("push", "motion"))
            wp.launch(k.obstacle_friction_loads, count, device=dev, inputs=[p], outputs=[load, push, motion])
            wp.launch(k.obstacle_friction, n, device=dev, inputs=[p, dv, load, push, motion, inv_mass],
                      outputs=[against_obstacles])
        between_cloth = arrays.zeros("between_cloth", n, vec3, recording)
        if self.model.collision.self_collision:
            self._per_node.zero_()
            wp.launch(k.cloth_pair_counts, count, device=dev, inputs=[p, self._per_node], record_tape=False)
            per_node = wp.clone(self._per_node) if recording else self._per_node
            impulse = arrays.zeros("impulse", count, vec3, recording)
            for sweep in range(FRICTION_SWEEPS):  # taped, each sweep in new arrays (the tape keeps every one);
                # untaped, two pairs of arrays in turn: a sweep reads the one before's
                change = arrays.zeros(f"change{sweep % 2}", n, vec3, recording)
                swept = arrays.empty(f"swept{sweep % 2}", count, vec3, recording)
                wp.launch(k.friction_sweep, count, device=dev,
                          inputs=[p, dv, against_obstacles, between_cloth, impulse, inv_mass, per_node],
                          outputs=[swept, change])
                between_cloth, impulse = change, swept
        out = arrays.empty("out", n, vec3, recording)
        wp.launch(k.add_friction, n, device=dev, inputs=[dv, against_obstacles, between_cloth], outputs=[out])
        return out

    def pair_inputs(self, x: wp.array, velocity: wp.array, nodes: wp.array, kind: wp.array, area: wp.array,
                    held: wp.array, implicit_dt: float | None = None):
        """The pair kernels' inputs; ``held``: the pair count, (1,) int32; ``implicit_dt`` as in :meth:`assemble`."""
        model = self.model
        p = self.kernels.PairInputs()
        p.nodes, p.kind, p.x, p.velocity, p.free, p.area = nodes, kind, x, velocity, self._free, area
        p.count = held
        p.stiffness, p.friction = model.contact_repulsion_stiffness, model.contact_friction
        p.cloth_count = self.cloth_count
        p.thickness = model.scalar(self.thickness)
        p.dt = model.scalar(self.dt if implicit_dt is None else implicit_dt)
        return p


def _edge_area(triangles: np.ndarray, tri_area: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Each edge's area: a third of its one or two triangles' [m^2] (ARCSim's, for edge-edge repulsion)."""
    row = {(int(a), int(b)): i for i, (a, b) in enumerate(np.sort(edges, axis=1))}
    area = np.zeros(len(edges))
    for c in range(3):
        ends = np.sort(np.stack([triangles[:, c], triangles[:, (c + 1) % 3]], axis=1), axis=1)
        idx = np.array([row[(int(a), int(b))] for a, b in ends], dtype=np.int64)
        np.add.at(area, idx, tri_area / 3.0)
    return area
