"""Command line: ``warpcloth simulate [SCENE]`` writes a time-sampled USD; ``warpcloth scenes`` lists scenes.

Exit status: 0 on success, 2 for a usage error (bad arguments, unknown scene, invalid scene file), 1 when the
simulation itself fails (diverges). Errors are one line on stderr, without a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence

__all__ = ["main"]

_USAGE_ERROR = 2
_RUNTIME_ERROR = 1


def _parser() -> argparse.ArgumentParser:
    from warpcloth.scene import DEFAULT_SCENE

    parser = argparse.ArgumentParser(prog="warpcloth", description="Differentiable cloth simulation in NVIDIA Warp.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    sim = sub.add_parser("simulate", help="simulate a scene and write a time-sampled USD")
    sim.add_argument(
        "scene",
        nargs="?",
        default=DEFAULT_SCENE,
        help=f"embedded scene name or path to a .toml scene file (default: {DEFAULT_SCENE})",
    )
    sim.add_argument("--steps", type=int, default=None, help="number of steps (default: the scene's)")
    sim.add_argument("--dt", type=float, default=None, help="time step in seconds (default: the scene's)")
    sim.add_argument("--usd", metavar="PATH", default=None, help="output USD file (default: <scene name>.usda)")
    sim.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: Warp's default)")

    sub.add_parser("scenes", help="list the embedded scenes")
    return parser


def _error(message: str, status: int) -> int:
    print(f"warpcloth: error: {message}", file=sys.stderr)
    return status


def _cmd_scenes() -> int:
    from warpcloth.scene import DEFAULT_SCENE, SCENE_NAMES, load_scene

    width = max(len(n) for n in SCENE_NAMES)
    for name in SCENE_NAMES:
        mark = " (default)" if name == DEFAULT_SCENE else ""
        print(f"{name:<{width}}  {load_scene(name).description}{mark}")
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from warpcloth.obstacles import obstacle_meshes_numpy
    from warpcloth.rollout import rollout
    from warpcloth.scene import load_scene
    from warpcloth.simulator import SimulationError
    from warpcloth.usd import write_usd

    if args.steps is not None and args.steps < 1:
        return _error(f"--steps must be >= 1, got {args.steps}", _USAGE_ERROR)
    if args.dt is not None and not (args.dt > 0.0 and args.dt < float("inf")):
        return _error(f"--dt must be a finite number > 0, got {args.dt}", _USAGE_ERROR)
    try:
        scene = load_scene(args.scene)
    except (ValueError, OSError) as exc:
        return _error(str(exc), _USAGE_ERROR)
    if args.steps is not None:
        scene.steps = args.steps
    if args.dt is not None:
        scene.dt = args.dt
    usd_path = args.usd if args.usd is not None else f"{scene.name}.usda"

    try:
        model, sim = scene.build(device=args.device)
    except (ValueError, RuntimeError) as exc:  # RuntimeError: Warp's answer to an unknown --device
        return _error(str(exc), _USAGE_ERROR)
    state0 = model.state()
    control = model.control()
    start = time.perf_counter()
    try:
        traj = rollout(sim, state0, control, steps=scene.steps, progress=True)
    except SimulationError as exc:
        return _error(str(exc), _RUNTIME_ERROR)
    wall = time.perf_counter() - start

    frames = [s.particle_x.numpy() for s in traj]
    # Obstacles: static ones once, moving ones at every frame's time (at the control's base placements).
    obstacles = obstacle_meshes_numpy(model, [s.time for s in traj])
    try:
        write_usd(usd_path, triangles=model.tri_indices.numpy(), frames=frames, fps=1.0 / scene.dt,
                  obstacles=obstacles)
    except (ValueError, OSError) as exc:
        return _error(str(exc), _RUNTIME_ERROR)

    total_cg = sim.stats["cg_iterations"]
    print(f"{scene.name}: {scene.steps} steps of {scene.dt:g} s on {model.device} in {wall:.2f} s wall time")
    print(f"CG iterations: {total_cg} total, {total_cg / scene.steps:.1f} per step")
    print(f"wrote {os.path.abspath(usd_path)} ({len(frames)} frames)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the ``warpcloth`` command line.

    Args:
        argv: Arguments without the program name; ``sys.argv[1:]`` when None.

    Returns:
        The exit status (0 success, 1 simulation failure, 2 usage error). Invalid arguments make argparse exit
        with status 2.
    """
    import warp as wp

    wp.config.quiet = True  # no Warp banner or module-load lines in the tool's output
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command == "simulate":
        return _cmd_simulate(args)
    if args.command == "scenes":
        return _cmd_scenes()
    parser.print_help(sys.stderr)
    return _USAGE_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
