"""Localize recordings without ground truth: train on the site's simulation, place every detection.

The field researcher's question, "where were my birds, and how sure are you?": the method is fitted
on simulated events of the site exactly as in the evaluation protocols (point model, gate, error
model and conformal calibrated over simulated positions), then applied to every detection of the
field recordings. Nothing here needs a true position; the run writes ``positions.csv`` (and
``predictions.parquet``) instead of error metrics.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.method.localizer import FittedLocalizer
from acoustlab.method.pipeline import LocalizationPipeline, MethodResult
from acoustlab.method.protocols.field import combine
from acoustlab.method.run_context import RunContext, field_dataset, simulated_dataset
from acoustlab.method.splits import cap_rows
from acoustlab.reporting.metrics import held_out_calibration_summary, split_diagnostics_summary
from acoustlab.reporting.positions import localization_summary, positions_summary_text
from acoustlab.reporting.run_files import plot_and_time, quality_flag_counts, write_positions, write_results
from acoustlab.stages.dataset import Dataset
from acoustlab.stages.mic_survey import mics_table_of, survey_allowance
from acoustlab.toolkit.input_uncertainty import InputUncertainty

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

    def __init__(self, max_train_rows: int = 1000, seed: int = 0, calibration_fraction: float = 0.2) -> None:
        if max_train_rows < 2:
            raise ConfigError(f"protocol.max_train_rows must be >= 2; got {max_train_rows}")
        if not 0 <= calibration_fraction < 1:
            raise ConfigError(f"protocol.calibration_fraction must be in [0, 1); got {calibration_fraction}")
        self.max_train_rows = int(max_train_rows)
        self.seed = int(seed)
        self.calibration_fraction = float(calibration_fraction)
        #: the method the last ``fit_and_place`` fitted (``acoustlab.api.localize(..., return_method=True)`` returns it)
        self.fitted: FittedLocalizer | None = None

    def run_job(self, context: RunContext, run_dir: Path) -> dict[str, Any]:
        """The ``localize`` job: fit, place every field detection, write ``positions.csv`` / ``.parquet``, the
        predictions, ``metrics.json`` and the positions map; returns the metrics."""
        started = time.perf_counter()
        dataset = simulated_dataset(context)
        if dataset is None:
            raise ConfigError("protocol=localize does not shard its simulation: run it without data.shard_count")
        field_data = field_dataset(context)
        timings = {"data_s": time.perf_counter() - started}
        stage_start = time.perf_counter()
        components, stated = context.components, None
        if context.calibration is None:  # the radii carry the mics table's stated survey error (a calibration's replaces it)
            stated = survey_allowance(
                components.input_uncertainty, mics_table_of(context.field_source, context.settings.config["site"]), context.site.n_mics
            )
            components = dataclasses.replace(components, input_uncertainty=stated)
        result = self.fit_and_place(dataset, LocalizationPipeline(components), field_data)
        timings["models_s"] = time.perf_counter() - stage_start
        return write_localization(context, run_dir, result, dataset, field_data, timings, started, stated)

    def fit_and_place(self, dataset: Dataset, pipeline: LocalizationPipeline, field_recordings: Dataset | None = None) -> MethodResult:
        """Fit on the simulation (and the playbacks with known positions); place every field detection without one.

        Error columns are NaN (there is no truth); ``positions`` is the positions table. The fitted
        method is kept as ``self.fitted`` (``acoustlab.api.place`` reuses it).
        """
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


def write_localization(
    context: RunContext,
    run_dir: Path,
    result: MethodResult,
    dataset: Dataset,
    field_data: Dataset,
    timings: dict[str, float],
    started: float,
    input_allowance: InputUncertainty | None = None,
) -> dict[str, Any]:
    """A run without ground truth: positions.csv / .parquet, predictions, metrics.json (a summary instead of error metrics),
    and a map; returns the metrics. ``input_allowance``: the stated input errors the radii carry, recorded where no
    calibration states them (its summary does)."""
    table, predictions, c = result.positions, result.predictions, context.components
    levels, scorers = c.levels, list(c.scorers)
    write_positions(run_dir, table)
    metrics: dict[str, Any] = {col.METRICS_LOCALIZATION: localization_summary(table, levels, scorers)}
    for split in result.split_diagnostics:
        if "training" in split:  # simulated events and calibration playbacks the method was fitted on
            metrics["training"] = split["training"]
        held_out = split.pop("held_out_calibration", None)
        if held_out is not None:  # the radii tested on the calibration playbacks, each spot held out
            metrics["held_out_calibration"] = held_out_calibration_summary(held_out, levels, scorers)
            _log_held_out(metrics["held_out_calibration"])
    if input_allowance is not None:  # m, °C, s
        metrics["input_allowance"] = dataclasses.asdict(input_allowance)
    if col.QUALITY_FLAGS in predictions:
        metrics[col.QUALITY_FLAGS] = quality_flag_counts(predictions)
    record = context.settings.record
    metrics.update(split_diagnostics_summary(result.split_diagnostics, record.get("choices", {}).get("gate") or type(c.gate).__name__))
    metrics.update(
        {
            "dataset_hash": dataset.dataset_hash,
            "field_dataset_hash": field_data.dataset_hash,
            "n_features": int(len(dataset.features.columns)),
            **record,
        }
    )
    write_results(run_dir, context.settings.config, predictions, metrics)

    def plot() -> None:
        from acoustlab.reporting.plots import write_positions_map  # matplotlib only when plotting

        write_positions_map(table, context.site, levels, scorers, run_dir / "plots")

    plot_and_time(context.settings.plots, run_dir, metrics, timings, started, "the positions map", plot)
    log.info(
        "positions (first %d of %d detections; all in %s):\n%s",
        min(len(table), 20),
        len(table),
        run_dir / "positions.csv",
        positions_summary_text(table.head(20), levels, scorers),
    )
    return metrics


def _log_held_out(summary: dict[str, Any]) -> None:
    """One line per scorer: the radii's coverage on the calibration playbacks, each spot held out."""
    for scorer, by_level in summary[col.METRICS_COVERAGE].items():
        cells = ", ".join(f"{level}: {'—' if c is None else format(c['detections'], '.2f')}" for level, c in by_level.items())
        log.info(
            "radii (%s) on the %d calibration playbacks at %d spots, each spot held out: coverage %s",
            scorer,
            summary["n_playbacks"],
            summary["n_spots"],
            cells,
        )
