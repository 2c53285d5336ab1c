"""Fits from what people record: the seed's own three target sequences as point clouds and as markers.

The seed's three target sequences (../shared/reference/liang2019/targets: 11oz, gray, tango; made by the seed's C++
code, their true fabrics known) fitted as material_estimation.py's cross-check fits them: the seed's demo_wind.obj
start, simulated as the seed did (lagged wind normals, self-collision), L-BFGS from the mean fabric, 50 steps, every
second step's frame compared. Each sequence is fitted three ways, with the same optimizer and ``--iters``
evaluations:

- vertices: every vertex of every compared frame (the cross-check's fit);
- point clouds (``warpcloth.recordings.point_cloud_recording``): ``--points`` points a frame with 2 mm Gaussian
  noise, sampled over the side a depth camera sees (``look_at``; 1.8 m in front of the hanging cloth, 0.3 m above
  the centre of its motion, 50 degrees wide, 640 x 480, the whole motion in view), the cloth's self-occlusion
  removed, 10 % of the frames dropped, fitted by the distance from each recorded point to the simulated surface;
- markers (``marker_recording``): ``--markers`` markers spread over the cloth, a fifth of the (frame, marker) pairs
  hidden.

The point clouds and the markers are drawn with ``--seeds`` recording seeds (0, 1, ...): every run is reported, and
the medians. Each fit's simulation error is measured against the seed's full vertex trajectory (the fit's
``reference``); density and linear stretching errors against the true fabric (``estimation.parameter_errors``).
Time per evaluation: the fit's wall time per evaluation and per simulated step. The losses' cost per frame: one
evaluation of each observation's loss (forward, and forward plus backward on a tape) on the seed's frames, per
frame that holds data. Targets (issue 55): the point-cloud fit's simulation error within 1.5x of the vertex fit's
on each sequence and its density error within 2x; the marker fit's simulation and density errors within 1.2x; the
point-cloud fit at most 2x the vertex fit's time per simulated step (medians over the seeds).

Usage: python benchmarks/recordings.py [--quick] [--out PATH] [--iters 150] [--seeds 3] [--sequences all|gray,...]
       [--optimizer lbfgs] [--steps 50] [--points 2000] [--markers 12]
       (--quick: gray, 4 steps, 2 evaluations, 1 seed, 200 points)
"""

from __future__ import annotations

import time

import common
import numpy as np
import warp as wp
from common import wc

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
"""Fraction of the (frame, marker) pairs hidden."""
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


def fit_once(files, frames, observation, truth, optimizer: str, iters: int, steps: int) -> dict:
    """One fit from the mean fabric; its errors against the seed's vertex frames and the true fabric."""
    model = S.hanging_cloth(E.initial_guess(), mesh_path=files[0], lagged_normals=True, self_collision=True)
    if observation is None:
        fit = E.TrajectoryFit(model, frames, steps=steps)
    else:
        fit = E.TrajectoryFit(model, observation, steps=steps, reference=frames)
    result = E.estimate_material(fit, optimizer=optimizer, iters=iters)
    errors = E.parameter_errors(result.material, truth)
    return {"sim_err_pct": result.simulation_error_pct, "sim_err_pct_start": result.initial_simulation_error_pct,
            "density_err_pct": errors["density_err_pct"],
            "stretch_linear_err_pct": errors["stretch_linear_err_pct"],
            "stretch_nonlinear_err_pct": errors["stretch_nonlinear_err_pct"],
            "bending_err_pct": errors["bending_err_pct"],
            "evaluations": len(result.losses), "simulated_steps": int(sum(result.horizons)),
            "seconds": result.seconds, "s_per_eval": result.seconds / max(len(result.losses), 1),
            "s_per_step_iter": result.seconds_per_step_iter, "diverged": len(result.diverged),
            "final_loss": float(min(result.losses))}


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


def run_sequence(short: str, args) -> dict:
    name = SEED_TARGETS[short]
    truth = wc.preset(name, thicken=S.THICKEN)
    files = wc.obj_sequence_files(common.seed_dir() / "targets" / short)
    frames = [np.asarray(f, dtype=np.float64) for f in wc.load_obj_sequence(files)]
    recorded = frames[: args.steps // E.FRAME_STRIDE + 1]  # the compared frames, frame 0 the start
    model = S.hanging_cloth(E.initial_guess(), mesh_path=files[0], lagged_normals=True, self_collision=True)
    triangles = model.triangles_np
    camera = camera_for(recorded)
    record = {"target": short, "material": name, "frames": len(recorded),
              "camera": {"eye": camera.eye, "forward": camera.forward, **CAMERA},
              "in_image": in_image(camera, recorded),
              "seen_fraction": seen_fraction(camera, recorded, triangles, np.random.default_rng(12345))}
    t0 = time.perf_counter()
    vertex = fit_once(files, frames, None, truth, args.optimizer, args.iters, args.steps)
    print(f"{short:6s} vertices     sim err {vertex['sim_err_pct']:.3g} %  density {vertex['density_err_pct']:.3g} % "
          f" linear str {vertex['stretch_linear_err_pct']:.3g} %  ({time.perf_counter() - t0:.0f} s)", flush=True)
    runs = {"point_clouds": [], "markers": []}
    observations = {}
    for seed in range(args.seeds):
        rng = np.random.default_rng(seed)
        clouds = R.point_cloud_recording(recorded, triangles, points=args.points, noise=NOISE, camera=camera,
                                         drop=DROP, rng=rng)
        markers = R.marker_recording(recorded, triangles, markers=args.markers, hidden=HIDDEN, rng=rng)
        observations[seed] = {"point_clouds": PointCloudFrames(clouds),
                              "markers": MarkerFrames(markers.triangles, markers.barycentric, markers.positions)}
        for kind in ("point_clouds", "markers"):
            t0 = time.perf_counter()
            run = fit_once(files, frames, observations[seed][kind], truth, args.optimizer, args.iters, args.steps)
            run["seed"] = seed
            if kind == "point_clouds":
                run["dropped_frames"] = [k for k, c in enumerate(clouds) if c is None]
            else:
                run["hidden_pairs"] = int(np.isnan(markers.positions[..., 0]).sum())
            runs[kind].append(run)
            print(f"{short:6s} {kind:12s} seed {seed}: sim err {run['sim_err_pct']:.3g} %  density "
                  f"{run['density_err_pct']:.3g} %  linear str {run['stretch_linear_err_pct']:.3g} %  "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
    record["vertices"] = {"runs": [vertex], "median": median_record([vertex])}
    for kind, rs in runs.items():
        record[kind] = {"runs": rs, "median": median_record(rs)}
    reps = 3 if args.quick else 10
    record["loss_cost"] = {"vertices": loss_cost(VertexFrames(np.stack(recorded)), model, recorded, reps),
                           **{kind: loss_cost(observations[0][kind], model, recorded, reps)
                              for kind in ("point_clouds", "markers")}}
    record["targets"] = targets(record)
    return record


def ratio(a: float, b: float) -> float:
    return a / b if b > 0.0 else float("inf")


def targets(record: dict) -> dict:
    """Each target of a sequence: the ratio of the recording's median to the vertex fit's, its limit and whether it
    is met."""
    vertex = record["vertices"]["median"]
    out = {}
    for kind, limits in LIMITS.items():
        for key, limit in limits.items():
            r = ratio(record[kind]["median"][key], vertex[key])
            out[f"{kind}.{key}"] = {"ratio": r, "limit": limit, "met": bool(r <= limit)}
    r = ratio(record["point_clouds"]["median"]["s_per_step_iter"], vertex["s_per_step_iter"])
    out["point_clouds.s_per_step_iter"] = {"ratio": r, "limit": SPEED_LIMIT, "met": bool(r <= SPEED_LIMIT)}
    return out


def main():
    args = common.parse_args(__doc__, iters=150, seeds=3, sequences="all", optimizer="lbfgs", steps=E.STEPS,
                             points=2000, markers=12,
                             quick={"iters": 2, "seeds": 1, "sequences": "gray", "steps": 4, "points": 200})
    info = common.machine_info()
    common.print_machine(info)
    shorts = list(SEED_TARGETS) if args.sequences == "all" else args.sequences.split(",")
    unknown = [s for s in shorts if s not in SEED_TARGETS]
    if unknown:
        raise SystemExit(f"--sequences: unknown {unknown}; choose from {', '.join(SEED_TARGETS)}")
    sequences = [run_sequence(short, args) for short in shorts]

    rows = []
    for s in sequences:
        for kind in KINDS:
            m = s[kind]["median"]
            rows.append([s["target"], kind, len(s[kind]["runs"])] + [m[k] for k in FIGURES])
    print(f"\nfits to the seed's target sequences, {args.optimizer}, {args.iters} evaluations of {args.steps} steps "
          f"each (medians over the recording seeds)")
    common.print_table(["sequence", "observation", "runs", "sim err %", "density %", "linear str %", "s/eval",
                        "s/step/iter"], rows, ["", "", "d", ".3g", ".3g", ".3g", ".3g", ".3g"])
    cost_rows = [[s["target"], kind, c["frames"], 1e3 * c["forward_s_per_frame"],
                  1e3 * c["forward_backward_s_per_frame"]] for s in sequences for kind, c in s["loss_cost"].items()]
    common.print_table(["sequence", "loss", "frames", "forward ms/frame", "fwd+bwd ms/frame"], cost_rows,
                       ["", "", "d", ".3g", ".3g"], title="the losses' cost per frame holding data")
    print("\ntargets (the recording's median over the vertex fit's):")
    for s in sequences:
        for key, t in s["targets"].items():
            print(f"  {s['target']:6s} {key:30s} {t['ratio']:6.2f}x  (limit {t['limit']}x): "
                  f"{'met' if t['met'] else 'not met'}")
    settings = {"optimizer": args.optimizer, "iters": args.iters, "seeds": args.seeds, "steps": args.steps,
                "frame_stride": E.FRAME_STRIDE, "points": args.points, "noise_m": NOISE, "drop": DROP,
                "markers": args.markers, "hidden": HIDDEN, "camera_offset_m": CAMERA_OFFSET, "camera": CAMERA,
                "lagged_normals": True, "self_collision": True}
    summary = {key: all(s["targets"][key]["met"] for s in sequences) for key in sequences[0]["targets"]}
    common.write_result(args, {"settings": settings, "sequences": sequences, "targets": summary})


if __name__ == "__main__":
    main()
