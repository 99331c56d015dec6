"""Field protocols: train on simulation, test on field recordings (``field_eval``) or rotate over
field positions adding part of the other positions' field data to training (``lopo``).

Positions are the exchangeable groups everywhere: a withheld field position never appears in
training or in conformal calibration (calibration is out-of-fold over training positions).
Field position ids are offset so they never collide with simulated ones.
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.progress import progress
from acoustlab.method.localizer import FIELD_POSITION_OFFSET, as_field_events
from acoustlab.method.pipeline import LocalizationPipeline, MethodResult
from acoustlab.method.splits import cap_rows
from acoustlab.stages.dataset import Dataset

log = logging.getLogger(__name__)


def combine(sim: Dataset, field_recordings: Dataset, need_truth: bool = True) -> tuple[pd.DataFrame, pd.DataFrame, np.ndarray, np.ndarray]:
    """Stack simulated and field tables; return features, events and the row indices of each part.

    With ``need_truth`` every field event must have a true position (x_m, y_m); without, unknown
    positions are NaN (localizing recordings).
    """
    missing = set(sim.features.columns) ^ set(field_recordings.features.columns)
    if missing:
        raise DataError(f"simulated and field feature tables differ in columns {sorted(missing)[:5]}")
    fev = as_field_events(field_recordings.events)
    if need_truth and fev[[col.TRUE_X, col.TRUE_Y]].isna().any().any():
        raise DataError(
            "field evaluation needs true positions for every field event (x_m, y_m); to localize recordings "
            "without them use protocol=localize (python -m acoustlab localize +site=NAME field=recordings)"
        )
    sev = sim.events.copy()
    sev["is_field"] = False
    events = pd.concat([sev, fev], ignore_index=True)
    features = pd.concat([sim.features, field_recordings.features[sim.features.columns]], ignore_index=True)
    n_sim = len(sim.events)
    return features, events, np.arange(n_sim), np.arange(n_sim, len(events))


class FieldEvalProtocol:
    """Train on simulation only (capped at ``max_train_rows``); test on every field event.

    Parameters
    ----------
    max_train_rows : int
        Training cap (whole simulated positions kept together).
    exclude_failed_from_summary : bool
        Leave positions with a known hardware failure out of the per-detection summaries
        (they stay in ``predictions.parquet``).
    seed : int
        Seed of the training subsample (and of the calibration spots).
    calibration_positions : int
        0: every field position is a test position. K > 0: K field positions drawn at random are
        playback spots of a field calibration (they join training and calibrate the radii, as
        calibration playbacks do under ``localize``); the others are the test positions. What a
        user with K playback spots can expect at the rest of the site.
    """

    needs_field = True

    def __init__(
        self, max_train_rows: int = 1000, exclude_failed_from_summary: bool = True, seed: int = 0, calibration_positions: int = 0
    ) -> None:
        if calibration_positions < 0:
            raise ConfigError(f"protocol.calibration_positions must be >= 0; got {calibration_positions}")
        self.max_train_rows = int(max_train_rows)
        self.exclude_failed_from_summary = bool(exclude_failed_from_summary)
        self.seed = int(seed)
        self.calibration_positions = int(calibration_positions)

    def run(self, dataset: Dataset, pipeline: LocalizationPipeline, field_recordings: Dataset | None = None) -> MethodResult:
        """Predictions for every field event (but the calibration spots'), from models trained on simulation (and those spots)."""
        if field_recordings is None:
            raise ConfigError("protocol=field_eval needs field data: choose a field source, e.g. field=playback_standin")
        features, events, sim_rows, field_rows = combine(dataset, field_recordings)
        groups = events[col.POSITION_ID].to_numpy()
        rng = np.random.default_rng([self.seed, 2])
        calibration = np.array([], dtype=int)
        if self.calibration_positions:
            spots = np.unique(groups[field_rows])
            if self.calibration_positions >= spots.size:
                raise ConfigError(
                    f"protocol.calibration_positions={self.calibration_positions} leaves no test position of the field's {spots.size}"
                )
            chosen = np.random.default_rng([self.seed, 3]).choice(spots, self.calibration_positions, replace=False)
            calibration = field_rows[np.isin(groups[field_rows], chosen)]
            field_rows = field_rows[~np.isin(groups[field_rows], chosen)]
            log.info(
                "field_eval: %d events at %d field positions calibrate; %d test events", calibration.size, chosen.size, field_rows.size
            )
        train = np.sort(np.concatenate([cap_rows(sim_rows, groups, self.max_train_rows - calibration.size, rng), calibration]))
        result = pipeline.fit_predict(features, events, train, field_rows)
        return MethodResult(_annotate(result.predictions, events, field_rows, self.exclude_failed_from_summary), result.split_diagnostics)


class LopoProtocol:
    """Leave one field position out in turn; train on simulation plus a fraction of the other positions' field data.

    Parameters
    ----------
    field_fraction : float
        Fraction of the training budget filled with field events of the other positions.
    max_train_rows : int
        Training cap, field rows included.
    exclude_failed_from_summary : bool
        As in ``FieldEvalProtocol``.
    seed : int
        Seed of the subsamples.
    """

    needs_field = True

    def __init__(
        self, field_fraction: float = 0.2, max_train_rows: int = 1000, exclude_failed_from_summary: bool = True, seed: int = 0
    ) -> None:
        if not 0 <= field_fraction < 1:
            raise ConfigError(f"protocol.field_fraction must be in [0, 1); got {field_fraction}")
        self.field_fraction = float(field_fraction)
        self.max_train_rows = int(max_train_rows)
        self.exclude_failed_from_summary = bool(exclude_failed_from_summary)
        self.seed = int(seed)

    def splits(self, events: pd.DataFrame, sim_rows: np.ndarray, field_rows: np.ndarray):
        """Yield (withheld position, train rows, test rows) for every field position."""
        groups = events[col.POSITION_ID].to_numpy()
        n_field = int(round(self.field_fraction * self.max_train_rows))
        for k, pos in enumerate(np.unique(groups[field_rows])):
            rng = np.random.default_rng([self.seed, 3, k])
            test = field_rows[groups[field_rows] == pos]
            others = field_rows[groups[field_rows] != pos]
            field_part = rng.choice(others, size=min(n_field, others.size), replace=False) if n_field else np.array([], int)
            sim_part = cap_rows(sim_rows, groups, self.max_train_rows - field_part.size, rng)
            yield pos, np.sort(np.concatenate([sim_part, field_part])), test

    def run(self, dataset: Dataset, pipeline: LocalizationPipeline, field_recordings: Dataset | None = None) -> MethodResult:
        """Pooled predictions of every withheld field position; one split diagnostics entry per position."""
        if field_recordings is None:
            raise ConfigError("protocol=lopo needs field data: choose a field source, e.g. field=playback_standin")
        features, events, sim_rows, field_rows = combine(dataset, field_recordings)
        pooled = []
        n_positions = np.unique(events[col.POSITION_ID].to_numpy()[field_rows]).size
        for pos, train, test in progress(self.splits(events, sim_rows, field_rows), total=n_positions, desc="LOPO", unit="position"):
            log.info("LOPO: withholding field position %d (%d test, %d training rows)", pos - FIELD_POSITION_OFFSET, test.size, train.size)
            result = pipeline.fit_predict(features, events, train, test)
            withheld = int(pos - FIELD_POSITION_OFFSET)
            out = result.predictions
            out[col.WITHHELD_POSITION] = withheld
            diagnostics = [{"split": f"withheld_position={withheld}", **d} for d in result.split_diagnostics]
            pooled.append(MethodResult(_annotate(out, events, test, self.exclude_failed_from_summary), diagnostics))
        return MethodResult.concat(pooled)


def _annotate(out: pd.DataFrame, events: pd.DataFrame, rows: np.ndarray, exclude_failed: bool) -> pd.DataFrame:
    out = out.copy()
    out[col.POSITION_ID] = out[col.POSITION_ID] - FIELD_POSITION_OFFSET
    failed = events[col.HARDWARE_FAILURE].to_numpy(bool)[rows] if col.HARDWARE_FAILURE in events else np.zeros(rows.size, bool)
    out[col.HARDWARE_FAILURE] = failed
    flagged = ~events["quality_ok"].fillna(True).to_numpy(bool)[rows] if "quality_ok" in events else np.zeros(rows.size, bool)
    if col.QUALITY_FLAGS in events:
        out[col.QUALITY_FLAGS] = events[col.QUALITY_FLAGS].fillna("").to_numpy(object)[rows]
    out[col.IN_SUMMARY] = ~(failed | flagged) if exclude_failed else ~flagged
    return out
