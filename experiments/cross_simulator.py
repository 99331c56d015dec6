"""What simulator misspecification costs: train on acoustlab's simulator, evaluate on an independent one.

Usage: python experiments/cross_simulator.py [--sites frozen_lake forest] [--n-positions 60] [--own-sim frozen_lake] [--wide-training 0.6]

Per site, in one script (XGBoost point model, XGBoost-quantile error model, learned gate, the
paper's fixed and GDOP-scaled conformal, ``tracking=none``, the project cache):

* **cross-simulator**: ``protocol=field_eval field=image_source``: fitted on 1,000 of the site's
  own simulated events, evaluated on ``--n-positions`` × 5 events rendered by pyroomacoustics'
  image-source method (sources in and around the array, heights over the site's range, SNR
  5–30 dB, real calls and noise; 30 % of positions outside the simulated source region). The
  trusted gate, the same gate before the trust check (``gate_without_trust``), the hybrid gate
  (the paper's, trusted) and the solver alone are all on the same predictions; a second run with
  ``pipeline.trust.enabled=false`` gives the radii the method had before the trust check;
* **the same under a stated ±1 °C thermometer error** (``--temperature-error-c``): the field
  events' speed of sound is computed from a temperature off by that much;
* with ``--wide-training 0.6``: the same, trained on a simulation of sources in the mics' hull grown
  by 0.6 × the array extent (``site.hull_expansion``), which covers the evaluation's outside
  positions: what covering "what the array hears" buys;
* with ``--own-sim SITE ...``: acoustlab's own simulation of those sites cross-fitted (``+experiment=cross_fit_gates``,
  5 folds, 1,100 events), trusted and untrusted gates side by side.

Failures count as infinite errors; intervals are 95 % position bootstraps. Writes
experiments/results/cross_simulator.md.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
from common import REPO, compose_cfg, fmt, machine, run_in_process, write_results

log = logging.getLogger("experiments.cross_simulator")
METHOD = [
    "model=xgboost",
    "error_model=xgboost_quantile",
    "gate=learned",
    "conformal=paper",
    "+gate@pipeline.extra_gates.hybrid=hybrid",
    "+gate@pipeline.extra_gates.solver_only=solver_only",
]
LEVELS = ("0.5", "0.8", "0.95")


def pct(v: float) -> str:
    return "—" if v is None or not np.isfinite(v) else f"{100 * v:.1f}"


def error_rows(m: dict, label: str) -> list[str]:
    rows = []
    for method, e in m["errors"].items():
        low, high = m["ci95"]["errors"][method]["share_gt_5m"]
        rows.append(
            f"| {label} | {method} | {fmt(e['p50'])} | {fmt(e['p95'])} | {fmt(e['p99'])} | {pct(e['share_gt_5m'])} ({pct(low)}–{pct(high)}) |"
        )
    return rows


def coverage_rows(m: dict, label: str) -> list[str]:
    rows = []
    for scorer, cov in m["coverage"].items():
        width = m["interval_width"][scorer]["0.95"]
        rows.append(
            f"| {label} | {scorer} | "
            + " / ".join(f"{cov[lv]:.3f}" for lv in LEVELS)
            + f" | {fmt(width['median_m'])} / {fmt(width['mean_m'])} / {fmt(width['max_m'])} | {width['max_m'] / max(width['median_m'], 1e-12):.0f} |"
        )
    return rows


def region_rows(site: str, label: str, predictions_file: Path) -> list[str]:
    """> 5 m shares and coverage of the trusted gate inside and outside the site's (default) simulated source region."""
    import pandas as pd

    from acoustlab.stages.sites import site_from_config
    from acoustlab.toolkit.geometry import distance_to_polygon_m, source_region

    site_obj = site_from_config(compose_cfg([f"+site={site}"]).site)
    p = pd.read_parquet(predictions_file)
    polygon, buffer_m = source_region(site_obj.mic_positions_m, site_obj.hull_expansion)
    outside = distance_to_polygon_m(p[["true_x_m", "true_y_m"]].to_numpy(float), polygon) > buffer_m
    rows = []
    for name, part in (("inside", p[~outside]), ("outside", p[outside])):
        shares = " / ".join(
            pct(float((part[f"error_{m}_m"] > 5).mean())) for m in ("solver", "model", "gate", "gate_without_trust", "gate_solver_only")
        )
        cover = " / ".join(f"{float((part['error_gate_m'] <= part[f'radius__fixed__{lv}']).mean()):.2f}" for lv in LEVELS)
        rows.append(f"| {label} | {name} ({len(part)}) | {shares} | {cover} |")
    return rows


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["frozen_lake", "forest"])
    parser.add_argument("--n-positions", type=int, default=60)
    parser.add_argument("--temperature-error-c", type=float, default=1.0)
    parser.add_argument(
        "--own-sim",
        nargs="*",
        default=[],
        metavar="SITE",
        help="also cross-fit on acoustlab's own simulation of these sites (slow on the forest)",
    )
    parser.add_argument(
        "--wide-training",
        type=float,
        default=None,
        metavar="EXPANSION",
        help="also train on a simulation whose source region is the mics' hull grown by EXPANSION × the array extent "
        "(site.hull_expansion), covering the evaluation's outside positions",
    )
    opts = parser.parse_args()
    field = ["protocol=field_eval", "field=image_source", f"field.n_positions={opts.n_positions}"]
    runs: dict[str, dict] = {}
    kept = REPO / "outputs" / "bench_cross_simulator"
    for site in opts.sites:
        base = [f"+site={site}", *METHOD]
        runs[f"{site}/cross_simulator"] = run_in_process([*base, *field], kept / f"{site}_cross_simulator.parquet")
        runs[f"{site}/cross_simulator_without_trust"] = run_in_process([*base, *field, "pipeline.trust.enabled=false"])
        runs[f"{site}/cross_simulator_thermometer_error"] = run_in_process(
            [*base, *field, f"field.temperature_error_c={opts.temperature_error_c}"]
        )
        if opts.wide_training is not None:
            runs[f"{site}/cross_simulator_wide_training"] = run_in_process(
                [*base, *field, f"site.hull_expansion={opts.wide_training}"], kept / f"{site}_cross_simulator_wide_training.parquet"
            )
        if site in opts.own_sim:
            runs[f"{site}/own_simulation"] = run_in_process(
                [
                    f"+site={site}",
                    "+experiment=cross_fit_gates",
                    "protocol.n_folds=5",
                    "conformal=paper",
                    "model=xgboost",
                    "data.n_events=1100",
                ]
            )
    lines = [
        "# Cross-simulator: trained on acoustlab's simulator, evaluated on pyroomacoustics' image-source renders",
        "",
        f"`python experiments/cross_simulator.py --sites {' '.join(opts.sites)} --n-positions {opts.n_positions}"
        f"{' --own-sim ' + ' '.join(opts.own_sim) if opts.own_sim else ''}{f' --wide-training {opts.wide_training:g}' if opts.wide_training is not None else ''}`. Methods on the same predictions: solver (consistent set), model (XGBoost), "
        "gate (learned, with the trust check), gate_without_trust (the same gate's choice before the check), gate_hybrid (the "
        "paper's gate, with the check), gate_solver_only, oracle (the better of solver and model; needs the truth). Failures are "
        "infinite errors; 95 % intervals by position bootstrap.",
        "",
        "| run | method | p50 (m) | p95 (m) | p99 (m) | > 5 m % (95 % CI) |",
        "|---|---|---|---|---|---|",
    ]
    for name, m in runs.items():
        lines += error_rows(m, name)
    lines += [
        "",
        "Conformal coverage at 0.50 / 0.80 / 0.95 and the 0.95 radius (median / mean / max, m; max ÷ median):",
        "",
        "| run | scorer | coverage | 0.95 radius | max ÷ median |",
        "|---|---|---|---|---|",
    ]
    for name, m in runs.items():
        lines += coverage_rows(m, name)
    lines += [
        "",
        "By region (the site's default simulated source region; the evaluation puts 30 % of its positions outside it): "
        "> 5 m % of solver / model / gate / gate_without_trust / gate_solver_only, and coverage of `fixed` at 0.50 / 0.80 / 0.95:",
        "",
        "| run | region (events) | > 5 m % | coverage |",
        "|---|---|---|---|",
    ]
    for kept_file in sorted(kept.glob("*.parquet")):
        site, _, label = kept_file.stem.partition("_cross_simulator")
        if site in opts.sites:
            lines += region_rows(site, f"{site}/cross_simulator{label}", kept_file)
    lines += ["", "Trust check (cross-simulator runs): gate decisions it overrode, by reason:", ""]
    for name, m in runs.items():
        if "trust" in m:
            lines.append(
                f"- {name}: {m['trust'].get('overridden')}; novel detections {m['trust'].get('n_novel')}, "
                f"solver fixes outside the training region {m['trust'].get('n_solver_outside_support')}"
            )
    write_results("cross_simulator", {"machine": machine(), "n_positions": opts.n_positions, "runs": runs}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
