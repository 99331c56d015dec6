"""End-to-end wall time of the main command with a cold cache, a warm cache, and only the model changed.

Usage: python benchmarks/bench_cache.py [--site frozen_lake] [--extra key=value ...]
Writes benchmarks/results/cache_<site>.json and .md. Each command runs in a fresh subprocess
(imports included), all in one session, so the ratios compare like with like.
"""

from __future__ import annotations

import argparse
import logging
import platform
import tempfile

from common import time_cli, write_results

log = logging.getLogger("bench_cache")


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--site", default="frozen_lake")
    parser.add_argument("--extra", nargs="*", default=[])
    opts = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        base = [f"+site={opts.site}", f"paths.outputs_dir={tmp}", *opts.extra]
        rows = {
            "cold cache (simulate + features + models + MLflow)": time_cli(base),
            "warm cache, same config": time_cli(base),
            "warm cache, model=random_forest": time_cli([*base, "model=random_forest"]),
            "cache bypassed (cache.enabled=false)": time_cli([*base, "cache.enabled=false"]),
        }
    cold = rows["cold cache (simulate + features + models + MLflow)"]
    result = {
        "site": opts.site,
        "extra_overrides": opts.extra,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": __import__("os").cpu_count(),
        "wall_s": {k: round(v, 2) for k, v in rows.items()},
        "ratio_to_cold": {k: round(v / cold, 3) for k, v in rows.items()},
    }
    lines = [
        f"# End-to-end wall time, site {opts.site}",
        "",
        f"`python benchmarks/bench_cache.py --site {opts.site}` ({result['cpus']} CPUs, Python {result['python']})",
        "",
        "| run | wall (s) | ratio to cold |",
        "|---|---|---|",
    ]
    lines += [f"| {k} | {v:.1f} | {result['ratio_to_cold'][k]:.2f} |" for k, v in rows.items()]
    write_results(f"cache_{opts.site}", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
