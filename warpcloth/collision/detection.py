"""Contact detection of the collision stage: BVH queries over swept boxes (kernels in kernels/collision.py)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from warpcloth.errors import ContactCapacityError
from warpcloth.kernels import projection as kp
from warpcloth.kernels.collision import collision_kernels
from warpcloth.model import Model
from warpcloth.obstacles import obstacle_points_numpy


@dataclass
class Contacts:
    """Contacts on the host, one row each (the modes: kernels/collision.py)."""

    nodes: np.ndarray
    """Node ids (m, 4) int32, cloth particles then obstacle vertices: vertex and face, or two edges."""
    mode: np.ndarray
    """VF_PLANE, EE_PLANE or EE_DIRECTION, (m,) int32."""
    t: np.ndarray
    """Time of impact in [0, 1] of the step (1 for proximity), (m,) float64."""
    sign: np.ndarray
    """Side of the normal, ±1 (unused by EE_DIRECTION), (m,) float64."""

    def __len__(self) -> int:
        return len(self.mode)

    @classmethod
    def empty(cls) -> Contacts:
        return cls(nodes=np.zeros((0, 4), dtype=np.int32), mode=np.zeros(0, dtype=np.int32),
                   t=np.zeros(0, dtype=np.float64), sign=np.zeros(0, dtype=np.float64))

    @classmethod
    def concatenate(cls, parts: Sequence[Contacts]) -> Contacts:
        return cls(nodes=np.concatenate([p.nodes for p in parts]), mode=np.concatenate([p.mode for p in parts]),
                   t=np.concatenate([p.t for p in parts]), sign=np.concatenate([p.sign for p in parts]))


def node_worlds(model: Model, obstacles: bool) -> np.ndarray:
    """The world of every node, (particle_count [+ obstacle_vertex_count with ``obstacles``],) int32."""
    worlds = [model.particle_world.numpy()]
    if obstacles:
        worlds.append(model.obstacle_world[model.obstacle_vertex_body.numpy()])
    return np.concatenate(worlds).astype(np.int32)


BVH_CONSTRUCTOR = {"cpu": "median", "cuda": "lbvh"}
"""The BVH build per device. Why the median split on the CPU: docs/decisions.md, "BVH build on the CPU"."""

MOTION_BLOCK_DIM = 128
"""Threads of the block that sums a world's cloth displacement on CUDA (on the CPU a block is one thread)."""


class PrimitiveSet:
    """Vertices, edges or triangles (node indices, one row each), their boxes and a BVH over them, grouped by world
    (``node_world``: each node's) so that a query meets only its own world's primitives."""

    def __init__(self, indices: np.ndarray, device, node_world: np.ndarray | None = None,
                 boxes: tuple[wp.array, wp.array] | None = None, rebuild: bool = True):
        self.count = len(indices)
        self.corners = indices.shape[1]
        self.indices = wp.array(indices.astype(np.int32), dtype=wp.int32, device=device)
        if boxes is None:
            boxes = (wp.zeros(self.count, dtype=wp.vec3, device=device),
                     wp.zeros(self.count, dtype=wp.vec3, device=device))
        self.lowers, self.uppers = boxes
        """The boxes (count,) vec3: their own, or views into a detector's (``boxes``)."""
        self.bvh: wp.Bvh | None = None
        self._constructor = BVH_CONSTRUCTOR["cpu" if self.indices.device.is_cpu else "cuda"]
        self.rebuild = rebuild
        self.groups = None
        if node_world is not None and self.count and node_world.max() > 0:
            self.groups = wp.array(node_world[indices[:, 0]], dtype=wp.int32, device=device)

    def update_bvh(self) -> None:
        """Build the BVH over the current boxes, then rebuild it in place (the same id) or, ``rebuild`` False, refit."""
        if self.bvh is None:
            self.bvh = wp.Bvh(self.lowers, self.uppers, groups=self.groups, constructor=self._constructor)
        elif self.rebuild:
            self.bvh.rebuild(self._constructor)
        else:
            self.bvh.refit()


class RowSort:
    """A stable radix sort of up to ``capacity`` rows by keys below ``key_bound`` (ValueError beyond int64): rows
    appended through an atomic counter come out in one order on both devices."""

    def __init__(self, capacity: int, key_bound: int, device, what: str = "rows"):
        m = max(int(capacity), 1)
        if key_bound >= 2**63:
            raise ValueError(f"the sort keys of the {what} ({key_bound}) do not fit in int64: a model this large "
                             "cannot be simulated as one")
        self.keys = wp.zeros(2 * m, dtype=wp.int64, device=device)
        self.values = wp.zeros(2 * m, dtype=wp.int32, device=device)
        self.order = self.values[:m]
        """After :meth:`sort`: the row in each sorted slot."""
        self.bits = max(int(key_bound - 1).bit_length(), 1)  # passes over the bits the keys use only
        if self.keys.device.is_cuda:
            # the sort's scratch sized for every count to come, outside any graph capture: growing it inside one
            # breaks the CUDA context (https://github.com/NVIDIA/warp/issues/1373)
            wp.utils.radix_sort_pairs(self.keys, self.values, m, end_bit=self.bits)

    def sort(self, count: int) -> None:
        """Sort the first ``count`` rows by key (``values`` holds each row's index on entry)."""
        if count:
            wp.utils.radix_sort_pairs(self.keys, self.values, int(count), end_bit=self.bits)


FOUND, DEGENERATE, FAILED, STRAINED = kp.FOUND, kp.DEGENERATE, kp.FAILED, kp.STRAINED
"""Slots of :attr:`ContactDetector.flags`: contacts found (counted past the capacity); 1 + the round's first contact
with a degenerate normal (count + 1: none); 1 where the last projection failed; 1 where it overstretched an edge."""


class ContactDetector:
    """Vertex-face and edge-edge contacts (CCD and proximity) between node positions (cloth particles, then obstacle
    vertices) at a step's start and end. ``thickness``: δ [m]; ``capacity``: most contacts one :meth:`detect` may
    find; ``obstacles``, ``self_collision``: detect cloth–obstacle, cloth–cloth contacts; ``rebuild_bvh``: rebuild
    the BVHs at each detection, else refit them (CollisionOptions.bvh)."""

    def __init__(self, model: Model, *, thickness: float, capacity: int, obstacles: bool, self_collision: bool,
                 rebuild_bvh: bool = True):
        self.device = dev = model.device
        self.thickness = float(thickness)
        self.capacity = int(capacity)
        self.kernels = collision_kernels(model.scalar)
        n = model.particle_count
        worlds = node_worlds(model, obstacles)
        self.node_world = wp.array(worlds, dtype=wp.int32, device=dev)
        """The world of every node (cloth particles, then obstacle vertices), (nodes,) int32."""
        self.node_world_host = worlds
        self.grouped = int(model.world_count > 1)
        rows = [model.triangles_np, np.arange(n)[:, None], model.edge_indices.numpy()]
        if obstacles:
            V = model.obstacle_vertex_count
            rows += [model.obstacle_tri_indices.numpy() + n, np.arange(n, n + V)[:, None],
                     model.obstacle_edge_indices.numpy() + n]
        # Every set's swept boxes in one launch (primitive_bounds_all): all primitives as rows of three corners, a
        # vertex's and an edge's padded by repeating their last corner (the same box: min and max are exact), and
        # each set's boxes a view into the one array of them.
        rows = [np.asarray(r, dtype=np.int32).reshape(len(r), -1) for r in rows]
        self._prims = wp.array(np.concatenate([np.pad(r, ((0, 0), (0, 3 - r.shape[1])), mode="edge") if len(r) else
                                               np.zeros((0, 3), dtype=np.int32) for r in rows]),
                               dtype=wp.int32, device=dev)
        self._particle_start = wp.array(np.asarray(model.world_particle_start, dtype=np.int32), dtype=wp.int32,
                                        device=dev)
        self._shift = wp.zeros(model.world_count, dtype=wp.vec3, device=dev)
        # each world's cloth's mean displacement over the step: the boxes' frame
        self._lowers = wp.zeros(max(self._prims.shape[0], 1), dtype=wp.vec3, device=dev)
        self._uppers = wp.zeros(max(self._prims.shape[0], 1), dtype=wp.vec3, device=dev)
        ends = [int(e) for e in np.cumsum([0] + [len(r) for r in rows])]
        sets = [PrimitiveSet(r, dev, worlds, boxes=(self._lowers[lo:hi], self._uppers[lo:hi]), rebuild=rebuild_bvh)
                for r, lo, hi in zip(rows, ends[:-1], ends[1:])]
        for prims, lo in zip(sets, ends[:-1]):
            prims.offset = lo  # its first primitive's row in self._prims (and box in self._lowers, self._uppers)
        cloth_tris, cloth_vertices, cloth_edges = sets[:3]
        self._sets = sets
        # (query set, target set, kind, skip-incident/same-set flag)
        self._queries: list[tuple[PrimitiveSet, PrimitiveSet, str, int]] = []
        if obstacles:
            obst_tris, obst_vertices, obst_edges = sets[3:]
            self._queries += [(cloth_vertices, obst_tris, "vf", 0), (obst_vertices, cloth_tris, "vf", 0),
                              (cloth_edges, obst_edges, "ee", 0)]
        if self_collision:
            self._queries += [(cloth_vertices, cloth_tris, "vf", 1), (cloth_edges, cloth_edges, "ee", 1)]
        # Every query in one launch (kernels/collision.py query_all): the queries that can find something, their
        # rows one after another (a vertex as (v, v), an edge as (a, b)), and each one's first thread, boxes, target
        # primitives, kind and flag; its BVH's id once the BVHs are built (the first detection).
        live = [q for q in self._queries if q[0].count and q[1].count]
        self._live_queries = live
        query_rows = [np.repeat(rows_of, 2, axis=1) if rows_of.shape[1] == 1 else rows_of
                      for rows_of in (rows[sets.index(q[0])] for q in live)]
        self._query_rows = wp.array(np.concatenate(query_rows) if live else np.zeros((0, 2), dtype=np.int32),
                                    dtype=wp.int32, device=dev)
        self._query_start = wp.array(np.cumsum([0] + [q[0].count for q in live]), dtype=int, device=dev)
        self._query_table = [wp.array(values, dtype=int, device=dev) for values in (
            [q[0].offset for q in live], [q[1].offset for q in live], [int(q[2] == "vf") for q in live],
            [q[3] for q in live])]
        self._bvh_ids: wp.array | None = None
        self.skip = wp.zeros(1, dtype=wp.int32, device=dev)
        """Detection finds nothing while ``skip[0]`` is not 0 (the Simulator's failure flag: diverged positions)."""
        self._world_modes: dict[bytes, wp.array] = {}  # set_world_modes: one array per pattern, never written again
        self.set_world_modes(np.zeros(model.world_count, dtype=np.int32))
        self.flags = wp.zeros(4, dtype=wp.int32, device=dev)
        """The round flags, (4,) int32 (FOUND, DEGENERATE, FAILED, STRAINED)."""
        self._count, self.degenerate, self.failed, self.strained = (self.flags[i:i + 1] for i in range(4))
        self.last_flags = np.zeros(4, dtype=np.int64)
        # the contacts as the queries append them, and sorted by their keys (query thread, side): each query's
        # contacts in the queries' order, one order on both devices (RowSort)
        self._appended = (wp.zeros((self.capacity, 4), dtype=wp.int32, device=dev),
                          wp.zeros(self.capacity, dtype=wp.int32, device=dev),
                          wp.zeros(self.capacity, dtype=wp.float64, device=dev),
                          wp.zeros(self.capacity, dtype=wp.float64, device=dev))
        self._sort = RowSort(self.capacity, 2 * max(self._query_rows.shape[0], 1), dev)
        self._nodes = wp.zeros((self.capacity, 4), dtype=wp.int32, device=dev)
        self._mode = wp.zeros(self.capacity, dtype=wp.int32, device=dev)
        self._t = wp.zeros(self.capacity, dtype=wp.float64, device=dev)
        self._sign = wp.zeros(self.capacity, dtype=wp.float64, device=dev)

    def set_world_modes(self, modes) -> None:
        """Set :attr:`world_mode`, each world's for the detections that follow: 0 the full thickness, 1 keep start gaps
        (a pair starting inside the thickness is a contact only where it comes closer), -1 skip the world."""
        # Never assigned into: the tape's contact-geometry launches keep the modes array of their try for the
        # backward pass. One array per pattern of modes, made the first time it is asked for and never written
        # again, so a step reuses it without allocating (the common pattern, all worlds at full thickness, is made
        # here at construction).
        modes = np.ascontiguousarray(modes, dtype=np.int32)
        array = self._world_modes.get(modes.tobytes())
        if array is None:
            array = self._world_modes[modes.tobytes()] = wp.array(modes, dtype=wp.int32, device=self.device)
        self.world_mode = array

    def detect(self, x0: wp.array, x1: wp.array, reference: wp.array | None = None) -> Contacts:
        """Contacts between node positions ``x0`` (start) and ``x1`` (end) on the host; ``reference`` (None: ``x1``)
        gives the side of a pair touching at the start.

        Raises:
            ContactCapacityError: more contacts than ``capacity``.
        """
        count = self.detect_on_device(x0, x1, reference)
        return Contacts(nodes=self.nodes.numpy()[:count].copy(), mode=self.mode.numpy()[:count].copy(),
                        t=self.t.numpy()[:count].copy(), sign=self.sign.numpy()[:count].copy())

    @property
    def nodes(self) -> wp.array:
        """The last detection's contacts' node ids (first ``count`` rows), (capacity, 4) int32 on the device."""
        return self._nodes

    @property
    def mode(self) -> wp.array:
        """... their modes (kernels/collision.py), (capacity,) int32."""
        return self._mode

    @property
    def t(self) -> wp.array:
        """... their times of impact, (capacity,) float64."""
        return self._t

    @property
    def sign(self) -> wp.array:
        """... their normals' sides, (capacity,) float64."""
        return self._sign

    def detect_on_device(self, x0: wp.array, x1: wp.array, reference: wp.array | None = None, *,
                         expected: int | None = None) -> int | None:
        """:meth:`detect` into the device buffers (:attr:`nodes` ...); returns the count, its one read :attr:`flags`.
        With ``expected`` (a captured step's plan) nothing is read: that many rows are sorted and None returned."""
        k = self.kernels
        half = 0.5 * self.thickness
        if self._prims.shape[0]:
            wp.launch_tiled(k.world_motion, dim=[self._shift.shape[0]], block_dim=MOTION_BLOCK_DIM, device=self.device,
                            inputs=[x0, x1, self._particle_start], outputs=[self._shift], record_tape=False)
            wp.launch(k.primitive_bounds, self._prims.shape[0], device=self.device,
                      inputs=[x0, x1, self._shift, self.node_world, self._prims, 3, half],
                      outputs=[self._lowers, self._uppers], record_tape=False)
        self._count.zero_()
        reference = x1 if reference is None else reference
        refitted = set()
        for _query, target, _kind, _flag in self._live_queries:
            if id(target) not in refitted:
                target.update_bvh()
            refitted.add(id(target))
        if self._live_queries:
            if self._bvh_ids is None:  # the BVHs are refitted in place from now on: their ids stay
                self._bvh_ids = wp.array(np.array([q[1].bvh.id for q in self._live_queries], dtype=np.uint64),
                                         dtype=wp.uint64, device=self.device)
            query_offset, target_offset, vertex_face, same = self._query_table
            wp.launch(k.query_all, self._query_rows.shape[0], device=self.device,
                      inputs=[x0, x1, reference, self._query_rows, self._prims, self._lowers, self._uppers,
                              self._query_start, query_offset, self._bvh_ids, target_offset, vertex_face, same,
                              wp.float64(self.thickness), self.world_mode, self.capacity, self.node_world,
                              self.grouped, self.skip],
                      outputs=[self._count, self._sort.keys, self._sort.values, *self._appended], record_tape=False)
        if expected is not None:
            self._sort_found(min(int(expected), self.capacity))
            return None
        count = int(self.read_flags()[FOUND])
        if count > self.capacity:
            raise ContactCapacityError(
                f"contact buffer overflow: {count} contacts found but contact_capacity is {self.capacity}; "
                f"raise CollisionOptions.contact_capacity to at least {count}")
        self._sort_found(count)
        return count

    def _sort_found(self, count: int) -> None:
        if count and self._live_queries:
            self._sort.sort(count)
            wp.launch(self.kernels.sort_found, count, device=self.device, inputs=[self._sort.order, *self._appended],
                      outputs=[self._nodes, self._mode, self._t, self._sign], record_tape=False)

    def read_flags(self) -> np.ndarray:
        """Read :attr:`flags` (the one read of a detection or of a projection's checks) into :attr:`last_flags`."""
        self.last_flags = self.flags.numpy().astype(np.int64)
        return self.last_flags

    def check_start_outside(self, model: Model) -> None:
        """Raise ValueError if a cloth particle starts inside a closed obstacle (the response cannot fix that)."""
        points = obstacle_points_numpy(model, 0.0)
        x0 = model.particle_x0
        ts = model.obstacle_tri_start
        for b in range(model.obstacle_count):
            local = model.obstacle_triangles_np[ts[b]: ts[b + 1]]
            edges = np.sort(np.concatenate([local[:, [0, 1]], local[:, [1, 2]], local[:, [2, 0]]]), axis=1)
            _, uses = np.unique(edges, axis=0, return_counts=True)
            if len(local) == 0 or np.any(uses != 2):
                continue  # open surface (plane, funnel): no inside
            mesh = wp.Mesh(points=wp.array(points, dtype=wp.vec3, device=self.device),
                           indices=wp.array(local.reshape(-1), dtype=wp.int32, device=self.device))
            inside = wp.zeros(model.particle_count, dtype=wp.int32, device=self.device)
            wp.launch(self.kernels.inside_mesh, model.particle_count, device=self.device,
                      inputs=[mesh.id, x0, 1.0e6], outputs=[inside], record_tape=False)
            bad = np.flatnonzero(inside.numpy() & (model.particle_world.numpy() == model.obstacle_world[b]))
            if bad.size:
                p = int(bad[0])
                raise ValueError(
                    f"cloth {model.particle_name(p)} at {x0.numpy()[p].tolist()} starts inside obstacle "
                    f"{model.obstacle_names[b]!r} ({bad.size} particles inside); move the cloth or the obstacle")
