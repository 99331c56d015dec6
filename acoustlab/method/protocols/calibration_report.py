"""What the ``calibrate`` job tells its user: warnings about the playbacks, the calibration's summary in ``metrics.json``
and its log lines."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.toolkit.array_calibration import MIN_REDUNDANCY, ArrayCalibration, Playbacks
from acoustlab.toolkit.physics import speed_of_sound_m_s

log = logging.getLogger(__name__)

#: A median second-to-first GCC peak ratio above this says the playbacks were tonal (``second_peak_ratio``).
TONAL_PEAK_RATIO = 0.75
#: The calibration's summary keys copied into ``metrics.json`` as they are.
SUMMARY_KEYS = (
    "n_playbacks",
    "n_spots",
    "temperature_offset_c",
    "temperature_offset_sd_c",
    "timing_sigma_s",
    "residual_median_abs_before_s",
    "residual_median_abs_after_s",
    "n_outliers",
    "not_identified",
    "redundancy",
    "held_out",
    "jackknife_sd",
    "shared_bias",
    "sd_unit",
)


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


def calibration_metrics(calibration: ArrayCalibration, path: Path, digest: str, peak_ratio: float | None) -> dict[str, Any]:
    """The ``calibration`` entry of ``metrics.json``: the file, its digest and the calibration's summary."""
    summary = calibration.to_json()
    return {
        "file": str(path),
        "sha256": digest,
        **{k: summary.get(k) for k in SUMMARY_KEYS},  # shared_bias only where the band was given
        "clock_offset_ms": [round(1e3 * v, 4) for v in summary["clock_offset_s"]],
        "mic_position_shift_m": summary["mic_position_shift_m"],
        "second_peak_ratio": peak_ratio,
        "speed_of_sound": calibration.extra.get("speed_of_sound"),
    }


def speed_of_sound_summary(calibration: ArrayCalibration, playbacks: Playbacks) -> dict[str, float]:
    """The speed of sound at the playbacks' mean thermometer reading and humidity, as read and as calibrated, m/s.

    acoustlab's air is humid (``acoustlab.toolkit.physics.speed_of_sound_m_s``: c = 20.05 √T_v, T_v the virtual
    temperature): an offset fitted against another formula (a renderer's dry air) is an offset of the formulas as well as
    of the thermometer, while the speed of sound it gives is what the time differences measured.
    """
    temperature, humidity = float(np.mean(playbacks.temperature_c)), float(np.mean(playbacks.relative_humidity_pct))
    return {
        "temperature_read_c": round(temperature, 3),
        col.HUMIDITY: round(humidity, 3),
        "as_read_m_s": round(float(speed_of_sound_m_s(temperature, humidity)), 4),
        "calibrated_m_s": round(float(speed_of_sound_m_s(temperature + calibration.temperature_offset_c, humidity)), 4),
    }


def log_calibration(calibration: ArrayCalibration) -> None:
    """What could not be estimated, whether the spots were enough, the estimates, and the held-out spots' errors."""
    summary = calibration.to_json()
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
    speed = calibration.extra.get("speed_of_sound") or {}
    log.info(
        "thermometer offset %+.2f ± %.2f °C (speed of sound %s m/s calibrated, %s m/s as read, at %s °C and %s %% humidity); "
        "clock offsets (ms) %s; mic shifts (m) %s; median time-difference residual %.3g → %.3g ms",
        calibration.temperature_offset_c,
        calibration.sd("temperature_offset_c"),
        speed.get("calibrated_m_s"),
        speed.get("as_read_m_s"),
        speed.get("temperature_read_c"),
        speed.get(col.HUMIDITY),
        np.round(1e3 * calibration.clock_offset_s, 3).tolist(),
        np.round(np.hypot(*calibration.mic_position_shift_m[:, :2].T), 2).tolist(),
        1e3 * (summary["residual_median_abs_before_s"] or np.nan),
        1e3 * (summary["residual_median_abs_after_s"] or np.nan),
    )
    log_sigma_cover(calibration)
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


def log_sigma_cover(calibration: ArrayCalibration) -> None:
    """One line: what the σ beside each estimate covers and what it does not (``sd_unit`` in calibration.json)."""
    shared = calibration.extra.get("shared_bias")
    reflection = (
        f"a ground reflection within the direct path's peak in {shared['band_hz'][0]:g}–{shared['band_hz'][1]:g} Hz "
        f"(up to {shared['fraction_max']:g} of its delay, the same at every spot: mics up to "
        f"{max((abs(v) for n, v in shared['shift_at_fraction_max'].items() if n.startswith('mic_')), default=0.0):.3f} m)"
        if shared
        else "no ground reflection (protocol.reflection_band_hz=null)"
    )
    log.info(
        "the ± σ count each playback's independent time differences, at least the spread between spots, and %s; not "
        "covered: any other bias every spot shares (a speaker stand off its survey in the same direction everywhere)",
        reflection,
    )
