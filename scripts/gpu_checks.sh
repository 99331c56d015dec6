#!/usr/bin/env bash
# The checks that need a CUDA GPU, in one go (a lent GPU machine has minutes, not hours):
#   gpu_tests: the gpu-marked tests (the torch GCC on CUDA gives the CPU path's peaks);
#   models:    python benchmarks/run.py models  (XGBoost; TabPFN at the published size on CPU and GPU);
#   stages:    python benchmarks/run.py stages  (the GCC on the GPU beside the CPU, and the other stages).
# Usage: bash scripts/gpu_checks.sh OUT_DIR [STEP ...]   (every step, or the named ones). Each step's log and the
# harness' result files (benchmarks/.results/*.json) land in OUT_DIR; a failing step does not stop the next.
# On a lent GPU machine without network, carry what its image lacks as wheels and put them on PYTHONPATH.
set -uo pipefail
out=${1:?output dir}
shift
wanted=" ${*:-gpu_tests models stages} "
mkdir -p "$out"
export PYTHONUNBUFFERED=1
status=0
step() {  # step NAME TIMEOUT_S COMMAND...
    local name=$1 limit=$2
    shift 2
    [[ $wanted == *" $name "* ]] || return 0
    local start=$SECONDS
    timeout "$limit" "$@" > "$out/$name.log" 2>&1
    local rc=$?
    echo "$name: exit $rc after $((SECONDS - start)) s"
    tail -n 25 "$out/$name.log"
    [ $rc -eq 0 ] || status=1
    cp benchmarks/.results/*.json "$out"/ 2>/dev/null || true
}
step gpu_tests 100 python3 -m pytest -q -m gpu -p no:cacheprovider tests/test_gcc_device.py
step models 240 python3 benchmarks/run.py models --repeat 3
step stages 300 python3 benchmarks/run.py stages --repeat 3
exit $status
