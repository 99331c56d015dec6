"""The full method with 10,000 training rows on the frozen lake, cross-fitted over 12,500 simulated events.

Usage: python experiments/method_10k_rows.py [--n-events 12500] [--max-train-rows 10000]

One job, the same as the command line
``python -m acoustlab +site=frozen_lake +experiment=cross_fit_gates data.n_events=12500 protocol.n_folds=5
protocol.max_train_rows=10000 gate.stakes_cap_m=null conformal=paper tracking=none``
(run in this process, without plots): XGBoost point model and error model, the learned gate with
equal weights and the hybrid gate on the same predictions, fixed and GDOP-scaled conformal radii,
5 folds over source positions. Failures count as infinite errors. Its metrics.json is written as
``experiments/results/method_10k_rows_frozen_lake.md`` (plus the commit that made it) with a table in ``.md``.
"""

from __future__ import annotations

import argparse
import logging

from common import fmt, run_in_process, write_results

log = logging.getLogger("experiments.method_10k_rows")
METHODS = (
    ("solver", "solver"),
    ("model", "model (XGBoost, ≤ {rows:,} rows)"),
    ("gate", "gate (learned, unweighted)"),
    ("oracle", "oracle"),
    ("gate_hybrid", "hybrid gate"),
)


def table(metrics: dict, rows: int) -> list[str]:
    """The Markdown lines of one run's metrics."""
    errors, gap = metrics["errors"], metrics["gate_gap"]
    lines = ["| method | p50 (m) | p95 | p99 | > 5 m | failed |", "|---|---|---|---|---|---|"]
    for key, label in METHODS:
        if key in errors:
            e = errors[key]
            lines.append(
                f"| {label.format(rows=rows)} | {fmt(e['p50'])} | {fmt(e['p95'])} | {fmt(e['p99'])} | "
                f"{100 * e['share_gt_5m']:.1f} % | {e['n_failed']} |"
            )
    coverage = ", ".join(
        f"{scorer} "
        + " / ".join(f"{c[level]:.3f}" for level in ("0.5", "0.8", "0.95"))
        + f" (median radius at 0.95 {metrics['interval_width'][scorer]['0.95']['median_m']:.2f} m)"
        for scorer, c in metrics["coverage"].items()
    )
    rho = metrics["spearman_rho"]
    return [
        *lines,
        "",
        f"Gate ÷ oracle: p95 {gap['p95_gate_over_oracle']:.2f}, p99 {gap['p99_gate_over_oracle']:.2f}; gate p50 ÷ solver "
        f"{gap['p50_gate_over_solver']:.2f}. Coverage at 0.50 / 0.80 / 0.95: {coverage}. Spearman ρ with the gate's error: "
        f"error model {rho['error_model']:.3f}, GDOP {rho['gdop']:.3f}; gross-error AUC of the error model "
        f"{metrics['gross_error_auc']['error_model']:.3f}.",
    ]


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-events", type=int, default=12500)
    parser.add_argument("--max-train-rows", type=int, default=10000)
    opts = parser.parse_args()
    overrides = [
        "+site=frozen_lake",
        "+experiment=cross_fit_gates",
        f"data.n_events={opts.n_events}",
        "protocol.n_folds=5",
        f"protocol.max_train_rows={opts.max_train_rows}",
        "gate.stakes_cap_m=null",
        "conformal=paper",
    ]
    metrics = run_in_process(overrides)
    timings = metrics.get("timings_s", {})
    lines = [
        f"# The method with {opts.max_train_rows:,} training rows (frozen lake, cross-fitted)",
        "",
        f"`python experiments/method_10k_rows.py --n-events {opts.n_events} --max-train-rows {opts.max_train_rows}`: "
        f"the job `python -m acoustlab {' '.join(overrides)} tracking=none` in one process "
        f"(models {timings.get('models_s', float('nan')):.0f} s, whole job {metrics['bench_seconds']:.0f} s). "
        "The JSON file is the run's metrics.json.",
        "",
        *table(metrics, opts.max_train_rows),
    ]
    write_results("method_10k_rows_frozen_lake", metrics, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
