"""Every warpcloth kernel module compiles for CUDA (PTX for sm_90, the H100's and H200's architecture) on a machine
without a GPU: Warp's AOT compiler (``wp.compile_aot_module``) runs NVRTC, which the warp-lang wheel carries. A GPU is
lent to this project only now and then, so this is what catches CUDA-only compile errors between GPU sessions (it
says nothing of how the kernels run there). Where CUDA is present the device tests compile and run the kernels
instead, and this test is skipped."""

import subprocess
import sys

import pytest
import warp as wp

SCRIPT = """
import importlib, pkgutil, sys
import warp as wp
wp.config.log_level = wp.LOG_WARNING
import warpcloth.kernels as kernels
failed = []
for info in pkgutil.iter_modules(kernels.__path__):
    module = wp.get_module(importlib.import_module("warpcloth.kernels." + info.name).__name__)
    if not module.kernels:
        continue  # functions only: compiled with the modules that call them
    try:
        wp.compile_aot_module(module, arch=90, module_dir=sys.argv[1], use_ptx=True)
        print("compiled", info.name, flush=True)
    except Exception as exc:
        failed.append(info.name)
        print("FAILED", info.name, type(exc).__name__, exc, flush=True)
sys.exit(1 if failed else 0)
"""


@pytest.mark.skipif(wp.is_cuda_available(), reason="a GPU is present: the device tests compile and run the kernels")
def test_every_kernel_module_compiles_for_cuda(tmp_path):
    run = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path)], capture_output=True, text=True, timeout=1200)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-4000:]
    compiled = [line.split()[1] for line in run.stdout.splitlines() if line.startswith("compiled")]
    # the modules with kernels (the others hold functions only); a module that stops compiling fails above
    assert {"cg_sequential", "cg_tiled", "cg_warp", "multigrid", "block_matrix", "implicit", "projection", "proximity",
            "collision", "render"} <= set(compiled), run.stdout
