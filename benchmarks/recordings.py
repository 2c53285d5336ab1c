"""Fits from what people record: the seed's own three target sequences as point clouds and as markers.

The seed's three target sequences (../shared/reference/liang2019/targets: 11oz, gray, tango; made by the seed's C++
code, their true fabrics known) fitted as material_estimation.py's cross-check fits them: the seed's demo_wind.obj
start, simulated as the seed did (lagged wind normals, self-collision), L-BFGS, 50 steps, every second step's frame
compared. Each sequence is fitted three ways, with the same optimizer and ``--iters`` evaluations, from each of
``STARTS`` (the mean fabric, then its bending halved and doubled: ``estimation.varied_start``):

- vertices: every vertex of every compared frame (the cross-check's fit);
- point clouds (``warpcloth.recordings.point_cloud_recording``): ``--points`` points a frame with 2 mm Gaussian
  noise, sampled over the side a depth camera sees (``look_at``; 1.8 m in front of the hanging cloth, 0.3 m above
  the centre of its motion, 50 degrees wide, 640 x 480, the whole motion in view), the cloth's self-occlusion
  removed, 10 % of the frames dropped, fitted by the distance from each recorded point to the simulated surface;
- markers (``marker_recording``): ``--markers`` markers spread over the cloth, a fifth of them (rounded) hidden in
  each frame.

The point clouds and markers are drawn with ``--seeds`` recording seeds, each fitted from every start; the vertex
recording has no seed, so its three fits are made once. For each recording seed the fit of least loss over its starts
is kept (as a user fits from several starts and keeps the least loss: a fit ends where its path takes it), and the
figures are medians over the seeds of these; the medians over every fit are reported beside them ("single"). Each
fit's simulation error is measured against the seed's full vertex trajectory (the fit's ``reference``); density and
linear stretching errors against the true fabric (``estimation.parameter_errors``). The fits run on ``--workers``
processes.
Time per evaluation: the fit's wall time per evaluation and per simulated step. The losses' cost per frame: one
evaluation of each observation's loss (forward, and forward plus backward on a tape) on the seed's frames, per
frame that holds data. Targets (issue 55): the point-cloud fit's simulation error within 1.5x of the vertex fit's
on each sequence and its density error within 2x; the marker fit's simulation and density errors within 1.2x (the
best of the starts, medians over the seeds; every fit's medians reported too); the point-cloud fit at most 2x the
vertex fit's time per simulated step (medians over every fit).

Scene parameters (``--parts parameters``): three scenes of the public API, their truth simulated, each recorded as
point clouds as above (``--points`` points, 2 mm noise, 10 % of the frames dropped, one depth camera) with
``--seeds`` recording seeds, and one unknown fitted with the material known (``estimate_material(free=[...])``,
L-BFGS, one stage, ``--param-iters`` evaluations of ``--steps`` steps) from a wrong start:

- friction: a 0.5 m square (12 x 12 cells) dropped flat from 5 cm onto a plane tilted 20 degrees, cloth-obstacle
  friction 0.3 (it lands and slides down part way); the fit starts from 0.1, bounds (0.01, 2); the camera above the
  plane's downhill side;
- wind: ``scenes.hanging_cloth`` (16 x 16 cells) in a wind of (4, 0, 1) m/s; the fit starts from (2, 1, 0) m/s,
  unbounded; the camera 2.4 m upwind of the sheet;
- damping: ``scenes.hanging_cloth`` in its 5 m/s wind with Rayleigh damping alpha 0.5 1/s and beta 2 ms, both
  unknown; the fit starts from 0.2 1/s and 5 ms, unbounded (log space); the camera as for the wind.

Target (issue 55, for the friction and the wind; the damping held to the same): each unknown recovered within 10 %
(the median over the seeds of the relative error: |fitted - true| / |true|, the vectors' norms for the wind, the
larger of the two coefficients' errors for the damping).

The start unknown (``--parts start``): each sequence from its frame ``--start-frame`` (the cloth draped and moving),
``--steps`` steps against the seed's frames from there, recorded as point clouds as above with ``--seeds`` seeds, the
material fitted (L-BFGS from the mean fabric, ``--iters`` evaluations) twice: given the true start (the seed's
vertices and its OBJ ``nv`` velocities at that frame, the scene's handles), and from the point clouds alone
(``estimation.registered_start`` on the start frame's cloud, which keeps the held corners where the scene holds them,
``place_start``; ``start_deformation`` and ``start_deformation_rate`` free from zero: the start's shape and velocity
in the cloth's smoothest displacements, the held corners fixed), fitted alone for the first ``START_SHARE`` of the
evaluations, then with the material, without the start scan. Reported: each fit's simulation error (from its own
start), its material's simulation error from the true start, its density error, the registered start's distance from
the true one (its handles' too) and the fitted start's, and the true material's simulation error from the registered
start (with the true velocities, and at rest): what the start alone costs.
Target (issue 55): the fit from point clouds alone within 2x of the fit given the start (medians over the seeds).

The parameters and start parts keep their own run metadata (``parameters.meta``, ``start.meta``); a run of some
parts keeps the other parts' records (and their metadata) from the file at ``--out``; the start part writes after
each sequence.

Usage: python benchmarks/recordings.py [--quick] [--out PATH] [--parts all|sequences|parameters|start,...]
       [--iters 150] [--seeds 3] [--sequences all|gray,...] [--optimizer lbfgs] [--steps 50] [--points 2000]
       [--markers 12] [--param-iters 20] [--start-frame 10] [--workers 1]
       (--quick: gray, 4 steps, 2 evaluations (--param-iters too), 1 seed, 200 points)
"""

from __future__ import annotations

import json
import math
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import common
import numpy as np
import warp as wp
from common import wc

from warpcloth import mesh_io
from warpcloth import recordings as R
from warpcloth.observations import MarkerFrames, PointCloudFrames, VertexFrames
from warpcloth.tasks import estimation as E
from warpcloth.tasks import scenes as S

SEED_TARGETS = {"11oz": "11oz-black-denim", "gray": "gray-interlock", "tango": "tango-red-jet-set"}
"""The seed's target sequences and their true fabrics."""
NOISE = 0.002
"""Standard deviation of the point clouds' noise along each axis [m]."""
DROP = 0.1
"""Fraction of the recorded frames dropped from a point cloud recording."""
HIDDEN = 0.2
"""Fraction of the markers hidden in each frame (rounded: 2 of 12)."""
CAMERA_OFFSET = (0.0, -1.8, 0.3)
"""The depth camera's eye from the centre of the recorded motion's bounding box [m]: in front of the sheet (which
hangs in the x-z plane and flutters along y), a little above its middle, looking at that centre."""
CAMERA = {"fov": 50.0, "width": 640, "height": 480}
KINDS = ("vertices", "point_clouds", "markers")
LIMITS = {"point_clouds": {"sim_err_pct": 1.5, "density_err_pct": 2.0},
          "markers": {"sim_err_pct": 1.2, "density_err_pct": 1.2}}
"""Targets: a recording's fit error at most this many times the vertex fit's (medians over the seeds)."""
SPEED_LIMIT = 2.0
"""Target: the point-cloud fit's time per simulated step at most this many times the vertex fit's."""
FIGURES = ("sim_err_pct", "density_err_pct", "stretch_linear_err_pct", "s_per_eval", "s_per_step_iter")


def camera_for(frames):
    """The depth camera, placed once for the whole recording (where one would stand to film the motion)."""
    x = np.concatenate(frames)
    centre = 0.5 * (x.min(axis=0) + x.max(axis=0))
    return R.look_at(centre + np.array(CAMERA_OFFSET), centre, **CAMERA)


def in_image(camera, frames) -> float:
    """The fraction of the frames' vertices inside the camera's image (1: the whole cloth is in view)."""
    x = np.concatenate(frames)
    rc = camera.pixel(x)
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < camera.height) & (rc[:, 1] >= 0) & (rc[:, 1] < camera.width)
    return float(np.mean(inside & ((x - camera.eye) @ camera.forward > 0)))


def seen_fraction(camera, frames, triangles, rng) -> float:
    """The median over frames of the fraction of the surface (uniform samples) the camera sees."""
    fractions = []
    for x in frames:
        points = R.sample_surface(x, triangles, 2000, rng)[0]
        fractions.append(float(np.mean(R.visible(points, x, triangles, camera))))
    return common.median(fractions)


STARTS = 3
"""The sequences' fits' starts: ``estimation.varied_start`` 0, 1, 2 of the mean fabric (``initial_guess``): its
bending times 1, 1/2 and 2. Why: docs/decisions.md, "Recording fits are compared over three starts"."""


def start_material(k: int):
    return E.varied_start(E.initial_guess(), k)


def start_name(k: int) -> str:
    return "mean fabric" if k == 0 else f"mean fabric, bending x{E.start_bending_factor(k):g}"


def fit_once(files, frames, observation, truth, optimizer: str, iters: int, steps: int, initial=None) -> dict:
    """One fit from ``initial`` (default the mean fabric); its errors against the seed's vertex frames and the true
    fabric, and its least loss over the whole horizon (what picks the best of several starts)."""
    model = S.hanging_cloth(E.initial_guess(), mesh_path=files[0], lagged_normals=True, self_collision=True)
    if observation is None:
        fit = E.TrajectoryFit(model, frames, steps=steps)
    else:
        fit = E.TrajectoryFit(model, observation, steps=steps, reference=frames)
    result = E.estimate_material(fit, initial=initial, optimizer=optimizer, iters=iters)
    errors = E.parameter_errors(result.material, truth)
    return {"sim_err_pct": result.simulation_error_pct, "sim_err_pct_start": result.initial_simulation_error_pct,
            "density_err_pct": errors["density_err_pct"],
            "stretch_linear_err_pct": errors["stretch_linear_err_pct"],
            "stretch_nonlinear_err_pct": errors["stretch_nonlinear_err_pct"],
            "bending_err_pct": errors["bending_err_pct"],
            "evaluations": len(result.losses), "simulated_steps": int(sum(result.horizons)),
            "seconds": result.seconds, "s_per_eval": result.seconds / max(len(result.losses), 1),
            "s_per_step_iter": result.seconds_per_step_iter, "diverged": len(result.diverged),
            "best_loss": result.best_loss}


def sequence_data(short: str, steps: int, points: int, markers: int, seeds: int) -> dict:
    """A sequence's true fabric, its OBJ files and vertex frames, the compared frames, the camera and each recording
    seed's point clouds and markers (seed k's drawn from ``default_rng(k)``, the point clouds first)."""
    files = wc.obj_sequence_files(common.seed_dir() / "targets" / short)
    frames = [np.asarray(f, dtype=np.float64) for f in wc.load_obj_sequence(files)]
    recorded = frames[: steps // E.FRAME_STRIDE + 1]  # the compared frames, frame 0 the start
    model = S.hanging_cloth(E.initial_guess(), mesh_path=files[0], lagged_normals=True, self_collision=True)
    camera = camera_for(recorded)
    recordings = []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        clouds = R.point_cloud_recording(recorded, model.triangles_np, points=points, noise=NOISE, camera=camera,
                                         drop=DROP, rng=rng)
        marker_set = R.marker_recording(recorded, model.triangles_np, markers=markers, hidden=HIDDEN, rng=rng)
        recordings.append({"clouds": clouds, "markers": marker_set,
                           "observations": {"vertices": None, "point_clouds": PointCloudFrames(clouds),
                                            "markers": MarkerFrames(marker_set.triangles, marker_set.barycentric,
                                                                    marker_set.positions)}})
    return {"truth": wc.preset(SEED_TARGETS[short], thicken=S.THICKEN), "files": files, "frames": frames,
            "recorded": recorded, "model": model, "camera": camera, "recordings": recordings}


_SEQUENCES: dict = {}


def fit_task(task: tuple) -> dict:
    """One fit of the sequences part: (sequence, kind, recording seed, start, settings); a worker process builds the
    sequence's data once."""
    short, kind, seed, start, st = task
    key = (short, st["steps"], st["points"], st["markers"], st["seeds"])
    if key not in _SEQUENCES:
        _SEQUENCES[key] = sequence_data(*key)
    data = _SEQUENCES[key]
    t0 = time.perf_counter()
    run = fit_once(data["files"], data["frames"], data["recordings"][seed]["observations"][kind], data["truth"],
                   st["optimizer"], st["iters"], st["steps"], initial=start_material(start))
    run["kind"], run["seed"], run["start"] = kind, seed, start_name(start)
    if kind == "point_clouds":
        run["dropped_frames"] = [k for k, c in enumerate(data["recordings"][seed]["clouds"]) if c is None]
    elif kind == "markers":
        run["hidden_pairs"] = int(np.isnan(data["recordings"][seed]["markers"].positions[..., 0]).sum())
    print(f"{short:6s} {kind:12s} seed {seed}, {run['start']}: sim err {run['sim_err_pct']:.3g} %  density "
          f"{run['density_err_pct']:.3g} %  loss {run['best_loss']:.3g}  ({time.perf_counter() - t0:.0f} s)",
          flush=True)
    return run


def loss_cost(observation, model, frames, reps: int) -> dict:
    """Seconds per frame holding data of one evaluation of ``observation``'s loss on ``frames`` 1.. (the seed's
    frames as the simulated positions): forward, and forward plus backward on a tape."""
    loss = observation.bind(model)
    ks = list(range(1, len(frames)))
    xs = [wp.array(np.asarray(frames[k]), dtype=model.types.vec3, device=model.device, requires_grad=True)
          for k in ks]
    if isinstance(observation, PointCloudFrames):
        counted = sum(observation.points[k] is not None for k in ks)
    else:
        counted = len(ks)
    ones = wp.ones(model.world_count, dtype=model.scalar, device=model.device)

    def forward():
        loss(xs, ks)

    def backward():
        tape = wp.Tape()
        with tape:
            out = loss(xs, ks)
        tape.backward(grads={out: ones})
        tape.zero()

    return {"frames": counted,
            "forward_s_per_frame": common.median_time(forward, reps=reps) / counted,
            "forward_backward_s_per_frame": common.median_time(backward, reps=reps) / counted}


def median_record(runs: list[dict]) -> dict:
    return {k: common.median([r[k] for r in runs]) for k in FIGURES}


def chosen_runs(runs: list[dict], seeds: int) -> list[dict]:
    """Each recording seed's fit of least loss over its starts (a vertex recording is the same for every seed: its
    one choice stands for each)."""
    by_seed = [[r for r in runs if r["seed"] == seed] for seed in range(seeds)]
    return [min(rs, key=lambda r: r["best_loss"]) for rs in by_seed if rs]


def sequence_tasks(short: str, args) -> list[tuple]:
    """The sequence's fits: the vertices from each start once (its recording has no seed), the point clouds and the
    markers from each start for each recording seed."""
    st = {"optimizer": args.optimizer, "iters": args.iters, "steps": args.steps, "points": args.points,
          "markers": args.markers, "seeds": args.seeds}
    return [(short, kind, seed, start, st) for kind in KINDS for seed in range(1 if kind == "vertices" else args.seeds)
            for start in range(STARTS)]


def sequence_record(short: str, runs: list[dict], args) -> dict:
    """A sequence's record from its fits: every run, each seed's choice, the medians and the targets."""
    data = sequence_data(short, args.steps, args.points, args.markers, args.seeds)
    recorded, model, camera = data["recorded"], data["model"], data["camera"]
    record = {"target": short, "material": SEED_TARGETS[short], "frames": len(recorded),
              "camera": {"eye": camera.eye, "forward": camera.forward, **CAMERA},
              "in_image": in_image(camera, recorded),
              "seen_fraction": seen_fraction(camera, recorded, model.triangles_np, np.random.default_rng(12345))}
    for kind in KINDS:
        rs = [r for r in runs if r["kind"] == kind]
        chosen = chosen_runs(rs, args.seeds)
        record[kind] = {"runs": rs, "chosen": chosen, "median": median_record(chosen),
                        "median_single": median_record(rs),
                        "s_per_eval": common.median([r["s_per_eval"] for r in rs]),
                        "s_per_step_iter": common.median([r["s_per_step_iter"] for r in rs])}
    reps = 3 if args.quick else 10
    observations = data["recordings"][0]["observations"]
    record["loss_cost"] = {"vertices": loss_cost(VertexFrames(np.stack(recorded)), model, recorded, reps),
                           **{kind: loss_cost(observations[kind], model, recorded, reps)
                              for kind in ("point_clouds", "markers")}}
    record["targets"] = targets(record)
    record["targets_single"] = targets(record, "median_single")
    return record


def ratio(a: float, b: float) -> float:
    return a / b if b > 0.0 else float("inf")


def targets(record: dict, median: str = "median") -> dict:
    """Each target of a sequence: the ratio of the recording's ``median`` (each seed's best of the starts, or
    ``"median_single"``: every fit's) to the vertex fit's, its limit and whether it is met; the time per step is
    every fit's median."""
    vertex = record["vertices"][median]
    out = {}
    for kind, limits in LIMITS.items():
        for key, limit in limits.items():
            r = ratio(record[kind][median][key], vertex[key])
            out[f"{kind}.{key}"] = {"ratio": r, "limit": limit, "met": bool(r <= limit)}
    r = ratio(record["point_clouds"]["s_per_step_iter"], record["vertices"]["s_per_step_iter"])
    out["point_clouds.s_per_step_iter"] = {"ratio": r, "limit": SPEED_LIMIT, "met": bool(r <= SPEED_LIMIT)}
    return out


# -- scene parameters --------------------------------------------------------------------------------------------
PARTS = ("sequences", "parameters", "start")
PARAMETER_LIMIT_PCT = 10.0
"""Target: each scene parameter recovered within this relative error [%] (median over the recording seeds)."""
TILT_DEG = 20.0
"""The table's tilt [degrees] (about y; downhill is -x)."""
TABLE_FRICTION = {"free": ["obstacle_friction"], "truth": [0.3], "start": [0.1], "bounds": [0.01, 2.0]}
WIND = {"free": ["wind"], "truth": [4.0, 0.0, 1.0], "start": [2.0, 1.0, 0.0]}
DAMPING = {"free": ["damping_mass", "damping_stiffness"], "truth": [0.5, 2e-3], "start": [0.2, 5e-3]}
"""The scene parameters: the free ones, their true values and the fits' starts (concatenated), bounds [-, m/s, 1/s
and s]."""
PARAMETER_SCENES = {"friction": TABLE_FRICTION, "wind": WIND, "damping": DAMPING}
DROP_HEIGHT = 0.05
"""The flat cloth's start above the table [m]."""
TABLE_CAMERA_OFFSET = (-0.6, -1.2, 1.2)
"""The camera's eye from the centre of the table motion's bounding box [m]: above the plane, on its downhill side."""
HANGING_CAMERA_OFFSET = (-2.4, 0.0, 0.3)
"""The camera's eye from the centre of the hanging cloth's motion [m]: upwind of the sheet (in the y-z plane)."""


def _rotation_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def table_scene(material, friction: float):
    """A 0.5 m square (12 x 12 cells) flat ``DROP_HEIGHT`` above a 3 m plane tilted ``TILT_DEG``; the model and the
    plane's (name, vertices, triangles) for the camera's occlusion."""
    rot = _rotation_y(TILT_DEG)
    b = wc.ModelBuilder(gravity=S.GRAVITY)
    b.add_obstacle_plane((3.0, 3.0), rot=rot)
    b.add_cloth_grid((12, 12), (0.5, 0.5), material=material, rot=rot, pos=rot @ np.array([-0.25, -0.25,
                                                                                            DROP_HEIGHT]))
    b.set_collision(obstacle_friction=friction)
    vertices, triangles = wc.plane_mesh((3.0, 3.0), (1, 1))
    return b.finalize(None, requires_grad=True), ("table", np.asarray(vertices) @ rot.T, np.asarray(triangles))


def wind_scene(material, wind):
    """``scenes.hanging_cloth`` in a wind of ``wind`` [m/s]."""
    model = S.hanging_cloth(material)
    model.wind_velocity.assign(np.array([wind], dtype=np.float64))
    return model, None


def damping_scene(material, damping):
    """``scenes.hanging_cloth`` (its 5 m/s wind) with Rayleigh damping ``damping`` (alpha [1/s], beta [s])."""
    model = S.hanging_cloth(material)
    _set_values("damping", model, damping)
    return model, None


def _scene(name, material, values):
    if name == "friction":
        return table_scene(material, values[0])
    return (wind_scene if name == "wind" else damping_scene)(material, values)


def _set_values(name, model, values):
    if name == "friction":
        friction = model.contact_friction.numpy()
        model.contact_friction.assign(np.array([friction[0], values[0]]))
    elif name == "wind":
        model.wind_velocity.assign(np.array([values], dtype=np.float64))
    else:
        model.damping_mass.assign(np.array([values[0]]))
        model.damping_stiffness.assign(np.array([values[1]]))


def _rel_err_pct(name, fitted, truth) -> float:
    # the wind: the vectors' norms; the damping: the larger of its two coefficients' relative errors
    fitted, truth = np.asarray(fitted, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    if name == "damping":
        return 100.0 * float(np.max(np.abs(fitted - truth) / truth))
    return 100.0 * float(np.linalg.norm(fitted - truth) / np.linalg.norm(truth))


def run_parameter(name: str, args) -> dict:
    """One scene parameter's fits from point clouds, one per recording seed, with the material known."""
    material = wc.preset("gray-interlock", thicken=S.THICKEN)
    spec = PARAMETER_SCENES[name]
    key = "+".join(spec["free"])
    truth = np.asarray(spec["truth"], dtype=np.float64)
    model, obstacle = _scene(name, material, spec["truth"])
    frames = E.TrajectoryFit.simulate_targets(model, material, steps=args.steps)
    x = np.concatenate(frames)
    centre = 0.5 * (x.min(axis=0) + x.max(axis=0))
    offset = TABLE_CAMERA_OFFSET if name == "friction" else HANGING_CAMERA_OFFSET
    camera = R.look_at(centre + np.array(offset), centre, **CAMERA)
    obstacles = () if obstacle is None else (obstacle,)
    rot = _rotation_y(TILT_DEG)
    record = {"scene": name, "parameter": key, "truth": truth, "start": np.asarray(spec["start"], dtype=np.float64),
              "bounds": spec.get("bounds"), "frames": len(frames),
              "camera": {"eye": camera.eye, "forward": camera.forward, **CAMERA},
              "in_image": in_image(camera, frames),
              "seen_fraction": seen_fraction(camera, frames, model.triangles_np, np.random.default_rng(12345))}
    if name == "friction":  # how far the centre slid down the table
        along = [(rot.T @ f.mean(axis=0))[0] for f in frames]
        record["slide_m"] = float(along[0] - along[-1])
    runs = []
    for seed in range(args.seeds):
        rng = np.random.default_rng(seed)
        clouds = R.point_cloud_recording(frames, model.triangles_np, points=args.points, noise=NOISE, camera=camera,
                                         drop=DROP, obstacles=obstacles, rng=rng)
        fit_model, _ = _scene(name, material, spec["truth"])
        _set_values(name, fit_model, spec["start"])
        fit = E.TrajectoryFit(fit_model, PointCloudFrames(clouds), steps=args.steps, reference=frames)
        t0 = time.perf_counter()
        bounds = {n: spec["bounds"] for n in spec["free"]} if spec.get("bounds") else None
        result = E.estimate_material(fit, initial=material, free=spec["free"], iters=args.param_iters,
                                     curriculum=None, bounds=bounds)
        fitted = np.concatenate([np.asarray(result.parameters[n], dtype=np.float64) for n in spec["free"]])
        run = {"seed": seed, "fitted": fitted, "rel_err_pct": _rel_err_pct(name, fitted, truth),
               "start_rel_err_pct": _rel_err_pct(name, record["start"], truth),
               "sim_err_pct": result.simulation_error_pct, "sim_err_pct_start": result.initial_simulation_error_pct,
               "evaluations": len(result.losses), "seconds": time.perf_counter() - t0,
               "diverged": len(result.diverged), "dropped_frames": [k for k, c in enumerate(clouds) if c is None]}
        runs.append(run)
        print(f"{name:8s} seed {seed}: {key} {np.array2string(fitted, precision=4)} (true "
              f"{np.array2string(truth, precision=4)}): error {run['rel_err_pct']:.3g} %  sim err "
              f"{run['sim_err_pct']:.3g} %  ({run['seconds']:.0f} s)", flush=True)
    record["runs"] = runs
    record["median_rel_err_pct"] = common.median([r["rel_err_pct"] for r in runs])
    record["limit_pct"] = PARAMETER_LIMIT_PCT
    record["met"] = bool(record["median_rel_err_pct"] <= PARAMETER_LIMIT_PCT)
    return record


def run_parameters(args) -> dict:
    scenes = [run_parameter(name, args) for name in PARAMETER_SCENES]
    print("\nscene parameters from point clouds (material known):")
    for s in scenes:
        print(f"  {s['scene']:8s} {s['parameter']:18s} median error {s['median_rel_err_pct']:.3g} % over "
              f"{len(s['runs'])} seed(s) (limit {s['limit_pct']:g} %): {'met' if s['met'] else 'not met'}")
    settings = {"optimizer": "lbfgs", "curriculum": None, "iters": args.param_iters, "seeds": args.seeds,
                "steps": args.steps, "dt": E.DT, "frame_stride": E.FRAME_STRIDE, "points": args.points,
                "noise_m": NOISE, "drop": DROP, "material": "gray-interlock", "tilt_deg": TILT_DEG,
                "drop_height_m": DROP_HEIGHT, "table_camera_offset_m": TABLE_CAMERA_OFFSET,
                "hanging_camera_offset_m": HANGING_CAMERA_OFFSET, "camera": CAMERA}
    return {"settings": settings, "scenes": scenes}


# -- a start shape unknown -----------------------------------------------------------------------------------------
START_FRAME = 10
"""The seed frame the start part starts from (the cloth draped and moving): the truth is the seed's frames from it."""
START_LIMIT = 2.0
"""Target: the fit from point clouds alone within this many times the fit given the start (simulation error)."""
START_FIGURES = ("sim_err_pct", "material_sim_err_pct", "density_err_pct", "stretch_linear_err_pct", "seconds")


START_KINDS = ("given", "alone")
"""The start part's fits: given the true start; from the point clouds alone (``registered_start``, the start's shape
and velocity free)."""
START_FREE = ["start_deformation", "start_deformation_rate"]
"""The start parameters the fit from point clouds alone frees beside the material."""
START_SHARE = 1 / 3
"""The share of its evaluations the fit from point clouds alone spends on the start alone, the material held, before
it fits both; the start scan is skipped (its forward runs would judge materials from a start not yet fitted)."""


def registration(files, frames, clouds, targets) -> tuple[np.ndarray, dict]:
    """The start registered on cloud 0 (``estimation.registered_start``) and its distances from the true start
    (frame 0) and of its handles from the scene's handle ``targets``."""
    model = S.hanging_cloth(E.initial_guess(), mesh_path=files[0], lagged_normals=True, self_collision=True)
    positions = E.registered_start(model, clouds[0])
    held = model.handle_particle.numpy()
    gap = np.linalg.norm(positions - frames[0], axis=1)
    return positions, {"registration_err_mean_m": float(gap.mean()), "registration_err_max_m": float(gap.max()),
                       "handle_err_m": gap[held],
                       "handle_target_shift_m": np.linalg.norm(positions[held] - targets, axis=1)}


def simulation_error_from(files, frames, clouds, material, velocities, args, registered=None) -> float:
    """The simulation error of ``material`` against the seed's vertex ``frames`` from the start with ``velocities``
    at its positions: without ``registered``, the true ones (frame 0) with the scene's handles; else those
    positions, placed by ``place_start``."""
    model = S.hanging_cloth(E.initial_guess(), mesh_path=files[0], lagged_normals=True, self_collision=True)
    if registered is None:
        model.particle_x0.assign(frames[0].astype(model.particle_x0.numpy().dtype))
    else:
        E.place_start(model, registered)
    model.particle_v0.assign(np.asarray(velocities).astype(model.particle_v0.numpy().dtype))
    return E.TrajectoryFit(model, PointCloudFrames(clouds), steps=args.steps, reference=frames).simulation_error(
        material)


def start_fit(files, frames, clouds, truth, args, start, positions=None) -> dict:
    """One fit of the material from point clouds ``clouds`` (frame 0: the start frame), its errors against the seed's
    vertex frames ``frames``: without ``positions``, from ``start``, the true (positions, velocities), with the
    scene's handles; else from the registered ``positions`` (``place_start``), the start parameters ``START_FREE``
    free from zero (alone for ``START_SHARE`` of the evaluations, then with the material), and the fitted start's
    distances from the true one."""
    model = S.hanging_cloth(E.initial_guess(), mesh_path=files[0], lagged_normals=True, self_collision=True)
    free = list(E.MATERIAL_PARTS)
    first = None
    if positions is not None:
        E.place_start(model, positions)
        free += START_FREE
    else:
        model.particle_x0.assign(start[0].astype(model.particle_x0.numpy().dtype))
        model.particle_v0.assign(start[1].astype(model.particle_v0.numpy().dtype))
    fit = E.TrajectoryFit(model, PointCloudFrames(clouds), steps=args.steps, reference=frames)
    if positions is None:
        result = E.estimate_material(fit, optimizer=args.optimizer, iters=args.iters, free=free)
    else:
        share = max(1, int(round(START_SHARE * args.iters))) if args.iters > 1 else 0
        if share:  # the fitted start stays in the model; the second fit frees it anew from there
            first = E.estimate_material(fit, optimizer=args.optimizer, iters=share, free=START_FREE)
        result = E.estimate_material(fit, optimizer=args.optimizer, iters=args.iters - share, free=free, scan=None)
    errors = E.parameter_errors(result.material, truth)
    run = {"sim_err_pct": result.simulation_error_pct,
           "material_sim_err_pct": simulation_error_from(files, frames, clouds, result.material, start[1], args),
           "sim_err_pct_start": (
               result.initial_simulation_error_pct if first is None else first.initial_simulation_error_pct),
           "density_err_pct": errors["density_err_pct"], "stretch_linear_err_pct": errors["stretch_linear_err_pct"],
           "bending_err_pct": errors["bending_err_pct"],
           "evaluations": len(result.losses) + (0 if first is None else len(first.losses)),
           "seconds": result.seconds + (0.0 if first is None else first.seconds), "diverged": len(result.diverged)}
    for name in free[len(E.MATERIAL_PARTS):]:
        run[name] = np.asarray(result.parameters[name], dtype=np.float64)
    if positions is not None:  # the model keeps the fitted start
        run["fitted_start_err_mean_m"] = float(np.linalg.norm(model.particle_x0.numpy() - start[0], axis=1).mean())
        run["fitted_velocity_err_rms"] = float(np.sqrt(np.mean(np.sum((model.particle_v0.numpy() - start[1]) ** 2,
                                                                      axis=1))))
    return run


def run_start_sequence(short: str, args) -> dict:
    """The start part on one seed sequence: per recording seed, each of ``START_KINDS``."""
    name = SEED_TARGETS[short]
    truth = wc.preset(name, thicken=S.THICKEN)
    files = wc.obj_sequence_files(common.seed_dir() / "targets" / short)
    frames = [np.asarray(f, dtype=np.float64) for f in wc.load_obj_sequence(files)]
    k = args.start_frame
    if k < 1 or k + args.steps // E.FRAME_STRIDE >= len(frames):
        raise SystemExit(f"--start-frame {k} with --steps {args.steps}: the seed's {short} has {len(frames)} frames")
    recorded = frames[k: k + args.steps // E.FRAME_STRIDE + 1]
    velocities = np.asarray(mesh_io.load_obj(files[k]).velocities, dtype=np.float64)  # the seed's own (nv lines)
    model = S.hanging_cloth(E.initial_guess(), mesh_path=files[0], lagged_normals=True, self_collision=True)
    held = model.handle_particle.numpy()
    targets = np.asarray(model.handle_rest_target, dtype=np.float64).copy()  # one per handle
    camera = camera_for(recorded)
    central = (frames[k + 1] - frames[k - 1]) / (2 * E.DT * E.FRAME_STRIDE)
    record = {"target": short, "material": name, "start_frame": k, "frames": len(recorded),
              "moved_from_frame0_m": float(np.linalg.norm(recorded[0] - frames[0], axis=1).mean()),
              "true_mean_velocity": velocities.mean(axis=0),
              "velocity_rms": float(np.sqrt((velocities ** 2).sum(axis=1).mean())),
              "velocity_vs_central_difference_rms": float(np.sqrt(((velocities - central) ** 2).sum(axis=1).mean())),
              "handles": held, "handle_sag_m": np.linalg.norm(recorded[0][held] - targets, axis=1),
              "in_image": in_image(camera, recorded)}
    runs = {kind: [] for kind in START_KINDS}
    for seed in range(args.seeds):
        clouds = R.point_cloud_recording(recorded, model.triangles_np, points=args.points, noise=NOISE,
                                         camera=camera, drop=DROP, rng=np.random.default_rng(seed))
        positions, placed = registration(files, recorded, clouds, targets)
        placed["truth_sim_err_pct"] = simulation_error_from(files, recorded, clouds, truth, velocities, args,
                                                            registered=positions)
        placed["truth_at_rest_sim_err_pct"] = simulation_error_from(files, recorded, clouds, truth,
                                                                    np.zeros_like(velocities), args,
                                                                    registered=positions)
        for kind in START_KINDS:
            t0 = time.perf_counter()
            if kind == "given":
                run, more = start_fit(files, recorded, clouds, truth, args, start=(recorded[0], velocities)), ""
            else:
                run = {**start_fit(files, recorded, clouds, truth, args, (recorded[0], velocities), positions),
                       **placed}
                more = (f"  registered: mean {placed['registration_err_mean_m'] * 100:.3g} cm, handles "
                        f"{np.array2string(placed['handle_err_m'] * 100, precision=3)} cm; fitted: mean "
                        f"{run['fitted_start_err_mean_m'] * 100:.3g} cm, velocity rms "
                        f"{run['fitted_velocity_err_rms']:.3g} m/s")
            run["seed"] = seed
            runs[kind].append(run)
            print(f"{short:6s} start {kind:16s} seed {seed}: sim err {run['sim_err_pct']:.3g} %  material from the "
                  f"true start {run['material_sim_err_pct']:.3g} %  density "
                  f"{run['density_err_pct']:.3g} %{more}  ({time.perf_counter() - t0:.0f} s)", flush=True)
    for kind, rs in runs.items():
        record[kind] = {"runs": rs, "median": {key: common.median([r[key] for r in rs]) for key in START_FIGURES}}
    record["targets"] = {key: {"ratio": r, "limit": START_LIMIT, "met": bool(r <= START_LIMIT)}
                         for key in ("sim_err_pct", "density_err_pct")
                         for r in [ratio(record["alone"]["median"][key], record["given"]["median"][key])]}
    record["material_ratio"] = ratio(record["alone"]["median"]["material_sim_err_pct"],
                                     record["given"]["median"]["material_sim_err_pct"])
    record["truth_from_registered"] = {key: common.median([r[key] for r in runs["alone"]])
                                       for key in ("truth_sim_err_pct", "truth_at_rest_sim_err_pct")}

    return record


def run_start(args, write=None) -> dict:
    """The start part: every chosen sequence; ``write(part)`` after each (so a cut-short run keeps what it did)."""
    shorts = list(SEED_TARGETS) if args.sequences == "all" else args.sequences.split(",")
    settings = {"optimizer": args.optimizer, "iters": args.iters, "seeds": args.seeds, "steps": args.steps,
                "start_frame": args.start_frame, "dt": E.DT, "frame_stride": E.FRAME_STRIDE, "points": args.points,
                "noise_m": NOISE, "drop": DROP, "camera_offset_m": CAMERA_OFFSET, "camera": CAMERA,
                "limit": START_LIMIT, "lagged_normals": True, "self_collision": True,
                "given": "the seed's vertices and velocities (its OBJ nv lines) at the start frame; the scene's "
                         "handles",
                "alone": "estimation.registered_start on the start frame's cloud (the held corners kept), "
                         "place_start, start_deformation and start_deformation_rate free from zero: alone for "
                         f"{START_SHARE:.3g} of the evaluations, then with the material, no start scan"}
    part = {"settings": settings, "sequences": []}
    for short in shorts:
        part["sequences"].append(run_start_sequence(short, args))
        part["targets"] = {key: all(s["targets"][key]["met"] for s in part["sequences"])
                           for key in ("sim_err_pct", "density_err_pct")}
        if write is not None:
            write(part)
    print(f"\nthe start unknown (from seed frame {args.start_frame}): point clouds alone over given the start "
          "(medians over the recording seeds)")
    for s in part["sequences"]:
        for key, t in s["targets"].items():
            print(f"  {s['target']:6s} {key:16s} alone {s['alone']['median'][key]:.3g}  given "
                  f"{s['given']['median'][key]:.3g}  {t['ratio']:6.2f}x  (limit {t['limit']}x): "
                  f"{'met' if t['met'] else 'not met'}")
        floor = s["truth_from_registered"]
        print(f"  {s['target']:6s} the fitted material from the true start: alone over given "
              f"{s['material_ratio']:.2f}x; the true material from the registered start: "
              f"{floor['truth_sim_err_pct']:.3g} % (true velocities), {floor['truth_at_rest_sim_err_pct']:.3g} % "
              "(at rest)")
    return part


def run_sequences(args) -> dict:
    shorts = list(SEED_TARGETS) if args.sequences == "all" else args.sequences.split(",")
    unknown = [s for s in shorts if s not in SEED_TARGETS]
    if unknown:
        raise SystemExit(f"--sequences: unknown {unknown}; choose from {', '.join(SEED_TARGETS)}")
    tasks = [t for short in shorts for t in sequence_tasks(short, args)]
    if args.workers > 1:
        with ProcessPoolExecutor(args.workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            runs = list(pool.map(fit_task, tasks))
    else:
        runs = [fit_task(t) for t in tasks]
    sequences = [sequence_record(short, [r for t, r in zip(tasks, runs) if t[0] == short], args) for short in shorts]

    rows = []
    for s in sequences:
        for kind in KINDS:
            m, single = s[kind]["median"], s[kind]["median_single"]
            rows.append([s["target"], kind, len(s[kind]["runs"]), m["sim_err_pct"], m["density_err_pct"],
                         m["stretch_linear_err_pct"], single["sim_err_pct"], single["density_err_pct"],
                         s[kind]["s_per_eval"], s[kind]["s_per_step_iter"]])
    print(f"\nfits to the seed's target sequences, {args.optimizer}, {args.iters} evaluations of {args.steps} steps "
          f"each, from {STARTS} starts: medians over the recording seeds of each one's fit of least loss "
          "(best), and over every fit (single)")
    common.print_table(["sequence", "observation", "fits", "sim err %", "density %", "linear str %",
                        "single: sim err %", "density %", "s/eval", "s/step/iter"], rows,
                       ["", "", "d", ".3g", ".3g", ".3g", ".3g", ".3g", ".3g", ".3g"])
    cost_rows = [[s["target"], kind, c["frames"], 1e3 * c["forward_s_per_frame"],
                  1e3 * c["forward_backward_s_per_frame"]] for s in sequences for kind, c in s["loss_cost"].items()]
    common.print_table(["sequence", "loss", "frames", "forward ms/frame", "fwd+bwd ms/frame"], cost_rows,
                       ["", "", "d", ".3g", ".3g"], title="the losses' cost per frame holding data")
    for title, key in (("best of the starts", "targets"), ("single fits", "targets_single")):
        print(f"\ntargets, {title} (the recording's median over the vertex fit's):")
        for s in sequences:
            for name, t in s[key].items():
                print(f"  {s['target']:6s} {name:30s} {t['ratio']:6.2f}x  (limit {t['limit']}x): "
                      f"{'met' if t['met'] else 'not met'}")
    settings = {"optimizer": args.optimizer, "iters": args.iters, "seeds": args.seeds, "steps": args.steps,
                "frame_stride": E.FRAME_STRIDE, "points": args.points, "noise_m": NOISE, "drop": DROP,
                "markers": args.markers, "hidden": HIDDEN, "camera_offset_m": CAMERA_OFFSET, "camera": CAMERA,
                "lagged_normals": True, "self_collision": True, "workers": args.workers,
                "starts": [start_name(k) for k in range(STARTS)]}
    summary = {key: all(s["targets"][key]["met"] for s in sequences) for key in sequences[0]["targets"]}
    summary_single = {key: all(s["targets_single"][key]["met"] for s in sequences)
                      for key in sequences[0]["targets_single"]}
    return {"settings": settings, "sequences": sequences, "targets": summary, "targets_single": summary_single}


def jsonable(obj):
    """``obj`` with arrays as lists and non-finite floats as None (strict JSON), as common.write_result writes."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    return None if isinstance(obj, float) and not math.isfinite(obj) else obj


def main():
    args = common.parse_args(__doc__, iters=150, seeds=3, sequences="all", optimizer="lbfgs", steps=E.STEPS,
                             points=2000, markers=12, parts="all", param_iters=20, start_frame=START_FRAME, workers=1,
                             quick={"iters": 2, "seeds": 1, "sequences": "gray", "steps": 4, "points": 200,
                                    "param_iters": 2})
    parts = list(PARTS) if args.parts == "all" else args.parts.split(",")
    unknown = [p for p in parts if p not in PARTS]
    if unknown or not parts:
        raise SystemExit(f"--parts: unknown {unknown}; choose all or some of {', '.join(PARTS)}")
    info = common.machine_info()
    common.print_machine(info)
    path = Path(args.out)
    old = json.loads(path.read_text()) if path.exists() and set(parts) != set(PARTS) else {}
    if old and "sequences" not in parts and old.get("meta", {}).get("quick", args.quick) != args.quick:
        raise SystemExit(f"--parts {args.parts}: {path} holds a {'--quick' if old['meta']['quick'] else 'full'} run; "
                         "this run is not: write elsewhere with --out")
    data = {}

    def write_parts(done: dict) -> None:
        # the parts run now (each but the sequences with its own meta); the others as the file at --out holds them
        if "sequences" in parts:
            kept = {k: old[k] for k in PARTS[1:] if k in old and k not in parts}
            common.write_result(args, {**done, **kept})
            return
        merged = {**old, **done} if old else {"meta": next(iter(done.values()))["meta"], **done}
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(jsonable(merged), indent=2) + "\n")
        print(f"\nwrote {path}: the {', '.join(parts)} part(s) (own meta); the rest as it was", flush=True)

    if "sequences" in parts:
        data.update(run_sequences(args))
    if "parameters" in parts:
        data["parameters"] = run_parameters(args)
        data["parameters"]["meta"] = common.run_metadata(args)  # this part's own run
    if "start" in parts:
        def partial(part):
            part["meta"] = common.run_metadata(args)
            if parts == ["start"]:
                write_parts({**data, "start": part})

        data["start"] = run_start(args, partial)
        data["start"]["meta"] = common.run_metadata(args)
    write_parts(data)


if __name__ == "__main__":
    main()
