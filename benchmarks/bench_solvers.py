"""Solvers side by side on the default simulation: least squares, closed-form hyperbolic, robust
multi-candidate, and SRP-PHAT (score-based, computed in the feature stage), per site.

Usage: python benchmarks/bench_solvers.py [--n-events 1100]
Writes benchmarks/results/solvers.{json,md}: error quantiles over all events, the share of gross
errors (> 5 m), time per event, and errors split by the SNR at the nearest mic (lowest and highest
third), which is where the methods part ways. Uses the project cache under outputs/.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
from common import compose_cfg, machine, write_results

from acoustlab.method.pipeline import error_2d_m
from acoustlab.run.registry import build, build_feature_sets, to_plain
from acoustlab.stages.cache import StageCache
from acoustlab.stages.dataset import SimulationPlan, load_or_build_simulated
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import add_solver_columns

log = logging.getLogger("bench_solvers")
SOLVERS = ("least_squares", "hyperbolic", "robust")


def evaluate(site_name: str, n_events: int) -> dict:
    cfg = compose_cfg([f"+site={site_name}", "features=physics_srp", f"data.n_events={n_events}"])
    site = site_from_config(cfg.site)
    plan = SimulationPlan(n_events, int(cfg.data.events_per_position), int(cfg.seed), int(cfg.data.chunk_size), n_jobs=2)
    data = load_or_build_simulated(site, build(cfg.simulator, "simulator"), to_plain(cfg.simulator), build_feature_sets(cfg.features),
                                   to_plain(cfg.features.groups), plan, StageCache(cfg.cache.dir))
    truth = data.events[["x_m", "y_m"]].to_numpy()
    snr = data.events["snr_db"].to_numpy()
    low, high = snr <= np.percentile(snr, 33.3), snr >= np.percentile(snr, 66.7)
    errors, timing = {}, {}
    height = float(np.mean(site.source_height_range_m))
    for name in SOLVERS:
        solver = build(compose_cfg([f"+site={site_name}", f"solver={name}"]).solver, "solver", source_height_m=height)
        start = time.perf_counter()
        table = add_solver_columns(data.features, data.events, site, solver)
        timing[name] = (time.perf_counter() - start) / len(truth)
        errors[name] = error_2d_m(table[["solver__x_m", "solver__y_m"]].to_numpy(), truth)
    errors["srp_phat"] = error_2d_m(data.features[["srp__x_m", "srp__y_m"]].to_numpy(), truth)
    timing["srp_phat"] = float("nan")

    def stats(e):
        return {"p50": float(np.percentile(e, 50)), "p90": float(np.percentile(e, 90)), "p95": float(np.percentile(e, 95)),
                "p99": float(np.percentile(e, 99)), "gross": float(np.mean(e > 5.0))}

    return {
        "n_events": int(len(truth)),
        "all": {k: stats(v) for k, v in errors.items()},
        "low_snr": {k: stats(v[low]) for k, v in errors.items()},
        "high_snr": {k: stats(v[high]) for k, v in errors.items()},
        "seconds_per_event": timing,
    }


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n-events", type=int, default=1100)
    opts = parser.parse_args()
    result = {"machine": machine(), "sites": {s: evaluate(s, opts.n_events) for s in ("frozen_lake", "forest")}}
    lines = ["# Solvers side by side", "", f"`python benchmarks/bench_solvers.py --n-events {opts.n_events}` (all simulated events; errors in m)", ""]
    for site, r in result["sites"].items():
        lines += [f"## {site}", "", "| method | p50 | p90 | p95 | p99 | gross > 5 m | p50 / p95, lowest-SNR third | p50 / p95, highest-SNR third | ms per event |", "|---|---|---|---|---|---|---|---|---|"]
        for name, s in r["all"].items():
            lo, hi = r["low_snr"][name], r["high_snr"][name]
            t = r["seconds_per_event"][name]
            lines.append(
                f"| {name} | {s['p50']:.2f} | {s['p90']:.1f} | {s['p95']:.1f} | {s['p99']:.0f} | {100 * s['gross']:.1f} % | "
                f"{lo['p50']:.2f} / {lo['p95']:.1f} | {hi['p50']:.2f} / {hi['p95']:.1f} | {'(feature stage)' if np.isnan(t) else f'{1e3 * t:.2f}'} |"
            )
        lines.append("")
    write_results("solvers", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
