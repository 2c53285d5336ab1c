"""Regenerate the documentation's pictures of cloth (the PNG files beside this script) through the public API: each
scene is simulated (the throws optimised first), then ray cast with ``warpcloth.preview.render_frame``.

    python docs/_static/make_pictures.py                 # every picture
    python docs/_static/make_pictures.py drape flag      # some of them
    python docs/_static/make_pictures.py --list

A throw is drawn as a strobe: the cloth at several moments of its flight in one picture, a copy each.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from PIL import Image

import warpcloth as wc
from warpcloth.preview import Camera, render_frame

HERE = Path(__file__).resolve().parent
WIDTH, HEIGHT, SAMPLES = 800, 500, 3


def simulate(name: str, steps: int | None = None):
    """A scene's trajectory on the CPU: cloth triangles, positions per step, obstacles at each step's time."""
    scene = wc.load_scene(name)
    if steps is not None:
        scene.steps = steps
    model, sim = scene.build(device="cpu")
    state, nxt, control = model.state(), model.empty_state(), model.control()
    frames, times = [state.particle_x.numpy().copy()], [state.time]
    for _ in range(scene.steps):
        sim.step(state, nxt, control)
        state, nxt = nxt, state
        frames.append(state.particle_x.numpy().copy())
        times.append(state.time)
    return model.tri_indices.numpy(), frames, wc.obstacle_meshes_numpy(model, times)


def at(obstacles, i: int):
    """The obstacles at frame ``i`` (static ones as they are)."""
    return [(name, v if v.ndim == 2 else v[i], t) for name, v, t in obstacles]


def picture(path: Path, triangles, positions, obstacles, view):
    """One frame, ray cast at WIDTH x HEIGHT with SAMPLES x SAMPLES rays a pixel."""
    rgb, _ = render_frame(triangles, positions, obstacles, width=WIDTH, height=HEIGHT, view=view, samples=SAMPLES,
                          device="cpu")
    Image.fromarray(rgb).save(path, optimize=True)


def strobe(path: Path, triangles, frames, obstacles, view, spacing: float):
    """The cloth at the moments its centre has moved ``spacing`` [m] since the last one drawn, and at the end."""
    centres = np.array([f.mean(axis=0) for f in frames])
    chosen = [0]
    for i in range(1, len(frames)):
        if np.linalg.norm(centres[i] - centres[chosen[-1]]) >= spacing:
            chosen.append(i)
    if chosen[-1] != len(frames) - 1:
        chosen.append(len(frames) - 1)
    n = len(frames[0])
    tris = np.concatenate([triangles + k * n for k in range(len(chosen))])
    points = np.concatenate([frames[i] for i in chosen])
    statics = at(obstacles, len(frames) - 1)
    camera = Camera.framing(np.concatenate([points] + [v for _, v, _ in statics]), WIDTH, HEIGHT, view)
    rgb, _ = render_frame(tris, points, statics, camera=camera, samples=SAMPLES, device="cpu")
    Image.fromarray(rgb).save(path, optimize=True)
    return chosen


def drape():
    """The landing page and run-faster: a 1 m square dropped onto a 0.3 m sphere, at rest after 1 s."""
    tris, frames, obstacles = simulate("drape-sphere")
    picture(HERE / "drape-sphere.png", tris, frames[-1], at(obstacles, -1), view=(20.0, -60.0))
    picture(HERE / "drape-sphere-contact.png", tris, frames[30], at(obstacles, 30), view=(18.0, -20.0))


def hanging():
    """fit-recorded-frames: the material-estimation cloth, hanging from two corners in a 5 m/s wind, after 1 s."""
    tris, frames, obstacles = simulate("hanging-wind")
    picture(HERE / "hanging-wind.png", tris, frames[-1], at(obstacles, -1), view=(15.0, -20.0))


def flag():
    """cluster: a flag pinned along one edge in a 6 m/s wind, after 1 s."""
    tris, frames, obstacles = simulate("flag")
    picture(HERE / "flag.png", tris, frames[-1], at(obstacles, -1), view=(20.0, -35.0))


def _throw(controller: str, iters: int, pictures: dict, **kwargs):
    """Optimise the basket throw from a lob and draw its trajectory as a strobe from each ``{path: view}``."""
    from warpcloth.tasks.control import ControlTask

    task = ControlTask.from_scene("basket-throw", device="cpu")
    result = task.run(controller=controller, iters=iters, progress=True, start=_lob(task.params_shape), **kwargs)
    frames = result.trajectory(task)
    times = [i * task.dt for i in range(len(frames))]
    obstacles = wc.obstacle_meshes_numpy(task.model, times)
    for path, view in pictures.items():
        chosen = strobe(path, task.model.tri_indices.numpy(), frames, obstacles, view=view, spacing=0.45)
    print(f"{controller}, error {result.error_pct:.1f} % after {result.simulations} simulations; frames {chosen}")


def _lob(shape) -> np.ndarray:
    """Pushes (intervals, corners, 3) of a lob over the wall: every corner pushed up and towards the basket in the
    first second only."""
    start = np.zeros(shape)
    start[0] = (1.73, -0.18, 13.8)  # [m/s^2]: 4 m/s up after 1 s against gravity, about 2 s of flight to x = 0
    return start.reshape(-1)


def throw():
    """control-scene, train-network: the basket throw optimised (open loop) from a lob, from the side and above."""
    _throw("open-loop", 10, {HERE / "basket-throw.png": (15.0, -70.0), HERE / "basket-throw-above.png": (45.0, -30.0)},
           max_step=2.0)


def _dots(rgb: np.ndarray, camera: Camera, points: np.ndarray, colour, radius: int = 2) -> np.ndarray:
    """``rgb`` with a square dot of ``colour`` at each point's pixel."""
    out = rgb.copy()
    rows, cols = np.floor(camera.pixel(points)).astype(int).T
    for dr in range(-radius + 1, radius):
        for dc in range(-radius + 1, radius):
            r, c = rows + dr, cols + dc
            keep = (r >= 0) & (r < out.shape[0]) & (c >= 0) & (c < out.shape[1])
            out[r[keep], c[keep]] = colour
    return out


def pointcloud():
    """fit-recorded-frames: a point-cloud recording (left) and the material fitted to it (right), mid-gust."""
    from warpcloth import recordings
    from warpcloth.observations import PointCloudFrames
    from warpcloth.scene import scene_from_toml
    from warpcloth.tasks import estimation as E

    text = (HERE.parent / "howto" / "fit-recorded-frames.md").read_text()
    text = text.split("```{code-block} toml")[1].split("```")[0].split("\n", 2)[2].split("\n[estimate]")[0]
    frames = E.TrajectoryFit.simulate_targets(scene_from_toml(text).finalize(device="cpu"),
                                              wc.preset("royal-target", thicken=2), steps=20, frame_stride=1)
    model = scene_from_toml(text).finalize(requires_grad=True, device="cpu")
    camera = recordings.look_at(eye=(-2.0, 0.0, 0.0), target=(0.0, 0.0, 0.0))
    clouds = recordings.point_cloud_recording(frames, model.triangles_np, points=2000, noise=0.002, camera=camera,
                                              drop=0.1, rng=np.random.default_rng(0))
    fit = E.TrajectoryFit(model, PointCloudFrames(clouds), steps=20, frame_stride=1, reference=frames)
    result = E.estimate_material(fit, iters=30)
    k = 12  # mid-gust, the sheet half blown over
    fitted = fit.trajectory(result.material)[k]
    view = Camera.framing(np.concatenate([frames[k], clouds[k]]), WIDTH // 2, HEIGHT, (25.0, -150.0))
    blank = np.full((HEIGHT, WIDTH // 2, 3), 255, dtype=np.uint8)
    left = _dots(blank, view, clouds[k], (40, 40, 40), radius=1)
    right, _ = render_frame(model.triangles_np, fitted, camera=view, samples=SAMPLES, device="cpu")
    right = _dots(right, view, clouds[k], (200, 30, 30), radius=1)
    Image.fromarray(np.concatenate([left, right], axis=1)).save(HERE / "pointcloud-fit.png", optimize=True)
    print(f"pointcloud: simulation error {result.simulation_error_pct:.2f} % after {result.evaluations} evaluations")


def _gripper_result(name: str, iters: int):
    """A gripper scene optimised with its own [control] settings: the task, the result and its trajectory."""
    from warpcloth.tasks.grippers import GripperTask

    task = GripperTask.from_scene(name, device="cpu")
    start = task.loss(task.default_params()).error
    result = task.run(iters=iters)
    print(f"{name}: {task.goal.name} {start:.4f} -> {result.error:.4f} after {result.simulations} simulations")
    frames = task.trajectory(result.params)
    return task, frames, wc.obstacle_meshes_numpy(task.model, [i * task.dt for i in range(len(frames))])


def _close_strobe(path: Path, triangles, frames, obstacles, view, chosen, shift=(0.0, 0.0, 0.0)):
    """The cloth at frames ``chosen`` in one picture, copy k moved by k ``shift`` [m], framed on the cloth (the
    table around it cut off)."""
    n = len(frames[0])
    tris = np.concatenate([triangles + k * n for k in range(len(chosen))])
    points = np.concatenate([frames[i] + k * np.asarray(shift) for k, i in enumerate(chosen)])
    camera = Camera.framing(points, WIDTH, HEIGHT, view)
    rgb, _ = render_frame(tris, points, at(obstacles, len(frames) - 1), camera=camera, samples=SAMPLES, device="cpu")
    Image.fromarray(rgb).save(path, optimize=True)


def grippers():
    """grippers how-to: the fling and the fold after the scenes' own searches, each at moments of its motion."""
    task, frames, obstacles = _gripper_result("fling", 100)
    _close_strobe(HERE / "fling.png", task.model.tri_indices.numpy(), frames, obstacles, (20.0, -35.0),
                  [0, 60, 110, 200])
    task, frames, obstacles = _gripper_result("fold", 100)
    _close_strobe(HERE / "fold.png", task.model.tri_indices.numpy(), frames, obstacles, (30.0, -60.0),
                  [60, 200], shift=(0.7, 0.0, 0.0))


PICTURES = {"drape": drape, "hanging": hanging, "flag": flag, "throw": throw, "pointcloud": pointcloud,
            "grippers": grippers}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("names", nargs="*", help=f"pictures to make (default all): {', '.join(PICTURES)}")
    parser.add_argument("--list", action="store_true", help="list the pictures and what each shows")
    args = parser.parse_args(argv)
    if args.list:
        for name, make in PICTURES.items():
            print(f"{name:<10} {make.__doc__}")
        return
    unknown = [n for n in args.names if n not in PICTURES]
    if unknown:
        parser.error(f"unknown picture(s) {unknown}; one of {', '.join(PICTURES)}")
    for name in args.names or PICTURES:
        start = time.perf_counter()
        PICTURES[name]()
        print(f"{name}: {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
