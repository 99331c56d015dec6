"""Error and coverage summaries of a run's predictions."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from scipy.stats import spearmanr

from acoustlab.core import columns as col

ERROR_QUANTILES = {"p50": 50, "p90": 90, "p95": 95, "p99": 99}
#: An error above this is a gross error (m); failures count as gross.
GROSS_ERROR_M = 5.0
#: Position-bootstrap resamples for the confidence intervals.
N_BOOTSTRAP = 1000
#: A failure's error while interpolating quantiles (any quantile it touches is reported as inf).
_FAILURE_STAND_IN_M = 1e300


def error_summary(errors_m: np.ndarray) -> dict[str, float]:
    """n, mean and p50/p90/p95/p99 of 2-D errors in m; failures count.

    A failure (no estimate: a non-finite error) is an infinite error in every percentile, so a
    method cannot look better by returning nothing; ``n_failed`` stands beside the percentiles and
    ``mean`` is the mean of the finite errors.

    Raises
    ------
    ValueError
        When there are no errors at all, or none is finite.
    """
    errors_m = np.asarray(errors_m, dtype=float)
    if errors_m.size == 0:
        raise ValueError("no errors to summarise")
    errors_m = np.where(np.isnan(errors_m), np.inf, errors_m)
    finite = errors_m[np.isfinite(errors_m)]
    out: dict[str, float] = {"n": int(errors_m.size), "n_failed": int(errors_m.size - finite.size)}
    if finite.size == 0:
        raise ValueError("no finite errors to summarise")
    out["mean"] = float(finite.mean())
    out["share_gt_5m"] = float(np.mean(~(errors_m <= GROSS_ERROR_M)))
    # linear interpolation as usual; a quantile that reaches into the failures is infinite
    stand_in = np.where(np.isfinite(errors_m), errors_m, _FAILURE_STAND_IN_M)
    for name, q in ERROR_QUANTILES.items():
        value = float(np.percentile(stand_in, q))
        out[name] = value if value < _FAILURE_STAND_IN_M / 1e3 else float("inf")
    return out


def errors_by_method(predictions: pd.DataFrame) -> dict[str, dict[str, float]]:
    """:func:`error_summary` of every method's error column."""
    return {m: error_summary(predictions[col.error_m(m)].to_numpy()) for m in col.METHODS}


def coverage_and_width(predictions: pd.DataFrame, levels: list[float], scorers: list[str]) -> tuple[dict, dict]:
    """Empirical coverage of the gate's error by every scorer's radius, and the radii's mean / median (m)."""
    coverage: dict[str, dict[str, float]] = {}
    width: dict[str, dict[str, dict[str, float]]] = {}
    err = predictions[col.error_m("gate")].to_numpy()
    for name in scorers:
        coverage[name], width[name] = {}, {}
        for level in levels:
            radius = predictions[col.radius(name, level)].to_numpy()
            coverage[name][col.level_key(level)] = float(np.mean(err <= radius))
            finite = radius[np.isfinite(radius)]
            width[name][col.level_key(level)] = {
                "mean_m": float(finite.mean()) if finite.size else float("inf"),
                "median_m": float(np.median(finite)) if finite.size else float("inf"),
            }
    return coverage, width


def crb_summary(predictions: pd.DataFrame) -> dict[str, float] | None:
    """Median and p90 of the per-event Cramér–Rao bound (m); None when absent or all non-finite."""
    if "crb_m" not in predictions:
        return None
    crb = predictions["crb_m"].to_numpy(float)
    crb = crb[np.isfinite(crb)]
    return {"p50": float(np.median(crb)), "p90": float(np.percentile(crb, 90))} if crb.size else None


def spearman_rho(predictions: pd.DataFrame) -> dict[str, float | None]:
    """Spearman ρ of the error model's prediction and of GDOP with the gate's actual error.

    A constant predictor (e.g. the constant error model) has no rank correlation: reported as None.
    """
    err_gate = predictions[col.error_m("gate")].to_numpy(float)
    ok = np.isfinite(err_gate)
    rho: dict[str, float | None] = {}
    if ok.sum() >= 3:
        for name, values in (("error_model", predictions["predicted_error_m"].to_numpy(float)), ("gdop", predictions["gdop"].to_numpy(float))):
            v = values[ok]
            rho[name] = float(spearmanr(v, err_gate[ok]).statistic) if np.ptp(v) > 0 and np.ptp(err_gate[ok]) > 0 else None
    return rho


def coverage_by_position(predictions: pd.DataFrame, levels: list[float], scorers: list[str]) -> dict:
    """Per scorer and level: mean and worst coverage over source positions, and how many positions."""
    by_position: dict[str, dict[str, dict[str, float]]] = {}
    gate_err = predictions[col.error_m("gate")]
    for name in scorers:
        by_position[name] = {}
        for level in levels:
            hit = (gate_err <= predictions[col.radius(name, level)]).groupby(predictions["position_id"]).mean()
            by_position[name][col.level_key(level)] = {"mean": float(hit.mean()), "min": float(hit.min()), "n_positions": int(hit.size)}
    return by_position


def _quantile_with_failures(errors_m: np.ndarray, q: float) -> float:
    stand_in = np.where(np.isfinite(errors_m), errors_m, _FAILURE_STAND_IN_M)
    value = float(np.percentile(stand_in, q))
    return value if value < _FAILURE_STAND_IN_M / 1e3 else float("inf")


def position_bootstrap_ci(predictions: pd.DataFrame, levels: list[float], scorers: list[str], n_boot: int = N_BOOTSTRAP,
                          seed: int = 0) -> dict[str, Any]:
    """95 % confidence intervals by position bootstrap for every error quantile, gross share and coverage.

    Source positions are the exchangeable units (events at one position share its geometry and
    propagation), so whole positions are resampled with replacement, ``n_boot`` times.

    Returns
    -------
    dict
        ``errors``: {method: {p50|p90|p95|p99|share_gt_5m: [low, high]}}; ``coverage``:
        {scorer: {level: [low, high]}}; ``n_bootstrap``; ``n_positions``.
    """
    groups = predictions["position_id"].to_numpy()
    codes, inverse = np.unique(groups, return_inverse=True)
    rows_of = [np.flatnonzero(inverse == k) for k in range(codes.size)]
    rng = np.random.default_rng(seed)
    errors = {m: np.where(np.isnan(e := predictions[col.error_m(m)].to_numpy(float)), np.inf, e) for m in col.METHODS if col.error_m(m) in predictions}
    gate_err = errors.get("gate")
    radii = {(s, lv): predictions[col.radius(s, lv)].to_numpy(float) for s in scorers for lv in levels}
    samples: dict[tuple, list[float]] = {}
    for _ in range(n_boot):
        idx = np.concatenate([rows_of[k] for k in rng.integers(0, codes.size, codes.size)])
        for m, e in errors.items():
            sub = e[idx]
            for name, q in ERROR_QUANTILES.items():
                samples.setdefault(("errors", m, name), []).append(_quantile_with_failures(sub, q))
            samples.setdefault(("errors", m, "share_gt_5m"), []).append(float(np.mean(~(sub <= GROSS_ERROR_M))))
        if gate_err is not None:
            for (s, lv), r in radii.items():
                samples.setdefault(("coverage", s, col.level_key(lv)), []).append(float(np.mean(gate_err[idx] <= r[idx])))
    out: dict[str, Any] = {"n_bootstrap": int(n_boot), "n_positions": int(codes.size), "errors": {}, "coverage": {}}
    for (block, key, stat), values in samples.items():
        v = np.asarray(values, dtype=float)
        finite = np.isfinite(v)
        # an interval end that reaches into the infinite values (failures) is reported as inf
        low = float(np.percentile(np.where(finite, v, _FAILURE_STAND_IN_M), 2.5))
        high = float(np.percentile(np.where(finite, v, _FAILURE_STAND_IN_M), 97.5))
        out[block].setdefault(key, {})[stat] = [x if x < _FAILURE_STAND_IN_M / 1e3 else float("inf") for x in (low, high)]
    return out


def gate_gap(errors: dict[str, dict[str, float]]) -> dict[str, float]:
    """The gate against the oracle (p95 and p99 ratios) and against the solver (p50 ratio)."""
    out = {}
    if "oracle" in errors and "gate" in errors:
        for q in ("p95", "p99"):
            o = errors["oracle"][q]
            out[f"{q}_gate_over_oracle"] = float(errors["gate"][q] / o) if np.isfinite(o) and o > 0 else float("nan")
    if "solver" in errors and "gate" in errors:
        s = errors["solver"]["p50"]
        out["p50_gate_over_solver"] = float(errors["gate"]["p50"] / s) if np.isfinite(s) and s > 0 else float("nan")
    return out


def summarise(predictions: pd.DataFrame, levels: list[float], scorers: list[str]) -> dict:
    """The ``errors``, ``coverage``, ``interval_width`` … blocks of metrics.json."""
    extra = {}
    crb = crb_summary(predictions)
    if crb is not None:
        extra["crb_m"] = crb
    extra["spearman_rho"] = spearman_rho(predictions)
    extra["coverage_by_position"] = coverage_by_position(predictions, levels, scorers)
    coverage, width = coverage_and_width(predictions, levels, scorers)
    errors = errors_by_method(predictions)
    extra["gate_gap"] = gate_gap(errors)
    extra["ci95"] = position_bootstrap_ci(predictions, levels, scorers)
    return {
        **extra,
        "errors": errors,
        "coverage": coverage,
        "interval_width": width,
        "substitution_rate": float(predictions["substituted"].mean()),
    }


def split_diagnostics_summary(split_diagnostics: list[dict[str, Any]]) -> dict[str, Any]:
    """What the fitted gates reported, for metrics.json.

    One split (sim-only, field evaluation): the gate's diagnostics as they are (``tau_star_db``,
    ``tau_rule_met``, ``tau_grid`` for the hybrid gate). Several splits (leave-one-position-out):
    every split's diagnostics under ``gate_by_split``, plus the median of each numeric scalar
    and, for flags, whether every split had it.
    """
    gates = [d.get("gate", {}) for d in split_diagnostics]
    if len(gates) == 1:
        return dict(gates[0])
    if not any(gates):
        return {}
    out: dict[str, Any] = {"gate_by_split": [{"split": d.get("split", str(k)), **g} for k, (d, g) in enumerate(zip(split_diagnostics, gates, strict=True))]}
    for key in gates[0]:
        values = [g.get(key) for g in gates]
        if all(isinstance(v, bool) for v in values):
            out[key] = all(values)
        elif all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            out[key] = float(np.median(values))
    return out


def error_table(metrics: dict) -> pd.DataFrame:
    """errors block as a table: one row per method."""
    return pd.DataFrame([{"method": m, **v} for m, v in metrics["errors"].items()])


def coverage_table(metrics: dict) -> pd.DataFrame:
    """coverage block as a table: one row per (scorer, nominal level)."""
    rows = []
    for scorer, by_level in metrics["coverage"].items():
        for level, empirical in by_level.items():
            w = metrics["interval_width"][scorer][level]
            rows.append({"scorer": scorer, "nominal": float(level), "empirical": empirical, **w})
    return pd.DataFrame(rows)


def flat_metrics(metrics: dict) -> dict[str, float]:
    """Scalar metrics for a tracker: ``error.<method>.<stat>``, ``coverage.<scorer>.<level>``…"""
    flat = {}
    for m, stats in metrics["errors"].items():
        for k, v in stats.items():
            flat[f"error.{m}.{k}"] = v
    for s, by_level in metrics["coverage"].items():
        for level, v in by_level.items():
            flat[f"coverage.{s}.{level}"] = v
            flat[f"width.{s}.{level}.median_m"] = metrics["interval_width"][s][level]["median_m"]
    flat["substitution_rate"] = metrics["substitution_rate"]
    for m, stats in metrics.get("ci95", {}).get("errors", {}).items():
        for k, (low, high) in stats.items():
            flat[f"error.{m}.{k}.ci_low"], flat[f"error.{m}.{k}.ci_high"] = low, high
    for s, by_level in metrics.get("ci95", {}).get("coverage", {}).items():
        for level, (low, high) in by_level.items():
            flat[f"coverage.{s}.{level}.ci_low"], flat[f"coverage.{s}.{level}.ci_high"] = low, high
    for k, v in metrics.get("gate_gap", {}).items():
        flat[f"gate_gap.{k}"] = v
    for k, v in metrics.get("crb_m", {}).items():
        flat[f"crb.{k}_m"] = v
    for k, v in metrics.get("spearman_rho", {}).items():
        if v is not None:
            flat[f"spearman_rho.{k}"] = v
    if "tau_star_db" in metrics:
        flat["tau_star_db"] = metrics["tau_star_db"]
    for k, v in metrics.get("timings_s", {}).items():
        flat[f"time.{k}"] = v
    return {k: float(v) for k, v in flat.items() if np.isfinite(v)}
