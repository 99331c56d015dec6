"""Error and coverage summaries of a run's predictions."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from scipy.stats import spearmanr
from sklearn.metrics import roc_auc_score

from acoustlab.core import columns as col
from acoustlab.toolkit.regions import inside_ellipse

ERROR_QUANTILES = {"p50": 50, "p90": 90, "p95": 95, "p99": 99}
#: An error above this is a gross error (m); failures count as gross.
GROSS_ERROR_M = 5.0
#: Position-bootstrap resamples for the confidence intervals.
N_BOOTSTRAP = 1000
#: A failure's error while interpolating quantiles (any quantile it touches is reported as inf).
_FAILURE_STAND_IN_M = 1e300


def _quantile_with_failures(values: np.ndarray, q: float) -> float:
    """The ``q``-th percentile (linear interpolation) with non-finite values as infinitely large; inf where it reaches them."""
    stand_in = np.where(np.isfinite(values), values, _FAILURE_STAND_IN_M)
    value = float(np.percentile(stand_in, q))
    return value if value < _FAILURE_STAND_IN_M / 1e3 else float("inf")


def share_gross(errors_m: np.ndarray) -> float:
    """Share of errors above ``GROSS_ERROR_M``; a failure (NaN or inf) counts as gross."""
    return float(np.mean(~(np.asarray(errors_m, dtype=float) <= GROSS_ERROR_M)))


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
    out["share_gt_5m"] = share_gross(errors_m)
    # linear interpolation as usual; a quantile that reaches into the failures is infinite
    for name, q in ERROR_QUANTILES.items():
        out[name] = _quantile_with_failures(errors_m, q)
    return out


def errors_by_method(predictions: pd.DataFrame) -> dict[str, dict[str, float]]:
    """``error_summary`` of every method's error column."""
    return {m: error_summary(predictions[col.error_m(m)].to_numpy()) for m in col.methods_in(predictions.columns)}


def coverage_and_width(predictions: pd.DataFrame, levels: list[float], scorers: list[str]) -> tuple[dict, dict]:
    """Empirical coverage of the gate's error by every scorer's radius, and the radii's mean / median / max (m)."""
    coverage: dict[str, dict[str, float]] = {}
    width: dict[str, dict[str, dict[str, float]]] = {}
    err = predictions[col.error_m("gate")].to_numpy()
    for name in scorers:
        coverage[name], width[name] = {}, {}
        for level in levels:
            radius = predictions[col.radius(name, level)].to_numpy(float)
            # no radius at all (too few calibration positions for this level): no coverage either, not 0
            coverage[name][col.level_key(level)] = float("nan") if np.isnan(radius).all() else float(np.mean(err <= radius))
            finite = radius[np.isfinite(radius)]
            width[name][col.level_key(level)] = {
                "mean_m": float(finite.mean()) if finite.size else float("inf"),
                "median_m": float(np.median(finite)) if finite.size else float("inf"),
                "max_m": float(finite.max()) if finite.size else float("inf"),
            }
    return coverage, width


def crb_summary(predictions: pd.DataFrame) -> dict[str, float] | None:
    """Median and p90 of the per-event Cramér–Rao bound (m); None when absent or all non-finite."""
    if col.CRB not in predictions:
        return None
    crb = predictions[col.CRB].to_numpy(float)
    crb = crb[np.isfinite(crb)]
    return {"p50": float(np.median(crb)), "p90": float(np.percentile(crb, 90))} if crb.size else None


def spearman_rho(predictions: pd.DataFrame) -> dict[str, float | None]:
    """Spearman ρ of the error model's prediction and of GDOP with the gate's actual error, pooled over detections; and
    the error model's between and within positions (``_rho_by_position``).

    A constant predictor (e.g. the constant error model) has no rank correlation: reported as None.
    """
    err_gate = predictions[col.error_m("gate")].to_numpy(float)
    ok = np.isfinite(err_gate)
    rho: dict[str, float | None] = {}
    if ok.sum() >= 3:
        for name, values in (
            ("error_model", predictions[col.PREDICTED_ERROR].to_numpy(float)),
            ("gdop", predictions["gdop"].to_numpy(float)),
        ):
            v = values[ok]
            rho[name] = float(spearmanr(v, err_gate[ok]).statistic) if np.ptp(v) > 0 and np.ptp(err_gate[ok]) > 0 else None
    if ok.sum() >= 3 and col.POSITION_ID in predictions:
        rho.update(
            _rho_by_position(predictions[col.PREDICTED_ERROR].to_numpy(float), err_gate, predictions[col.POSITION_ID].to_numpy(), ok)
        )
    return rho


def _rho_by_position(predicted: np.ndarray, error: np.ndarray, groups: np.ndarray, ok: np.ndarray) -> dict[str, float | None]:
    """The error model's Spearman ρ between positions (of their median predicted and actual errors) and within them
    (the mean over positions with 3 or more detections of each position's own ρ).

    Pooled over detections, ρ mixes the two: an error model that only tells hard positions from
    easy ones shows a high pooled ρ while it ranks nothing within a position.
    """
    table = pd.DataFrame({"predicted": predicted[ok], "error": error[ok], "group": groups[ok]})
    medians = table.groupby("group").median()
    between = (
        float(spearmanr(medians["predicted"], medians["error"]).statistic)
        if len(medians) >= 3 and np.ptp(medians["predicted"]) > 0 and np.ptp(medians["error"]) > 0
        else None
    )
    within = [
        spearmanr(g["predicted"], g["error"]).statistic
        for _, g in table.groupby("group")
        if len(g) >= 3 and np.ptp(g["predicted"]) > 0 and np.ptp(g["error"]) > 0
    ]
    return {"error_model_between_positions": between, "error_model_within_positions": float(np.mean(within)) if within else None}


def gross_error_auc(predictions: pd.DataFrame, gross_m: float = 5.0) -> dict[str, float | None]:
    """ROC AUC of the error model's prediction and of GDOP for "the gate's error exceeds ``gross_m``" (m).

    Events without an estimate count as gross. None where one class is empty or the score is constant.
    """
    err_gate = np.nan_to_num(predictions[col.error_m("gate")].to_numpy(float), nan=np.inf)
    gross = err_gate > gross_m
    auc: dict[str, float | None] = {}
    for name, values in (("error_model", predictions[col.PREDICTED_ERROR].to_numpy(float)), ("gdop", predictions["gdop"].to_numpy(float))):
        usable = 0 < gross.sum() < gross.size and np.isfinite(values).all() and np.ptp(values) > 0
        auc[name] = float(roc_auc_score(gross, values)) if usable else None
    return auc


#: Bins of the conditions coverage is broken down by: GDOP at the estimate, distance outside the mics' hull (array extents), SNR (dB).
CONDITION_BINS = {
    "gdop": ("gdop", (0.0, 2.0, 5.0, 20.0, np.inf)),
    "hull_distance": (col.HULL_DISTANCE, (-np.inf, 0.0, 0.25, 0.5, np.inf)),
    col.SNR: (col.SNR, (-np.inf, 5.0, 10.0, 20.0, np.inf)),
}


def coverage_by_condition(predictions: pd.DataFrame, levels: list[float], scorers: list[str]) -> dict[str, list[dict[str, Any]]]:
    """Coverage per detection and per position in bins of GDOP, hull distance and SNR: where the radii fail.

    Each bin: ``bin`` (its range; the first hull bin, ``(-inf, 0]``, is inside the hull), ``n``
    detections, ``n_positions``, and per scorer and level the share of detections covered and the
    mean over positions of their share covered. A bin of fewer than 20 detections is reported with
    ``too_few: true`` (a coverage on so few says little).
    """
    err = predictions[col.error_m("gate")].to_numpy(float)
    err = np.where(np.isnan(err), np.inf, err)
    out: dict[str, list[dict[str, Any]]] = {}
    for name, (column, edges) in CONDITION_BINS.items():
        if column not in predictions:
            continue
        value = predictions[column].to_numpy(float)
        rows = []
        for low, high in zip(edges[:-1], edges[1:], strict=True):
            inside = np.isfinite(value) & (value > low) & (value <= high) if np.isfinite(low) else np.isfinite(value) & (value <= high)
            if not inside.any():
                continue
            positions = predictions[col.POSITION_ID].to_numpy()[inside]
            entry: dict[str, Any] = {"bin": f"({low:g}, {high:g}]", "n": int(inside.sum()), "n_positions": int(np.unique(positions).size)}
            entry["too_few"] = bool(inside.sum() < 20)
            for scorer in scorers:
                for level in levels:
                    hit = err[inside] <= predictions[col.radius(scorer, level)].to_numpy(float)[inside]
                    by_position = pd.Series(hit).groupby(positions).mean()
                    entry[f"{scorer}@{col.level_key(level)}"] = {"detections": float(hit.mean()), "positions": float(by_position.mean())}
            rows.append(entry)
        out[name] = rows
    return out


def held_out_calibration_summary(table: pd.DataFrame, levels: list[float], scorers: list[str]) -> dict[str, Any]:
    """Coverage of the calibration playbacks with radii calibrated without their own spot, overall and by condition.

    ``table``: ``FittedMethod.held_out_calibration``. Per scorer and level, the share of playbacks
    covered and the mean over spots of their share covered (None where the other spots cannot
    guarantee the level, or the scorer has its own quantile model); ``by_condition`` as
    ``coverage_by_condition``.
    """
    valid = {(s, lv): bool(np.isfinite(table[col.radius(s, lv)].to_numpy(float)).any()) for s in scorers for lv in levels}
    err = np.where(np.isnan(table[col.error_m("gate")].to_numpy(float)), np.inf, table[col.error_m("gate")].to_numpy(float))
    coverage: dict[str, dict[str, Any]] = {}
    for s in scorers:
        for lv in levels:
            if not valid[(s, lv)]:
                coverage.setdefault(s, {})[col.level_key(lv)] = None
                continue
            hit = err <= table[col.radius(s, lv)].to_numpy(float)
            by_spot = pd.Series(hit).groupby(table[col.POSITION_ID].to_numpy()).mean()
            coverage.setdefault(s, {})[col.level_key(lv)] = {"detections": float(hit.mean()), "positions": float(by_spot.mean())}
    by_condition = coverage_by_condition(table, levels, scorers)
    for rows in by_condition.values():
        for entry in rows:
            for (s, lv), ok in valid.items():
                if not ok:
                    entry[f"{s}@{col.level_key(lv)}"] = None
    return {
        "n_playbacks": int(len(table)),
        "n_spots": int(table[col.POSITION_ID].nunique()),
        col.METRICS_COVERAGE: coverage,
        "by_condition": by_condition,
        "note": "each spot's radii calibrated on the other spots, its errors from models that never saw it",
    }


def coverage_by_position(predictions: pd.DataFrame, levels: list[float], scorers: list[str]) -> dict:
    """Per scorer and level: mean and worst coverage over source positions, and how many positions."""
    by_position: dict[str, dict[str, dict[str, float]]] = {}
    gate_err = predictions[col.error_m("gate")]
    for name in scorers:
        by_position[name] = {}
        for level in levels:
            hit = (gate_err <= predictions[col.radius(name, level)]).groupby(predictions[col.POSITION_ID]).mean()
            by_position[name][col.level_key(level)] = {"mean": float(hit.mean()), "min": float(hit.min()), "n_positions": int(hit.size)}
    return by_position


def position_bootstrap_ci(
    predictions: pd.DataFrame, levels: list[float], scorers: list[str], n_boot: int = N_BOOTSTRAP, seed: int = 0
) -> dict[str, Any]:
    """95 % confidence intervals by position bootstrap for every error quantile, gross share and coverage.

    Source positions are the exchangeable units (events at one position share its geometry and
    propagation), so whole positions are resampled with replacement, ``n_boot`` times.

    Returns
    -------
    dict
        ``errors``: {method: {p50|p90|p95|p99|share_gt_5m: [low, high]}}; ``coverage``:
        {scorer: {level: [low, high]}}; ``n_bootstrap``; ``n_positions``.
    """
    groups = predictions[col.POSITION_ID].to_numpy()
    codes, inverse = np.unique(groups, return_inverse=True)
    rows_of = [np.flatnonzero(inverse == k) for k in range(codes.size)]
    rng = np.random.default_rng(seed)
    errors = {
        m: np.where(np.isnan(e := predictions[col.error_m(m)].to_numpy(float)), np.inf, e) for m in col.methods_in(predictions.columns)
    }
    gate_err = errors.get("gate")
    radii = {(s, lv): predictions[col.radius(s, lv)].to_numpy(float) for s in scorers for lv in levels}
    samples: dict[tuple, list[float]] = {}
    for _ in range(n_boot):
        idx = np.concatenate([rows_of[k] for k in rng.integers(0, codes.size, codes.size)])
        for m, e in errors.items():
            sub = e[idx]
            for name, q in ERROR_QUANTILES.items():
                samples.setdefault((col.METRICS_ERRORS, m, name), []).append(_quantile_with_failures(sub, q))
            samples.setdefault((col.METRICS_ERRORS, m, "share_gt_5m"), []).append(share_gross(sub))
        if gate_err is not None:
            for (s, lv), r in radii.items():
                samples.setdefault((col.METRICS_COVERAGE, s, col.level_key(lv)), []).append(float(np.mean(gate_err[idx] <= r[idx])))
    out: dict[str, Any] = {"n_bootstrap": int(n_boot), "n_positions": int(codes.size), col.METRICS_ERRORS: {}, col.METRICS_COVERAGE: {}}
    for (block, key, stat), values in samples.items():
        # an interval end that reaches into the infinite values (failures) is reported as inf
        v = np.asarray(values, dtype=float)
        out[block].setdefault(key, {})[stat] = [_quantile_with_failures(v, 2.5), _quantile_with_failures(v, 97.5)]
    return out


def gate_gap(errors: dict[str, dict[str, float]]) -> dict[str, float]:
    """Every gate against the oracle (p95 and p99 ratios) and against the solver (p50 ratio).

    Keys ``<q>_<gate>_over_oracle`` and ``p50_<gate>_over_solver`` for the configured gate
    (``gate``) and every extra gate (``gate_<name>``).
    """

    def ratio(a: float, b: float) -> float:
        return float(a / b) if np.isfinite(b) and b > 0 else float("nan")

    out = {}
    for gate in [m for m in errors if m == "gate" or m.startswith(col.EXTRA_GATE_PREFIX)]:
        if "oracle" in errors:
            for q in ("p95", "p99"):
                out[f"{q}_{gate}_over_oracle"] = ratio(errors[gate][q], errors["oracle"][q])
        if "solver" in errors:
            out[f"p50_{gate}_over_solver"] = ratio(errors[gate]["p50"], errors["solver"]["p50"])
    return out


#: Shares of events placed at which the risk–coverage curve is reported.
PLACED_SHARES = (1.0, 0.99, 0.95, 0.91, 0.9, 0.8, 0.7, 0.6, 0.5)


def risk_coverage(predictions: pd.DataFrame) -> list[dict[str, float]]:
    """Error of the gate's estimate among the events placed when only the lowest predicted errors are kept.

    For each share in ``PLACED_SHARES``, events are placed in order of the error model's
    prediction (lowest first); reported: the predicted-error threshold (m), the share placed, and
    p50 / p95 / p99 and the share > 5 m among the placed (failures count as infinite errors).
    """
    err = predictions[col.error_m("gate")].to_numpy(float)
    err = np.where(np.isnan(err), np.inf, err)
    pred = predictions[col.PREDICTED_ERROR].to_numpy(float)
    order = np.argsort(pred, kind="stable")
    rows = []
    for share in PLACED_SHARES:
        k = max(1, int(round(share * err.size)))
        kept = err[order[:k]]
        rows.append(
            {
                "share_placed": k / err.size,
                "threshold_m": float(pred[order[k - 1]]),
                **{name: _quantile_with_failures(kept, q) for name, q in (("p50", 50), ("p95", 95), ("p99", 99))},
                "share_gt_5m": share_gross(kept),
            }
        )
    return rows


def selective_summary(predictions: pd.DataFrame) -> dict[str, Any] | None:
    """With selective localization: the share placed and the gate's errors among the placed (None without it)."""
    if col.PLACED not in predictions:
        return None
    placed = predictions[col.PLACED].to_numpy(bool)
    out: dict[str, Any] = {"share_placed": float(placed.mean()), "n_placed": int(placed.sum())}
    if placed.any():
        err = predictions[col.error_m("gate")].to_numpy(float)[placed]
        out.update({k: v for k, v in error_summary(err).items() if k in ("p50", "p90", "p95", "p99", "share_gt_5m")})
        by_position = pd.Series(~(err <= GROSS_ERROR_M)).groupby(predictions[col.POSITION_ID].to_numpy()[placed]).mean()
        out["worst_position_share_gt_5m"] = float(by_position.max())
    return out


def ellipse_coverage(predictions: pd.DataFrame, levels: list[float]) -> dict[str, dict[str, float]] | None:
    """Per level: how often the truth lies inside the gate estimate's error ellipse, the worst position, and the
    median ellipse area against the median area of the circle of the ``fixed``-style radius (None without ellipses)."""
    if col.ellipse(levels[0], "a_m") not in predictions:
        return None
    d = predictions[list(col.estimate_xy("gate"))].to_numpy(float) - predictions[list(col.estimate_xy("true"))].to_numpy(float)
    out = {}
    for level in levels:
        a, b, angle = (predictions[col.ellipse(level, p)].to_numpy(float) for p in ("a_m", "b_m", "angle_deg"))
        hit = inside_ellipse(np.nan_to_num(d, nan=np.inf), a, b, angle) & np.isfinite(d).all(axis=1)
        by_position = pd.Series(hit).groupby(predictions[col.POSITION_ID].to_numpy()).mean()
        out[col.level_key(level)] = {
            col.METRICS_COVERAGE: float(hit.mean()),
            "worst_position": float(by_position.min()),
            "median_area_m2": float(np.median(np.pi * a * b)),
        }
    return out


def summarise(predictions: pd.DataFrame, levels: list[float], scorers: list[str]) -> dict:
    """The ``errors``, ``coverage``, ``interval_width`` … blocks of metrics.json."""
    extra = {}
    crb = crb_summary(predictions)
    if crb is not None:
        extra[col.CRB] = crb
    extra[col.METRICS_SPEARMAN] = spearman_rho(predictions)
    extra[col.METRICS_GROSS_AUC] = gross_error_auc(predictions)
    extra[col.METRICS_COVERAGE_BY_POSITION] = coverage_by_position(predictions, levels, scorers)
    extra[col.METRICS_COVERAGE_BY_CONDITION] = coverage_by_condition(predictions, levels, scorers)
    coverage, width = coverage_and_width(predictions, levels, scorers)
    errors = errors_by_method(predictions)
    extra[col.METRICS_GATE_GAP] = gate_gap(errors)
    extra[col.METRICS_CI95] = position_bootstrap_ci(predictions, levels, scorers)
    extra[col.METRICS_RISK_COVERAGE] = risk_coverage(predictions)
    ellipses = ellipse_coverage(predictions, levels)
    if ellipses is not None:
        extra["ellipse"] = ellipses
    selective = selective_summary(predictions)
    if selective is not None:
        extra["selective"] = selective
    return {
        **extra,
        col.METRICS_ERRORS: errors,
        col.METRICS_COVERAGE: coverage,
        col.METRICS_WIDTH: width,
        col.METRICS_SUBSTITUTION: float(predictions[col.SUBSTITUTED].mean()),
    }


def split_diagnostics_summary(split_diagnostics: list[dict[str, Any]], gate_name: str = "gate") -> dict[str, Any]:
    """What the fitted gates (and the trust check, selective localization, calibration) reported, for metrics.json.

    The configured gate's diagnostics land under ``metrics["gate"]``: ``{"name": <gate>,
    "diagnostics": {...}}``, whatever keys that gate reports (the hybrid gate's ``tau_star_db``,
    ``tau_grid``; the learned gate's ``threshold``, ``fallback``). With several splits
    (leave-one-position-out, cross-fitting) ``diagnostics`` holds the median of each numeric
    scalar and, for flags, whether every split had it, and ``by_split`` every split's own.

    Parameters
    ----------
    split_diagnostics : list of dict
        One entry per split, as ``MethodResult`` has them.
    gate_name : str
        The configured gate's name (its ``gate=`` option).
    """
    gates = [d.get("gate", {}) for d in split_diagnostics]
    selective = [d["selective"] for d in split_diagnostics if "selective" in d]
    out: dict[str, Any] = {"selective_by_split": selective} if selective else {}
    trust = [d["trust"] for d in split_diagnostics if "trust" in d]
    if trust:  # the point model's training region and what the trust check overrode
        out.update({"trust": trust[0]} if len(trust) == 1 else {"trust_by_split": trust})
    calibration = [d["calibration"] for d in split_diagnostics if "calibration" in d]
    if calibration:  # which rows calibrated conformal in each split (all training rows, or the field rows)
        out["calibration_by_split"] = calibration
    if not any(gates):
        return out
    if len(gates) == 1:
        out["gate"] = {"name": gate_name, "diagnostics": dict(gates[0])}
        return out
    pooled: dict[str, Any] = {}
    for key in gates[0]:
        values = [g.get(key) for g in gates]
        if all(isinstance(v, bool) for v in values):
            pooled[key] = all(values)
        elif all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            pooled[key] = float(np.median(values))
    by_split = [{"split": d.get("split", str(k)), **g} for k, (d, g) in enumerate(zip(split_diagnostics, gates, strict=True))]
    out["gate"] = {"name": gate_name, "diagnostics": pooled, "by_split": by_split}
    return out


def gate_scalars(metrics: dict[str, Any]) -> dict[str, float]:
    """The configured gate's numeric scalar diagnostics (``{"tau_star_db": 3.1}`` for the hybrid gate); {} without a gate block."""
    diagnostics = metrics.get("gate", {}).get("diagnostics", {})
    return {k: float(v) for k, v in diagnostics.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def error_table(metrics: dict) -> pd.DataFrame:
    """errors block as a table: one row per method."""
    return pd.DataFrame([{"method": m, **v} for m, v in metrics[col.METRICS_ERRORS].items()])


def coverage_table(metrics: dict) -> pd.DataFrame:
    """coverage block as a table: one row per (scorer, nominal level)."""
    rows = []
    for scorer, by_level in metrics[col.METRICS_COVERAGE].items():
        for level, empirical in by_level.items():
            w = metrics[col.METRICS_WIDTH][scorer][level]
            rows.append({"scorer": scorer, "nominal": float(level), "empirical": empirical, **w})
    return pd.DataFrame(rows)


def flat_metrics(metrics: dict) -> dict[str, float]:
    """Scalar metrics for a tracker: ``error.<method>.<stat>``, ``coverage.<scorer>.<level>``…"""
    flat = {}
    for m, stats in metrics[col.METRICS_ERRORS].items():
        for k, v in stats.items():
            flat[f"error.{m}.{k}"] = v
    for s, by_level in metrics[col.METRICS_COVERAGE].items():
        for level, v in by_level.items():
            flat[f"coverage.{s}.{level}"] = v
            flat[f"width.{s}.{level}.median_m"] = metrics[col.METRICS_WIDTH][s][level]["median_m"]
    flat[col.METRICS_SUBSTITUTION] = metrics[col.METRICS_SUBSTITUTION]
    for m, stats in metrics.get(col.METRICS_CI95, {}).get(col.METRICS_ERRORS, {}).items():
        for k, (low, high) in stats.items():
            flat[f"error.{m}.{k}.ci_low"], flat[f"error.{m}.{k}.ci_high"] = low, high
    for s, by_level in metrics.get(col.METRICS_CI95, {}).get(col.METRICS_COVERAGE, {}).items():
        for level, (low, high) in by_level.items():
            flat[f"coverage.{s}.{level}.ci_low"], flat[f"coverage.{s}.{level}.ci_high"] = low, high
    for k, v in metrics.get(col.METRICS_GATE_GAP, {}).items():
        flat[f"gate_gap.{k}"] = v
    for row in metrics.get(col.METRICS_RISK_COVERAGE, []):
        for k in ("p95", "share_gt_5m"):
            flat[f"risk_coverage.{row['share_placed']:.2f}.{k}"] = row[k]
    for level, v in (metrics.get("ellipse") or {}).items():
        flat[f"ellipse.{level}.coverage"] = v[col.METRICS_COVERAGE]
    for k, v in (metrics.get("selective") or {}).items():
        flat[f"selective.{k}"] = v
    for k, v in metrics.get(col.CRB, {}).items():
        flat[f"crb.{k}_m"] = v
    for block in (col.METRICS_SPEARMAN, col.METRICS_GROSS_AUC):
        for k, v in metrics.get(block, {}).items():
            if v is not None:
                flat[f"{block}.{k}"] = v
    gate_name = metrics.get("gate", {}).get("name", "gate")
    for k, v in gate_scalars(metrics).items():
        flat[f"gate.{gate_name}.{k}"] = v
    for k, v in metrics.get("timings_s", {}).items():
        flat[f"time.{k}"] = v
    return {k: float(v) for k, v in flat.items() if np.isfinite(v)}


#: One line per method of the console's error table: what the row is.
METHOD_LEGEND = {
    "solver": "solver: the closed-form TDOA fix alone",
    "model": "model: the learned point model's estimate alone",
    "gate": "gate: the reported position (the solver's fix unless the gate and the hand-over check give the model's)",
    "oracle": "oracle: per detection the better of solver and model (needs the truth: the bound a perfect gate would reach)",
    f"gate_{col.GATE_WITHOUT_TRUST}": (
        f"gate_{col.GATE_WITHOUT_TRUST}: the gate's own choice before the hand-over check (what that check changes); a learned "
        "gate's threshold inf means it never hands over (it fell back to the solver's fix)"
    ),
}


def summary_text(metrics: dict) -> str:
    """A compact, human-readable end-of-run summary: errors by method, coverage and median radius by scorer and level."""

    def num(v: float) -> str:
        return "inf" if v == float("inf") else "-" if np.isnan(v) else f"{v:.2f}" if abs(v) < 10 else f"{v:.0f}"

    errors = metrics[col.METRICS_ERRORS]
    w = max([len("method"), *(len(m) for m in errors)]) + 2  # the widest method name sets the first column
    lines = [f"{'method':<{w}}{'p50 m':>8}{'p95 m':>8}{'p99 m':>8}{'> 5 m':>8}{'failed':>8}"]
    for method, e in errors.items():
        lines.append(
            f"{method:<{w}}{num(e['p50']):>8}{num(e['p95']):>8}{num(e['p99']):>8}{100 * e.get('share_gt_5m', float('nan')):>7.1f}%"
            f"{e['n_failed']:>8}"
        )
    lines += [f"  {line}" for name, line in METHOD_LEGEND.items() if name in errors]
    levels = sorted({lv for by in metrics[col.METRICS_COVERAGE].values() for lv in by}, key=float)
    lines.append("")
    ws = max([len(col.METRICS_COVERAGE), *(len(sc) for sc in metrics[col.METRICS_COVERAGE])]) + 2
    lines.append(
        f"{col.METRICS_COVERAGE:<{ws}}" + "".join(f"{'@' + lv:>10}" for lv in levels) + f"{'radius@' + levels[-1]:>14}" if levels else ""
    )
    by_position = metrics.get(col.METRICS_COVERAGE_BY_POSITION, {})
    for scorer, by in metrics[col.METRICS_COVERAGE].items():
        width = metrics[col.METRICS_WIDTH][scorer][levels[-1]]["median_m"]
        lines.append(f"{scorer:<{ws}}" + "".join(f"{by[lv]:>10.3f}" for lv in levels) + f"{num(width) + ' m':>14}")
        if scorer in by_position:  # the guarantee's unit is the position: its mean coverage over positions beside
            cells = "".join(f"{by_position[scorer][lv]['mean']:>10.3f}" if lv in by_position[scorer] else f"{'-':>10}" for lv in levels)
            lines.append(f"{'  per position':<{ws}}" + cells)
    if by_position:
        lines.append("  coverage per detection; per position: the mean over source positions of each position's coverage")
    return "\n".join(lines)
