#!/usr/bin/env bash
# The CUDA checks of one lent-GPU session (../shared/gpu/README.md): the device tests, then the graph benchmark and
# the CLI on cuda:0. Run on the GPU machine after `bash .gpu/on-device.sh install` (or `sync`) as
#   root=$(pwd); . /tmp/warp/env.sh; cd /tmp && bash "$root/benchmarks/gpu_checks.sh" "$root"
# Logs and JSON go to $OUT (they come back); each part has its own timeout so one hang does not cost the rest.
set -u
root=${1:?project root}
out=${OUT:-/tmp/out}
mkdir -p "$out"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$out/gpu.txt" 2>&1
py=python3
part() {  # part NAME SECONDS COMMAND...
  local name=$1 limit=$2; shift 2
  local t0=$(date +%s)
  timeout "$limit" "$@" > "$out/$name.log" 2>&1
  echo "$name: rc=$? in $(( $(date +%s) - t0 )) s" | tee -a "$out/summary.txt"
}
part tests 240 $py -m pytest -q -p no:cacheprovider -x -k "cuda" "$root/tests/test_devices.py" "$root/tests/test_capture.py"
part graph_step 300 $py "$root/benchmarks/graph_step.py" --device cuda:0 --sizes "${SIZES:-16,64}" \
  --worlds "${WORLDS:-1,64,1024}" --steps 50 --reps 3 --out "$out/graph_step_cuda.json"
tail -n 30 "$out/graph_step.log" >> "$out/summary.txt"
