"""Benchmarks that cannot rot: every script in benchmarks/ runs with ``--quick`` (a few seconds each) and writes its
JSON, uses no private attribute, and every figure in the results blocks of README.md and of the documentation (docs/)
is what benchmarks/readme_tables.py renders from the JSON files in benchmarks/results/."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import seed_data

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
HAS_NEWTON = importlib.util.find_spec("newton") is not None
HAS_TORCH = importlib.util.find_spec("torch") is not None

HELPERS = {"common", "readme_tables"}
"""Modules in benchmarks/ that are not benchmarks."""

# name: (top-level keys of its JSON besides "meta", needs the seed's reference data, slow: > 10 s on 2 cores)
BENCHMARKS = {
    "step_time": (("scene", "targets", "records"), False, False),
    "components": (("rows", "phases"), False, False),
    "cg_solvers": (("tol", "solves", "sizes"), False, False),
    "gradient_growth": (("records", "tape_max"), False, False),
    "collision_ablation": (("records", "seed"), True, False),
    "seed_trajectories": (("materials", "frames", "steps"), True, False),
    "peers": (("records", "equal_error", "settings", "newton"), False, True),
    "tradeoff": (("scenes",), False, True),
    "material_estimation": (("per_material", "means", "seed"), True, True),
    "motion_control": (("open_loop",), False, True),
    "contact": (("drape", "incline"), False, False),
    "contact_gradients": (("throw", "drape", "before"), False, False),
    "integrators": (("T", "orders", "energies"), False, False),
    "newton_corrections": (("rows", "horizon", "library_check_max_dx_m"), False, False),
    "memory": (("records", "target_ratio"), False, False),
    "prediction": (("records", "means", "motions"), True, False),
    "worlds": (("records", "target_speedup"), False, False),
    "graph_step": (("cases", "gradients", "throw"), False, False),
    "jobs": (("records", "workers", "target_speedup"), True, True),
    "global_search": (("scene", "target", "optimizers"), False, False),
    "grippers": (("fling", "fold"), False, False),
    "estimation_batch": (("records", "iters", "reps"), True, False),
    "bvh_update": (("cases",), False, False),
    "projection_qp": (("records",), False, False),
    "recordings": (("settings", "sequences", "targets"), True, False),
}


def _params():
    for name, (_, _, slow) in BENCHMARKS.items():
        marks = [pytest.mark.slow] if slow else []
        yield pytest.param(name, marks=marks, id=name)


def test_every_benchmark_is_tested():
    scripts = {p.stem for p in BENCH.glob("*.py")} - HELPERS
    assert scripts == set(BENCHMARKS), "add new benchmarks to BENCHMARKS (and run them with --quick here)"


@pytest.mark.parametrize("name", list(_params()))
def test_quick_run(name, tmp_path):
    if BENCHMARKS[name][1]:
        seed_data()  # fails, naming the path, where ../shared is missing
    out = tmp_path / f"{name}.json"
    # one BLAS thread: a multi-threaded BLAS spin-waits against the other tests' processes (minutes, not seconds)
    env = dict(os.environ, PYTHONUNBUFFERED="1", OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, str(BENCH / f"{name}.py"), "--quick", "--out", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=900, env=env)
    assert proc.returncode == 0, f"{name} --quick failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    assert out.is_file(), f"{name} --quick wrote no JSON to {out}"
    data = json.loads(out.read_text())
    keys, _, _ = BENCHMARKS[name]
    missing = [k for k in ("meta", *keys) if k not in data]
    assert not missing, f"{name}: JSON lacks {missing}"
    meta = data["meta"]
    assert meta["quick"] is True and meta["benchmark"] == name
    for key in ("date", "command", "warp", "device", "cpu_count", "loadavg_start", "loadavg_end", "wall_s"):
        assert key in meta, f"{name}: meta lacks {key}"
    if name == "peers" and not HAS_NEWTON:
        assert data["newton"] is None and data["newton_skipped"]
        pytest.skip("newton is not installed (pip install -e '.[bench]'): peers.py ran warpcloth's side only")
    if name == "motion_control" and not HAS_TORCH:
        pytest.skip("torch is not installed: motion_control.py skipped its MLP controller")


@pytest.mark.parametrize("variant", ["two_graphs_kept_zero_after", "per_step_kept", "per_step_slab"])
def test_the_gpu_capture_probe_replays_on_the_cpu(variant):
    # benchmarks/gpu/capture_probe.py asks a GPU which captures of a taped rollout replay; the ways warpcloth captures
    # on the CPU must replay there to the uncaptured gradient, or the probe would not tell a GPU's fault from its own
    out = subprocess.run([sys.executable, str(BENCH / "gpu" / "capture_probe.py"), "--device", "cpu", "--variant",
                          variant], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "gradient off by 0.0e+00, 0.0e+00" in out.stdout, out.stdout


def test_no_private_access():
    """Benchmarks use the public API: no ``obj._name`` (Warp's own ``warp._src`` excepted, used for profiling)."""
    bad = []
    for path in sorted(BENCH.glob("*.py")):
        for i, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#", 1)[0].replace("warp._src", "")
            if re.search(r"\w\._[a-z]", code):
                bad.append(f"{path.name}:{i}: {line.strip()}")
    assert not bad, "private attribute access in benchmarks:\n" + "\n".join(bad)


# -- the README and the docs against the results ---------------------------------------------------------------------
def _readme_tables():
    spec = importlib.util.spec_from_file_location("readme_tables", BENCH / "readme_tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def rt():
    return _readme_tables()


@pytest.fixture(scope="module")
def pages(rt):
    """{page name: text} of README.md and every docs page."""
    return {rt.page_name(p): p.read_text() for p in rt.pages()}


def test_pages_cover_readme_and_docs(rt, pages):
    assert "README.md" in pages and any(name.startswith("docs/") for name in pages)
    assert rt.blocks(pages["README.md"]), "the README's headline results block is missing"
    assert sum(len(rt.blocks(text)) for text in pages.values()) >= 18, "results blocks are missing"
    names = [m["name"] for text in pages.values() for m in rt.blocks(text)]
    unused = set(rt.BLOCKS) - set(names)
    assert not unused, f"results blocks no page shows: {sorted(unused)}"


def test_figures_match_results(rt, pages):
    diffs = [d for name, text in pages.items() for d in rt.differences(text, name)]
    assert not diffs, ("figures differ from benchmarks/results (regenerate with python benchmarks/readme_tables.py "
                       "after a full run):\n" + "\n".join(diffs))


def test_results_are_full_runs(rt, pages):
    for text in pages.values():
        for m in rt.blocks(text):
            for path in m["files"].split():
                assert path.startswith("benchmarks/results/") and "/quick/" not in path, path
                meta = json.loads((ROOT / path).read_text()).get("meta")
                if meta is not None:
                    assert meta["quick"] is False, f"{path} is a --quick run"


def _holds_a_figure(line: str) -> bool:
    """A number other than a date or a GPU's model name (H200)."""
    return bool(re.search(r"\d", re.sub(r"\b20\d\d-\d\d-\d\d\b|\b[A-Z]\d{2,4}\b", "", line)))


def test_tables_are_generated(rt, pages):
    """Every Markdown table of README.md and docs/ that holds a figure is inside a results block: none is copied by
    hand. A table of names, dates and GPU models (what ran where) may stand outside."""
    assert _holds_a_figure("| 16x16 | 0.99 ms |") and not _holds_a_figure("| runs | H200, 2026-11-27 |")
    loose = []
    for name, text in pages.items():
        spans = [(m.start(), m.end()) for m in rt.blocks(text)]
        pos = 0
        for i, line in enumerate(text.splitlines(keepends=True), 1):
            if (line.lstrip().startswith("|") and _holds_a_figure(line)
                    and not any(a <= pos < b for a, b in spans)):
                loose.append(f"{name}:{i}: {line.strip()[:80]}")
            pos += len(line)
    assert not loose, "tables outside a results block:\n" + "\n".join(loose)


def test_check_catches_an_edited_figure(rt, pages):
    """The comparison fails when one figure of a table is changed, in the README and in a docs page."""
    for name in ("README.md", next(n for n, t in pages.items() if n.startswith("docs/") and rt.blocks(t))):
        text = pages[name]
        m = rt.blocks(text)[0]
        body = m["body"]
        digit = re.search(r"\| (\d)", body.split("\n", 2)[2])  # first figure of the first data row
        assert digit
        start = m.start("body") + len(body.split("\n", 2)[0]) + len(body.split("\n", 2)[1]) + 2 + digit.start(1)
        edited = text[:start] + str((int(text[start]) + 1) % 10) + text[start + 1:]
        assert rt.differences(edited, name)
        assert not rt.differences(text, name)
