"""Localize recordings without ground truth: train on the site's simulation, place every detection.

The field researcher's question, "where were my birds, and how sure are you?": the method is fitted
on simulated events of the site exactly as in the evaluation protocols (point model, gate, error
model and conformal calibrated over simulated positions), then applied to every detection of the
field recordings. Nothing here needs a true position; the run writes ``positions.csv`` (and
``predictions.parquet``) instead of error metrics.
"""

from __future__ import annotations

import logging
import re

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.method.pipeline import FittedMethod, LocalizationPipeline, MethodResult
from acoustlab.method.protocols.field import combine
from acoustlab.method.splits import cap_rows
from acoustlab.stages.dataset import Dataset

log = logging.getLogger(__name__)

#: The rank-1 lag columns of the pairs (0, j): t_j − t_0 in s.
TDOA_TO_MIC0 = re.compile(r"tdoa__lag_0_(\d+)_s")

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


class LocalizeProtocol:
    """Fit on the site's simulation (capped at ``max_train_rows``); predict every field detection.

    Parameters
    ----------
    max_train_rows : int
        Training cap (whole simulated positions kept together).
    seed : int
        Seed of the training subsample.
    """

    needs_field = True
    #: no ground truth: the app writes positions, not error metrics
    evaluates = False

    def __init__(self, max_train_rows: int = 1000, seed: int = 0, calibration_fraction: float = 0.2) -> None:
        if max_train_rows < 2:
            raise ConfigError(f"protocol.max_train_rows must be >= 2; got {max_train_rows}")
        if not 0 <= calibration_fraction < 1:
            raise ConfigError(f"protocol.calibration_fraction must be in [0, 1); got {calibration_fraction}")
        self.max_train_rows = int(max_train_rows)
        self.seed = int(seed)
        self.calibration_fraction = float(calibration_fraction)
        #: the method the last ``run`` fitted (``acoustlab.api.localize(..., return_method=True)`` reuses it)
        self.fitted: FittedMethod | None = None

    def run(self, dataset: Dataset, pipeline: LocalizationPipeline, field_recordings: Dataset | None = None) -> MethodResult:
        """Positions of every field detection (error columns are NaN: there is no truth)."""
        if field_recordings is None:
            raise ConfigError("protocol=localize needs recordings: choose field=recordings (see docs/localize.md)")
        features, events, sim_rows, all_field_rows = combine(dataset, field_recordings, need_truth=False)
        groups = events[col.POSITION_ID].to_numpy()
        known = np.isfinite(events[[col.TRUE_X, col.TRUE_Y]].to_numpy(float)[all_field_rows]).all(axis=1)
        usable = known & events["quality_ok"].fillna(True).to_numpy(bool)[all_field_rows] if "quality_ok" in events else known
        calibration_rows, field_rows = all_field_rows[usable], all_field_rows[~known]
        if field_rows.size == 0:
            raise ConfigError(
                "protocol=localize: every detection has a known position (x_m, y_m), so there is nothing to localize; "
                "to evaluate on them use protocol=field_eval or protocol=lopo"
            )
        rng = np.random.default_rng([self.seed, 1])
        n_calibration = min(calibration_rows.size, int(round(self.calibration_fraction * self.max_train_rows)))
        calibration = cap_rows(calibration_rows, groups, n_calibration, rng) if n_calibration else np.array([], int)
        train = np.concatenate([cap_rows(sim_rows, groups, self.max_train_rows - calibration.size, rng), calibration])
        log.info(
            "localize: training on %d simulated events%s, placing %d detections",
            train.size - calibration.size,
            f" and {calibration.size} calibration playbacks with known positions" if calibration.size else "",
            field_rows.size,
        )
        result, self.fitted = pipeline.fit_predict_keeping(features, events, np.sort(train), field_rows)
        result.split_diagnostics[0]["training"] = {
            "n_simulated": int(train.size - calibration.size),
            "n_calibration_playbacks": int(calibration.size),
        }
        placed_events = field_recordings.events.iloc[field_rows - sim_rows.size]
        predictions = without_truth(result.predictions, features.iloc[field_rows], placed_events)
        return MethodResult(predictions, result.split_diagnostics)


def without_truth(predictions: pd.DataFrame, features: pd.DataFrame, detections: pd.DataFrame) -> pd.DataFrame:
    """Predictions of field detections as a localization reports them (rows of the three tables alike).

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
    keep = [c for c in detections.columns if c not in predictions.columns and c not in (col.TRUE_X, col.TRUE_Y, col.TRUE_Z)]
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
