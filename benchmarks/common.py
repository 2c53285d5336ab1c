"""Shared helpers of the benchmarks: command line, scenes, timing, profiling, tables and JSON output.

Every benchmark runs standalone (``python benchmarks/<name>.py [--quick] [--out PATH]``); this module sits beside
them and is imported as ``common`` (the script's folder is on ``sys.path``). Benchmarks use warpcloth's public API
only (``import warpcloth as wc``).

Results: a full run writes ``benchmarks/results/<name>.json`` (the figures the README quotes, checked against them by
``tests/test_benchmarks.py``); ``--quick`` (a few seconds: tiny sizes, few steps) writes
``benchmarks/results/quick/<name>.json`` (ignored by git), so a quick run never overwrites a committed result.
Every file starts with ``meta``: date, command line, versions, device, CPUs and the load average at start and end.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import platform
import shlex
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING  # no init banner / module-load lines (Warp 1.19)
if "--deterministic" in sys.argv:  # fixed when warpcloth's kernel modules are made, so before its import
    wp.config.deterministic = wp.DeterministicMode.RUN_TO_RUN

import warpcloth as wc  # noqa: E402
from warpcloth.tasks import scenes  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
SEED_DIR = REPO_ROOT.parent / "shared" / "reference" / "liang2019"
"""The seed's reference data (meshes, target trajectories), ``../shared/reference/liang2019`` from the repo root."""

DT = 0.02
# the seed's hanging-cloth scene (warpcloth.tasks.scenes)
GRAVITY = scenes.GRAVITY
WIND = scenes.WIND
HANDLE_STIFFNESS = scenes.DEFAULT_HANDLE_STIFFNESS
THICKEN = scenes.THICKEN

# Grid x -> world y, grid y -> world z: a vertical sheet in the YZ plane whose normal is +x, the wind's direction.
VERTICAL_YZ = scenes.GRID_TO_YZ


# -- command line, machine -------------------------------------------------------------------------------------------
RESULTS_DIR = REPO_ROOT / "benchmarks" / "results"
"""Committed results of full runs, one ``<name>.json`` per benchmark (the README's figures)."""
QUICK_DIR = RESULTS_DIR / "quick"
"""Results of ``--quick`` runs (ignored by git)."""


def parse_args(description: str | None = None, *, name: str | None = None, quick: dict | None = None,
               configure=None, **extra) -> argparse.Namespace:
    """A benchmark's command line: ``--quick``, ``--out PATH`` (alias ``--json``) and one ``--name default`` option
    per keyword (type taken from the default). ``name`` defaults to the script's file name.

    ``quick`` maps option names to the defaults ``--quick`` uses instead (an option given on the command line wins).
    ``configure(parser)`` may add options of its own. The namespace also carries ``name``, the start time and load
    average (for :func:`write_result`) and ``out``: the given path, else ``results/<name>.json``, or
    ``results/quick/<name>.json`` with ``--quick``.
    """
    loadavg = _loadavg() if STARTED[1] is None else STARTED[1]
    started = STARTED[0]
    name = name or Path(sys.argv[0]).stem
    p = argparse.ArgumentParser(description=(description or name).strip().splitlines()[0],
                                epilog=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="a few seconds: tiny sizes, few steps (writes results/quick/<name>.json unless --out)")
    p.add_argument("--out", "--json", dest="out", metavar="PATH",
                   help=f"write the figures to this JSON file (default benchmarks/results/{name}.json)")
    for key, default in extra.items():
        p.add_argument(f"--{key.replace('_', '-')}", type=type(default), default=None,
                       help=f"default {default!r}" + (f"; --quick: {quick[key]!r}" if quick and key in quick else ""))
    p.add_argument("--deterministic", action="store_true",
                   help="Warp's deterministic mode (RUN_TO_RUN): CUDA's atomic sums in a fixed order")
    if configure is not None:
        configure(p)
    args = p.parse_args()
    for key, default in extra.items():
        if getattr(args, key) is None:
            setattr(args, key, quick[key] if args.quick and quick and key in quick else default)
    if not args.out:
        args.out = str((QUICK_DIR if args.quick else RESULTS_DIR) / f"{name}.json")
    args.name = name
    args.started = started
    args.loadavg_start = loadavg
    args.argv = ["python", os.path.relpath(sys.argv[0], REPO_ROOT) if sys.argv[0] else name, *sys.argv[1:]]
    return args


def _loadavg() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except (AttributeError, OSError):
        return None


STARTED = (time.perf_counter(), _loadavg())
"""When this module was imported (the start of a benchmark's run) and the load average then."""


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
    """1 m square sheet, vertical (YZ plane, facing the +x wind), soft handles on the two top corners: the seed's
    scene (``scenes.hanging_cloth``) at ``res`` x ``res`` cells."""
    return scenes.hanging_cloth(wc.preset(material, thicken=THICKEN), res=res, device=device, dtype=dtype,
                                requires_grad=requires_grad)


def seed_dir() -> Path:
    """The seed reference folder, or exit with a message saying where it was looked for."""
    if not (SEED_DIR / "meshes" / "demo_wind.obj").is_file():
        sys.exit(f"seed reference data not found: expected {SEED_DIR}/meshes/demo_wind.obj "
                 "(../shared/reference/liang2019 relative to the repository root)")
    return SEED_DIR


def seed_wind_cloth(material: str, *, requires_grad: bool = False, dtype=wp.float32, device: str = "cpu",
                    lagged_normals: bool = False, self_collision: bool = False) -> wc.Model:
    """The seed's material-estimation scene (SPEC §5(b)): demo_wind.obj, handles on vertices 2 and 3, 5 m/s wind.

    The cloth starts at rest: the seed's targets match a start from rest to 1e-6 m after one frame, not the
    ``nv`` velocities stored in demo_wind.obj (0.1 mm off). ``lagged_normals`` reproduces ARCSim's one-step lag of
    the wind's face normals. Built by ``scenes.hanging_cloth``.
    """
    mesh = seed_dir() / "meshes" / "demo_wind.obj"
    return scenes.hanging_cloth(wc.preset(material, thicken=THICKEN), mesh_path=mesh, lagged_normals=lagged_normals,
                                self_collision=self_collision, device=device, dtype=dtype,
                                requires_grad=requires_grad)


def advance(sim: wc.Simulator, state: wc.State, steps: int) -> wc.State:
    """Step ``steps`` times outside any tape and return the last state (a spin-up; also compiles the kernels)."""
    for _ in range(steps):
        nxt = sim.model.empty_state(requires_grad=False)
        sim.step(state, nxt)
        state = nxt
    return state


def cold(state: wc.State, *, requires_grad: bool = False) -> wc.State:
    """The positions and velocities of ``state`` as a new trajectory's start: no first guess for the solve, so
    repeated timed rollouts from it are alike."""
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
    """Time every ``wp.launch``, ``wp.launch_tiled`` and recorded ``wp.Launch.launch`` (CPU launches are
    synchronous, so wall time = kernel + launch overhead).

    Yields a dict ``{kernel key (+ " [adj]" for adjoint launches): [calls, seconds]}``. Patches ``warp.launch`` and
    ``warp.launch_tiled``, which the simulator and ``Tape.backward`` look up at call time (``launch_tiled`` calls
    Warp's own ``launch``, so a tiled launch counts once).
    """
    orig, orig_tiled = wp.launch, wp.launch_tiled
    stats = defaultdict(lambda: [0, 0.0])

    def timed_launch(launcher):
        def launch(kernel, *args, **kwargs):
            t0 = time.perf_counter()
            try:
                return launcher(kernel, *args, **kwargs)
            finally:
                key = getattr(kernel, "key", str(kernel)).split("__locals__")[-1]
                key += " [adj]" if kwargs.get("adjoint") else ""
                s = stats[key]
                s[0] += 1
                s[1] += time.perf_counter() - t0
        return launch

    orig_cmd = wp.Launch.launch

    def launch_cmd(self, *args, **kwargs):  # recorded launches (record_cmd=True), e.g. warp.optim's dot products
        t0 = time.perf_counter()
        try:
            return orig_cmd(self, *args, **kwargs)
        finally:
            s = stats[getattr(self.kernel, "key", "?").split("__locals__")[-1] + " [cmd]"]
            s[0] += 1
            s[1] += time.perf_counter() - t0

    wp.launch, wp.launch_tiled = timed_launch(orig), timed_launch(orig_tiled)
    wp.Launch.launch = launch_cmd
    try:
        yield stats
    finally:
        wp.launch, wp.launch_tiled = orig, orig_tiled
        wp.Launch.launch = orig_cmd


@contextlib.contextmanager
def alloc_profile():
    """Count host allocations of Warp arrays on the CPU device: yields ``{"count": n, "bytes": b}`` (both None when
    this Warp version has no such allocator to patch: the figures are left out, the benchmark still runs)."""
    try:
        from warp._src.context import CpuDefaultAllocator  # Warp's internals: the one private name used here
    except ImportError:
        yield {"count": None, "bytes": None}
        return

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


THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""Environment variables that set NumPy's BLAS threads (the host-side collision QP): recorded with every run."""


def run_metadata(args: argparse.Namespace, device: str = "cpu") -> dict:
    """What a result file says about its run: date, command, quick flag, versions, device, CPUs, load averages."""
    info = machine_info(device)
    return {
        "benchmark": args.name,
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": shlex.join(args.argv),
        "quick": bool(args.quick),
        "options": {k: v for k, v in vars(args).items()
                    if k not in ("name", "started", "loadavg_start", "argv", "out")},
        "warp": info["warp"],
        "warpcloth": getattr(wc, "__version__", None) or _package_version("warpcloth"),
        "device": info["device"],
        "cpu": info["cpu"],
        "cpu_count": info["cpu_count"],
        "cpu_usable": info["cpu_usable"],
        "platform": info["platform"],
        "python": info["python"],
        "numpy": info["numpy"],
        "env": {k: os.environ[k] for k in THREAD_VARS if k in os.environ},
        "loadavg_start": args.loadavg_start,
        "loadavg_end": _loadavg(),
        "wall_s": round(time.perf_counter() - args.started, 2),
    }


def _package_version(name: str) -> str | None:
    try:
        from importlib.metadata import version

        return version(name)
    except Exception:  # noqa: BLE001 - metadata is optional
        return None


def kept_records(path: str, keys: list[str], **same) -> dict:
    """The records ``keys`` of the earlier result at ``path``, for a benchmark's ``--only`` (which reruns the others),
    each with the earlier run's metadata under ``"kept_meta"``; {} where there is none. ``same``: settings the earlier
    run must share (a mismatch exits, naming it)."""
    file = Path(path)
    if not file.exists():
        return {}
    old = json.loads(file.read_text())
    for key, value in same.items():
        if old.get(key) != value:
            raise SystemExit(f"--only: {path} was run with {key} = {old.get(key)!r}, this run has {value!r}: "
                             "run every record")
    meta = old.get("meta", {})
    earlier = meta.get("kept_meta", {})  # a record kept before keeps its first run's metadata
    return {key: {**old[key], "kept_meta": old[key].get("kept_meta") or earlier.get(key) or meta}
            for key in keys if key in old}


def write_result(args: argparse.Namespace, data: dict, *, device: str = "cpu", kept=()) -> Path:
    """Write ``{"meta": run_metadata(...), **data}`` to ``args.out`` and return the path. ``kept``: the keys of
    ``data`` taken over from an earlier result (:func:`kept_records`), listed in ``meta.kept``."""
    meta = run_metadata(args, device)
    if kept:
        meta["kept"] = list(kept)
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_jsonable({"meta": meta, **data}), indent=2) + "\n")
    load = meta["loadavg_start"], meta["loadavg_end"]
    print(f"\nwrote {path} ({meta['wall_s']:.1f} s; load average {load[0]} at start, {load[1]} at the end)")
    return path
