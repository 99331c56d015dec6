"""What verifying the cache costs a warm run: checksums of every file of an entry, checked on each lookup.

Usage: python benchmarks/bench_cache_verify.py [--site frozen_lake] [--repeats 5]
Writes benchmarks/results/cache_verify_<site>.json and .md. One session: a cold run fills a
temporary cache, a warm run of the same command is timed end to end (fresh process), then the warm
data stage (cache lookups + reading the feature table) is timed in-process with verification on and
off, interleaved, median of ``repeats``. The goal: verification adds ≤ 5 % to a warm run.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
import time
from unittest import mock

from common import compose_cfg, machine, time_cli, write_results

from acoustlab.run.registry import build, build_feature_sets, to_plain
from acoustlab.stages import cache as cache_module
from acoustlab.stages.cache import StageCache
from acoustlab.stages.dataset import SimulationPlan, load_or_build_simulated
from acoustlab.stages.sites import site_from_config

log = logging.getLogger("bench_cache_verify")


def warm_data_stage(cfg, cache_dir: str) -> float:
    """Seconds to get the simulated dataset from a warm cache, in this process."""
    site = site_from_config(cfg.site)
    simulator = build(cfg.simulator, "simulator")
    features = build_feature_sets(cfg.features)
    plan = SimulationPlan(seed=cfg.seed, **{**to_plain(cfg.data), "n_jobs": 1})
    start = time.perf_counter()
    load_or_build_simulated(site, simulator, to_plain(cfg.simulator), features, to_plain(cfg.features.groups), plan, StageCache(cache_dir))
    return time.perf_counter() - start


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--site", default="frozen_lake")
    parser.add_argument("--repeats", type=int, default=5)
    opts = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        base = [f"+site={opts.site}", f"paths.outputs_dir={tmp}", "tracking=none"]
        cold = time_cli(base)
        warm = time_cli(base)
        cfg = compose_cfg([f"+site={opts.site}", f"paths.outputs_dir={tmp}"])
        logging.getLogger("acoustlab").setLevel(logging.WARNING)
        on, off = [], []
        for _ in range(opts.repeats):
            on.append(warm_data_stage(cfg, f"{tmp}/cache"))
            with mock.patch.object(cache_module, "verify_entry", lambda _entry: None):
                off.append(warm_data_stage(cfg, f"{tmp}/cache"))
    verify_s = statistics.median(on) - statistics.median(off)
    result = {
        "site": opts.site,
        **machine(),
        "cold_run_s": round(cold, 2),
        "warm_run_s": round(warm, 2),
        "warm_data_stage_verified_s": round(statistics.median(on), 4),
        "warm_data_stage_unverified_s": round(statistics.median(off), 4),
        "verification_s": round(verify_s, 4),
        "verification_share_of_warm_run": round(verify_s / warm, 4),
        "goal_share": 0.05,
    }
    lines = [
        f"# Cost of cache verification on a warm run, site {opts.site}",
        "",
        f"`python benchmarks/bench_cache_verify.py --site {opts.site}` ({result['cpus']} CPUs, Python {result['python']}; "
        f"median of {opts.repeats})",
        "",
        "| what | seconds |",
        "|---|---|",
        f"| cold run (fresh process) | {cold:.1f} |",
        f"| warm run, same command (fresh process) | {warm:.1f} |",
        f"| warm data stage, verified | {result['warm_data_stage_verified_s']:.3f} |",
        f"| warm data stage, verification off | {result['warm_data_stage_unverified_s']:.3f} |",
        f"| verification | {verify_s:.3f} ({100 * verify_s / warm:.1f} % of the warm run; goal ≤ 5 %) |",
    ]
    write_results(f"cache_verify_{opts.site}", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
