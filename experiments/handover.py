"""What the hand-over check costs on acoustlab's own simulation and buys off it.

Usage: python experiments/handover.py [--own-sim frozen_lake] [--cross-sim frozen_lake forest] [--n-positions 60]

A gate hands a detection over to the point model only where the model's estimate explains the
measured time differences (all but a quarter of the pairs, each at its nearest GCC candidate) at
least as well as the solver's fix, within a tolerance in position metres (the misfit's excess times
the GDOP at the estimate) set on simulation (``pipeline.trust.handover_*``; acoustlab/method/trust.py).
The check runs after the gate, so the same run's predictions also give the positions without it
(the trust check's other rules applied alone): both are reported from one run, on the same
point-model predictions. Runs (XGBoost point model and error model, learned gate, the project cache):

* **own simulation**: ``+experiment=cross_fit_gates`` cross-fitted, 5 folds, 1,100 events (the hybrid gate beside it);
* **second simulator**: ``protocol=field_eval field=image_source`` (pyroomacoustics' image-source
  renders with real calls and noise, 30 % of the positions outside the simulated region), fitted on
  1,000 events of acoustlab's simulator.

Failures count as infinite errors; intervals are 95 % position bootstraps. Writes experiments/results/handover.md.
"""

from __future__ import annotations

import argparse
import json
import logging

import numpy as np
import pandas as pd
from common import REPO, code_version, fmt, machine, run_in_process, write_results

from acoustlab.core import columns as col
from acoustlab.method import trust
from acoustlab.reporting.metrics import error_summary, share_gross

log = logging.getLogger("experiments.handover")
METHOD = ["model=xgboost", "error_model=xgboost_quantile", "gate=learned", "+gate@pipeline.extra_gates.hybrid=hybrid"]
N_BOOT = 1000
#: the runs' predictions (git-ignored), reused when the same overrides are asked for again
KEPT = REPO / "outputs" / "bench_handover"


def without_handover_check(p: pd.DataFrame, method: str = "gate") -> np.ndarray:
    """(E, 2) the gate's positions had the hand-over check been off: its overrides undone where no other trust rule applies."""
    reported = p[list(col.estimate_xy(method))].to_numpy(float)
    if method != "gate":  # extra gates' positions carry no reason column: recompute from the flags
        return reported
    other = (
        p[col.trust_flag("model_outside_support")].to_numpy(bool)
        | (p[col.trust_flag("novelty")].to_numpy(float) > 1)
        | (p[col.trust_flag("solver_outside_support")].to_numpy(bool) & p[col.trust_flag("solver_consistent")].to_numpy(bool))
    )
    by_check = p[col.TRUST_REASON].isin([trust.REASON_EXPLAINS_WORSE, trust.REASON_ABSTAIN_MISFIT]).to_numpy() & ~other
    before = p[list(col.estimate_xy(col.extra_gate_method(col.GATE_WITHOUT_TRUST)))].to_numpy(float)
    return np.where(by_check[:, None], before, reported)


def errors_of(p: pd.DataFrame, position_m: np.ndarray) -> np.ndarray:
    e = np.hypot(*(position_m - p[["true_x_m", "true_y_m"]].to_numpy(float)).T)
    return np.where(np.isfinite(e), e, np.inf)


def bootstrap_share(errors: np.ndarray, groups: np.ndarray, seed: int = 0) -> tuple[float, float]:
    """95 % position-bootstrap interval of the > 5 m share."""
    codes, inverse = np.unique(groups, return_inverse=True)
    rows_of = [np.flatnonzero(inverse == k) for k in range(codes.size)]
    rng = np.random.default_rng(seed)
    shares = [share_gross(errors[np.concatenate([rows_of[k] for k in rng.integers(0, codes.size, codes.size)])]) for _ in range(N_BOOT)]
    return float(np.quantile(shares, 0.025)), float(np.quantile(shares, 0.975))


def rows_for(label: str, p: pd.DataFrame) -> tuple[list[str], dict]:
    groups = p[col.POSITION_ID].to_numpy()
    variants = {
        "solver": errors_of(p, p[list(col.estimate_xy("solver"))].to_numpy(float)),
        "gate, hand-over check on": errors_of(p, p[list(col.estimate_xy("gate"))].to_numpy(float)),
        "gate, hand-over check off": errors_of(p, without_handover_check(p)),
        "gate before any trust rule": errors_of(p, p[list(col.estimate_xy(col.extra_gate_method(col.GATE_WITHOUT_TRUST)))].to_numpy(float)),
    }
    lines, raw = [], {}
    for name, e in variants.items():
        s = error_summary(e)
        low, high = bootstrap_share(e, groups)
        raw[name] = {**s, "share_gt_5m_ci95": [low, high]}
        lines.append(
            f"| {label} | {name} | {fmt(s['p50'])} | {fmt(s['p95'])} | {fmt(s['p99'])} | "
            f"{100 * s['share_gt_5m']:.1f} ({100 * low:.1f}–{100 * high:.1f}) | {int(np.isinf(e).sum())} |"
        )
    reasons = p[col.TRUST_REASON].value_counts().to_dict()
    raw["overridden"] = {str(k): int(v) for k, v in reasons.items() if k}
    raw["n_events"], raw["n_positions"] = len(p), int(np.unique(groups).size)
    raw["substituted"] = int(p[col.SUBSTITUTED].sum())
    raw["gt5_ratio_gate_over_solver"] = raw["gate, hand-over check on"]["share_gt_5m"] / max(raw["solver"]["share_gt_5m"], 1e-12)
    return lines, raw


def predictions_of(label: str, overrides: list[str]) -> tuple[pd.DataFrame, dict]:
    """A run's predictions and metrics, kept under outputs/ (git-ignored) so the tables can be remade without re-running.

    Reused only for the same overrides and the same code (``common.code_version``).
    """
    keep = KEPT / (label.replace("/", "_") + ".parquet")
    metrics_file = keep.with_suffix(".json")
    code = code_version()
    if keep.is_file() and metrics_file.is_file():
        kept = json.loads(metrics_file.read_text())
        if code and kept.get("overrides") == overrides and kept.get("code") == code:
            log.info("%s: reusing %s", label, keep)
            return pd.read_parquet(keep), kept
    metrics = run_in_process(overrides, keep)
    metrics["overrides"], metrics["code"] = overrides, code
    metrics_file.write_text(json.dumps(metrics, default=str))
    return pd.read_parquet(keep), metrics


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--own-sim", nargs="*", default=["frozen_lake"], metavar="SITE")
    parser.add_argument("--cross-sim", nargs="*", default=["frozen_lake", "forest"], metavar="SITE")
    parser.add_argument("--n-positions", type=int, default=60)
    opts = parser.parse_args()
    jobs = {
        **{
            f"{site}/own_simulation": [
                f"+site={site}",
                "+experiment=cross_fit_gates",
                "protocol.n_folds=5",
                "data.n_events=1100",
                "model=xgboost",
            ]
            for site in opts.own_sim
        },
        **{
            f"{site}/second_simulator": [
                f"+site={site}",
                *METHOD,
                "protocol=field_eval",
                "field=image_source",
                f"field.n_positions={opts.n_positions}",
            ]
            for site in opts.cross_sim
        },
    }
    lines = [
        "# The hand-over check: the gate uses the point model only where its estimate explains the measured time differences",
        "",
        f"`python experiments/handover.py --own-sim {' '.join(opts.own_sim)} --cross-sim {' '.join(opts.cross_sim)} "
        f"--n-positions {opts.n_positions}`. One run per row group; the check on and off are the same run's predictions "
        "(the check acts after the gate). Failures are infinite errors; 95 % position-bootstrap intervals of the > 5 m share.",
        "",
        "| run | positions of | p50 (m) | p95 (m) | p99 (m) | > 5 m % (95 % CI) | failures |",
        "|---|---|---|---|---|---|---|",
    ]
    raw: dict[str, dict] = {}
    for label, overrides in jobs.items():
        p, metrics = predictions_of(label, overrides)
        rows, raw[label] = rows_for(label, p)
        raw[label]["seconds"] = metrics["bench_seconds"]
        splits = metrics.get("trust_by_split", [metrics.get("trust", {})])
        tolerances = [t.get("training_region", {}).get("handover_tolerance_m") for t in splits]
        raw[label]["handover_tolerance_m"] = float(np.median([t for t in tolerances if t is not None] or [np.nan]))
        lines += rows
    lines += [
        "",
        "Per run: hand-over tolerance (m of position: the misfit over the solver's times the GDOP at the estimate), gate decisions overridden by reason, events, seconds:",
        "",
    ]
    for label, r in raw.items():
        tol = r["handover_tolerance_m"]
        lines.append(
            f"- {label}: tolerance {fmt(tol)} m; overridden {r['overridden']}; {r['substituted']} hand-overs kept; "
            f"{r['n_events']} events at {r['n_positions']} positions; gate > 5 m ÷ solver > 5 m = {r['gt5_ratio_gate_over_solver']:.2f}; "
            f"{r['seconds']:.0f} s"
        )
    write_results("handover", {"machine": machine(), "runs": raw}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
