"""Peak memory of back-propagating a long rollout: one full tape against ``wc.checkpointed_backward``.

Scenes (float64 where the gradient is compared):
- throw: the seed's throw into the basket (warpcloth.tasks.throw, 700 steps at dt 0.01, the basket and the wall,
  contact with repulsion and friction), pushes drawn with sigma 5 m/s^2 (numpy.random.default_rng(0));
- throw-16: 16 worlds of it in one batch, each with its own pushes (where a control task checkpoints by default);
- hanging: the seed's hanging cloth in a 5 m/s wind (16x16, gray-interlock), 500 steps at dt 0.01, no contact;
- drape: the drape-sphere scene (24x24 falling onto a sphere, repulsion and friction), 300 steps at dt 0.01.
The loss is a random linear function of the final positions (hanging, drape) or the throw's own; the gradient is
taken with respect to the start positions and the material densities (hanging, drape) or the pushes (throw).

Each mode (one tape or checkpointed segments; run as it comes, or captured as graphs and replayed:
``wc.CapturedRollout``, with ``segment_steps`` when checkpointed) of each scene runs in a fresh process: the kernels
are loaded by a two-step warm-up, then the process's peak resident set size is reset (``/proc/self/clear_refs`` 5)
and the figure is the peak (VmHWM) during one forward + backward minus the resident size before it; in a captured
mode, the peak over the capture and the replays (what the graphs hold, and what a replay adds). Warp's CPU arrays
live in the process heap. (Until issue 24 the throw's figure came from ``ru_maxrss``, the process's lifetime peak,
which the warm-up set: 382 MB for both modes.)

Usage: python benchmarks/memory.py [--quick] [--out PATH] [--scale 1.0]   (--quick: a tenth of the steps)
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import common
import numpy as np
import warp as wp
from common import wc

from warpcloth.tasks import throw
from warpcloth.tasks.scenes import THICKEN, basket_scene, hanging_cloth

SCENES = {"throw": throw.STEPS, "throw-16": throw.STEPS, "hanging": 500, "drape": 300}
"""Steps of each scene's rollout."""
WORLDS = {"throw-16": 16}
"""Worlds of a scene simulated as one batch (``ControlTask.worlds``: each world its own pushes): where a control task
checkpoints by default (more than gradients.WHOLE_TAPE_PARTICLE_STEPS particle-steps)."""
TARGET_RATIO = 0.25
"""Issue 24: the checkpointed backward's peak at most this fraction of the full tape's."""


def _status_mb(key: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"/proc/self/status has no {key}")


@wp.kernel
def _weighted_sum(x: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(out, 0, wp.dot(x[i], w[i]))


def _rollout_gradient(model: wc.Model, dt: float, steps: int, segment_steps: int | None) -> np.ndarray:
    """dL/d(x0, densities) of a random linear loss of the final positions, by checkpointed_backward."""
    sim = wc.Simulator(model, dt)
    w = wp.array(np.random.default_rng(1).standard_normal((model.particle_count, 3)), dtype=wp.vec3d)

    def loss(i, state, out):
        if i == steps:
            wp.launch(_weighted_sum, model.particle_count, inputs=[state.particle_x, w], outputs=[out])

    state = model.state()
    wc.checkpointed_backward(sim, state, None, steps=steps, loss=loss, segment_steps=segment_steps)
    return np.concatenate([state.particle_x.grad.numpy().ravel(), model.material_density.grad.numpy().ravel()])


def _captured_gradient(model: wc.Model, dt: float, steps: int, segment_steps: int | None):
    """A ``wc.CapturedRollout`` of the same loss (in segments where ``segment_steps``); returns the function that
    replays it and gives dL/d(x0, densities)."""
    sim = wc.Simulator(model, dt)
    w = wp.array(np.random.default_rng(1).standard_normal((model.particle_count, 3)), dtype=wp.vec3d)
    state = model.state(requires_grad=True)

    def loss(trajectory):
        out = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        wp.launch(_weighted_sum, model.particle_count, inputs=[trajectory[-1].particle_x, w], outputs=[out])
        return out

    captured = wc.CapturedRollout(sim, state, None, steps=steps, loss=loss, segment_steps=segment_steps)

    def replay():
        captured.run()
        return np.concatenate([state.particle_x.grad.numpy().ravel(), model.material_density.grad.numpy().ravel()])
    return replay


def _build(scene: str) -> tuple[wc.Model, float]:
    if scene == "hanging":
        return hanging_cloth(wc.preset("gray-interlock", thicken=THICKEN), dtype=wp.float64), 0.01
    drape = wc.load_scene("drape-sphere")
    return drape.model_builder.finalize(requires_grad=True, dtype=wp.float64), drape.dt


MODES = ("full", "checkpointed", "captured full", "captured checkpointed")
"""One tape over the rollout, or sqrt(T) segments (``wc.checkpointed_backward``); run, or replayed from graphs
(``wc.CapturedRollout``, with ``segment_steps`` when checkpointed)."""
REPLAYS = 3
"""Replays timed in a captured mode (the median is reported)."""


def child(scene: str, mode: str, steps: int) -> None:
    """One forward + backward in this process; prints JSON: peak memory above the start, seconds, gradient. A
    captured mode's peak spans its capture and replays (what the graphs hold, and what a replay adds), its seconds
    are the median replay's, and ``capture_seconds`` the time to the first replay."""
    # one segment is one tape over the whole rollout; checkpointed: sqrt(T) segments (a ControlTask's default tapes a
    # rollout this short whole)
    segment = steps if mode.endswith("full") else math.ceil(math.sqrt(steps))
    captured = mode.startswith("captured")
    if scene.startswith("throw"):
        model = basket_scene(dtype=wp.float64)
        throw.ThrowTask(model, steps=2).loss_and_grad(np.zeros(throw.N_PARAMS))  # loads every kernel module
        task = throw.ThrowTask(model, steps=steps, segment_steps=segment)
        worlds = WORLDS.get(scene, 1)
        if worlds > 1:
            task = task.worlds(worlds)
        params = list(np.random.default_rng(0).normal(scale=5.0, size=(worlds, throw.N_PARAMS)))

        def run():
            return np.concatenate([e.grad for e in task.evaluate_worlds(params, [None] * worlds)])
        if captured:
            run()  # a task captures its evaluation at the second (ControlTask._captured)
    else:
        model, dt = _build(scene)
        _rollout_gradient(model, dt, 2, None)  # loads every kernel module

        def run():
            model.material_density.grad.zero_()
            return _rollout_gradient(model, dt, steps, segment)
    Path("/proc/self/clear_refs").write_text("5")  # reset the peak resident size (VmHWM) to the current one
    before = _status_mb("VmRSS")
    t0 = time.perf_counter()
    if captured and not scene.startswith("throw"):
        run = _captured_gradient(model, dt, steps, segment if segment < steps else None)
    grad = run()
    seconds = time.perf_counter() - t0
    record = {"seconds": seconds}
    if captured:
        record["capture_seconds"] = seconds
        times = []
        for _ in range(REPLAYS):
            t0 = time.perf_counter()
            again = run()
            times.append(time.perf_counter() - t0)
        if not np.array_equal(again, grad):
            raise RuntimeError(f"{scene}, {mode}: a replay's gradient differs from the first's")
        record.update(seconds=float(np.median(times)), replay_seconds=times)
    record.update(peak_mb=_status_mb("VmHWM") - before, grad=grad.tolist())
    print(json.dumps(record))


def measure(scene: str, steps: int) -> dict:
    out = {"scene": scene, "steps": steps}
    for mode in MODES:
        proc = subprocess.run([sys.executable, __file__, "--child", scene, mode, str(steps)], capture_output=True,
                              text=True)
        if proc.returncode:
            raise RuntimeError(f"{scene}, {mode}: the child process failed:\n{proc.stderr[-3000:]}")
        out[mode] = json.loads(proc.stdout.strip().splitlines()[-1])
    grads = {m: np.asarray(out[m].pop("grad")) for m in MODES}
    full = grads["full"]
    out["grad_rel_diff"] = float(np.linalg.norm(grads["checkpointed"] - full) / np.linalg.norm(full))
    out["captured_grad_rel_diff"] = max(float(np.linalg.norm(grads[m] - full) / np.linalg.norm(full))
                                        for m in MODES[2:])
    out["grad_norm"] = float(np.linalg.norm(full))
    out["ratio"] = out["checkpointed"]["peak_mb"] / out["full"]["peak_mb"]
    out["captured_ratio"] = out["captured checkpointed"]["peak_mb"] / out["captured full"]["peak_mb"]
    return out


def main():
    if len(sys.argv) == 5 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3], int(sys.argv[4]))
        return
    args = common.parse_args(__doc__, scale=1.0, quick={"scale": 0.1})
    records = [measure(scene, max(2, round(steps * args.scale))) for scene, steps in SCENES.items()]
    rows = [[r["scene"], r["steps"], r["full"]["peak_mb"], r["checkpointed"]["peak_mb"], r["ratio"],
             r["full"]["seconds"], r["checkpointed"]["seconds"], r["grad_rel_diff"],
             "ok" if r["ratio"] <= TARGET_RATIO and r["grad_rel_diff"] <= 1e-6 else "FAIL"] for r in records]
    common.print_table(["scene", "steps", "full MB", "checkpointed MB", "ratio", "full s", "checkpointed s",
                        "gradient rel. diff", f"ratio <= {TARGET_RATIO:g}, diff <= 1e-6"], rows,
                       ["", "", ".1f", ".1f", ".3f", ".2f", ".2f", ".1e", ""],
                       title="peak resident memory above the start of one forward + backward (fresh process each)")
    rows = [[r["scene"], r["steps"], r["captured full"]["peak_mb"], r["captured checkpointed"]["peak_mb"],
             r["captured_ratio"], r["captured full"]["seconds"], r["captured checkpointed"]["seconds"],
             r["captured checkpointed"]["capture_seconds"], r["captured_grad_rel_diff"]] for r in records]
    common.print_table(["scene", "steps", "full MB", "checkpointed MB", "ratio", "full s", "checkpointed s",
                        "checkpointed capture s", "gradient rel. diff"], rows,
                       ["", "", ".1f", ".1f", ".3f", ".2f", ".2f", ".2f", ".1e"],
                       title=f"the same replayed from graphs (wc.CapturedRollout; seconds: the median of {REPLAYS} "
                             "replays; MB: the peak over the capture and the replays)")
    common.write_result(args, {"records": records, "target_ratio": TARGET_RATIO})


if __name__ == "__main__":
    main()
