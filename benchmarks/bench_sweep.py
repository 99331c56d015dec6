"""Wall time of the README's main command (cold and warm cache) and of a three-model sweep on a warm
cache, against the models' own fitting time.

Usage: python benchmarks/bench_sweep.py [--site frozen_lake] [--models xgboost,random_forest,knn]
Writes benchmarks/results/sweep_<site>.json and .md. Every command is a fresh subprocess (imports
included) in one temporary outputs folder, one after the other in the same session. Each starts only
once the 1-minute load average has fallen below 0.5 (at most 5 minutes of waiting): the config's
``${threads:}`` is the free cores at a run's start, so a command started straight after the previous
one would see that one's load and run with fewer threads than a user on an idle machine gets. The
free cores each command saw are reported.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import tempfile
import time
from pathlib import Path

from common import machine, time_cli, write_results

from acoustlab.core.cores import free_cores

log = logging.getLogger("bench_sweep")


def job_timings(outputs: Path, pattern: str) -> list[dict]:
    """``timings_s`` of every job whose metrics.json matches ``pattern`` under ``outputs``."""
    return [json.loads(p.read_text())["timings_s"] for p in sorted(outputs.glob(pattern))]


def when_idle(limit_s: float = 300.0, below: float = 0.5) -> int:
    """Wait until the 1-minute load average is below ``below`` (at most ``limit_s``); the free cores a run then sees."""
    start = time.monotonic()
    while os.getloadavg()[0] >= below and time.monotonic() - start < limit_s:
        time.sleep(5.0)
    log.info("load %.2f after %.0f s of waiting", os.getloadavg()[0], time.monotonic() - start)
    return free_cores()


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--site", default="frozen_lake")
    parser.add_argument("--models", default="xgboost,random_forest,knn")
    opts = parser.parse_args()
    n_models = len(opts.models.split(","))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        base = [f"+site={opts.site}", f"paths.outputs_dir={out}"]
        cores = {"cold": when_idle()}
        cold = time_cli(base)
        cores["warm"] = when_idle()
        warm = time_cli(base)
        singles = job_timings(out, "runs/*/*/metrics.json")
        cores["sweep"] = when_idle()
        sweep = time_cli(["-m", *base, f"model={opts.models}"])
        sweep_jobs = job_timings(out, "multirun/*/*/*/metrics.json")
    models_s = sum(t["models_s"] for t in sweep_jobs)
    in_job_s = sum(t["total_before_tracking_s"] for t in sweep_jobs)
    result = {
        "site": opts.site,
        "models": opts.models,
        **machine(),
        "main_command_cold_s": round(cold, 2),
        "main_command_warm_s": round(warm, 2),
        "warm_over_cold": round(warm / cold, 3),
        "main_command_stage_timings_s": {"cold": singles[0], "warm": singles[1]},
        "sweep_wall_s": round(sweep, 2),
        "sweep_models_s": round(models_s, 2),
        "sweep_jobs_before_tracking_s": round(in_job_s, 2),
        "sweep_overhead_s": round(sweep - models_s, 2),
        "sweep_overhead_per_job_s": round((sweep - models_s) / n_models, 2),
        "sweep_wall_over_models": round(sweep / models_s, 3),
        "sweep_job_timings_s": sweep_jobs,
        "free_cores_at_start": cores,
    }
    lines = [
        f"# Main command and a {n_models}-model sweep ({opts.site})",
        "",
        f"Measured with `python benchmarks/bench_sweep.py --site {opts.site} --models {opts.models}` "
        f"({result['cpus']} CPUs, Python {result['python']}). Each row is a fresh `python -m acoustlab` process, started once the "
        f"load average fell below 0.5; free cores at the start (`${{threads:}}`): cold {cores['cold']}, warm {cores['warm']}, "
        f"sweep {cores['sweep']}.",
        "",
        "| command | wall (s) | notes |",
        "|:--|--:|:--|",
        f"| `python -m acoustlab +site={opts.site}`, cold cache | {cold:.1f} | simulate + features + model + plots + MLflow |",
        f"| same, warm cache | {warm:.1f} | {warm / cold:.2f}× cold |",
        f"| `-m model={opts.models}`, warm cache | {sweep:.1f} | models' own fit/predict time {models_s:.1f} s; "
        f"everything else {sweep - models_s:.1f} s ({(sweep - models_s) / n_models:.1f} s per job: data read, plots, MLflow, report) |",
        "",
        "Per-job stage timings (s) in the sweep: "
        + "; ".join(", ".join(f"{k} {v:.1f}" for k, v in t.items()) for t in sweep_jobs),
    ]
    write_results(f"sweep_{opts.site}", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
