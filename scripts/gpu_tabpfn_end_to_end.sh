#!/usr/bin/env bash
# End-to-end TabPFN on a GPU box without internet: build a random checkpoint of the published v2
# regressor's size, then run the README's main job with a random forest and with TabPFN point + error
# models, timing each (the model stage is in metrics.json timings_s). Usage:
#   bash scripts/gpu_tabpfn_end_to_end.sh OUT_DIR
set -euo pipefail
out=${1:?output dir}
mkdir -p "$out"
python3 -c "from plugins.models.tabpfn_checkpoint import FULL_SIZE, build_random_checkpoint; build_random_checkpoint('$out/random-regressor.ckpt', FULL_SIZE)"
common=(+site=frozen_lake tracking=none data.n_jobs=8 paths.outputs_dir="$out/outputs")
start=$SECONDS
python3 -m acoustlab "${common[@]}" model=random_forest hydra.run.dir="$out/run_random_forest" > "$out/random_forest.log" 2>&1
echo "random_forest wall $((SECONDS - start)) s (simulation and features included: cold cache)"
start=$SECONDS
python3 -m acoustlab "${common[@]}" model=tabpfn error_model=tabpfn \
    model.model_path="$out/random-regressor.ckpt" error_model.model_path="$out/random-regressor.ckpt" \
    hydra.run.dir="$out/run_tabpfn" > "$out/tabpfn.log" 2>&1
echo "tabpfn wall $((SECONDS - start)) s (warm cache)"
for r in random_forest tabpfn; do python3 -c "import json; m=json.load(open('$out/run_$r/metrics.json')); print('$r', m['timings_s'], m['choices'] if m.get('choices') else '')"; done
