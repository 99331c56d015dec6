"""Localize recordings without ground truth: train on the site's simulation, place every detection.

The field researcher's question, "where were my birds, and how sure are you?": the method is fitted
on simulated events of the site exactly as in the evaluation protocols (point model, gate, error
model and conformal calibrated over simulated positions), then applied to every detection of the
field recordings. Nothing here needs a true position; the run writes ``positions.csv`` (and
``predictions.parquet``) instead of error metrics.
"""

from __future__ import annotations

import logging

import numpy as np

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.method.localizer import FittedLocalizer
from acoustlab.method.pipeline import LocalizationPipeline, MethodResult
from acoustlab.method.protocols.field import combine
from acoustlab.method.splits import cap_rows
from acoustlab.stages.dataset import Dataset

log = logging.getLogger(__name__)


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
        self.fitted: FittedLocalizer | None = None

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
        self.fitted = FittedLocalizer(pipeline.fit(features, events, np.sort(train)))
        # the field rows were solved before the fit (the playbacks among them train): placed as solved
        placement = self.fitted.place_solved(features.iloc[field_rows], field_recordings.events.iloc[field_rows - sim_rows.size])
        info = self.fitted.method.split_info(placement.trust)
        if self.fitted.method.held_out_calibration is not None:  # a table, summarised by the localize job
            info["held_out_calibration"] = self.fitted.method.held_out_calibration
        info["training"] = {"n_simulated": int(train.size - calibration.size), "n_calibration_playbacks": int(calibration.size)}
        return MethodResult(placement.predictions, [info], positions=placement.positions)
