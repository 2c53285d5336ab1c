"""The multigrid preconditioner's aggregation hierarchy, built once per model on the host from the mesh; the kernels
form P^T A P each solve. Why: docs/decisions.md, "Multigrid aggregates along triangle edges"."""

from __future__ import annotations

import numpy as np
import warp as wp

MAX_COARSEST = 12
"""Most nodes of the coarsest level, solved by a dense Cholesky factorisation (3 unknowns per node)."""
ISOLATED_GROUP = 4


def aggregate(neighbours: list[list[int]], active: np.ndarray) -> tuple[np.ndarray, int]:
    """Greedy aggregation of a graph's ``active`` nodes: a node whose neighbours are all free starts an aggregate with
    them, the rest join the one they touch most. Returns (each node's aggregate or -1, the aggregate count)."""
    n = len(neighbours)
    on = np.asarray(active, dtype=bool).tolist()
    near = [[j for j in nb if on[j]] for nb in neighbours]
    agg = [-1] * n
    count = 0
    for i in range(n):
        if on[i] and agg[i] < 0 and near[i] and all(agg[j] < 0 for j in near[i]):
            agg[i] = count
            for j in near[i]:
                agg[j] = count
            count += 1
    isolated = []
    for i in range(n):
        if on[i] and agg[i] < 0:
            touched = [agg[j] for j in near[i] if agg[j] >= 0]
            if touched:  # join the aggregate it touches most; ties: the lowest id
                agg[i] = max(sorted(set(touched)), key=touched.count)
            else:
                isolated.append(i)
    # Nodes with no active neighbour (separate pieces, once coarsened to a node each) are grouped in fours: a
    # piecewise-constant P over unconnected nodes is still a valid coarse space, and the levels keep shrinking.
    for first in range(0, len(isolated), ISOLATED_GROUP):
        for i in isolated[first:first + ISOLATED_GROUP]:
            agg[i] = count
        count += 1
    return np.array(agg, dtype=np.int64), count


def _mesh_neighbours(n: int, triangles: np.ndarray) -> list[list[int]]:
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    a = np.concatenate([t[:, 0], t[:, 1], t[:, 2], t[:, 1], t[:, 2], t[:, 0]])
    b = np.concatenate([t[:, 1], t[:, 2], t[:, 0], t[:, 0], t[:, 1], t[:, 2]])
    return _neighbours(n, a, b)


def _neighbours(n: int, rows: np.ndarray, cols: np.ndarray) -> list[list[int]]:
    keep = rows != cols
    rows, cols = rows[keep], cols[keep]
    order = np.lexsort((cols, rows))
    rows, cols = rows[order], cols[order]
    first = np.ones(len(rows), dtype=bool)
    first[1:] = (rows[1:] != rows[:-1]) | (cols[1:] != cols[:-1])
    rows, cols = rows[first], cols[first]
    starts = np.searchsorted(rows, np.arange(n + 1)).tolist()
    cols = cols.tolist()
    return [cols[starts[i]:starts[i + 1]] for i in range(n)]


def gather_lists(targets: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``(start, sources)``: for each target t in [0, count), the positions k with ``targets[k] == t``, ascending, as
    ``sources[start[t]:start[t + 1]]`` (negative targets: none)."""
    targets = np.asarray(targets, dtype=np.int64)
    sources = np.flatnonzero(targets >= 0)
    sources = sources[np.argsort(targets[sources], kind="stable")]
    return np.searchsorted(targets[sources], np.arange(count + 1)), sources


class Hierarchy:
    """One world's aggregation hierarchy, level-local, from its block pattern, triangles and pins.

    Raises:
        ValueError: every particle is pinned."""

    def __init__(self, offsets: np.ndarray, columns: np.ndarray, triangles: np.ndarray, pinned: np.ndarray):
        n0 = len(offsets) - 1
        rows = np.repeat(np.arange(n0), np.diff(offsets))
        cols = np.asarray(columns, dtype=np.int64)
        active = ~np.asarray(pinned, dtype=bool)
        neighbours = _mesh_neighbours(n0, triangles)
        sizes = [n0]
        aggregates = []  # per level above the coarsest: each node's aggregate (level-local ids, -1 none)
        slot_maps = []  # per level: each of its blocks' slot in the next level's blocks (level-local, -1 none)
        patterns = []  # per coarse level: (offsets, columns, diag_slot), level-local
        while True:
            agg, count = aggregate(neighbours, active)
            if count == 0:
                raise ValueError("the multigrid preconditioner needs at least one particle that is not pinned; "
                                 "use preconditioner='block_ssor' (the sequential CG backend) or 'block_jacobi'")
            ca, cb = agg[rows], agg[cols]
            keep = (ca >= 0) & (cb >= 0)
            keys = ca * count + cb
            unique = np.unique(keys[keep])
            slots = np.full(len(rows), -1, dtype=np.int64)
            slots[keep] = np.searchsorted(unique, keys[keep])
            crow, ccol = unique // count, unique % count
            coffsets = np.searchsorted(crow, np.arange(count + 1))
            cdiag = np.searchsorted(unique, np.arange(count) * count + np.arange(count))
            if not np.array_equal(unique[cdiag], np.arange(count) * (count + 1)):
                raise AssertionError("a coarse node without a diagonal block")
            aggregates.append(agg)
            slot_maps.append(slots)
            patterns.append((coffsets, ccol, cdiag))
            sizes.append(count)
            if count <= MAX_COARSEST:
                break
            rows, cols = crow, ccol
            neighbours = _neighbours(count, crow, ccol)
            active = np.ones(count, dtype=bool)
        self.sizes = sizes
        """Nodes per level, the particles first."""
        self.aggregates = aggregates  # per level but the coarsest: each node's aggregate on the next (-1: none)
        self.slot_maps = slot_maps  # per level but the coarsest: each block's slot in the next level's (-1: none)
        self.patterns = patterns  # per coarse level: (offsets, columns, diagonal slots), level-local


class WorldHierarchies:
    """A model's worlds' hierarchies in the kernels' flat layout: nodes by level, then world; world w's nodes of level
    l are ``[world_level_lo[w, l], world_level_hi[w, l])``, so its V-cycle is bitwise that of the world alone."""

    def __init__(self, offsets: np.ndarray, columns: np.ndarray, triangles: np.ndarray, pinned: np.ndarray,
                 world_particle_start: np.ndarray):
        offsets, columns = np.asarray(offsets, dtype=np.int64), np.asarray(columns, dtype=np.int64)
        triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        pinned = np.asarray(pinned, dtype=bool)
        starts = [int(p) for p in world_particle_start]
        W = len(starts) - 1
        built: dict = {}
        self.worlds: list[Hierarchy] = []
        for w in range(W):
            p0, p1 = starts[w], starts[w + 1]
            local = (offsets[p0:p1 + 1] - offsets[p0], columns[offsets[p0]:offsets[p1]] - p0,
                     triangles[(triangles[:, 0] >= p0) & (triangles[:, 0] < p1)] - p0, pinned[p0:p1])
            key = tuple(a.tobytes() for a in local)
            if key not in built:
                try:
                    built[key] = Hierarchy(*local)
                except ValueError as exc:
                    raise ValueError(f"world {w}: {exc}" if W > 1 else str(exc)) from exc
            self.worlds.append(built[key])
        L = max(len(h.sizes) for h in self.worlds)
        sizes = [sum(h.sizes[level] for h in self.worlds if level < len(h.sizes)) for level in range(L)]
        self.sizes = sizes
        """Nodes per level over all worlds, the particles first."""
        self.level_start = np.concatenate([[0], np.cumsum(sizes)])
        n0, total = sizes[0], int(self.level_start[-1])

        def blocks(h: Hierarchy, level: int) -> int:
            return len(h.patterns[level - 1][1]) if 0 < level < len(h.sizes) else 0

        block_level_start = np.concatenate([[0], np.cumsum([sum(blocks(h, level) for h in self.worlds)
                                                            for level in range(1, L)])])
        node_lo = np.zeros((W, L), dtype=np.int64)
        block_lo = np.zeros((W, L), dtype=np.int64)
        for level in range(L):
            node, block = (0, 0) if level == 0 else (int(self.level_start[level]), int(block_level_start[level - 1]))
            for w, h in enumerate(self.worlds):
                node_lo[w, level] = starts[w] if level == 0 else node
                block_lo[w, level] = block
                if level > 0 and level < len(h.sizes):
                    node += h.sizes[level]
                    block += blocks(h, level)
        coarse_blocks = int(block_level_start[-1])
        self.aggregate = np.full(total, -1, dtype=np.int64)
        self.fine_slot = np.full(int(offsets[n0]), -1, dtype=np.int64)
        self.coarse_slot = np.full(coarse_blocks, -1, dtype=np.int64)
        self.offsets = np.zeros(total - n0 + 1, dtype=np.int64)
        self.offsets[-1] = coarse_blocks
        self.columns = np.zeros(coarse_blocks, dtype=np.int64)
        self.diag_slot = np.zeros(total - n0, dtype=np.int64)
        self.world_levels = np.array([len(h.sizes) for h in self.worlds], dtype=np.int64)
        self.world_level_lo = np.zeros((W, L), dtype=np.int64)
        self.world_level_hi = np.zeros((W, L), dtype=np.int64)
        for w, h in enumerate(self.worlds):
            levels = len(h.sizes)
            for level in range(levels):
                lo = node_lo[w, level]
                self.world_level_lo[w, level], self.world_level_hi[w, level] = lo, lo + h.sizes[level]
                if level + 1 < levels:
                    agg = h.aggregates[level]
                    self.aggregate[lo:lo + h.sizes[level]] = np.where(agg >= 0, agg + node_lo[w, level + 1], -1)
                if level == 0:
                    slots = h.slot_maps[0]
                    self.fine_slot[offsets[starts[w]]:offsets[starts[w + 1]]] = np.where(
                        slots >= 0, slots + block_lo[w, 1], -1)
                    continue
                b0 = block_lo[w, level]
                coffsets, ccolumns, cdiag = h.patterns[level - 1]
                rows = slice(lo - n0, lo - n0 + h.sizes[level])
                self.offsets[rows] = coffsets[:-1] + b0
                self.diag_slot[rows] = cdiag + b0
                self.columns[b0:b0 + len(ccolumns)] = ccolumns + lo
                if level + 1 < levels:
                    slots = h.slot_maps[level]
                    self.coarse_slot[b0:b0 + len(slots)] = np.where(slots >= 0, slots + block_lo[w, level + 1], -1)

    @classmethod
    def of_model(cls, model) -> WorldHierarchies:
        return cls(model.bsr_offsets.numpy(), model.bsr_columns.numpy(), model.tri_indices.numpy(),
                   model.particle_pin.numpy() >= 0, model.world_particle_start)

    def multigrid(self, kernels, scalar, device):
        """The ``Multigrid`` struct of ``kernels`` (multigrid_kernels(scalar)) with these arrays and its scratch."""
        vec3, mat33 = wp.types.vector(3, scalar), wp.types.matrix((3, 3), scalar)

        def ints(a):
            return wp.array(np.asarray(a, dtype=np.int32), dtype=wp.int32, device=device)

        mg = kernels.Multigrid()
        mg.levels = len(self.sizes)
        mg.level_start = ints(self.level_start)
        mg.world_levels = ints(self.world_levels)
        mg.world_level_lo, mg.world_level_hi = ints(self.world_level_lo), ints(self.world_level_hi)
        mg.aggregate, mg.fine_slot, mg.coarse_slot = ints(self.aggregate), ints(self.fine_slot), ints(self.coarse_slot)
        mg.offsets, mg.columns, mg.diag_slot = ints(self.offsets), ints(self.columns), ints(self.diag_slot)
        mg.values = wp.zeros(len(self.columns), dtype=mat33, device=device)
        # the maps above inverted, as lists a thread per target gathers from (parallel forms: no atomics)
        total, blocks = int(self.level_start[-1]), len(self.columns)
        mg.member_start, mg.members = (ints(a) for a in gather_lists(self.aggregate, total))
        mg.fine_start, mg.fine_sources = (ints(a) for a in gather_lists(self.fine_slot, blocks))
        mg.coarse_start, mg.coarse_sources = (ints(a) for a in gather_lists(self.coarse_slot, blocks))
        m = 3 * max(h.sizes[-1] for h in self.worlds)
        mg.factor = wp.zeros((len(self.worlds), m, m), dtype=wp.float64, device=device)
        total = int(self.level_start[-1])
        mg.b = wp.zeros(total, dtype=vec3, device=device)
        mg.x = wp.zeros(total, dtype=vec3, device=device)
        mg.work = wp.zeros((len(self.worlds), m), dtype=wp.float64, device=device)
        return mg


class ParallelMultigrid:
    """The warp backend's ``"multigrid"``: one symmetric V-cycle of damped block-Jacobi sweeps over one world's
    :class:`WorldHierarchies`, a thread per node or block. Why: docs/decisions.md, "Parallel multigrid smoothing"."""

    OMEGA = 0.5
    """The damping of the block-Jacobi sweeps; it must keep OMEGA times the largest eigenvalue of D^-1 A under 2."""

    BLOCK_NODES = 1024
    BLOCK_DIM = 256
    """The levels from the first of at most BLOCK_NODES nodes down run in one thread block of BLOCK_DIM threads."""

    def __init__(self, hierarchy: Hierarchy, mg, kernels, model, device):
        self.kernels, self.mg, self.model, self.device = kernels, mg, model, device
        self.scalar = model.scalar
        start = [int(s) for s in hierarchy.level_start]
        self.start = start
        n0, levels = start[1], len(hierarchy.sizes)
        self.levels = levels

        # the coarse levels' block ranges in the flat block list (mg.values)
        first_block = [int(hierarchy.offsets[s - n0]) for s in start[1:]]
        self.galerkin = [(first_block[level - 1], first_block[level] - first_block[level - 1])
                         for level in range(1, levels)]  # per coarse level: (first block, block count)
        self.block_level = next(level for level in range(1, levels)  # the first level of the one-block launch
                                if start[level + 1] - start[level] <= self.BLOCK_NODES or level == levels - 1)
        self.scratch = wp.zeros(start[-1], dtype=mg.x.dtype, device=device)
        self.smoother = wp.zeros(start[-1], dtype=mg.values.dtype, device=device)  # each node's inverse diagonal
        self._diag0 = model.particle_diag_slot

    def setup(self, A) -> None:
        """The smoother and the coarse levels of A (``A``: the BlockMatrix of the particles' level)."""
        k, mg, dev, start = self.kernels, self.mg, self.device, self.start
        for first, count in self.galerkin:  # level by level: each reads the one before
            wp.launch(k.mg_galerkin, count, device=dev, inputs=[A.values, mg, first], record_tape=False)
        for level in range(self.levels - 1):
            matrix = [self._diag0, A.values, 0] if level == 0 else [mg.diag_slot, mg.values, start[1]]
            wp.launch(k.mg_diag_inverse, start[level + 1] - start[level], device=dev,
                      inputs=[*matrix, start[level]], outputs=[self.smoother], record_tape=False)
        wp.launch(k.mg_factor, 1, device=dev, inputs=[mg], record_tape=False)

    def apply(self, A, r: wp.array, y: wp.array, alpha: float, beta: float, z: wp.array) -> None:
        """z = alpha M^-1 r + beta y, M^-1 one V-cycle; ``A``: the BlockMatrix of the particles' level."""
        k, mg, dev, start = self.kernels, self.mg, self.device, self.start
        omega, dinv = self.scalar(self.OMEGA), self.smoother
        solution, other = mg.x, self.scratch  # each level's result ends in mg.x; ``other`` holds its first sweep up

        def matrix(level):
            if level == 0:
                return [A.offsets, A.columns, A.values, 0]
            return [mg.offsets, mg.columns, mg.values, start[1]]

        for level in range(self.block_level):
            lo, n = start[level], start[level + 1] - start[level]
            b = r if level == 0 else mg.b
            wp.launch(k.mg_down, n, device=dev, inputs=[*matrix(level), lo, dinv, b, omega], outputs=[solution],
                      record_tape=False)
            wp.launch(k.mg_restrict, start[level + 2] - start[level + 1], device=dev,
                      inputs=[*matrix(level), mg, b, start[level + 1]], record_tape=False)
        wp.launch_tiled(k.mg_coarse_cycle, dim=[1], block_dim=self.BLOCK_DIM, device=dev,
                        inputs=[mg, dinv, other, self.block_level, omega],
                        record_tape=False)
        for level in reversed(range(self.block_level)):
            lo, n = start[level], start[level + 1] - start[level]
            b = r if level == 0 else mg.b
            wp.launch(k.mg_up, n, device=dev, inputs=[*matrix(level), lo, dinv, b, mg.aggregate, solution, omega],
                      outputs=[other], record_tape=False)
            if level > 0:
                wp.launch(k.mg_smooth, n, device=dev, inputs=[*matrix(level), lo, dinv, b, other, omega],
                          outputs=[solution], record_tape=False)
        wp.launch(k.mg_smooth_output, start[1], device=dev,
                  inputs=[*matrix(0)[:3], dinv, r, other, omega, y, self.scalar(alpha), self.scalar(beta)],
                  outputs=[z], record_tape=False)
