"""Motion control (the seed's Table 3 task): push a cloth's corners so that it lands in a basket behind a wall.

36 numbers (a push per corner for each of the first 3 seconds) are optimised by damped Gauss-Newton; every gradient
comes from one forward and one checkpointed backward pass through 700 steps with collisions. The task is the embedded
scene ``basket-throw`` (its [control] table); ``warpcloth control SCENE.toml`` runs a scene of your own. With
``--mlp`` a PyTorch MLP that reads the cloth's state once per second is trained through the simulator instead (needs
the torch extra).

    python examples/example_throw_into_basket.py --iters 30 --usd throw.usda --preview throw.gif
"""

import argparse

import warpcloth as wc
from warpcloth.preview import write_preview
from warpcloth.tasks import scenes
from warpcloth.tasks import throw as control


def main(iters: int = 30, steps: int = control.STEPS, mlp: bool = False, usd: str | None = None,
         preview: str | None = None, device=None):
    task = control.ThrowTask(scenes.basket_scene(device), steps=steps)
    if mlp:
        result = control.train_mlp(task, iters=iters, progress=True)
    else:
        result = control.optimize_open_loop(task, iters=iters, progress=True)
    print(f"error {result.error_pct:.1f} % after {result.simulations} simulations "
          f"(100 % = as far from the target as it started; no pushes at all: 5508 %)")
    if usd or preview:
        frames = result.trajectory(task)
        times = [i * control.DT for i in range(len(frames))]
        drawing = dict(triangles=task.model.tri_indices.numpy(), frames=frames, fps=1.0 / control.DT,
                       obstacles=wc.obstacle_meshes_numpy(task.model, times))
        if usd:
            wc.write_usd(usd, **drawing)
            print(f"wrote {usd}")
        if preview:  # the cloth, the wall and the basket drawn
            write_preview(preview, **drawing, title="throw into a basket")
            print(f"wrote {preview}")
    return result


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iters", type=int, default=30)
    parser.add_argument("--mlp", action="store_true")
    parser.add_argument("--usd", default=None)
    parser.add_argument("--preview", default="example_throw_into_basket.gif", help=".gif, .png or .mp4 (ffmpeg)")
    parser.add_argument("--device", default=None)
    args = parser.parse_args()
    main(args.iters, mlp=args.mlp, usd=args.usd, preview=args.preview, device=args.device)
