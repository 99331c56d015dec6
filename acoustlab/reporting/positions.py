"""The positions table of a localization run (no ground truth): one row per detection, for spatial models."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col

#: Columns of a detection's own record carried into the table when present.
DETECTION_FIELDS = ("event_id", "file", "start_s", "end_s", "label", "quality_flags", "hardware_failure")


def positions_table(predictions: pd.DataFrame, levels: list[float], scorers: list[str]) -> pd.DataFrame:
    """One row per detection: the position (gate), the solver's and model's estimates, the decision, radii, flags.

    Columns: the detection's own fields; ``x_m, y_m`` (the method's estimate; NaN where it abstains),
    ``z_m`` (the solver's height: estimated with ``solver.dimensions=3``, else assumed);
    ``solver_x_m, solver_y_m, model_x_m, model_y_m``; ``source`` (``solver`` or ``model``: which
    estimate the gate kept) and ``gate_reason`` (why); ``predicted_error_m``; ``radius_<scorer>_<level>_m`` per scorer and level;
    ellipse columns when computed; ``placed`` and ``abstain_reason``; quality flags from the solver
    stage (``solver__failure``, ``solver__consistency``, ``solver__n_mics_used``, GDOPs, …).
    """
    out = pd.DataFrame({c: predictions[c] for c in DETECTION_FIELDS if c in predictions})
    gate_x, gate_y = col.estimate_xy("gate")
    placed = predictions["placed"].to_numpy(bool) if "placed" in predictions else np.isfinite(predictions[[gate_x, gate_y]].to_numpy(float)).all(1)
    out["x_m"] = np.where(placed, predictions[gate_x], np.nan)
    out["y_m"] = np.where(placed, predictions[gate_y], np.nan)
    if col.SOLVER_SOURCE_HEIGHT in predictions:
        out["z_m"] = np.where(placed, predictions[col.SOLVER_SOURCE_HEIGHT], np.nan)
    for method in ("solver", "model"):
        for axis, name in zip(("x", "y"), col.estimate_xy(method), strict=True):
            out[f"{method}_{axis}_m"] = predictions[name]
    substituted = predictions["substituted"].to_numpy(bool)
    out["source"] = np.where(substituted, "model", "solver")
    solver_fix = np.isfinite(predictions[list(col.estimate_xy("solver"))].to_numpy(float)).all(axis=1)
    out["gate_reason"] = np.where(~substituted, "solver fix kept", np.where(
        solver_fix, "the gate judged the solver's fix worse than the model's", "the solver found no fix (or one outside the plausible region)"))
    out["predicted_error_m"] = predictions["predicted_error_m"]
    for scorer in scorers:
        for level in levels:
            out[f"radius_{scorer}_{col.level_key(level)}_m"] = np.where(placed, predictions[col.radius(scorer, level)], np.nan)
    for c in predictions.columns:
        if c.startswith("ellipse__"):
            out[c] = np.where(placed, predictions[c], np.nan)
    out["placed"] = placed
    out["abstain_reason"] = predictions["abstain_reason"] if "abstain_reason" in predictions else np.where(placed, "", "no estimate")
    for c in predictions.columns:
        if col.GROUP_SEPARATOR in c and c.startswith("solver__"):
            out[c] = predictions[c]
    return out


def localization_summary(table: pd.DataFrame, levels: list[float], scorers: list[str]) -> dict[str, Any]:
    """For metrics.json of a localization run: counts, share placed, and the median radius per scorer and level (m)."""
    radii = {s: {col.level_key(lv): float(np.nanmedian(table[f"radius_{s}_{col.level_key(lv)}_m"])) if table["placed"].any() else float("nan")
                 for lv in levels} for s in scorers}
    return {"n_detections": len(table), "n_placed": int(table["placed"].sum()),
            "share_from_model": float((table["source"] == "model").mean()) if len(table) else float("nan"),
            "median_radius_m": radii}
