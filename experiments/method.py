"""The method end to end: solver, point model and hybrid gate errors, conformal coverage and the
error model's rank correlation, on the forest simulation (sim-only) and on the frozen-lake field
stand-in (leave-one-position-out).

Usage: python experiments/method.py [--n-events 1100]
Writes experiments/results/method.md. Goals from the issue: forest gate p99 ≥ 5× lower than
the solver's with p50 ≤ 1.1× the solver's; LOPO GDOP-scaled coverage within ±0.03 of nominal and
ρ(error model) > ρ(GDOP). Uses the project cache under outputs/.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

from common import compose_cfg, machine, write_results

from acoustlab.reporting.metrics import gate_scalars
from acoustlab.run.app import run_experiment

log = logging.getLogger("experiments.method")


def run(overrides: list[str]) -> dict:
    cfg = compose_cfg([*overrides, "tracking=none"])
    with tempfile.TemporaryDirectory() as tmp:
        return run_experiment(cfg, Path(tmp) / "run", {})


def rho_text(rho: dict) -> str:
    """Spearman ρ of the error model and of GDOP to two decimals (a ρ of ~1,000 events is not known better), "n/a" where absent."""
    show = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    return f"error model {show(rho.get('error_model'))}, GDOP {show(rho.get('gdop'))}"


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n-events", type=int, default=1100)
    opts = parser.parse_args()
    forest = {}
    for name, extra in (
        ("xgboost", ["model=xgboost"]),
        ("xgboost, correction target", ["model=xgboost", "pipeline.model_target=correction"]),
        ("random_forest", ["model=random_forest"]),
        ("knn", ["model=knn"]),
    ):
        forest[name] = run(["+site=forest", "+experiment=paper_forest", f"data.n_events={opts.n_events}", *extra])
    lake = run(["+site=frozen_lake", "+experiment=paper_frozen_lake", f"data.n_events={opts.n_events}", "model=xgboost"])
    result = {"machine": machine(), "forest_sim_only": forest, "frozen_lake_standin_lopo": lake}
    lines = [
        "# The method end to end",
        "",
        f"`python experiments/method.py --n-events {opts.n_events}`",
        "",
        "## Forest simulation, sim-only (hybrid gate, τ* on simulation; XGBoost-quantile error model)",
        "",
        "| point model | solver p50 / p95 / p99 | model p50 / p95 / p99 | gate p50 / p95 / p99 | gate p99 ÷ solver p99 | gate p50 ÷ solver p50 | τ* (dB) | substitution |",
        "|---|---|---|---|---|---|---|---|",
    ]
    fmt = lambda e: f"{e['p50']:.2f} / {e['p95']:.1f} / {e['p99']:.1f}"  # noqa: E731
    for name, m in forest.items():
        e = m["errors"]
        lines.append(
            f"| {name} | {fmt(e['solver'])} | {fmt(e['model'])} | {fmt(e['gate'])} | {e['gate']['p99'] / max(e['solver']['p99'], 1e-9):.2f} | "
            f"{e['gate']['p50'] / max(e['solver']['p50'], 1e-9):.2f} | {gate_scalars(m).get('tau_star_db', float('nan')):.3g} | {100 * m['substitution_rate']:.0f} % |"
        )
    lines += ["", "Coverage (XGBoost):", "", "| scorer | 0.50 | 0.80 | 0.95 | median width at 0.95 (m) |", "|---|---|---|---|---|"]
    for scorer, cov in forest["xgboost"]["coverage"].items():
        w = forest["xgboost"]["interval_width"][scorer]["0.95"]["median_m"]
        lines.append(f"| {scorer} | {cov['0.5']:.2f} | {cov['0.8']:.2f} | {cov['0.95']:.2f} | {w:.1f} |")
    lines += ["", f"Spearman ρ with the actual error: {rho_text(forest['xgboost']['spearman_rho'])}.", ""]
    e = lake["errors"]
    lines += [
        "## Frozen lake, SYNTHETIC field stand-in, leave-one-position-out (XGBoost)",
        "",
        f"Per-detection errors (failed position excluded, n = {e['gate']['n']}): solver {fmt(e['solver'])}, model {fmt(e['model'])}, gate {fmt(e['gate'])} m; τ* = {gate_scalars(lake).get('tau_star_db', float('nan')):.3g} dB.",
        "",
        "| scorer | 0.50 | 0.80 | 0.95 | worst position at 0.95 |",
        "|---|---|---|---|---|",
    ]
    for scorer, cov in lake["coverage"].items():
        lines.append(
            f"| {scorer} | {cov['0.5']:.2f} | {cov['0.8']:.2f} | {cov['0.95']:.2f} | {lake['coverage_by_position'][scorer]['0.95']['min']:.2f} |"
        )
    lines += ["", f"Spearman ρ with the actual error: {rho_text(lake['spearman_rho'])}."]
    write_results("method", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
