"""TabPFN end to end on a GPU: the README's main job with TabPFN point and error models against a random forest.

Usage: python benchmarks/bench_tabpfn_gpu_end_to_end.py [--n-jobs 8]

On a machine without internet (a lent GPU box), with a randomly initialised checkpoint of the
published TabPFN v2 regressor's size (``plugins.models.tabpfn_checkpoint``): the README's main job
(``+site=frozen_lake``, sim-only) runs twice through the command line, first with
``model=random_forest`` (cold cache: the simulation and the features are computed), then with
``model=tabpfn error_model=tabpfn`` on that checkpoint (warm cache: the same data). Reported: each
run's stage timings from its metrics.json, the wall time, whether both saw the same dataset hash,
and where TabPFN ran (its device is the plugin's default: the GPU when torch sees one). With random
weights the predictions are meaningless; this measures the whole pipeline on CUDA and its cost.

Writes benchmarks/results/tabpfn_gpu_end_to_end.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import REPO, machine, write_results

log = logging.getLogger("bench_tabpfn_gpu_end_to_end")


def run_job(overrides: list[str], run_dir: Path) -> tuple[dict, float]:
    """metrics.json of one ``python -m acoustlab`` job and its wall time, s (SystemExit with the log's end when it fails)."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "acoustlab", *overrides, f"hydra.run.dir={run_dir}"], cwd=REPO, capture_output=True,
                          text=True)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"job failed: {overrides}\n{proc.stderr[-3000:]}")
    return json.loads((run_dir / "metrics.json").read_text()), wall


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-jobs", type=int, default=8, help="data.n_jobs: processes simulating and extracting features")
    opts = parser.parse_args()
    import tabpfn
    import torch

    from plugins.models.tabpfn_checkpoint import FULL_SIZE, build_random_checkpoint

    with tempfile.TemporaryDirectory() as tmp:
        ckpt = build_random_checkpoint(Path(tmp) / "random-regressor.ckpt", FULL_SIZE)
        common = ["+site=frozen_lake", "tracking=none", f"data.n_jobs={opts.n_jobs}", f"paths.outputs_dir={tmp}/outputs"]
        runs = {
            "random_forest": run_job([*common, "model=random_forest"], Path(tmp) / "run_random_forest"),
            "tabpfn": run_job([*common, "model=tabpfn", "error_model=tabpfn", f"model.model_path={ckpt}", f"error_model.model_path={ckpt}"],
                              Path(tmp) / "run_tabpfn"),
        }
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    result = {"machine": {**machine(), "gpu": gpu, "torch": torch.__version__, "tabpfn": getattr(tabpfn, "__version__", "?")},
              "n_jobs": opts.n_jobs, "dataset_hash_same": runs["random_forest"][0].get("dataset_hash") == runs["tabpfn"][0].get("dataset_hash"),
              "runs": {name: {"timings_s": m["timings_s"], "wall_s": round(wall, 1), "choices": m.get("choices", {})}
                       for name, (m, wall) in runs.items()}}
    rows = [("random_forest (cold cache)", runs["random_forest"]), ("tabpfn point + error model (warm cache)", runs["tabpfn"])]
    lines = ["# TabPFN end to end on a GPU (random weights of the published size)", "",
             f"`python benchmarks/bench_tabpfn_gpu_end_to_end.py --n-jobs {opts.n_jobs}` (GPU: {gpu}; torch {torch.__version__}, "
             f"{result['machine']['cpus']} CPU cores): the README's main job (`+site=frozen_lake`, sim-only) with `model=random_forest`, "
             "then with `model=tabpfn error_model=tabpfn` on a randomly initialised checkpoint of the published v2 regressor's size "
             f"(the same data: dataset hash identical = {result['dataset_hash_same']}).", "",
             "| run | preflight (s) | data (s) | models (s) | plots (s) | wall (s) |", "|:--|--:|--:|--:|--:|--:|"]
    for label, (m, wall) in rows:
        t = m["timings_s"]
        lines.append(f"| {label} | {t.get('preflight_s', float('nan')):.1f} | {t.get('data_s', float('nan')):.1f} | "
                     f"{t.get('models_s', float('nan')):.1f} | {t.get('plots_s', float('nan')):.1f} | {wall:.0f} |")
    lines += ["", "The TabPFN run fits and predicts with TabPFN for x and y over the calibration folds and the final fit, and the "
              "error model likewise; its preflight includes importing torch and TabPFN and checking the weights. With random "
              "weights the predictions are meaningless: this checks the whole pipeline on CUDA and its cost, not accuracy."]
    if gpu is None:
        lines += ["", "No CUDA GPU was visible: both runs used the CPU."]
    write_results("tabpfn_gpu_end_to_end", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
