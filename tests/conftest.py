"""Shared scene for the gradient, physics and error tests: a small cloth hanging in a vertical plane."""

import os
from pathlib import Path

import numpy as np
import pytest
import warp as wp

import warpcloth as wc

wp.config.log_level = wp.LOG_WARNING  # no module-load lines in the test output

VERTICAL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Rotation taking the grid's local XY plane to world XZ (local y -> world z, so the grid hangs in a wall)."""


def top_corners(res: int) -> tuple[int, int]:
    """Particle indices of the top-left and top-right vertices of a res x res grid."""
    return res * (res + 1), res * (res + 1) + res


def hanging_builder(*, res=4, size=0.5, material=None, gravity=(0.0, 0.0, -2.0), handle_stiffness=300.0,
                    wind=(0.5, 2.0, 0.0), moving_pin=False) -> wc.ModelBuilder:
    """res x res cloth in the XZ plane, top edge at z = 0, held at its top corners by two soft handles.

    ``wind`` (None for none) blows mostly across the plane so the cloth bends; with ``moving_pin`` the top-left
    corner is a hard pin with scripted motion instead of a handle.
    """
    b = wc.ModelBuilder(gravity=gravity)
    material = material if material is not None else wc.preset("gray-interlock", thicken=2)
    b.add_cloth_grid((res, res), (size, size), material=material, rot=VERTICAL, pos=(0.0, 0.0, -size))
    left, right = top_corners(res)
    if moving_pin:
        b.add_pin(left, motion=[(0.0, (0.0, 0.0, 0.0)), (0.1, (0.02, 0.04, 0.03)), (1.0, (0.02, 0.04, 0.03))])
    else:
        b.add_handle(left, stiffness=handle_stiffness)
    b.add_handle(right, stiffness=handle_stiffness)
    if wind is not None:
        b.set_wind(wind, density=1.0, drag=0.1)
    return b


DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
"""Every device the suite runs on: the CPU always, CUDA when present."""


@pytest.fixture(params=DEVICES)
def device(request):
    """Each device of DEVICES in turn, for a test that takes ``device``: CI runs the CPU; the lent GPU runs both."""
    return request.param

SEED_DATA = Path(__file__).resolve().parents[2] / "shared" / "reference" / "liang2019"
"""The seed's reference data, in ../shared beside the checkout (as in CI)."""


def seed_data(relative: str = "") -> Path:
    """A path in the seed's reference data. Missing data fails the test, naming the path: CI has ../shared beside
    the checkout, so a skip there would hide a broken check. WARPCLOTH_SKIP_SEED_DATA=1 skips instead, for
    checkouts without it."""
    path = SEED_DATA / relative
    if not path.exists():
        message = f"seed reference data missing: {path} (expected ../shared beside the checkout)"
        if os.environ.get("WARPCLOTH_SKIP_SEED_DATA") == "1":
            pytest.skip(message)
        pytest.fail(message + "; set WARPCLOTH_SKIP_SEED_DATA=1 to skip the tests that need it")
    return path


def gpu_devices() -> list:
    """The CUDA devices a cross-device test compares with the CPU; a test without one skips, saying so."""
    if wp.is_cuda_available():
        return ["cuda:0"]
    reason = "no CUDA device: the CPU is compared with a GPU only where there is one"
    return [pytest.param("cuda:0", marks=pytest.mark.skip(reason=reason))]


SMALL_SCENE = """
name = "small"
[sim]
dt = 0.02
steps = 12
[solver]
cg_tol = 1e-12
[cloth]
grid = {{ res = [4, 4], size = [0.5, 0.5] }}
rot_deg = [90.0, 0.0, 90.0]
material = "gray-interlock"
thicken = 2.0
[[handles]]
grid_vertex = [0, -1]
[[handles]]
grid_vertex = [-1, -1]
{extra}
"""


def small_scene(tmp_path, extra: str = "", name: str = "small.toml"):
    """A small hanging sheet (4x4 cells of 0.5 m, two soft handles, 12 steps of 0.02 s) with ``extra`` TOML, written
    to ``tmp_path / name``; returns the path."""
    path = tmp_path / name
    path.write_text(SMALL_SCENE.format(extra=extra))
    return path
