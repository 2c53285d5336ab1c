"""The seed's Table 1: back-propagation through the collision response, dense KKT against the QR formula.

Scene (SPEC.md §5(a)): the pre-crumpled cloths ``demo_collision{16x16,32x32,64x64}.obj`` inside the funnel
``contain.obj`` translated by (-0.5, -1, -0.55), gray-interlock (thicken 2), gravity, dt 0.02, cloth-obstacle and
self-collision on, float64 (as the seed), one step; loss = mean over vertices of |x_i|.

For each mesh and repetition: the step is taped and timed (``forward_s``: implicit solve, detection and every
projection round); ``tape.backward`` runs with the QR adjoint; then the recorded adjoint of every projection round of
that step is timed again on the same dL/dz in both modes, each from scratch (the QR factorisation included, it is
computed lazily): ``qr_backward_s`` and ``kkt_backward_s`` are those sums over the step's rounds and zones, i.e. the
backward time of the collision response in one step (every round of it); the per-zone means (zones with more than
one contact) compare with the seed's per-zone log line. Matrix sizes are per impact zone with more than one contact, over all rounds
and repetitions: ``kkt_size`` = nvar + ncon (the dense KKT system), ``qr_size`` = independent active constraints
(the columns of the QR). Seed numbers are the slides' (authors' machine).

Usage: python benchmarks/collision_ablation.py [--meshes 16x16,32x32,64x64] [--reps 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import warp as wp

import common
from common import wc
from warpcloth.collision import projection

SEED = {  # mesh: (baseline size, baseline s, ours size, ours s, speedup)
    "16x16": ("599 ± 76", 0.33, "66 ± 26", 0.013, 25),
    "32x32": ("1326 ± 23", 1.2, "97 ± 24", 0.011, 112),
    "64x64": ("2024 ± 274", 4.6, "242 ± 47", 0.072, 64),
}
TARGET_FORWARD_32_S = 1.0


def build(mesh: str):
    meshes = common.seed_dir() / "meshes"
    b = wc.ModelBuilder()
    b.add_cloth_obj(meshes / f"demo_collision{mesh}.obj", material=wc.preset("gray-interlock", thicken=2))
    b.add_obstacle_obj(meshes / "contain.obj", pos=(-0.5, -1.0, -0.55))
    b.set_collision(self_collision=True)
    model = b.finalize("cpu", requires_grad=True, dtype=wp.float64)
    return model, wc.Simulator(model, 0.02)


def time_adjoints(stage, mode: str) -> tuple[float, list[float]]:
    """Seconds to run every recorded projection adjoint of the last step in ``mode`` (factorisations included),
    and the per-zone times of the zones with more than one contact."""
    total, per_zone = 0.0, []
    for result, z in stage.last_projections:
        for zone in result.zones:
            if zone is not None:
                zone.qr = None  # the QR is computed lazily by the first backward: time it every time
        grad = z.grad.numpy().astype(np.float64)
        t0 = time.perf_counter()
        projection.backward(result, grad, mode=mode)
        total += time.perf_counter() - t0
        per_zone += [rec["backward_s"] for rec in result.backward_stats if rec["kkt_size"] > 4]
    return total, per_zone


def run_mesh(mesh: str, reps: int) -> dict:
    model, sim = build(mesh)
    forward, qr_s, kkt_s, kkt_sizes, qr_sizes, rounds, contacts = [], [], [], [], [], [], []
    qr_zone, kkt_zone = [], []
    for _ in range(reps):
        sim._previous_dv = None
        state = model.state()
        out = model.empty_state()
        tape = wp.Tape()
        t0 = time.perf_counter()
        with tape:
            sim.step(state, out)
        forward.append(time.perf_counter() - t0)
        x = out.particle_x.numpy()
        grad = x / np.linalg.norm(x, axis=1, keepdims=True) / model.particle_count  # d mean|x_i| / dx
        tape.backward(grads={out.particle_x: wp.array(grad, dtype=wp.vec3d)})
        stage = sim.collision
        t, zones = time_adjoints(stage, "qr")
        qr_s.append(t)
        qr_zone += zones
        t, zones = time_adjoints(stage, "kkt")
        kkt_s.append(t)
        kkt_zone += zones
        for result, _ in stage.last_projections:
            for rec in result.zones_stats():
                if rec["ncon"] > 1:
                    kkt_sizes.append(rec["kkt_size"])
                    qr_sizes.append(rec["qr_size"])
        rounds.append(stage.last["rounds"])
        contacts.append(stage.last["contacts"])
        tape.zero()
    kkt = float(np.median(kkt_s))
    qr = float(np.median(qr_s))
    return {
        "mesh": mesh,
        "particles": model.particle_count,
        "kkt_size": float(np.mean(kkt_sizes)), "kkt_size_std": float(np.std(kkt_sizes)),
        "kkt_size_max": int(np.max(kkt_sizes)),
        "qr_size": float(np.mean(qr_sizes)), "qr_size_std": float(np.std(qr_sizes)),
        "qr_size_max": int(np.max(qr_sizes)),
        "zones": len(kkt_sizes) // reps,
        "kkt_backward_s": kkt, "kkt_backward_s_all": kkt_s,
        "qr_backward_s": qr, "qr_backward_s_all": qr_s,
        "speedup": kkt / qr,
        "kkt_backward_zone_s": float(np.mean(kkt_zone)), "qr_backward_zone_s": float(np.mean(qr_zone)),
        "kkt_backward_zone_s_std": float(np.std(kkt_zone)), "qr_backward_zone_s_std": float(np.std(qr_zone)),
        "forward_s": float(np.median(forward)), "forward_s_all": forward,
        "rounds": int(np.median(rounds)), "contacts": int(np.median(contacts)),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", default="16x16,32x32,64x64")
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--json", default=None, help="write the records here")
    args = parser.parse_args()
    wp.config.quiet = True
    wp.init()
    records = [run_mesh(m, args.reps) for m in args.meshes.split(",")]

    print(f"one step of the crumpled cloth in the funnel, float64, {args.reps} repetitions (medians); "
          "sizes: mean ± std (max) over impact zones with > 1 contact; seed: slides, authors' machine")
    header = ["mesh", "KKT size", "QR size", "KKT bwd s", "QR bwd s", "speedup", "KKT s/zone", "QR s/zone",
              "fwd s", "rounds", "contacts",
              "seed KKT s", "seed QR s", "seed speedup", "targets"]
    rows = []
    for r in records:
        seed = SEED.get(r["mesh"], ("-", float("nan"), "-", float("nan"), float("nan")))
        targets = [f"speedup >= {seed[4]}: {'ok' if r['speedup'] >= seed[4] else 'FAIL'}",
                   f"QR <= {seed[3] / 10 * 1e3:.1f} ms: {'ok' if r['qr_backward_s'] <= seed[3] / 10 else 'FAIL'}"]
        if r["mesh"] == "32x32":
            ok = r["forward_s"] < TARGET_FORWARD_32_S
            targets.append(f"fwd < {TARGET_FORWARD_32_S:g} s: {'ok' if ok else 'FAIL'}")
        rows.append([r["mesh"], f"{r['kkt_size']:.0f} ± {r['kkt_size_std']:.0f} ({r['kkt_size_max']})",
                     f"{r['qr_size']:.0f} ± {r['qr_size_std']:.0f} ({r['qr_size_max']})",
                     f"{r['kkt_backward_s']:.4f}", f"{r['qr_backward_s']:.4f}", f"{r['speedup']:.1f}",
                     f"{r['kkt_backward_zone_s']:.4f}", f"{r['qr_backward_zone_s']:.4f}",
                     f"{r['forward_s']:.3f}", str(r["rounds"]), str(r["contacts"]), f"{seed[1]:g}", f"{seed[3]:g}",
                     f"{seed[4]:g}", "; ".join(targets)])
    common.print_table(header, rows)
    common.write_json(args.json, records)


if __name__ == "__main__":
    main()
