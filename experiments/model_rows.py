"""Point-model error against training rows, cross-fitted on the same events (the paper caps at 1,000 for TabPFN).

Usage: python experiments/model_rows.py [--site frozen_lake] [--n-events 12500] [--rows 1000 3000 10000]

With 5 folds each fit sees 4/5 of the events (12,500 events: 10,000 rows).

One cross-fitted run per cap (``protocol=cross_fit protocol.n_folds=5 protocol.max_train_rows=<rows>``),
XGBoost point model, consistent-set solver, ``gate=learned`` with equal weights (``gate.stakes_cap_m=null``:
scikit-learn's boosting is ~5× slower with sample weights, which at 10,000 rows dominates the run),
the constant error model (the point model is what is measured). Every cap predicts the same events, so the rows are side by side.
Also the point model as a correction of the first-stage estimate (``pipeline.model_target=correction``)
at the smallest cap. Writes experiments/results/model_rows.md.
"""

from __future__ import annotations

import argparse
import logging

from common import fmt, machine, run_in_process, write_results

log = logging.getLogger("experiments.model_rows")


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--site", default="frozen_lake")
    parser.add_argument("--n-events", type=int, default=12500)
    parser.add_argument("--rows", type=int, nargs="+", default=[1000, 3000, 10000])
    opts = parser.parse_args()
    base = [
        f"+site={opts.site}",
        f"data.n_events={opts.n_events}",
        "protocol=cross_fit",
        "protocol.n_folds=5",
        "model=xgboost",
        "gate=learned",
        "gate.stakes_cap_m=null",
        "error_model=constant",
        "conformal=fixed",
    ]
    runs = {f"absolute, ≤ {rows} rows": run_in_process([*base, f"protocol.max_train_rows={rows}"]) for rows in opts.rows}
    runs[f"correction, ≤ {opts.rows[0]} rows"] = run_in_process(
        [*base, f"protocol.max_train_rows={opts.rows[0]}", "pipeline.model_target=correction"]
    )
    lines = [
        f"# Point model against training rows ({opts.site}, cross-fitted)",
        "",
        f"`python experiments/model_rows.py --site {opts.site} --n-events {opts.n_events} --rows {' '.join(map(str, opts.rows))}`: "
        f"{opts.n_events} events, 5 folds over positions, XGBoost, learned gate with equal weights. Failures count as infinite errors.",
        "",
        "| point model target, training cap | model p50 (m) | model p95 | model p99 | model > 5 m | gate p50 | gate p95 | gate p99 | oracle p95 | seconds |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, m in runs.items():
        e = m["errors"]
        lines.append(
            f"| {name} | {fmt(e['model']['p50'])} | {fmt(e['model']['p95'])} | {fmt(e['model']['p99'])} | "
            f"{100 * e['model']['share_gt_5m']:.1f} % | {fmt(e['gate']['p50'])} | {fmt(e['gate']['p95'])} | {fmt(e['gate']['p99'])} | "
            f"{fmt(e['oracle']['p95'])} | {m['bench_seconds']:.0f} |"
        )
    write_results("model_rows", {"machine": machine(), "site": opts.site, "n_events": opts.n_events, "runs": runs}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
