"""Placing field detections with a fitted method: the one path from features to a positions table.

``localize``, every chunk of a ``season`` and ``acoustlab.api`` place detections through
``FittedLocalizer.place`` (or ``place_solved`` where the solver stage already ran, as for the
recordings ``localize`` also trains on), so what a positions row holds is defined here once:

1. the solver stage (``solve_detections`` under ``Components.placement``): weak recorders left out, the field calibration's
   thermometer and clocks applied, the solver's columns under the plausible-region bound;
2. the fitted method's predictions (``FittedMethod.predict``);
3. the predictions as a localization reports them (``without_truth``: no errors, the detections'
   own fields, flagged clips not placed);
4. the positions table (``acoustlab.reporting.positions.positions_table``), the calibration each
   row was placed with, the detections' extra fields, and the positions in the mics table's
   projected coordinates where it has them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.contracts import FeatureSet
from acoustlab.core.types import Site
from acoustlab.method.fitted import FittedMethod
from acoustlab.method.pipeline import Components
from acoustlab.method.trust import TrainingSupport
from acoustlab.reporting.positions import positions_table
from acoustlab.stages.field_calibration import CALIBRATION_COLUMN, FieldCalibration, field_solver_columns
from acoustlab.toolkit.quality import dropped_mask

#: The rank-1 lag columns of the pairs (0, j): t_j − t_0 in s.
TDOA_TO_MIC0 = re.compile(r"tdoa__lag_0_(\d+)_s")
#: Added to a field detection's position id so it never shares a group with a simulated position.
FIELD_POSITION_OFFSET = 10**9

#: Solver-stage columns copied into the positions table as quality flags.
QUALITY_COLUMNS = (
    col.SOLVER_FAILURE,
    col.SOLVER_SOURCE_HEIGHT,
    col.SOLVER_HEIGHT_GDOP,
    col.SOLVER_HEIGHT_AMBIGUOUS,
    col.SOLVER_RESIDUAL,
    col.SOLVER_CONSISTENCY,
    col.SOLVER_N_MICS_USED,
    col.SOLVER_GDOP,
)


def solve_detections(components: Components, features: pd.DataFrame, detections: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The solver stage of field detections under ``components.placement``: features with the solver's columns, detections
    with ``mics_used``."""
    rules = components.placement
    return field_solver_columns(
        features,
        detections,
        components.site,
        components.solver,
        rules.plausible_margin_fraction,
        rules.calibration,
        rules.min_gcc_peak,
        rules.min_gcc_peak_relative,
    )


@dataclass
class Placement:
    """What placing detections gives: the method's full predictions (``predictions.parquet``), the positions table
    (``positions.csv``) and the trust check's summary."""

    predictions: pd.DataFrame
    positions: pd.DataFrame
    trust: dict[str, Any]


@dataclass
class FittedLocalizer:
    """A fitted method that places field detections; any number of them, in any chunks.

    A row's position depends on this object and that row alone, so a season placed chunk by chunk
    (or shard by shard), ``localize`` and ``acoustlab.api`` give the same row for the same clip.
    Its site, feature groups, solver, radii and placement rules are the ones it was fitted with
    (``FittedMethod.pipeline``'s components).

    Attributes
    ----------
    method : FittedMethod
        The point model, gate, error model and conformal scorers fitted on the site's simulation (and playbacks).
    sample_rate_hz : float, optional
        The rate the method's features were computed at, Hz (a season resamples its clips to it).
    recipe : tuple of str
        The command-line overrides the method was fitted from (``acoustlab.api.place`` reads other recordings with them).
    """

    method: FittedMethod
    sample_rate_hz: float | None = None
    recipe: tuple[str, ...] = ()

    @property
    def components(self) -> Components:
        """The configured plugins and settings the method was fitted with."""
        return self.method.pipeline.c

    @property
    def site(self) -> Site:
        """The array the method places detections of."""
        return self.components.site

    @property
    def feature_sets(self) -> dict[str, FeatureSet]:
        """The feature groups a detection's clips must be turned into before ``place``."""
        return self.components.feature_sets

    @property
    def calibration(self) -> FieldCalibration | None:
        """The field calibration the detections are corrected with (``calibration=PATH``), or None."""
        return self.components.placement.calibration

    def place(self, features: pd.DataFrame, detections: pd.DataFrame, extra_fields: pd.DataFrame | None = None) -> Placement:
        """Positions of field detections from their features (the solver stage not yet run).

        Parameters
        ----------
        features : pandas.DataFrame
            One row per detection: the configured feature groups.
        detections : pandas.DataFrame
            The same rows: the detections' own fields (``event_id``, times, weather, quality flags, …).
        extra_fields : pandas.DataFrame, optional
            The same rows: columns put in the positions table as they are, after ``event_id`` (a season's ``time``,
            ``recorders``, …).

        Returns
        -------
        Placement
        """
        solved_features, solved_detections = solve_detections(self.components, features, detections)
        return self.place_solved(solved_features, solved_detections, extra_fields)

    def place_solved(self, features: pd.DataFrame, detections: pd.DataFrame, extra_fields: pd.DataFrame | None = None) -> Placement:
        """``place`` for features that already carry the solver's columns (``solve_detections``)."""
        c = self.components
        predictions, trust = self.method.predict(features, as_field_events(detections))
        predictions = without_truth(predictions, features, detections)
        predictions = with_support_flags(predictions, features, self.method.support, c.site.n_mics)
        predictions = with_mic_residuals(predictions, features, c.site.mic_positions_m)
        table = positions_table(predictions, c.levels, list(c.scorers))
        if extra_fields is not None:  # after event_id, in place of a column of the same name
            table = table.drop(columns=[name for name in extra_fields.columns if name in table])
            for at, name in enumerate(extra_fields.columns, start=1):
                table.insert(at, name, extra_fields[name].to_numpy())
        if c.placement.calibration is not None:  # which field calibration placed each detection
            table[CALIBRATION_COLUMN] = c.placement.calibration.sha256
        if c.placement.projection is not None:
            table = c.placement.projection.add_columns(table)
        return Placement(predictions, table, trust)


def as_field_events(detections: pd.DataFrame) -> pd.DataFrame:
    """Field detections as the method sees them beside simulated events: truth columns (NaN where unknown), position ids
    offset past every simulated one (each detection its own where none is given), ``is_field``."""
    events = detections.copy()
    for name in (col.TRUE_X, col.TRUE_Y, col.TRUE_Z):
        if name not in events:
            events[name] = np.nan
    if col.POSITION_ID not in events or events[col.POSITION_ID].isna().any():
        events[col.POSITION_ID] = np.arange(len(events))  # unknown positions: every detection its own group
    events[col.POSITION_ID] = events[col.POSITION_ID].astype(np.int64) + FIELD_POSITION_OFFSET
    events["is_field"] = True
    return events


def without_truth(predictions: pd.DataFrame, features: pd.DataFrame, detections: pd.DataFrame) -> pd.DataFrame:
    """Predictions of field detections as a localization reports them.

    Error and oracle columns are blanked (there is no truth), the solver stage's quality columns
    and the detections' own fields (file, times, label, …) are added, and a detection whose clip
    was flagged (``quality_ok`` false) is not placed, its ``abstain_reason`` naming the flags.
    """
    predictions = predictions.copy()
    for method in col.methods_in(predictions.columns):  # no truth, no errors
        predictions[col.error_m(method)] = np.nan
    for name in col.estimate_xy("oracle"):
        predictions[name] = np.nan
    for name in QUALITY_COLUMNS:  # why a fix may be weak, from the solver stage
        if name in features:
            predictions[name] = features[name].to_numpy()
    for name in features.columns:  # the measured time differences to mic 0 (the strongest GCC peak; clocks corrected)
        match = TDOA_TO_MIC0.fullmatch(name)
        if match:
            predictions[f"tdoa_0_{match.group(1)}_s"] = features[name].to_numpy(float)
    keep = [c for c in detections.columns if c not in predictions.columns and c not in (col.TRUE_X, col.TRUE_Y, col.TRUE_Z, "is_field")]
    for name in keep:  # the detection's own fields (file, start time, …)
        predictions[name] = detections[name].to_numpy()
    if "quality_ok" in predictions:  # a clip out of its file, dead, truncated, …: no position, and why
        has_fix = (
            predictions[col.PLACED].to_numpy(bool)
            if col.PLACED in predictions
            else np.isfinite(predictions[list(col.estimate_xy("gate"))].to_numpy(float)).all(1)
        )
        good = predictions["quality_ok"].to_numpy(bool)
        reason = (
            predictions[col.ABSTAIN_REASON].to_numpy(object) if col.ABSTAIN_REASON in predictions else np.where(has_fix, "", "no estimate")
        )
        predictions[col.PLACED] = has_fix & good
        predictions[col.ABSTAIN_REASON] = np.where(good, reason, "quality: " + predictions[col.QUALITY_FLAGS].astype(str))
    return predictions


def with_support_flags(predictions: pd.DataFrame, features: pd.DataFrame, support: TrainingSupport | None, n_mics: int) -> pd.DataFrame:
    """``predictions`` with ``weak_support`` (bool) and, where it is true, a note in ``quality_flags`` and ``radius_note``.

    A solver fix has weak support where the solver left mics out (it rests on fewer than the mics
    whose clips were usable) and its residual is above what good fixes of the training simulation
    reach (``TrainingSupport.residual_limit_s_``: the timing noise those fixes had): the mics it
    kept disagree with one another more than timing noise explains, so a second source, an echo
    or a wrong peak may have moved it, and a radius calibrated on fixes that fit their time
    differences may be too small. The position is still reported; the flag says to look twice.
    Without a residual limit (no redundant mics in training, or no trust check) nothing is flagged.
    """
    out = predictions.copy()
    limit = support.residual_limit_s_ if support is not None else None
    residual_name = col.solver_column("residual_s")
    weak = np.zeros(len(out), dtype=bool)
    if limit is not None and residual_name in features and col.SOLVER_N_MICS_USED in features:
        residual_s = features[residual_name].to_numpy(float)
        used = features[col.SOLVER_N_MICS_USED].to_numpy(float)
        usable = n_mics - dropped_mask(out.get(col.MICS_DROPPED), len(out), n_mics).sum(axis=1)
        fixed = np.isfinite(features[list(col.SOLVER_ESTIMATE_COLUMNS)].to_numpy(float)).all(axis=1)
        weak = fixed & np.isfinite(residual_s) & (residual_s > limit) & np.isfinite(used) & (used < usable)
        if weak.any():
            notes = np.array(
                [
                    f"weak support: the fix rests on {int(u)} of {int(n)} mics with a residual of {1e3 * r:.2f} ms, above the "
                    f"{1e3 * limit:.2f} ms of good fixes (a second source, an echo or a wrong peak?); its radius may be too small"
                    if w
                    else ""
                    for w, u, n, r in zip(weak, used, usable, residual_s, strict=True)
                ],
                dtype=object,
            )
            for name in (col.QUALITY_FLAGS, col.RADIUS_NOTE):
                if name in out:
                    current = out[name].fillna("").astype(str).to_numpy(object)
                    out[name] = np.where(weak, np.where(current != "", current + "; " + notes, notes), current)
                else:
                    out[name] = notes
    out[col.WEAK_SUPPORT] = weak
    return out


def mic_residual_column(mic: int) -> str:
    """The positions table's column of mic ``mic``'s arrival residual at the solver's fix, m."""
    return f"residual_mic_{mic}_m"


def with_mic_residuals(predictions: pd.DataFrame, features: pd.DataFrame, mics_m: np.ndarray) -> pd.DataFrame:
    """``predictions`` with each mic's arrival residual at the solver's fix (``residual_mic_<m>_m``), m of range.

    The measured arrival of mic m relative to mic 0 is ``tdoa_0_<m>_s`` (t_0's 0); the fix predicts
    ``‖s − p_m‖ / c`` plus one emission time, taken as the mean over the mics the fix rests on
    (``mics_used``) of measured less predicted. A mic's residual is its measured less predicted
    arrival less that time, times c: near 0 for every mic the fix explains, metres for a mic whose
    peak it does not (a left-out mic's residual says how far off its peak was). NaN without a fix,
    without a mic's time difference, or without the speed of sound the solver used.
    """
    out = predictions.copy()
    n_mics = len(mics_m)
    names = [col.tdoa_lag(0, m) for m in range(1, n_mics)]
    if not set(names) <= set(features.columns) or col.ENV_SPEED_OF_SOUND not in features:
        return out
    measured = np.column_stack([np.zeros(len(features)), features[names].to_numpy(float)])  # (B, M) arrival after mic 0's, s
    z = features[col.SOLVER_SOURCE_HEIGHT].to_numpy(float) if col.SOLVER_SOURCE_HEIGHT in features else np.full(len(features), np.nan)
    source = np.column_stack([features[list(col.SOLVER_ESTIMATE_COLUMNS)].to_numpy(float), z])
    speed = features[col.ENV_SPEED_OF_SOUND].to_numpy(float)
    predicted = np.linalg.norm(source[:, None, :] - np.asarray(mics_m, float)[None], axis=-1) / speed[:, None]  # (B, M), s
    used = dropped_mask(out.get(col.MICS_USED), len(out), n_mics)  # the same ";"-list as mics_dropped
    used[~used.any(axis=1)] = True  # none listed: every mic
    gap = measured - predicted
    kept = np.where(used, gap, np.nan)
    counted = np.isfinite(kept).sum(axis=1, keepdims=True)
    emission = np.where(counted > 0, np.nansum(kept, axis=1, keepdims=True) / np.maximum(counted, 1), np.nan)  # no fix: NaN
    residual = (gap - emission) * speed[:, None]
    for m in range(n_mics):
        out[mic_residual_column(m)] = residual[:, m]
    return out


def unknown_position_rows(detections: pd.DataFrame) -> np.ndarray:
    """Rows of field detections without a known ``x_m, y_m`` (the ones to place; the others are playbacks)."""
    if not {col.TRUE_X, col.TRUE_Y} <= set(detections.columns):
        return np.arange(len(detections))
    return np.flatnonzero(~np.isfinite(detections[[col.TRUE_X, col.TRUE_Y]].to_numpy(float)).all(axis=1))
