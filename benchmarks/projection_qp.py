"""The device projection's QP and its adjoint (warpcloth/collision/projection.py): time per call.

Each world's QP is solved by one thread block (kernels/projection.py; on the CPU a block is one thread). The problem:
``layers`` cloth layers of res x res particles (10 g each) over a floor, every particle in a vertex-face contact,
those of the lowest layer with the floor's triangles and the others with a triangle of the layer below (a staggered
grid, so the contacts share particles), all of them pressed in by 0 to 60 % of the thickness (1 mm); ``worlds``
copies of it as the worlds of one call. Per case: ``project`` (MPRGP to a KKT residual of 1e-10 m, from a cold start)
and ``adjoint_on_device`` (its CG on the active set), medians of ``--reps`` timed calls, synchronised, no read-back
in the timed adjoint; on CUDA for each block size of ``--block-dims``.

Usage: python benchmarks/projection_qp.py [--quick] [--out PATH] [--device cpu] [--reps 7] [--block-dims 32,64,128,256]
"""

from __future__ import annotations

import common
import numpy as np
import warp as wp

from warpcloth.collision.projection import DeviceProjection

THICKNESS = 1.0e-3
SPACING = 0.01
"""Distance between neighbouring particles of a layer [m]."""


def stack(res: int, layers: int, seed: int) -> dict:
    """One world's problem: positions (particles, then the floor's 4 vertices), free flags, inverse masses and
    vertex-face contacts (nodes, weights, normals)."""
    rng = np.random.default_rng(seed)
    size = SPACING * (res + 1)
    floor = np.array([[-size, -size, 0.0], [size, -size, 0.0], [size, size, 0.0], [-size, size, 0.0]])
    n = res * res * layers
    x = np.zeros((n, 3))
    nodes, weights = [], []
    grid = np.arange(res) * SPACING
    for layer in range(layers):
        for i in range(res):
            for j in range(res):
                p = (layer * res + i) * res + j
                xy = np.array([grid[i], grid[j]]) + SPACING * (0.5 * layer + rng.uniform(-0.1, 0.1, 2))
                if layer == 0:  # on the floor's triangle under it
                    tri = [0, 1, 2] if xy[0] >= xy[1] else [0, 2, 3]
                    corners = floor[tri, :2]
                    below = [n + t for t in tri]
                    base = 0.0
                else:  # on the triangle of the layer below whose cell it lies in
                    ci, cj = (min(int((c - 0.5 * (layer - 1) * SPACING) / SPACING), res - 2) for c in xy)
                    q = [((layer - 1) * res + ci + di) * res + cj + dj for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1))]
                    local = xy - x[q[0], :2]
                    below = [q[0], q[1], q[2]] if local[0] >= local[1] else [q[0], q[2], q[3]]
                    corners = x[below, :2]
                    base = x[below, 2].mean()
                bary = np.linalg.solve(np.vstack([corners.T, np.ones(3)]), np.array([*xy, 1.0]))
                x[p] = [*xy, base + THICKNESS * (1.0 - rng.uniform(0.0, 0.6))]
                nodes.append([p, *below])
                weights.append([1.0, *(-bary)])
    positions = np.concatenate([x, floor])
    return dict(positions=positions, free=np.r_[np.ones(n), np.zeros(4)].astype(np.int32),
                inv_mass=np.r_[np.full(n, 100.0), np.zeros(4)], nodes=np.array(nodes, dtype=np.int32),
                weights=np.array(weights), normals=np.tile([0.0, 0.0, 1.0], (len(nodes), 1)))


def worlds_of(problem: dict, worlds: int) -> tuple[dict, np.ndarray]:
    """``worlds`` copies of one world's problem, and every node's world."""
    nodes_per_world = problem["positions"].shape[0]
    out = {key: np.concatenate([value] * worlds) for key, value in problem.items() if key != "nodes"}
    out["nodes"] = np.concatenate([problem["nodes"] + w * nodes_per_world for w in range(worlds)]).astype(np.int32)
    return out, np.repeat(np.arange(worlds, dtype=np.int32), nodes_per_world)


def case(res: int, layers: int, worlds: int, device: str, block_dim: int, reps: int) -> dict:
    problem, node_world = worlds_of(stack(res, layers, seed=res), worlds)
    count = problem["nodes"].shape[0]
    on = {key: wp.array(problem[key], dtype=dtype, device=device) for key, dtype in (
        ("positions", wp.vec3d), ("free", wp.int32), ("inv_mass", wp.float64), ("nodes", wp.int32),
        ("weights", wp.vec4d), ("normals", wp.vec3d))}
    solver = DeviceProjection(device, problem["positions"].shape[0], count,
                              wp.array(node_world, dtype=wp.int32, device=device), worlds, block_dim=block_dim)
    g = wp.array(np.random.default_rng(0).normal(size=problem["positions"].shape) * problem["inv_mass"][:, None],
                 dtype=wp.vec3d, device=device)
    d_z = wp.empty_like(g)
    worst = wp.zeros(1, dtype=wp.float64, device=device)

    def project():
        return solver.project(on["positions"], on["free"], on["inv_mass"], on["nodes"], on["weights"],
                              on["normals"], count, THICKNESS)

    def adjoint():
        wp.copy(d_z, g)
        solver.adjoint_on_device(solution, d_z, worst=worst)

    solution = project()
    if not solution.converged:
        raise RuntimeError(f"the {res}x{res}x{layers} stack did not converge in worlds {solution.failed_worlds()}")
    project_s = common.median_time(project, reps=reps)
    solution = project()
    adjoint_s = common.median_time(adjoint, reps=reps)
    z = solution.z.numpy()
    return {"res": res, "layers": layers, "worlds": worlds, "block_dim": block_dim, "contacts": count,
            "iterations": solution.iterations, "residual_m": solution.residual,
            "largest_move_m": float(np.abs(z - problem["positions"]).max()), "project_ms": 1e3 * project_s,
            "adjoint_ms": 1e3 * adjoint_s, "adjoint_residual": float(worst.numpy()[0])}


def main():
    def configure(p):
        p.add_argument("--device", default="cpu")
        p.add_argument("--block-dims", default="32,64,128,256",
                       help="CUDA: thread-block sizes to time (the CPU runs a block as one thread)")

    args = common.parse_args(__doc__, reps=7, quick={"reps": 2}, configure=configure)
    device = wp.get_device(args.device)
    common.print_machine(common.machine_info(str(device)))
    block_dims = [int(b) for b in args.block_dims.split(",")] if device.is_cuda else [1]
    shapes = [(6, 2, 1), (6, 2, 4)] if args.quick else [(8, 3, 1), (16, 3, 1), (32, 3, 1), (16, 3, 16), (8, 3, 256)]
    records = [case(res, layers, worlds, str(device), block_dim, args.reps)
               for res, layers, worlds in shapes for block_dim in block_dims]
    common.print_table(["res", "layers", "worlds", "block", "contacts", "iterations", "project ms", "adjoint ms",
                        "residual m"],
                       [[r["res"], r["layers"], r["worlds"], r["block_dim"], r["contacts"], r["iterations"],
                         r["project_ms"], r["adjoint_ms"], r["residual_m"]] for r in records],
                       specs=["d", "d", "d", "d", "d", "d", ".3f", ".3f", ".1e"],
                       title=f"device projection on {device}, medians of {args.reps} calls")
    common.write_result(args, {"records": records}, device=str(device))


if __name__ == "__main__":
    wp.init()
    main()
