"""Shared helpers of the benchmarks: scenes, timing, profiling, tables and JSON output.

Every benchmark runs standalone (``python benchmarks/<name>.py [--json PATH]``); this module sits beside them and is
imported as ``common`` (the script's folder is on ``sys.path``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING  # no init banner / module-load lines (Warp 1.19)

import warpcloth as wc  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
SEED_DIR = REPO_ROOT.parent / "shared" / "reference" / "liang2019"
"""The seed's reference data (meshes, target trajectories), ``../shared/reference/liang2019`` from the repo root."""

DT = 0.02
GRAVITY = (0.0, 0.0, -9.8)
WIND = (5.0, 0.0, 0.0)
HANDLE_STIFFNESS = 1.0e3
THICKEN = 2.0

# Grid x -> world y, grid y -> world z: a vertical sheet in the YZ plane whose normal is +x, the wind's direction.
VERTICAL_YZ = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


# -- command line, machine -------------------------------------------------------------------------------------------
def parse_args(description: str, **extra) -> argparse.Namespace:
    """``--json PATH`` plus any extra ``--name default`` options given as keywords (type taken from the default)."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--json", metavar="PATH", help="write the figures to this JSON file")
    for name, default in extra.items():
        p.add_argument(f"--{name.replace('_', '-')}", type=type(default), default=default)
    return p.parse_args()


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info(device: str = "cpu") -> dict:
    wp.init()
    d = wp.get_device(device)
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpu_usable": usable,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "warp": wp.__version__,
        "device": f"{d.alias} ({d.name})",
    }


def print_machine(info: dict) -> None:
    print(f"machine: {info['cpu']}, {info['cpu_usable']}/{info['cpu_count']} CPUs usable, {info['platform']}")
    print(f"         python {info['python']}, numpy {info['numpy']}, warp {info['warp']}, device {info['device']}")
    print("         (Warp CPU kernels run on one thread; launches are synchronous)")


# -- scenes ----------------------------------------------------------------------------------------------------------
def hanging_cloth(res: int, *, requires_grad: bool = False, material: str = "gray-interlock", dtype=wp.float32,
                  device: str = "cpu") -> wc.Model:
    """1 m square sheet, vertical (YZ plane, facing the +x wind), soft handles on the two top corners."""
    b = wc.ModelBuilder(gravity=GRAVITY)
    b.add_cloth_grid((res, res), (1.0, 1.0), material=wc.preset(material, thicken=THICKEN), rot=VERTICAL_YZ,
                     pos=(0.0, -0.5, -0.5))
    top = res * (res + 1)  # vertex (i, j) = j * (res + 1) + i; top row j = res
    b.add_handle(top, stiffness=HANDLE_STIFFNESS)
    b.add_handle(top + res, stiffness=HANDLE_STIFFNESS)
    b.set_wind(WIND, density=1.0, drag=0.0)
    return b.finalize(device, requires_grad=requires_grad, dtype=dtype)


def seed_dir() -> Path:
    """The seed reference folder, or exit with a message saying where it was looked for."""
    if not (SEED_DIR / "meshes" / "demo_wind.obj").is_file():
        sys.exit(f"seed reference data not found: expected {SEED_DIR}/meshes/demo_wind.obj "
                 "(../shared/reference/liang2019 relative to the repository root)")
    return SEED_DIR


def seed_wind_cloth(material: str, *, requires_grad: bool = False, dtype=wp.float32, device: str = "cpu",
                    lagged_normals: bool = False) -> wc.Model:
    """The seed's material-estimation scene (SPEC §5(b)): demo_wind.obj, handles on vertices 2 and 3, 5 m/s wind.

    The cloth starts at rest: the seed's targets match a start from rest to 1e-6 m after one frame, not the
    ``nv`` velocities stored in demo_wind.obj (0.1 mm off). ``lagged_normals`` reproduces ARCSim's one-step lag of
    the wind's face normals.
    """
    b = wc.ModelBuilder(gravity=GRAVITY)
    b.add_cloth_obj(seed_dir() / "meshes" / "demo_wind.obj", material=wc.preset(material, thicken=THICKEN),
                    vel=(0.0, 0.0, 0.0))
    for p in (2, 3):
        b.add_handle(p, stiffness=HANDLE_STIFFNESS)
    b.set_wind(WIND, density=1.0, drag=0.0, lagged_normals=lagged_normals)
    return b.finalize(device, requires_grad=requires_grad, dtype=dtype)


def advance(sim: wc.Simulator, state: wc.State, steps: int) -> wc.State:
    """Step ``steps`` times outside any tape and return the last state (a spin-up; also compiles the kernels)."""
    for _ in range(steps):
        nxt = sim.model.empty_state(requires_grad=False)
        sim.step(state, nxt)
        state = nxt
    return state


def copy_state(model: wc.Model, state: wc.State, *, requires_grad: bool) -> wc.State:
    return wc.State(wp.clone(state.particle_x, requires_grad=requires_grad),
                    wp.clone(state.particle_v, requires_grad=requires_grad), state.time)


# -- timing ----------------------------------------------------------------------------------------------------------
def timed(fn, *args, **kwargs):
    """(seconds, result) of one call, synchronised before and after."""
    wp.synchronize()
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    wp.synchronize()
    return time.perf_counter() - t0, out


def median_time(fn, *, reps: int, warmup: int = 1, min_time: float = 0.0) -> float:
    """Median wall time [s] of ``fn()`` over ``reps`` repetitions (more while their total is under ``min_time``)."""
    for _ in range(warmup):
        fn()
    times = []
    while len(times) < reps or sum(times) < min_time:
        times.append(timed(fn)[0])
    return statistics.median(times)


def median(values) -> float:
    return float(statistics.median(values))


# -- profiling -------------------------------------------------------------------------------------------------------
@contextlib.contextmanager
def launch_profile():
    """Time every ``wp.launch`` and recorded ``wp.Launch.launch`` (CPU launches are synchronous, so wall time =
    kernel + launch overhead).

    Yields a dict ``{kernel key (+ " [adj]" for adjoint launches): [calls, seconds]}``. Patches ``warp.launch``,
    which the simulator and ``Tape.backward`` both look up at call time.
    """
    orig = wp.launch
    stats = defaultdict(lambda: [0, 0.0])

    def launch(kernel, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            return orig(kernel, *args, **kwargs)
        finally:
            key = getattr(kernel, "key", str(kernel)).split("__locals__")[-1]
            key += " [adj]" if kwargs.get("adjoint") else ""
            s = stats[key]
            s[0] += 1
            s[1] += time.perf_counter() - t0

    orig_cmd = wp.Launch.launch

    def launch_cmd(self, *args, **kwargs):  # recorded launches (record_cmd=True), e.g. warp.optim's dot products
        t0 = time.perf_counter()
        try:
            return orig_cmd(self, *args, **kwargs)
        finally:
            s = stats[getattr(self.kernel, "key", "?").split("__locals__")[-1] + " [cmd]"]
            s[0] += 1
            s[1] += time.perf_counter() - t0

    wp.launch = launch
    wp.Launch.launch = launch_cmd
    try:
        yield stats
    finally:
        wp.launch = orig
        wp.Launch.launch = orig_cmd


@contextlib.contextmanager
def alloc_profile():
    """Count host allocations of Warp arrays on the CPU device: yields ``{"count": n, "bytes": b}``."""
    from warp._src.context import CpuDefaultAllocator

    stats = {"count": 0, "bytes": 0}
    orig = CpuDefaultAllocator.allocate

    def allocate(self, size_in_bytes):
        stats["count"] += 1
        stats["bytes"] += int(size_in_bytes)
        return orig(self, size_in_bytes)

    CpuDefaultAllocator.allocate = allocate
    try:
        yield stats
    finally:
        CpuDefaultAllocator.allocate = orig


@contextlib.contextmanager
def method_profile(obj, names):
    """Time calls of the bound methods ``names`` of ``obj`` (instance attributes shadow the class's)."""
    stats = defaultdict(lambda: [0, 0.0])
    for name in names:
        orig = getattr(obj, name)

        def wrapper(*args, _orig=orig, _name=name, **kwargs):
            t0 = time.perf_counter()
            try:
                return _orig(*args, **kwargs)
            finally:
                s = stats[_name]
                s[0] += 1
                s[1] += time.perf_counter() - t0

        setattr(obj, name, wrapper)
    try:
        yield stats
    finally:
        for name in names:
            delattr(obj, name)


# -- output ----------------------------------------------------------------------------------------------------------
def fmt(value, spec: str = "") -> str:
    if value is None:
        return "-"
    if isinstance(value, str) or (isinstance(value, float) and not np.isfinite(value)):
        return str(value)
    return format(value, spec)


def print_table(headers, rows, specs=None, title: str | None = None) -> None:
    """Print an aligned text table; ``specs`` are format specs per column ('' = str)."""
    specs = specs or [""] * len(headers)
    cells = [[fmt(v, s) for v, s in zip(row, specs)] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(headers)]
    if title:
        print(f"\n{title}")
    print("  ".join(h.rjust(w) for h, w in zip(headers, widths)))
    print("  ".join("-" * w for w in widths))
    for r in cells:
        print("  ".join(c.rjust(w) for c, w in zip(r, widths)))


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None  # strict JSON has no NaN/inf
    return obj


def write_json(path: str | None, data) -> None:
    if not path:
        return
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(_jsonable(data), indent=2) + "\n")
    print(f"\nwrote {path}")
