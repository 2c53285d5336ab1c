#!/usr/bin/env bash
# The CUDA checks of one lent-GPU session (../shared/gpu/README.md): the device tests, the graph benchmark and the
# material-estimation and control CLIs on cuda:0. Run on the GPU machine after `bash .gpu/on-device.sh install`
# (or `sync`) as
#   root=$(pwd); . /tmp/warp/env.sh; cd /tmp && bash "$root/benchmarks/gpu/checks.sh" "$root"
# Logs and JSON go to $OUT (they come back); each part has its own timeout so one hang does not cost the rest.
# PARTS (part names, space-separated; default: all), TESTS, SIZES, WORLDS, PRECONDITIONERS, BLOCK_DIMS, ITERS,
# VARIANT and PROBE_DEBUG (capture_probe's) override what runs. The first CUDA compile of the kernel modules takes about a minute on a
# fresh machine (2026-11-27, H200). On an H100 (2026-11-27, cold kernel cache) the tests below took 164 s; all the parts
# together take longer than one session's 15 minutes of device time: choose PARTS.
set -u
root=${1:?project root}
out=${OUT:-/tmp/out}
mkdir -p "$out"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$out/gpu.txt" 2>&1
py=python3
parts=" ${PARTS:-tests graph_step tiled_multigrid deterministic projection_qp estimate_cuda control_cuda global_search capture_probe} "
# a hung test dumps its stack into tests.log (pytest's faulthandler) before the part's timeout
part() {  # part NAME SECONDS COMMAND...: runs COMMAND if NAME is in PARTS
  local name=$1 limit=$2; shift 2
  [[ $parts == *" $name "* ]] || return 0
  local t0=$SECONDS
  timeout "$limit" "$@" > "$out/$name.log" 2>&1
  echo "$name: rc=$? in $((SECONDS - t0)) s" | tee -a "$out/summary.txt"
}
part tests 280 $py -m pytest -v -p no:cacheprovider -o faulthandler_timeout=150 --durations=15 -k "${TESTS:-cuda}" \
  "$root/tests/test_devices.py" "$root/tests/test_capture.py" "$root/tests/test_gradients.py" \
  "$root/tests/test_worlds.py" "$root/tests/test_collision_gradients.py" "$root/tests/test_contact.py" \
  "$root/tests/test_tasks.py" "$root/tests/test_torch.py" "$root/tests/test_projection.py" \
  "$root/tests/test_detection.py" "$root/tests/test_collision.py" "$root/tests/test_solve.py" \
  "$root/tests/test_multigrid.py" "$root/tests/test_inverse.py" "$root/tests/test_determinism.py"
grep -E "PASSED|FAILED|ERROR|passed|failed" "$out/tests.log" | tail -n 40 >> "$out/summary.txt"
part graph_step 150 $py "$root/benchmarks/graph_step.py" --device cuda:0 --sizes "${SIZES:-16,64}" \
  --worlds "${WORLDS:-1,1024}" --steps 50 --reps 3 --preconditioners "${PRECONDITIONERS:-auto,block_jacobi,multigrid}" \
  --out "$out/graph_step_cuda.json"  # the multigrids against block Jacobi on one card (tiled: 16x16, 1024 worlds)
tail -n 16 "$out/graph_step.log" >> "$out/summary.txt"
# the tiled CG with the multigrid's V-cycle on each world's block against block Jacobi, 64x64 included ("auto" runs
# that one on the warp backend): whether the multigrid should become CUDA's default for worlds
part tiled_multigrid 150 $py "$root/benchmarks/graph_step.py" --device cuda:0 --backends tiled \
  --preconditioners block_jacobi,multigrid --sizes 16,64 --worlds 1,1024 --steps 50 --reps 3 \
  --out "$out/graph_step_tiled_cuda.json"
tail -n 12 "$out/tiled_multigrid.log" >> "$out/summary.txt"
# Warp's deterministic mode: what it costs a step, and max diff (captured against uncaptured) should read 0
part deterministic 150 $py "$root/benchmarks/graph_step.py" --device cuda:0 --deterministic --sizes 16,64 \
  --worlds 1,1024 --steps 50 --reps 3 --out "$out/graph_step_deterministic_cuda.json"
tail -n 16 "$out/deterministic.log" >> "$out/summary.txt"
part projection_qp 90 $py "$root/benchmarks/projection_qp.py" --device cuda:0 --reps 5 \
  --block-dims "${BLOCK_DIMS:-32,64,128,256}" --out "$out/projection_qp_cuda.json"  # the QP's block size
tail -n 24 "$out/projection_qp.log" >> "$out/summary.txt"
part estimate_cuda 45 warpcloth estimate --device cuda:0 --iters "${ITERS:-5}"
grep -E "runtime|simulation error" "$out/estimate_cuda.log" >> "$out/summary.txt"
part control_cuda 90 warpcloth control --device cuda:0 --iters 2
tail -n 3 "$out/control_cuda.log" >> "$out/summary.txt"
part global_search 240 $py "$root/benchmarks/global_search.py" --device cuda:0 --optimizers cmaes --starts 1 \
  --iters 42 --out "$out/global_search_cuda.json"  # issue 38: time to result on CUDA
tail -n 6 "$out/global_search.log" >> "$out/summary.txt"
part estimation_batch 240 $py "$root/benchmarks/estimation_batch.py" --device cuda:0 --reps 1 \
  --fabrics tango-red-jet-set --iters 60 --out "$out/estimation_batch_cuda.json"  # issue 38: a search's trials as worlds
tail -n 7 "$out/estimation_batch.log" >> "$out/summary.txt"
# not in the default PARTS: every optimisable parameter's gradient through contact, against central differences
part gradient_matrix 400 $py -m pytest -q -p no:cacheprovider -k cuda "$root/tests/test_contact_gradient_matrix.py"
tail -n 5 "$out/gradient_matrix.log" >> "$out/summary.txt"
# PROBE_DEBUG=1: bounds-checked kernels (Warp's debug mode; compiling takes minutes), so a fault names its access
part capture_probe 240 $py "$root/benchmarks/gpu/capture_probe.py" --device cuda:0 ${VARIANT:+--variant $VARIANT} \
  ${PROBE_DEBUG:+--debug}
cat "$out/capture_probe.log" >> "$out/summary.txt"
