"""Calibrate a field array from playbacks at known spots (``python -m acoustlab calibrate``).

The events of ``field=recordings`` with a known position (``x_m, y_m``, optionally ``z_m``, and a
``position_id`` per spot) are playbacks. From their measured time differences the run estimates
the thermometer's offset, each recorder's clock offset (and drift where the playbacks span at
least ``min_drift_span_s``) and corrections to the mic positions within their stated GPS error
(``position_sigma_m``, per mic from the mics table's column of that name where it has one), and
writes ``calibration.json`` and ``calibration.png`` in the run directory. Nothing is simulated.

How much the calibration buys at this site is measured on the playbacks themselves, held out by
spot: each spot's playbacks are solved with the array calibrated without that spot, and with the
stated array, by the configured solver (``held_out`` in ``metrics.json``). The same calibrations
without a group of spots give each estimate's delete-group jackknife standard deviation
(``jackknife_sd``); each re-picks its GCC candidates until its picks hold, as the full calibration
did, so the picks' own uncertainty is in it. Unlike the posterior's, it also holds what the fit's
model lacks (multipath that biases one spot's peaks, a speed-of-sound formula not the air's), which
the posterior, counting every playback as independent, leaves out (docs/calibrate.md gives the
measured shares of mics beyond 2 σ).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.contracts import FieldSource, SolverInputs
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.types import Site, require_range
from acoustlab.method.protocols.calibration_report import (
    calibration_metrics,
    log_calibration,
    speed_of_sound_summary,
    warn_if_one_playback_per_spot,
    warn_if_tonal,
)
from acoustlab.method.protocols.playback_checks import check_positions, unheard_mics, with_unknown_uncertainty_from_one_spot, without_mics
from acoustlab.method.run_context import RunContext, field_dataset
from acoustlab.reporting.run_files import write_metrics
from acoustlab.stages.field_calibration import load_calibration, playback_rows, playbacks_from, second_peak_ratio, write_calibration
from acoustlab.stages.mic_survey import mic_position_sigmas, mics_table_of
from acoustlab.stages.solver_columns import pair_candidate_weights
from acoustlab.toolkit.array_calibration import (
    PARAMETER_KINDS,
    ArrayCalibration,
    Playbacks,
    Priors,
    annealed_prediction_s,
    calibrate_array,
    calibrate_until_picks_hold,
    lag_margin_needed_s,
)
from acoustlab.toolkit.event_physics import assumed_source_height_m
from acoustlab.toolkit.physics import speed_of_sound_m_s
from acoustlab.toolkit.recorder_clocks import clock_errors_s

log = logging.getLogger(__name__)


class CalibrateProtocol:
    """Estimate the array's corrections from playbacks (module docstring).

    Parameters
    ----------
    estimate : list of str
        Which of ``temperature``, ``clocks``, ``drift``, ``positions`` to estimate.
    position_sigma_m : float
        Stated horizontal error of the mic positions per axis, m (where the mics table gives none).
    temperature_sigma_c : float
        The thermometer's error, °C.
    clock_sigma_s : float
        Clock offsets between recorders before calibration, s.
    drift_sigma : float
        Clock drift between recorders, s per s.
    min_drift_span_s : float
        Drift is estimated only from playbacks spread over at least this long, s.
    held_out_folds : int
        Spots are held out in this many groups to measure what the calibration buys (0: not measured).
    reflection_band_hz : list of float, optional
        The band of the playbacks' GCC peaks, Hz (the playback sweep's 1–8 kHz by default): the σ
        then carries a ground reflection within the direct path's peak, a bias every spot shares
        (``toolkit.array_calibration.shared_reflection_response``); null: it does not.
    """

    needs_field = True

    def __init__(
        self,
        estimate: list[str] | tuple[str, ...] = PARAMETER_KINDS,
        position_sigma_m: float = 2.0,
        temperature_sigma_c: float = 3.0,
        clock_sigma_s: float = 0.002,
        drift_sigma: float = 1e-5,
        min_drift_span_s: float = 3600.0,
        held_out_folds: int = 10,
        reflection_band_hz: list[float] | tuple[float, float] | None = (1000.0, 8000.0),
    ) -> None:
        unknown = sorted(set(estimate) - set(PARAMETER_KINDS))
        if unknown:
            raise ConfigError(f"protocol.estimate: {unknown} cannot be estimated; choose from {list(PARAMETER_KINDS)}")
        for name, value in (
            (col.POSITION_SIGMA, position_sigma_m),  # protocol.position_sigma_m: the mics table column's default
            ("temperature_sigma_c", temperature_sigma_c),
            ("clock_sigma_s", clock_sigma_s),
            ("drift_sigma", drift_sigma),
        ):
            if not np.isfinite(value) or value <= 0:
                raise ConfigError(f"protocol.{name} must be a number > 0; got {value}")
        if held_out_folds < 0:
            raise ConfigError(f"protocol.held_out_folds must be >= 0; got {held_out_folds}")
        self.estimate = tuple(estimate)
        self.position_sigma_m = float(position_sigma_m)
        self.temperature_sigma_c = float(temperature_sigma_c)
        self.clock_sigma_s = float(clock_sigma_s)
        self.drift_sigma = float(drift_sigma)
        self.min_drift_span_s = float(min_drift_span_s)
        self.held_out_folds = int(held_out_folds)
        self.reflection_band_hz = None if reflection_band_hz is None else _band(reflection_band_hz)

    def config_patch(self, site: Site, field_source: FieldSource | None, config: dict[str, Any]) -> dict[str, Any] | None:
        """The GCC lag window's margin widened to what the stated mics and clocks may be off, where the config's is narrower.

        A localization run's margin (2 ms by default) is for an array known to centimetres; before
        calibration the mics may be metres off, and a playback near a pair's endfire then has its
        direct path outside the window (``lag_margin_needed_s``). Only widened, never narrowed. A config
        with ``calibration=PATH`` is refused here, in the preflight: calibrate starts from the stated array.
        """
        if config.get("calibration"):
            raise ConfigError("calibrate starts from the stated array: drop calibration=… (a calibration is not calibrated again)")
        gcc = (config.get("features") or {}).get("gcc")
        needed = lag_margin_needed_s(self.priors(site, mics_table_of(field_source)))
        if not gcc or "max_lag_margin_s" not in gcc or float(gcc["max_lag_margin_s"]) >= needed:
            return None
        log.info(
            "calibrate: the GCC lag window's margin is widened from %.1f to %.1f ms, what the stated mics (GPS error) and clocks may "
            "shift a pair's time difference by (3 sigma)",
            1e3 * float(gcc["max_lag_margin_s"]),
            1e3 * needed,
        )
        return {"features": {"gcc": {"max_lag_margin_s": needed}}}

    def run_job(self, context: RunContext, run_dir: Path) -> dict[str, Any]:
        """The ``calibrate`` job: calibrate the array from the field events with known positions; write ``calibration.json``,
        ``metrics.json`` and ``calibration.png``; returns the metrics."""
        site = context.site
        mics_table = mics_table_of(context.field_source)
        priors = self.priors(site, mics_table)
        field = field_dataset(context, solved=False)
        playback_events = field.events[playback_rows(field.events)].reset_index(drop=True)
        mic_ids = (
            mics_table["mic_id"].astype(str).tolist()
            if mics_table is not None and "mic_id" in mics_table and len(mics_table) == site.n_mics
            else [str(m) for m in range(site.n_mics)]
        )
        check_positions(field.events, site)
        log.info("calibrating %d mics from %d playbacks", site.n_mics, len(playback_events))
        warn_if_one_playback_per_spot(playback_events)
        peak_ratio = second_peak_ratio(field.features, field.events, site)
        warn_if_tonal(peak_ratio)

        def calibrated(features: pd.DataFrame) -> tuple[ArrayCalibration, Playbacks]:
            # the field sources fill each event's weather (their defaults where a table has none)
            return calibrate_playbacks(
                features,
                field.events,
                site,
                lambda p: self.calibrate(p, priors, mic_ids),
                anneal=lambda p, lags, heights: self.annealed_prediction(p, lags, heights, priors),
            )

        calibration, playbacks = calibrated(field.features)
        unheard = unheard_mics(calibration, mic_ids)
        if unheard:  # fitted again without them: their stated positions and clocks stay, and the file says why
            calibration, playbacks = calibrated(without_mics(field.features, site, unheard))
            unheard_mics(calibration, mic_ids)
            calibration.not_identified["unheard"] = (
                f"recorder(s) {', '.join(mic_ids[m] for m in unheard)} did not hear the playbacks: kept at their stated "
                "positions and clocks"
            )
        calibration = with_unknown_uncertainty_from_one_spot(calibration)
        held_out, jackknife, arrays = self.held_out(playbacks, priors, mic_ids, site, context.components.solver)
        calibration.extra["held_out"], calibration.extra["jackknife_sd"] = held_out, jackknife
        calibration.extra["speed_of_sound"] = speed_of_sound_summary(calibration, playbacks)
        calibration.extra["spots"] = spot_rows(playbacks)
        calibration.extra["held_out_arrays"] = arrays
        digest = write_calibration(run_dir / "calibration.json", calibration, site, playback_events)
        try:  # what localize will check when it reads the file, checked before anyone can use it
            load_calibration(str(run_dir / "calibration.json"), site, quiet=True)
        except DataError as exc:
            (run_dir / "calibration.json").unlink()
            raise DataError(f"calibrate: the playbacks do not determine the array ({exc}); nothing written") from None
        metrics = {
            "calibration": calibration_metrics(calibration, run_dir / "calibration.json", digest, peak_ratio),
            **context.settings.record,
        }
        write_metrics(run_dir, metrics)
        log_calibration(calibration)
        if context.settings.plots:
            from acoustlab.reporting.plots import write_calibration_plot  # matplotlib only when plotting

            write_calibration_plot(
                calibration, residual_rows(calibration, playback_events), playbacks.source_m, site, run_dir / "calibration.png"
            )
        log.info(
            "calibration written to %s (use it: localize … calibration=%s)", run_dir / "calibration.json", run_dir / "calibration.json"
        )
        return metrics

    def priors(self, site: Site, mics_table: pd.DataFrame | None) -> Priors:
        """The stated array: the site's mics, their GPS error from the mics table's ``position_sigma_m`` where given."""
        given = mic_position_sigmas(mics_table, site.n_mics)
        sigma = np.full(site.n_mics, self.position_sigma_m) if given is None else given
        return Priors(site.mic_positions_m, sigma, self.temperature_sigma_c, self.clock_sigma_s, self.drift_sigma)

    def calibrate(self, playbacks: Playbacks, priors: Priors, mic_ids: list[str]) -> ArrayCalibration:
        """The calibration from every playback."""
        return calibrate_array(
            playbacks, priors, mic_ids, self.estimate, min_drift_span_s=self.min_drift_span_s, reflection_band_hz=self.reflection_band_hz
        )

    def annealed_prediction(
        self, playbacks: Playbacks, candidate_lags_s: np.ndarray, candidate_heights: np.ndarray | None, priors: Priors
    ) -> np.ndarray:
        """(N, M) t_m − t_0 of the array that best explains every pair's GCC candidates (``annealed_prediction_s``), s."""
        return annealed_prediction_s(
            playbacks,
            candidate_lags_s,
            priors,
            self.estimate,
            min_drift_span_s=self.min_drift_span_s,
            candidate_heights=candidate_heights,
        )

    def held_out(
        self, playbacks: Playbacks, priors: Priors, mic_ids: list[str], site: Site, solver: Any
    ) -> tuple[dict[str, Any] | None, dict[str, Any] | None, list[dict[str, Any]]]:
        """Errors of each spot's playbacks solved with the array calibrated without that spot, and with the stated array, m;
        the estimates' jackknife standard deviations over those calibrations (``jackknife_sd``); and those calibrations
        themselves with the spots each was fitted without (``held_out_arrays``: ``localize`` solves a radii calibration
        playback with the array fitted without its spot, so the radii see the array's error at a spot it was not fitted
        on). None, None, [] with fewer than 4 spots or ``held_out_folds=0``.

        The calibrated array is measured on the held-out playbacks' GCC peaks nearest the lags it
        predicts at their spots (where the playbacks carry their candidates), the stated array on the
        full calibration's picks (the direct paths where that calibration is right: its figure is the
        stated geometry's error alone, not that of the echoes it would pick).

        Beside the fixes' errors, the median |residual| of the held-out playbacks' time differences
        (``median_abs_residual_ms``): what the array predicts at a spot it was not fitted on, free of
        the fix's geometry. A fix outside a 3-mic array magnifies a small error of the array many
        times, so with few spots the fixes' errors can grow where the time differences shrink.
        """
        spots = np.unique(playbacks.spot)
        if self.held_out_folds == 0 or spots.size < 4:
            return None, None, []
        folds = np.array_split(np.random.default_rng(0).permutation(spots), min(self.held_out_folds, spots.size))
        stated = np.full(len(playbacks.spot), np.nan)
        calibrated = np.full(len(playbacks.spot), np.nan)
        residual = {"stated": np.full(playbacks.tdoa_s.shape, np.nan), "calibrated": np.full(playbacks.tdoa_s.shape, np.nan)}
        without: list[ArrayCalibration] = []
        arrays: list[dict[str, Any]] = []

        def fit(p: Playbacks) -> ArrayCalibration:
            return self.calibrate(p, priors, mic_ids)

        for held in folds:
            test = np.isin(playbacks.spot, held)
            tested = playbacks.subset(test)
            kept = playbacks.subset(~test)
            # the same estimator, rounds of re-picking included: a jackknife of another measures that one
            cal = fit(kept) if kept.candidates_s is None else calibrate_until_picks_hold(kept, fit, quiet=True)[0]
            without.append(cal)
            arrays.append(held_out_array(cal, [str(spot) for spot in held]))
            stated[test] = _solve_errors(tested, site.mic_positions_m, np.zeros(site.n_mics), 0.0, site, solver)
            residual["stated"][test] = tested.pair_differences_s(tested.travel_times_s(site.mic_positions_m)) - tested.tdoa_s
            predicted = cal.predicted_tdoa_s(tested)  # of the spots, weather and times: the same whichever peaks are picked
            # the held-out spot's peaks as this calibration picks them: the full calibration's picks were made knowing that spot
            if tested.candidates_s is not None:
                tested = tested.picked(predicted)
            clock = clock_errors_s(cal.clock_offset_s, cal.clock_drift, cal.drift_origin_s, tested.time_s)
            calibrated[test] = _solve_errors(tested, cal.mic_positions_m, clock, cal.temperature_offset_c, site, solver)
            residual["calibrated"][test] = tested.pair_differences_s(predicted) - tested.tdoa_s

        def summary(e: np.ndarray, r: np.ndarray) -> dict[str, float | None]:
            e = np.where(np.isfinite(e), e, np.inf)
            r = np.abs(r[np.isfinite(r)])
            return {
                "p50_m": float(np.median(e)),
                "p95_m": float(np.quantile(e, 0.95)),
                "share_gt_1m": float(np.mean(e > 1.0)),
                "median_abs_residual_ms": float(1e3 * np.median(r)) if r.size else None,
            }

        held_out = {
            "n_playbacks": int(len(stated)),
            "n_spots": int(spots.size),
            "stated": summary(stated, residual["stated"]),
            "calibrated": summary(calibrated, residual["calibrated"]),
        }
        return held_out, jackknife_sd(without), arrays


def _band(band: list[float] | tuple[float, float]) -> tuple[float, float]:
    """``protocol.reflection_band_hz`` checked as every config range is (``require_range``), and not empty, Hz."""
    low, high = require_range("protocol.reflection_band_hz", band, lower=0.0)
    if low == high:
        raise ConfigError(f"protocol.reflection_band_hz must be [low, high] in Hz with low < high; got {band}")
    return low, high


def held_out_array(calibration: ArrayCalibration, spots: list[str]) -> dict[str, Any]:
    """The array, clocks and thermometer offset of a calibration fitted without ``spots`` (position ids), for
    ``calibration.json``'s ``held_out_arrays``."""
    return {
        "without_spots": spots,
        "mic_positions_m": np.round(calibration.mic_positions_m, 6).tolist(),
        "temperature_offset_c": float(calibration.temperature_offset_c),
        "clock_offset_s": calibration.clock_offset_s.tolist(),
        "clock_drift_s_per_s": calibration.clock_drift.tolist(),
        "drift_origin_s": float(calibration.drift_origin_s),
    }


def spot_rows(playbacks: Playbacks) -> list[dict[str, Any]]:
    """One row per playback spot: its position id and surveyed position, m (``calibration.json``'s ``spots``)."""
    rows = []
    for spot in np.unique(playbacks.spot):
        x, y, z = playbacks.source_m[np.flatnonzero(playbacks.spot == spot)[0]]
        rows.append({col.POSITION_ID: str(spot), col.TRUE_X: float(x), col.TRUE_Y: float(y), col.TRUE_Z: float(z)})
    return rows


def jackknife_sd(without: list[ArrayCalibration]) -> dict[str, Any]:
    """Delete-group jackknife standard deviations of the estimates from the G calibrations each without one group of spots.

    sd² = (G − 1)/G · Σ_g (θ_(−g) − mean θ_(−·))² (Efron & Stein 1981; the grouped form for spots held out in groups).
    Mic positions: per axis, the root mean square over x and y as ``mic_position_sd_m``.
    """
    g = len(without)

    def sd(values: np.ndarray) -> np.ndarray:
        return np.sqrt((g - 1) / g * ((values - values.mean(axis=0)) ** 2).sum(axis=0))

    mics = sd(np.array([c.mic_positions_m[:, :2] for c in without]))  # (M, 2)
    return {
        "n_groups": g,
        "mic_position_sd_m": np.round(np.sqrt((mics**2).mean(axis=1)), 6).tolist(),
        "temperature_offset_sd_c": float(sd(np.array([c.temperature_offset_c for c in without]))),
        "clock_offset_sd_s": sd(np.array([c.clock_offset_s for c in without])).tolist(),
        "clock_drift_sd_s_per_s": sd(np.array([c.clock_drift for c in without])).tolist(),
    }


def _solve_errors(
    p: Playbacks, mics_m: np.ndarray, clock_s: np.ndarray, temperature_offset_c: float, site: Site, solver: Any
) -> np.ndarray:
    """(N,) 2-D errors of the solver's fixes of playbacks ``p`` with the given array, clocks ((N, M) or (M,)) and thermometer offset, m.

    The solver gets the time differences to mic 0 (the pairs (0, m)), as it would from a detection.
    """
    reference = p.reference_tdoa_s(site.n_mics)
    clock = np.broadcast_to(clock_s, reference.shape)
    tdoa = reference - (clock - clock[:, :1])
    speed = speed_of_sound_m_s(p.temperature_c + temperature_offset_c, p.relative_humidity_pct)
    result = solver.solve(
        SolverInputs(
            mic_positions_m=mics_m, tdoa_s=np.nan_to_num(tdoa), speed_of_sound_m_s=speed, source_height_m=assumed_source_height_m(site)
        )
    )
    return np.hypot(*(np.asarray(result.position_m, dtype=float)[:, :2] - p.source_m[:, :2]).T)


def residual_rows(calibration: ArrayCalibration, events: pd.DataFrame) -> pd.DataFrame:
    """One row per playback and mic pair: its time difference's residual before and after calibration, s (for the plot)."""
    names = [f"{calibration.mic_ids[i]}-{calibration.mic_ids[j]}" for i, j in calibration.pairs]
    rows = []
    for k, (eid, spot) in enumerate(zip(events[col.EVENT_ID], calibration.spot, strict=True)):
        for p, name in enumerate(names):
            rows.append((eid, spot, name, calibration.residual_before_s[k, p], calibration.residual_after_s[k, p]))
    return pd.DataFrame(rows, columns=[col.EVENT_ID, col.POSITION_ID, "mic_pair", "residual_before_s", "residual_after_s"])


def calibrate_playbacks(
    features: pd.DataFrame,
    events: pd.DataFrame,
    site: Site,
    fit: Callable[[Playbacks], ArrayCalibration],
    temperature_c: float = 15.0,
    humidity_pct: float = 60.0,
    max_rounds: int = 30,
    anneal: Callable[[Playbacks, np.ndarray, np.ndarray | None], np.ndarray] | None = None,
) -> tuple[ArrayCalibration, Playbacks]:
    """Calibrate, re-pick each pair's GCC candidate with what the calibration predicts, and calibrate again until the picks hold.

    The rounds are ``calibrate_until_picks_hold``'s: a stated array metres off predicts lags far
    enough off that the first picks take an echo on most pairs. From few spots the rounds can
    settle on picks that are wrong but agree with each other, so they run from three starts — the
    peaks nearest the stated array's lags, the highest peaks and, with ``anneal``, the peaks
    nearest the lags of the array that explains all candidates at once
    (``acoustlab.toolkit.array_calibration.annealed_prediction_s``) — and the calibration whose
    time differences fit their picks more tightly (smaller robust timing σ) is kept. ``fit`` is the
    calibration (``CalibrateProtocol.calibrate``), ``anneal`` that search
    (``CalibrateProtocol.annealed_prediction``: playbacks, their (N, P, K) candidate lags and the
    candidates' GCC peak heights, None without the ``xcorr`` feature group).
    """
    strongest = playbacks_from(features, events, site, temperature_c, humidity_pct, strongest=True)
    starts = {
        "the stated array's lags": strongest.picked(strongest.travel_times_s(site.mic_positions_m)),
        "the highest GCC peaks": strongest,
    }
    if anneal is not None:
        heights = pair_candidate_weights(features[playback_rows(events)], site, strongest.candidates_s.shape[2])
        if heights is None:
            log.info(
                "calibrate: the features have no GCC peak heights (the 'xcorr' group); the annealed search weighs each pair's candidates equally"
            )
        starts["the annealed search over all candidates"] = strongest.picked(anneal(strongest, strongest.candidates_s, heights))
    results = {name: calibrate_until_picks_hold(first, fit, max_rounds) for name, first in starts.items()}
    best = min(results, key=lambda name: results[name][0].timing_sigma_s)  # ties: the first (the stated array's)
    log.info(
        "calibrate: kept the picks started from %s (timing sigma %s)",
        best,
        ", ".join(f"{1e6 * cal.timing_sigma_s:.0f} us from {name}" for name, (cal, _) in results.items()),
    )
    return results[best]
