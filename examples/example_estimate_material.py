"""Material estimation (the seed's Table 2 task): recover a fabric's 40 material numbers from its motion.

A 1 m cloth hangs from two soft handles in a 5 m/s wind. Its motion over 1 s is simulated with a measured fabric;
starting from the mean of 8 fabrics, L-BFGS on Warp's tape fits density, stretching and bending to that motion.

The fitted cloth's motion is drawn against the target's (translucent).

    python examples/example_estimate_material.py --material tango-red-jet-set --iters 60 --preview fit.gif
"""

import argparse

import numpy as np

import warpcloth as wc
from warpcloth.preview import write_preview
from warpcloth.tasks import estimation, scenes


def main(material: str = "tango-red-jet-set", iters: int = 60, steps: int = estimation.STEPS, device=None,
         preview: str | None = None):
    truth = wc.preset(material, thicken=scenes.THICKEN)
    model = scenes.hanging_cloth(truth, device=device)  # the material here only sets the initial arrays
    targets = estimation.TrajectoryFit.simulate_targets(model, truth, steps=steps)
    fit = estimation.TrajectoryFit(model, targets, steps=steps)
    result = estimation.estimate_material(fit, optimizer="lbfgs", iters=iters, progress=True)
    before = estimation.parameter_errors(result.initial, truth)
    after = estimation.parameter_errors(result.material, truth)
    for key, label in estimation.ERROR_LABELS.items():
        print(f"{label:34s} {before[key]:8.1f} -> {after[key]:8.1f}")
    print(f"{'simulation error [%]':34s} {result.initial_simulation_error_pct:8.2f} -> "
          f"{result.simulation_error_pct:8.2f}")
    print(f"{result.seconds_per_step_iter * 1e3:.1f} ms per step per iteration (forward + backward)")
    if preview:
        fitted = fit.trajectory(result.material)[:: fit.frame_stride]  # the frames the loss compares
        tris = model.tri_indices.numpy()
        write_preview(preview, triangles=tris, frames=fitted, fps=1.0 / (fit.sim.dt * fit.frame_stride),
                      obstacles=[("target", np.stack(targets[: len(fitted)]), tris)], title=f"fit of {material}")
        print(f"wrote {preview}")
    return result, truth


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--material", default="tango-red-jet-set", choices=wc.PRESET_NAMES)
    parser.add_argument("--iters", type=int, default=60)
    parser.add_argument("--device", default=None)
    parser.add_argument("--preview", default="example_estimate_material.gif", help=".gif, .png or .mp4 (ffmpeg)")
    args = parser.parse_args()
    main(args.material, args.iters, device=args.device, preview=args.preview)
