"""The positions table of a localization run (no ground truth): one row per detection, for spatial models."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col

#: Columns of a detection's own record carried into the table when present.
DETECTION_FIELDS = (
    col.EVENT_ID,
    "file",
    col.START,
    col.END,
    "label",
    col.QUALITY_FLAGS,
    col.MICS_DROPPED,
    col.MICS_USED,
    col.HARDWARE_FAILURE,
    col.WEAK_SUPPORT,
)


def _add_radius_columns(out: pd.DataFrame, predictions: pd.DataFrame, levels: list[float], scorers: list[str], placed: np.ndarray) -> None:
    """The radii per scorer and level (m, empty where not placed), what one set of calibration spots gives them, and why
    a level has none."""
    for scorer in scorers:
        for level in levels:
            out[f"radius_{scorer}_{col.level_key(level)}_m"] = np.where(placed, predictions[col.radius(scorer, level)], np.nan)
    for level in levels:  # with probability 0.9 over the user's calibration spots, each radius at that level covers at least this
        if col.one_set_coverage(level) in predictions:
            out[col.one_set_coverage(level)] = predictions[col.one_set_coverage(level)]
    if col.RADIUS_NOTE in predictions:  # a level without a guarantee (too few calibration spots) has no radius, and says so
        out[col.RADIUS_NOTE] = predictions[col.RADIUS_NOTE].fillna("").astype(str)


def positions_table(predictions: pd.DataFrame, levels: list[float], scorers: list[str]) -> pd.DataFrame:
    """One row per detection: the position (gate), the solver's and model's estimates, the decision, radii, flags.

    Columns: the detection's own fields (``quality_flags``; ``mics_dropped``: the mics, by index in
    the mics table's order, whose clips were unusable and were left out of the solve; ``mics_used``:
    the mics the solver's fix rests on, also without those the solver found inconsistent; ``weak_support``: that fix rests
    on a subset of the usable mics with a residual above good fixes', said in ``quality_flags`` and ``radius_note``); ``x_m, y_m, z_m`` (the method's estimate, all three from
    one estimate: the solver's fix with its height, estimated with ``solver.dimensions=3`` or else
    assumed, or the model's, which has no height: ``z_m`` NaN; NaN where it abstains);
    ``solver_x_m, solver_y_m, solver_z_m, model_x_m, model_y_m`` and ``solver_model_distance_m``;
    ``source`` (``solver``, ``model`` or ``none``) and ``gate_reason`` (why);
    ``outside_training_region`` (the solver's fix lies outside the region the model was trained
    on) and ``novelty`` (> 1: the detection is unlike the training data); ``predicted_error_m``;
    ``radius_<scorer>_<level>_m`` per scorer and level (empty where the calibration has too few
    positions for that level's guarantee, ``radius_note`` saying so); under a field calibration
    ``radius_covers_at_least__<level>`` (with probability 0.9 over the calibration spots, the
    share of calls at a new spot those radii cover at least); ellipse columns when computed; ``placed``
    and ``abstain_reason``; quality flags from the solver stage (``solver__failure``,
    ``solver__consistency``, ``solver__n_mics_used``, GDOPs, …); ``tdoa_0_<j>_s``, the measured
    time differences t_j − t_0 (s, the strongest GCC peak of each pair with mic 0, after a field
    calibration's clock correction); ``residual_mic_<m>_m``, each mic's arrival residual at the
    solver's fix (m of range; ``acoustlab.method.localizer.with_mic_residuals``).
    """
    out = pd.DataFrame({c: predictions[c] for c in DETECTION_FIELDS if c in predictions})
    if "event_name" in predictions and col.EVENT_ID in out:  # the user's own text ids (call00, …) where they gave them
        out[col.EVENT_ID] = predictions["event_name"].to_numpy(object)
    gate_x, gate_y = col.estimate_xy("gate")
    placed = (
        predictions[col.PLACED].to_numpy(bool)
        if col.PLACED in predictions
        else np.isfinite(predictions[[gate_x, gate_y]].to_numpy(float)).all(1)
    )
    substituted = predictions[col.SUBSTITUTED].to_numpy(bool)
    has_estimate = np.isfinite(predictions[[gate_x, gate_y]].to_numpy(float)).all(1)
    solver_z = (
        predictions[col.SOLVER_SOURCE_HEIGHT].to_numpy(float) if col.SOLVER_SOURCE_HEIGHT in predictions else np.full(len(out), np.nan)
    )
    out[col.TRUE_X] = np.where(placed, predictions[gate_x], np.nan)
    out[col.TRUE_Y] = np.where(placed, predictions[gate_y], np.nan)
    out[col.TRUE_Z] = np.where(
        placed & ~substituted, solver_z, np.nan
    )  # the model estimates no height: never the solver's z under its x, y
    for method in ("solver", "model"):
        for axis, name in zip(("x", "y"), col.estimate_xy(method), strict=True):
            out[f"{method}_{axis}_m"] = predictions[name]
        if method == "solver":
            out[col.POSITION_SOLVER_Z] = solver_z
    solver_xy = predictions[list(col.estimate_xy("solver"))].to_numpy(float)
    out[col.SOLVER_MODEL_DISTANCE] = np.sqrt(((solver_xy - predictions[list(col.estimate_xy("model"))].to_numpy(float)) ** 2).sum(axis=1))
    out["source"] = np.where(~has_estimate, "none", np.where(substituted, "model", "solver"))
    solver_fix = np.isfinite(solver_xy).all(axis=1)
    reason = np.where(
        ~substituted,
        "solver fix kept",
        np.where(
            solver_fix,
            "the gate judged the solver's fix worse than the model's",
            "the solver found no fix (or one outside the plausible region)",
        ),
    )
    trust = predictions[col.TRUST_REASON].fillna("").astype(str).to_numpy() if col.TRUST_REASON in predictions else np.full(len(out), "")
    out["gate_reason"] = np.where(trust != "", trust, reason)  # where the trust check overrode the gate: its reason
    if col.trust_flag("solver_outside_support") in predictions:
        out["outside_training_region"] = predictions[col.trust_flag("solver_outside_support")].to_numpy(bool)
        out["novelty"] = predictions[col.trust_flag("novelty")].to_numpy(float)
    out[col.PREDICTED_ERROR] = predictions[col.PREDICTED_ERROR]
    _add_radius_columns(out, predictions, levels, scorers, placed)
    for c in predictions.columns:
        if c.startswith("ellipse__"):
            out[c] = np.where(placed, predictions[c], np.nan)
    out[col.PLACED] = placed
    default_reason = np.where(placed, "", np.where(trust != "", trust, "no estimate"))
    out[col.ABSTAIN_REASON] = predictions[col.ABSTAIN_REASON] if col.ABSTAIN_REASON in predictions else default_reason
    for c in predictions.columns:
        if col.GROUP_SEPARATOR in c and c.startswith("solver__"):
            out[c] = predictions[c]
        if c.startswith("tdoa_0_"):  # the measured time differences to mic 0 the solver worked from, s
            out[c] = predictions[c]
    for c in predictions.columns:  # each mic's arrival residual at the solver's fix, m
        if c.startswith("residual_mic_"):
            out[c] = predictions[c]
    return out


def localization_summary(table: pd.DataFrame, levels: list[float], scorers: list[str]) -> dict[str, Any]:
    """For metrics.json of a localization run: counts, share placed, and the median, mean and largest radius per scorer and level (m)."""

    def spread(values: pd.Series) -> dict[str, float]:
        v = values.to_numpy(float)[table[col.PLACED].to_numpy(bool)]
        v = v[np.isfinite(v)]
        return {"median": float(np.median(v)), "mean": float(np.mean(v)), "max": float(np.max(v))} if v.size else {"median": float("nan")}

    radii = {s: {col.level_key(lv): spread(table[f"radius_{s}_{col.level_key(lv)}_m"]) for lv in levels} for s in scorers}
    return {
        "n_detections": len(table),
        "n_placed": int(table[col.PLACED].sum()),
        "share_from_model": float((table["source"] == "model").mean()) if len(table) else float("nan"),
        # placed fixes resting on a subset of the mics that fit worse than timing noise allows (look at these twice)
        "n_weak_support": int((table[col.WEAK_SUPPORT].fillna(False).to_numpy(bool) & table[col.PLACED].to_numpy(bool)).sum())
        if col.WEAK_SUPPORT in table
        else 0,
        "radius_m": radii,
    }


def positions_summary_text(table: pd.DataFrame, levels: list[float], scorers: list[str]) -> str:
    """The console's view of positions: event id, x, y, the height only where a 3-D fix determined it (``—`` where it was
    assumed, ambiguous or the model's), the source, and the first scorer's radius at the highest level, m."""
    shown = pd.DataFrame({name: table[name] for name in (col.EVENT_ID, col.TRUE_X, col.TRUE_Y) if name in table})
    if col.TRUE_Z in table:
        determined = (
            np.isfinite(table[col.SOLVER_HEIGHT_GDOP].to_numpy(float)) if col.SOLVER_HEIGHT_GDOP in table else np.zeros(len(table), bool)
        )
        if col.SOLVER_HEIGHT_AMBIGUOUS in table:
            determined &= table[col.SOLVER_HEIGHT_AMBIGUOUS].to_numpy(float) != 1
        z = table[col.TRUE_Z].to_numpy(float)
        shown[col.TRUE_Z] = np.where(determined & np.isfinite(z), np.char.mod("%.2f", np.nan_to_num(z)), "—")
    shown["source"] = table["source"].to_numpy()
    if scorers and levels:
        name = f"radius_{scorers[0]}_{col.level_key(max(levels))}_m"
        if name in table:
            shown[name] = table[name].to_numpy(float)
    shown[col.PLACED] = table[col.PLACED].to_numpy(bool)
    return shown.to_string(index=False, float_format=lambda v: f"{v:.2f}")
