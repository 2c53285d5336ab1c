"""Warp's deterministic mode (``wp.config.deterministic``, set before warpcloth is imported): every kernel compiles
under it, and a step's sums then come out in one order on CUDA too. Each run is a fresh process, since the mode is
fixed when the kernel modules are made."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import DEVICES

HERE = Path(__file__).parent

SCRIPT = """
import sys
import numpy as np
import warp as wp
mode, device, out = sys.argv[1:4]
if mode == "deterministic":
    wp.config.deterministic = wp.DeterministicMode.RUN_TO_RUN
sys.path.insert(0, {tests!r})
import warpcloth as wc
from test_devices import sphere_contact_model

results = {{}}
# repulsion pairs (each backend's pair products), contacts (the projection) and self-collision, with gradients
for backend in ("sequential", "tiled", "warp"):
    model = sphere_contact_model(device, self_collision=True)
    sim = wc.Simulator(model, 0.01, options=wc.SolverOptions(cg_tol=1e-10, cg_backend=backend,
                                                             preconditioner="block_jacobi"))
    control = model.control(requires_grad=True)
    tape = wp.Tape()
    with wp.ScopedDevice(device), tape:
        final = wc.rollout(sim, model.state(), control, steps=15)[-1]
    tape.backward(grads={{final.particle_x: wp.array(np.ones((model.particle_count, 3)), dtype=wp.vec3d,
                                                      device=device)}})
    assert sim.proximity.last_count > 0, "no repulsion pairs: the scene tests none of the pair products"
    results[backend + "-x"] = final.particle_x.numpy()
    results[backend + "-density"] = model.material_density.grad.numpy()
    results[backend + "-obstacle"] = control.obstacle_transform.grad.numpy()
np.savez(out, **results)
"""


def run(mode: str, device: str, out: Path) -> dict:
    subprocess.run([sys.executable, "-c", SCRIPT.format(tests=str(HERE)), mode, device, str(out)], check=True,
                   timeout=900)
    with np.load(out) as data:
        return dict(data)


@pytest.mark.parametrize("device", DEVICES)
def test_every_kernel_runs_under_warps_deterministic_mode(device, tmp_path):
    first = run("deterministic", device, tmp_path / "first.npz")
    if device == "cpu":
        # the CPU adds in one order anyway: the mode changes nothing there (one thread a world adds the pairs'
        # products, as the tiled backend's one thread per block does)
        other = run("default", device, tmp_path / "default.npz")
    else:  # CUDA: the mode's point, bitwise the same result at every run
        other = run("deterministic", device, tmp_path / "second.npz")
    assert first.keys() == other.keys()
    for key in first:
        assert np.array_equal(first[key], other[key]), key
        assert np.all(np.isfinite(first[key])) and np.abs(first[key]).max() > 0, key
