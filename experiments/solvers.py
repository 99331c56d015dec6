"""Solvers side by side on the default simulation: least squares, closed-form hyperbolic, robust
multi-candidate, and SRP-PHAT (score-based, computed in the feature stage), per site.

Usage: python experiments/solvers.py [--n-events 1100]
Writes experiments/results/solvers.md: error quantiles over all events, the share of gross
errors (> 5 m), time per event, and errors split by the SNR at the nearest mic (lowest and highest
third), which is where the methods part ways. Uses the project cache under outputs/.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
from common import compose_cfg, machine, write_results

from acoustlab.core import columns as col
from acoustlab.method.pipeline import error_2d_m
from acoustlab.run.app import build_run, prepare_data, solver_features
from acoustlab.run.registry import build

log = logging.getLogger("experiments.solvers")
SOLVERS = ("least_squares", "hyperbolic", "baseline_robust")


def evaluate(site_name: str, n_events: int) -> dict:
    cfg = compose_cfg([f"+site={site_name}", "features=physics_srp", f"data.n_events={n_events}"])
    built = build_run(cfg)
    data = prepare_data(cfg, built).dataset  # the data a real run gets, plausible-region bound included
    truth = data.events[list(col.TRUE_XY)].to_numpy()
    snr = data.events[col.SNR].to_numpy()
    low, high = snr <= np.percentile(snr, 33.3), snr >= np.percentile(snr, 66.7)
    errors, timing = {}, {}
    for name in SOLVERS:
        solver = build(compose_cfg([f"+site={site_name}", f"solver={name}"]).solver, "solver")
        start = time.perf_counter()
        table = solver_features(cfg, data.features, data.events, built.site, solver)
        timing[name] = (time.perf_counter() - start) / len(truth)
        errors[name] = error_2d_m(table[list(col.SOLVER_ESTIMATE_COLUMNS)].to_numpy(), truth)  # a fix outside the bound: infinite
    errors["srp_phat"] = error_2d_m(data.features[[col.SRP_X, col.SRP_Y]].to_numpy(), truth)
    timing["srp_phat"] = float("nan")

    def stats(e):
        def q(p: float) -> float:  # empirical quantile: inf where it falls among the failures (no inf - inf interpolation)
            return float(np.percentile(e, p, method="inverted_cdf"))

        return {"p50": q(50), "p90": q(90), "p95": q(95), "p99": q(99), "gross": float(np.mean(e > 5.0))}

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
    lines = [
        "# Solvers side by side",
        "",
        f"`python experiments/solvers.py --n-events {opts.n_events}` (all simulated events; errors in m; a fix outside the plausible region a run applies is a failure, an infinite error; empirical percentiles, so inf means the percentile falls among the failures)",
        "",
    ]
    for site, r in result["sites"].items():
        lines += [
            f"## {site}",
            "",
            "| method | p50 | p90 | p95 | p99 | gross > 5 m | p50 / p95, lowest-SNR third | p50 / p95, highest-SNR third | ms per event |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
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
