"""The method with statistical power: every simulated event predicted once (cross-fitted), gates
side by side on the same point-model predictions, every conformal variant, selective localization,
95 % intervals by position.

Usage: python experiments/crossfit.py [--n-events 1100] [--n-folds 5]

Runs (XGBoost point model, XGBoost-quantile error model, ``tracking=none``, the project cache):

* forest and frozen lake simulation, ``+experiment=cross_fit_gates``: the learned gate, with the
  hybrid gate (τ* against the box-gated solver, data grid) beside it, and the oracle (the better of
  solver and model per event, which needs the truth: the bound a gate can reach);
  ``pipeline.selective.enabled=true`` (δ = 1 %, ε = 0.1) and ``conformal.ellipse=true``;
* the frozen-lake SYNTHETIC field stand-in, leave-one-position-out (``+experiment=paper_frozen_lake conformal=cqr``:
  the hybrid gate as in the paper, the learned gate beside it).

Failures count as infinite errors in every percentile. Writes
experiments/results/crossfit.md; the goals of the issue are checked in the Markdown.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
from common import fmt, machine, run_in_process, write_results

log = logging.getLogger("experiments.crossfit")
SELECTIVE = ["pipeline.selective.enabled=true", "pipeline.selective.delta=0.01", "pipeline.selective.epsilon=0.1", "conformal.ellipse=true"]


def ci(metrics: dict, method: str, stat: str) -> str:
    low, high = metrics["ci95"]["errors"][method][stat]
    if stat == "share_gt_5m":
        return f"{100 * low:.1f}–{100 * high:.1f}"
    return f"{fmt(low)}–{fmt(high)}"


def error_lines(m: dict) -> list[str]:
    lines = ["| method | p50 (m) | p95 (95 % CI) | p99 (95 % CI) | > 5 m % (95 % CI) | failures |", "|---|---|---|---|---|---|"]
    for method, e in m["errors"].items():
        lines.append(
            f"| {method} | {fmt(e['p50'])} | {fmt(e['p95'])} ({ci(m, method, 'p95')}) | {fmt(e['p99'])} ({ci(m, method, 'p99')}) | "
            f"{100 * e['share_gt_5m']:.1f} ({ci(m, method, 'share_gt_5m')}) | {e['n_failed']} |"
        )
    return lines


def coverage_lines(m: dict) -> list[str]:
    lines = [
        "| scorer | 0.50 | 0.80 | 0.95 (95 % CI) | worst position at 0.80 / 0.95 | median width at 0.95 (m) | width ÷ gate p95 |",
        "|---|---|---|---|---|---|---|",
    ]
    p95 = m["errors"]["gate"]["p95"]
    for scorer, cov in m["coverage"].items():
        low, high = m["ci95"]["coverage"][scorer]["0.95"]
        worst = m["coverage_by_position"][scorer]
        width = m["interval_width"][scorer]["0.95"]["median_m"]
        lines.append(
            f"| {scorer} | {cov['0.5']:.3f} | {cov['0.8']:.3f} | {cov['0.95']:.3f} ({low:.3f}–{high:.3f}) | "
            f"{worst['0.8']['min']:.2f} / {worst['0.95']['min']:.2f} | {fmt(width)} | {width / p95:.2f} |"
        )
    return lines


def risk_lines(m: dict) -> list[str]:
    lines = ["| share placed | predicted-error threshold (m) | p50 | p95 | p99 | > 5 m |", "|---|---|---|---|---|---|"]
    for r in m["risk_coverage"]:
        lines.append(
            f"| {100 * r['share_placed']:.0f} % | {fmt(r['threshold_m'])} | {fmt(r['p50'])} | {fmt(r['p95'])} | {fmt(r['p99'])} | "
            f"{100 * r['share_gt_5m']:.1f} % |"
        )
    return lines


def site_section(title: str, m: dict) -> list[str]:
    gap = m["gate_gap"]
    rho = m["spearman_rho"]
    lines = [
        f"## {title}",
        "",
        f"{m['errors']['gate']['n']} events at {m['ci95']['n_positions']} positions; {m['bench_seconds']:.0f} s.",
        "",
        *error_lines(m),
        "",
        "Gates against the oracle: " + ", ".join(f"{k} {v:.2f}" for k, v in gap.items()) + ".",
        "",
        "Conformal (radius around the configured gate's estimate):",
        "",
        *coverage_lines(m),
        "",
        f"Spearman ρ with the gate's actual error: error model {rho.get('error_model')}, GDOP {rho.get('gdop')}.",
        "",
        "Risk–coverage (events placed in order of predicted error):",
        "",
        *risk_lines(m),
    ]
    if "ellipse" in m:
        lines += [
            "",
            "Error ellipses (shape from the local TDOA geometry, size from conformal; coverage of the truth, worst position, "
            "median area against the median area of the `fixed` circle):",
            "",
        ]
        for level, e in m["ellipse"].items():
            circle = np.pi * m["interval_width"]["fixed"][level]["median_m"] ** 2
            lines.append(
                f"- {level}: coverage {e['coverage']:.3f}, worst position {e['worst_position']:.2f}, "
                f"median area {e['median_area_m2']:.1f} m² (circle {circle:.1f} m²)"
            )
    if "selective" in m:
        s = m["selective"]
        per_split = m.get("selective_by_split", [])
        lines += [
            "",
            f"Selective localization (certified on calibration positions, δ = 1 %, ε = 0.1): {100 * s['share_placed']:.1f} % placed, "
            f"p95 {fmt(s.get('p95', float('nan')))} m, > 5 m among placed {100 * s.get('share_gt_5m', float('nan')):.2f} % "
            f"(worst position {100 * s.get('worst_position_share_gt_5m', float('nan')):.0f} %); thresholds per fold: "
            + ", ".join(fmt(x["threshold_m"]) for x in per_split)
            + " m.",
        ]
    return lines


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-events", type=int, default=1100)
    parser.add_argument("--n-folds", type=int, default=5)
    opts = parser.parse_args()
    common = [f"data.n_events={opts.n_events}", "model=xgboost"]
    runs = {
        "forest": run_in_process(["+site=forest", "+experiment=cross_fit_gates", f"protocol.n_folds={opts.n_folds}", *common, *SELECTIVE]),
        "frozen_lake": run_in_process(
            ["+site=frozen_lake", "+experiment=cross_fit_gates", f"protocol.n_folds={opts.n_folds}", *common, *SELECTIVE]
        ),
        "frozen_lake_standin_lopo": run_in_process(["+site=frozen_lake", "+experiment=paper_frozen_lake", "conformal=cqr", *common]),
    }
    lines = [
        "# The method, cross-fitted",
        "",
        f"`python experiments/crossfit.py --n-events {opts.n_events} --n-folds {opts.n_folds}`. "
        "Methods: solver (consistent set), model (XGBoost), gate (the configured gate: learned on the simulations, hybrid on the "
        "stand-in as in the paper), gate_<name> (another gate on the same predictions), oracle (the better of solver and model per "
        "event; needs the truth). Failures are infinite errors; intervals are 95 % position bootstraps.",
        "",
    ]
    lines += site_section("Forest simulation, cross-fitted (learned gate; hybrid beside it)", runs["forest"]) + [""]
    lines += site_section("Frozen-lake simulation, cross-fitted (learned gate; hybrid beside it)", runs["frozen_lake"]) + [""]
    lines += site_section(
        "Frozen lake, SYNTHETIC field stand-in, leave-one-position-out (hybrid gate as in the paper; learned beside it)",
        runs["frozen_lake_standin_lopo"],
    )
    write_results("method_crossfit", {"machine": machine(), "n_events": opts.n_events, "n_folds": opts.n_folds, "runs": runs}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
