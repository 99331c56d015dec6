#!/usr/bin/env bash
# The checks that need a CUDA GPU, in one go (a lent GPU machine has minutes, not hours):
#   1. the gpu-marked tests (the torch GCC on CUDA gives the CPU path's peaks);
#   2. benchmarks/bench_gcc_device.py: the GCC and the lean feature stage on the GPU against the CPU, and
#      the first stage's accuracy on each path's features (writes benchmarks/results/gcc_device.*);
#   3. benchmarks/bench_tabpfn_device.py: the TabPFN point model on CPU and GPU (benchmarks/results/tabpfn_device.*);
#   4. benchmarks/bench_season_device.py: a forest season end to end, the GCC on the GPU against the CPU (needs XGBoost there);
#   5. benchmarks/bench_tabpfn_gpu_end_to_end.py: the README's main job with TabPFN point and error models on the GPU.
# Usage: bash scripts/gpu_checks.sh OUT_DIR [STEP ...]   (every step, or the named ones: gpu_tests bench_gcc_device
# bench_tabpfn_device bench_season_device bench_tabpfn_gpu_end_to_end; each step's log, and its result files as soon as
# it ends, land in OUT_DIR; a failing step does not stop the next). Together they take about 12 minutes on an H200
# machine, more on the H100 machine, whose CPU is about half as fast (2026-11-27: gpu_tests 18 s, bench_gcc_device 78 s,
# bench_tabpfn_gpu_end_to_end 228 s; bench_season_device ran past the 420 s it then had, with one CPU fit of 186 s): give
# bench_season_device a call of its own.
# On a lent GPU machine without network, carry what its image lacks as wheels for its Python (3.12 there):
# hydra-core, omegaconf, antlr4-python3-runtime (built here with pip wheel), soundfile, cffi, pycparser,
# tabpfn, lightgbm, pydantic, pydantic-core, pydantic-settings, python-dotenv, annotated-types,
# typing-inspection, typing-extensions, skrub, pydot, tabulate and xgboost-cpu; install them with
# pip install --no-index --no-deps --target DIR and put DIR and the repository on PYTHONPATH.
set -uo pipefail
out=${1:?output dir}
shift
wanted=" ${*:-gpu_tests bench_gcc_device bench_tabpfn_device bench_season_device bench_tabpfn_gpu_end_to_end} "
mkdir -p "$out"
touch "$out/started"
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
    local result=benchmarks/results/${name#bench_}
    if [ -f "$result.json" ] && [ "$result.json" -nt "$out/started" ]; then cp "$result".* "$out"/; fi  # now: a later step may be cut off
}
step gpu_tests 100 python3 -m pytest -q -m gpu -p no:cacheprovider tests/test_gcc_device.py
step bench_gcc_device 300 python3 benchmarks/bench_gcc_device.py --sites forest frozen_lake --n-events 1100 --batch-sizes 16 64 256
step bench_tabpfn_device 160 python3 benchmarks/bench_tabpfn_device.py
step bench_season_device 570 python3 benchmarks/bench_season_device.py --site forest --calls 1000
step bench_tabpfn_gpu_end_to_end 300 python3 benchmarks/bench_tabpfn_gpu_end_to_end.py --n-jobs 8
exit $status
