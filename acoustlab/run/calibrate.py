"""The ``calibrate`` job: playbacks at known spots → ``calibration.json``, ``calibration.png`` and ``metrics.json``.

``python -m acoustlab calibrate +site=NAME field=recordings field.audio_dir=… field.mics_csv=… field.events_csv=…``
(the protocol and the maths: ``acoustlab.method.protocols.calibrate`` and ``acoustlab.toolkit.array_calibration``).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from acoustlab.core import columns as col
from acoustlab.core.contracts import hook
from acoustlab.method.protocols.calibrate import residual_rows
from acoustlab.run.registry import build_feature_sets, to_plain
from acoustlab.stages.cache import atomic_write_bytes
from acoustlab.stages.dataset import load_or_build_field
from acoustlab.stages.field_calibration import calibrate_playbacks, playback_rows, second_peak_ratio, write_calibration
from acoustlab.toolkit.array_calibration import MIN_REDUNDANCY, lag_margin_needed_s

log = logging.getLogger(__name__)


def _lag_window_for(cfg: DictConfig, priors: Any) -> DictConfig:
    """The run's config with the GCC lag window's margin widened to what the stated array and clocks may be off.

    A localization run's margin (2 ms by default) is for an array known to centimetres; before
    calibration the mics may be metres off, and a playback near a pair's endfire then has its
    direct path outside the window (``lag_margin_needed_s``). Only widened, never narrowed.
    """
    gcc = cfg.features.get("gcc")
    needed = lag_margin_needed_s(priors)
    if gcc is None or "max_lag_margin_s" not in gcc or float(gcc.max_lag_margin_s) >= needed:
        return cfg
    log.info(
        "calibrate: the GCC lag window's margin is widened from %.1f to %.1f ms, what the stated mics (GPS error) and clocks may shift "
        "a pair's time difference by (3 sigma)",
        1e3 * float(gcc.max_lag_margin_s),
        1e3 * needed,
    )
    return OmegaConf.merge(cfg, {"features": {"gcc": {"max_lag_margin_s": needed}}})


#: A median second-to-first GCC peak ratio above this says the playbacks were tonal (``second_peak_ratio``).
TONAL_PEAK_RATIO = 0.75


def warn_if_tonal(ratio: float | None) -> None:
    """Warn where the playbacks' cross-correlations have a second peak nearly as high as the first on most pairs."""
    if ratio is not None and ratio >= TONAL_PEAK_RATIO:
        log.warning(
            "calibrate: on most mic pairs the playbacks' cross-correlation has a second peak nearly as high as the first "
            "(median ratio %.2f; a sweep's is about 0.4-0.7): the signal played back is tonal (a song?) and its peaks repeat at its "
            "period, or echoes are strong; from few spots the fit can take a neighbouring peak. If it was a song, play back the "
            "sweep (acoustlab.api.write_playback_sweep; docs/calibrate.md)",
            ratio,
        )


def warn_if_one_playback_per_spot(playback_events: pd.DataFrame) -> None:
    """Warn where no spot has two playbacks: the call-to-call spread of the thermometer's error is then measured too small."""
    if len(playback_events) and playback_events[col.POSITION_ID].value_counts().max() < 2:
        log.warning(
            "calibrate: one playback per spot: how far the thermometer's error varies from call to call (temperature_call_sd_c) "
            "is then measured across spots, where the fit absorbs part of it, and may be too small; play back 2-3 times per spot"
        )


def run_calibration(cfg: DictConfig, run_dir: Path, built: Any, choices: dict[str, str]) -> dict[str, Any]:
    """Calibrate the array from the field events with known positions; write the calibration and its summary."""
    site, protocol, source = built.site, built.protocol, built.field_source
    tables = hook(source, "tables")
    mics_table = tables()[0] if tables is not None else None
    priors = protocol.priors(site, mics_table)
    widened = _lag_window_for(cfg, priors)
    feature_sets = built.feature_sets if widened is cfg else build_feature_sets(widened.features)
    field = load_or_build_field(site, source, to_plain(cfg.field), feature_sets, to_plain(widened.features.groups), built.cache)
    playback_events = field.events[playback_rows(field.events)].reset_index(drop=True)
    mic_ids = (
        mics_table["mic_id"].astype(str).tolist()
        if mics_table is not None and "mic_id" in mics_table and len(mics_table) == site.n_mics
        else [str(m) for m in range(site.n_mics)]
    )
    log.info("calibrating %d mics from %d playbacks", site.n_mics, len(playback_events))
    warn_if_one_playback_per_spot(playback_events)
    peak_ratio = second_peak_ratio(field.features, field.events, site)
    warn_if_tonal(peak_ratio)
    # the field sources fill each event's weather (their defaults where a table has none)
    calibration, playbacks = calibrate_playbacks(
        field.features,
        field.events,
        site,
        lambda p: protocol.calibrate(p, priors, mic_ids),
        anneal=lambda p, lags, heights: protocol.annealed_prediction(p, lags, heights, priors),
    )
    calibration.extra["held_out"], calibration.extra["jackknife_sd"] = protocol.held_out(
        playbacks, priors, mic_ids, site, built.components.solver
    )
    digest = write_calibration(run_dir / "calibration.json", calibration, site, playback_events)
    summary = calibration.to_json()
    metrics = {
        "calibration": {
            "file": str(run_dir / "calibration.json"),
            "sha256": digest,
            **{k: summary[k] for k in ("n_playbacks", "n_spots", "temperature_offset_c", "temperature_offset_sd_c", "timing_sigma_s")},
            **{
                k: summary[k]
                for k in (
                    "residual_median_abs_before_s",
                    "residual_median_abs_after_s",
                    "n_outliers",
                    "not_identified",
                    "redundancy",
                    "held_out",
                    "jackknife_sd",
                )
            },
            "clock_offset_ms": [round(1e3 * v, 4) for v in summary["clock_offset_s"]],
            "mic_position_shift_m": summary["mic_position_shift_m"],
            "second_peak_ratio": peak_ratio,
        },
        "site": site.name,
        "choices": choices,
    }
    atomic_write_bytes(run_dir / "metrics.json", json.dumps(metrics, indent=2).encode())
    for kind, why in calibration.not_identified.items():
        log.warning("calibrate: %s not estimated: %s", kind, why)
    enough = summary["redundancy"]
    if not enough["enough"]:
        log.warning(
            "calibrate: %d spots give %d independent time differences for %d unknowns (%.1f each); with fewer than %.0f each a "
            "set of wrong GCC peaks can fit as tightly as the right one: plan %s spots or more (docs/calibrate.md)",
            calibration.n_spots,
            enough["independent_time_differences"],
            enough["unknowns"],
            enough["per_unknown"],
            MIN_REDUNDANCY,
            enough["spots_needed"],
        )
    log.info(
        "thermometer offset %+.2f ± %.2f °C; clock offsets (ms) %s; mic shifts (m) %s; median time-difference residual %.3g → %.3g ms",
        calibration.temperature_offset_c,
        calibration.sd("temperature_offset_c"),
        np.round(1e3 * calibration.clock_offset_s, 3).tolist(),
        np.round(np.hypot(*calibration.mic_position_shift_m[:, :2].T), 2).tolist(),
        1e3 * (summary["residual_median_abs_before_s"] or np.nan),
        1e3 * (summary["residual_median_abs_after_s"] or np.nan),
    )
    held = calibration.extra["held_out"]
    if held is not None:
        log.info(
            "held-out spots (%d playbacks): median time-difference residual %.3g ms with the stated array, %.3g ms calibrated; "
            "median error of their fixes %.2f m stated, %.2f m calibrated (p95 %.2f → %.2f m; outside the array a fix magnifies "
            "the array's error)",
            held["n_playbacks"],
            held["stated"]["median_abs_residual_ms"] or np.nan,
            held["calibrated"]["median_abs_residual_ms"] or np.nan,
            held["stated"]["p50_m"],
            held["calibrated"]["p50_m"],
            held["stated"]["p95_m"],
            held["calibrated"]["p95_m"],
        )
    if cfg.plots:
        from acoustlab.reporting.plots import write_calibration_plot  # matplotlib only when plotting

        write_calibration_plot(
            calibration, residual_rows(calibration, playback_events), playbacks.source_m, site, run_dir / "calibration.png"
        )
    log.info("calibration written to %s (use it: localize … calibration=%s)", run_dir / "calibration.json", run_dir / "calibration.json")
    return metrics
