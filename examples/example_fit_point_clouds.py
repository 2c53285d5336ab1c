"""Fit a fabric to what a depth camera recorded: point-cloud files on disk, no vertex correspondence.

A stand-in recording is made first: the hanging cloth in a 5 m/s wind, moved by a fabric the fit is not told
(royal-target), recorded at 50 frames a second as one depth camera upwind of it sees it (2,000 points a frame on the
side facing it, 2 mm noise, a tenth of the frames dropped) with a few flying pixels (points 10 cm off), written as one
``.ply`` file a frame. Then it is fitted as any recording would be: a scene file names the directory
(``[estimate] targets``), its length and frame rate (``frame_count``: a dropped last frame has no file;
``frame_rate``) and a loss that leaves out each frame's farthest points
(``trimmed``), and ``EstimationTask.from_scene`` reads it. The fitted material's errors are printed against the
truth, and a preview draws the fitted cloth's motion against the true one (translucent) and the recorded points (red).

    python examples/example_fit_point_clouds.py --iters 60 --preview fit.gif
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np

import warpcloth as wc
from warpcloth import recordings
from warpcloth.preview import write_preview
from warpcloth.scene import scene_from_toml
from warpcloth.tasks.estimation import EstimationTask, TrajectoryFit, parameter_errors

SCENE = """
name = "point-cloud-fit"
[sim]
dt = 0.02
steps = {steps}
[cloth]
grid = {{ res = [10, 10], size = [0.6, 0.6] }}
rot_deg = [90.0, 0.0, 90.0]
pos = [0.0, -0.3, -0.3]
material = "gray-interlock"
thicken = 2.0
[[handles]]
grid_vertex = [0, -1]
[[handles]]
grid_vertex = [-1, -1]
[wind]
velocity = [5.0, 0.0, 0.0]
"""
TASK = """
[estimate]
targets = "clouds"
frame_count = {frames}
frame_rate = 50.0
trimmed = 0.05
iters = {iters}
"""


def record(directory: Path, truth: wc.Material, steps: int, points: int, seed: int = 0) -> list[np.ndarray]:
    """Simulate ``truth`` in the scene and write what the camera records into ``directory/clouds``; returns the true
    vertex frames (to compare with, here only)."""
    model = scene_from_toml(SCENE.format(steps=steps)).finalize()
    frames = TrajectoryFit.simulate_targets(model, truth, steps=steps, frame_stride=1)
    rng = np.random.default_rng(seed)
    camera = recordings.look_at(eye=(-2.0, 0.0, 0.0), target=(0.0, 0.0, 0.0))
    clouds = recordings.point_cloud_recording(frames, model.triangles_np, points=points, noise=0.002, camera=camera,
                                              drop=0.1, rng=rng)
    for cloud in clouds:
        if cloud is not None:  # flying pixels: 2 % of the points far off the cloth
            stray = max(1, len(cloud) // 50)
            cloud[:stray] += rng.normal(0.0, 0.1, (stray, 3))
    recordings.write_point_clouds(directory / "clouds", clouds, kind=".ply")
    return frames


def main(truth_name: str = "royal-target", iters: int = 60, steps: int = 20, points: int = 2000, device=None,
         preview: str | None = None, directory: str | None = None):
    workdir = Path(directory or tempfile.mkdtemp(prefix="warpcloth-clouds-"))
    truth = wc.preset(truth_name, thicken=2)
    true_frames = record(workdir, truth, steps, points)
    scene_path = workdir / "fit.toml"
    scene_path.write_text(SCENE.format(steps=steps) + TASK.format(frames=steps + 1, iters=iters))
    task = EstimationTask.from_scene(scene_path, device=device)  # the recording read back from its files
    result = task.run()
    print(result.summary())
    for key, value in parameter_errors(result.material, truth).items():
        print(f"{key}: {value:.3g}")
    if preview:
        fitted = task.fit.trajectory(result.material)
        tris = task.fit.model.triangles_np
        write_preview(preview, triangles=tris, frames=fitted, fps=50.0, points=task.fit.observation.points,
                      obstacles=[("truth", np.stack(true_frames), tris)], title="fitted to point clouds")
        print(f"wrote {preview}")
    return result, truth


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--truth", default="royal-target", help="the fabric that moves the recorded cloth")
    parser.add_argument("--iters", type=int, default=60)
    parser.add_argument("--device", default=None)
    parser.add_argument("--preview", default="example_fit_point_clouds.gif", help=".gif, .png or .mp4 (ffmpeg)")
    args = parser.parse_args()
    main(args.truth, iters=args.iters, device=args.device, preview=args.preview)
