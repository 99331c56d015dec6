"""Error and coverage summaries of a run's predictions."""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.stats import spearmanr

METHODS = ("solver", "model", "gate")
ERROR_QUANTILES = {"p50": 50, "p90": 90, "p95": 95, "p99": 99}


def error_summary(errors_m: np.ndarray) -> dict[str, float]:
    """n, mean and p50/p90/p95/p99 of 2-D errors in m (non-finite errors count as failures, ``n_failed``)."""
    errors_m = np.asarray(errors_m, dtype=float)
    finite = errors_m[np.isfinite(errors_m)]
    out: dict[str, float] = {"n": int(errors_m.size), "n_failed": int(errors_m.size - finite.size)}
    if finite.size == 0:
        raise ValueError("no finite errors to summarise")
    out["mean"] = float(finite.mean())
    for name, q in ERROR_QUANTILES.items():
        out[name] = float(np.percentile(finite, q))
    return out


def summarise(predictions: pd.DataFrame, levels: list[float], scorers: list[str]) -> dict:
    """The ``errors``, ``coverage`` and ``interval_width`` blocks of metrics.json."""
    errors = {m: error_summary(predictions[f"error_{m}_m"].to_numpy()) for m in METHODS}
    coverage: dict[str, dict[str, float]] = {}
    width: dict[str, dict[str, dict[str, float]]] = {}
    err = predictions["error_gate_m"].to_numpy()
    for name in scorers:
        coverage[name], width[name] = {}, {}
        for level in levels:
            radius = predictions[f"radius__{name}__{level:g}"].to_numpy()
            coverage[name][f"{level:g}"] = float(np.mean(err <= radius))
            finite = radius[np.isfinite(radius)]
            width[name][f"{level:g}"] = {
                "mean_m": float(finite.mean()) if finite.size else float("inf"),
                "median_m": float(np.median(finite)) if finite.size else float("inf"),
            }
    extra = {}
    if "crb_m" in predictions:
        crb = predictions["crb_m"].to_numpy(float)
        crb = crb[np.isfinite(crb)]
        if crb.size:
            extra["crb_m"] = {"p50": float(np.median(crb)), "p90": float(np.percentile(crb, 90))}
    err_gate = predictions["error_gate_m"].to_numpy(float)
    ok = np.isfinite(err_gate)
    rho = {}
    if ok.sum() >= 3:
        # a constant predictor (e.g. the constant error model) has no rank correlation: reported as None
        for name, values in (("error_model", predictions["predicted_error_m"].to_numpy(float)), ("gdop", predictions["gdop"].to_numpy(float))):
            v = values[ok]
            rho[name] = float(spearmanr(v, err_gate[ok]).statistic) if np.ptp(v) > 0 and np.ptp(err_gate[ok]) > 0 else None
    by_position: dict[str, dict[str, dict[str, float]]] = {}
    for name in scorers:
        by_position[name] = {}
        for level in levels:
            hit = (predictions["error_gate_m"] <= predictions[f"radius__{name}__{level:g}"]).groupby(predictions["position_id"]).mean()
            by_position[name][f"{level:g}"] = {"mean": float(hit.mean()), "min": float(hit.min()), "n_positions": int(hit.size)}
    extra["spearman_rho"] = rho
    extra["coverage_by_position"] = by_position
    return {
        **extra,
        "errors": errors,
        "coverage": coverage,
        "interval_width": width,
        "substitution_rate": float(predictions["substituted"].mean()),
    }


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
