"""A field calibration as a file: made from playbacks (``acoustlab calibrate``), applied to later recordings.

``calibration.json`` holds the calibrated array (``acoustlab.toolkit.array_calibration``): mic
positions, the thermometer's offset, each recorder's clock offset and drift, their covariance, and
every playback's residuals before and after. ``calibration=PATH`` in ``localize`` and ``season``:

* the site's mics move to their calibrated positions (the simulation the method learns from then
  has the real array too);
* every detection's temperature gets the thermometer's offset (so its speed of sound is the one the
  playbacks measured);
* every measured time difference loses the recorders' clock offsets (and drifts, at the
  detection's ``time_s``, else its ``start_s``);
* the calibration's remaining uncertainty becomes the input errors of the radii (in place of
  ``conformal.input_uncertainty``): its posterior covariance, each estimate's variance raised to
  the jackknife's over spots where that is larger, correlations kept
  (``acoustlab.toolkit.input_uncertainty.CorrelatedInputErrors``). A recorder's clock and its
  distance to the spots trade off; carried as independent errors they would count twice what the
  playbacks tie down. The thermometer's variance also carries how far its error varied from
  playback to playback about the one offset (``temperature_call_sd_c``): a season's calls meet the
  air as the playbacks did, not at one fixed error. Where drift was estimated, its covariance with
  the rest comes too, and a call's clock errors grow with its time since the drift's origin (a
  drift from playbacks an hour apart, extrapolated over weeks, can be milliseconds off). Where it
  was not, the recorders are taken not to drift, and nothing is carried for it.

The file is JSON (nothing in it can run code) and carries the SHA-256 of its content, which a run
records in ``metrics.json`` and ``positions.csv``; a file edited by hand fails the check.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import DataError
from acoustlab.core.files import atomic_write_bytes
from acoustlab.core.types import Site
from acoustlab.stages.solver_columns import (
    add_solver_columns,
    drop_weakly_correlated_mics,
    events_dropped_mask,
    mics_used,
    pair_candidate_lags,
    pair_candidate_weights,
    solve_events,
)
from acoustlab.toolkit.array_calibration import ArrayCalibration, Playbacks
from acoustlab.toolkit.event_physics import assumed_source_height_m
from acoustlab.toolkit.input_uncertainty import CorrelatedInputErrors
from acoustlab.toolkit.physics import speed_of_sound_m_s
from acoustlab.toolkit.recorder_clocks import clock_errors_s

log = logging.getLogger(__name__)

#: Largest calibration file read, bytes (a calibration of 100 mics and 10⁴ playbacks is far smaller).
MAX_FILE_BYTES = 64 * 2**20
FORMAT = "acoustlab-calibration/1"
#: Column of positions.csv naming the calibration a detection was placed with.
CALIBRATION_COLUMN = "calibration_sha256"


def event_time_s(events: pd.DataFrame) -> np.ndarray:
    """(E,) when each event happened, s: ``time_s`` where given, else ``start_s`` (drift is per second of it), else NaN."""
    for name in ("time_s", col.START):
        if name in events:
            return pd.to_numeric(events[name], errors="coerce").to_numpy(float)
    return np.full(len(events), np.nan)


def playback_rows(events: pd.DataFrame) -> np.ndarray:
    """(E,) True for the playbacks: events with a known position (``x_m, y_m``) whose clips are usable."""
    known = np.isfinite(events[[col.TRUE_X, col.TRUE_Y]].to_numpy(float)).all(axis=1)
    if "quality_ok" in events:
        known &= events["quality_ok"].fillna(True).to_numpy(bool)
    return known


def playbacks_from(
    features: pd.DataFrame,
    events: pd.DataFrame,
    site: Site,
    temperature_c: float,
    humidity_pct: float,
    strongest: bool = False,
) -> Playbacks:
    """The playbacks (events with a known ``x_m, y_m``), every mic pair's GCC candidates and one pick per pair.

    Per pair, of its GCC candidates the one closest to the lag the stated array predicts from the
    known spot is picked (the strongest peak may be an echo; the spot says where the direct path
    must be); with ``strongest`` the highest GCC peak instead. Later picks come from
    ``Playbacks.picked``. ``z_m`` where given, else the site's assumed source height.
    """
    known = playback_rows(events)
    if known.sum() == 0:
        raise DataError("calibrate: no event has a known position (x_m, y_m) and usable clips: playbacks at known spots are needed")
    ev = events[known].reset_index(drop=True)
    lags = pair_candidate_lags(features[known], site)  # (N, P, K), t_j − t_i of every pair's candidates
    if lags is None:
        raise DataError(f"calibrate: the features lack {col.tdoa_lag(0, 1)}; the 'tdoa' feature group is needed")
    z = ev[col.TRUE_Z].to_numpy(float) if col.TRUE_Z in ev else np.full(len(ev), np.nan)
    source = np.column_stack([ev[[col.TRUE_X, col.TRUE_Y]].to_numpy(float), np.where(np.isfinite(z), z, assumed_source_height_m(site))])
    temperature = ev[col.TEMPERATURE].fillna(temperature_c).to_numpy(float) if col.TEMPERATURE in ev else np.full(len(ev), temperature_c)
    humidity = ev[col.HUMIDITY].fillna(humidity_pct).to_numpy(float) if col.HUMIDITY in ev else np.full(len(ev), humidity_pct)
    spot_sigma = np.nan_to_num(ev[col.POSITION_SIGMA].to_numpy(float), nan=0.0) if col.POSITION_SIGMA in ev else None
    playbacks = Playbacks(
        source,
        lags[:, :, 0],
        temperature,
        humidity,
        event_time_s(ev),
        ev[col.POSITION_ID].to_numpy(),
        list(site.mic_pairs),
        lags,
        spot_sigma,
    )
    if strongest:
        return playbacks
    return playbacks.picked(playbacks.travel_times_s(site.mic_positions_m))


def second_peak_ratio(features: pd.DataFrame, events: pd.DataFrame, site: Site) -> float | None:
    """Median over the playbacks' mic pairs of the second-highest GCC candidate's height over the highest (None without
    the ``xcorr`` group's heights).

    A tonal playback (a song) correlates with itself one period apart, so most pairs have a second
    peak almost as high as the first; the sweep's second peak is a reflection or an echo, lower
    (the measured ranges: docs/calibrate.md). From few spots the fit can take the neighbouring
    peaks (``acoustlab.toolkit.playback_signal``).
    """
    known = playback_rows(events)
    lags = pair_candidate_lags(features[known], site)
    heights = None if lags is None or lags.shape[2] < 2 else pair_candidate_weights(features[known], site, lags.shape[2])
    if heights is None:
        return None
    ranked = -np.sort(-heights, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = ranked[:, :, 1] / ranked[:, :, 0]
    return float(np.nanmedian(ratio)) if np.isfinite(ratio).any() else None


def _digest(body: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def write_calibration(path: Path, calibration: ArrayCalibration, site: Site, events: pd.DataFrame) -> str:
    """Write ``calibration.json`` (atomically) and return its SHA-256; ``events`` are the playbacks' rows (ids for the residuals).

    Each playback's residuals are per mic pair, in the order of the file's ``pairs``.
    """
    body = {
        "format": FORMAT,
        "site": site.name,
        "stated_mic_positions_m": np.round(site.mic_positions_m, 6).tolist(),
        **calibration.to_json(),
        "playbacks": [
            {
                col.EVENT_ID: str(eid),
                col.POSITION_ID: str(spot),
                "residual_before_s": [None if not np.isfinite(v) else float(v) for v in before],
                "residual_after_s": [None if not np.isfinite(v) else float(v) for v in after],
            }
            for eid, spot, before, after in zip(
                events[col.EVENT_ID], calibration.spot, calibration.residual_before_s, calibration.residual_after_s, strict=True
            )
        ],
    }
    digest = _digest(body)
    atomic_write_bytes(path, json.dumps({**body, "sha256": digest}, indent=1).encode())
    return digest


#: A field event lies at a playback spot when its known position is within this of the spot's, m.
SPOT_MATCH_M = 0.5


@dataclasses.dataclass(frozen=True)
class HeldOutArray:
    """The calibration refitted without some playback spots (one entry of ``calibration.json``'s ``held_out_arrays``)."""

    #: indices into ``FieldCalibration.spots_m`` of the spots it was fitted without
    spot_indices: np.ndarray
    mic_positions_m: np.ndarray
    temperature_offset_c: float
    clock_offset_s: np.ndarray
    clock_drift: np.ndarray
    drift_origin_s: float


def _held_out_arrays(body: dict[str, Any], spot_ids: list[str], mics_shape: tuple[int, ...]) -> tuple[HeldOutArray, ...]:
    """``calibration.json``'s ``held_out_arrays``, each checked against the file's spots and its array's shape."""
    arrays = []
    for k, entry in enumerate(body.get("held_out_arrays") or []):
        missing = [spot for spot in entry["without_spots"] if spot not in spot_ids]
        mics = np.asarray(entry["mic_positions_m"], dtype=float)
        if missing or mics.shape != mics_shape:
            raise ValueError(f"held_out_arrays[{k}]")
        arrays.append(
            HeldOutArray(
                spot_indices=np.array([spot_ids.index(spot) for spot in entry["without_spots"]], dtype=int),
                mic_positions_m=mics,
                temperature_offset_c=float(entry["temperature_offset_c"]),
                clock_offset_s=np.asarray(entry["clock_offset_s"], dtype=float),
                clock_drift=np.asarray(entry["clock_drift_s_per_s"], dtype=float),
                drift_origin_s=float(entry["drift_origin_s"]),
            )
        )
    return tuple(arrays)


@dataclasses.dataclass(frozen=True)
class FieldCalibration:
    """A loaded ``calibration.json``: what ``apply_calibration`` and ``calibrated_site`` need.

    Each ``*_sd_*`` is the larger of the posterior standard deviation and the jackknife one over
    spots (``jackknife_sd``, where the file has it): what the calibration leaves uncertain.
    """

    path: str
    sha256: str
    mic_positions_m: np.ndarray
    temperature_offset_c: float
    temperature_offset_sd_c: float
    clock_offset_s: np.ndarray
    clock_offset_sd_s: np.ndarray
    clock_drift: np.ndarray
    drift_origin_s: float
    clock_drift_sd: np.ndarray
    mic_position_sd_m: np.ndarray
    n_spots: int
    not_identified: dict[str, str]
    #: the estimated parameters' names (``ArrayCalibration.parameters``) and their posterior covariance
    parameters: tuple[str, ...] = ()
    covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))
    #: ``calibrate``'s count of independent time differences per unknown (``array_calibration.redundancy``); None in older files
    redundancy: dict[str, Any] | None = None
    #: the thermometer error's spread from playback to playback about its offset, °C (``playback_temperature_spread_c``)
    temperature_call_sd_c: float = 0.0
    #: (S, 2) surveyed x, y of the playback spots the calibration was fitted on, m; None in files made before it was written
    spots_m: np.ndarray | None = None
    #: the calibration refitted without some spots, one per group of spots (``calibrate``'s ``held_out_arrays``)
    held_out: tuple[HeldOutArray, ...] = ()

    def held_out_group(self, events: pd.DataFrame) -> np.ndarray:
        """(E,) for each event at one of the calibration's spots, the index in ``held_out`` of the calibration fitted
        without that spot; −1 for the other events.

        An event is at a spot when its known position (``x_m, y_m``) lies within ``SPOT_MATCH_M`` of
        it. One line warns where events lie at the calibration's spots and no held-out calibration
        exists for them: their fixes, and radii calibrated on them, rest on an array fitted on them.
        """
        group = np.full(len(events), -1)
        if self.spots_m is None or len(self.spots_m) == 0 or col.TRUE_X not in events or col.TRUE_Y not in events:
            return group
        known = events[[col.TRUE_X, col.TRUE_Y]].to_numpy(float)
        offset = known[:, None, :] - self.spots_m[None, :, :]  # (E, S, 2)
        distance = np.nan_to_num(np.hypot(offset[..., 0], offset[..., 1]), nan=np.inf)  # unknown positions: at no spot
        nearest = distance.argmin(axis=1)
        at_spot = distance.min(axis=1) <= SPOT_MATCH_M
        for k, held in enumerate(self.held_out):
            group[at_spot & np.isin(nearest, held.spot_indices)] = k
        leaked = at_spot & (group < 0)
        if leaked.any():
            log.warning(
                "calibration=%s: %d event(s) at %d of its playback spots have no calibration fitted without their spot "
                "(calibrate with >= 4 spots and protocol.held_out_folds > 0): they are solved with an array fitted on them, "
                "and radii calibrated on them are too small",
                self.path,
                int(leaked.sum()),
                int(np.unique(nearest[leaked]).size),
            )
        return group

    def without_spots(self, k: int) -> FieldCalibration:
        """This calibration with the array, clocks and thermometer offset of ``held_out[k]`` (fitted without its spots);
        the uncertainties stay the full calibration's."""
        held = self.held_out[k]
        return dataclasses.replace(
            self,
            mic_positions_m=held.mic_positions_m,
            temperature_offset_c=held.temperature_offset_c,
            clock_offset_s=held.clock_offset_s,
            clock_drift=held.clock_drift,
            drift_origin_s=held.drift_origin_s,
            held_out=(),
        )

    def summary(self) -> dict[str, Any]:
        """For metrics.json: where it came from and what it changed."""
        return {
            "path": self.path,
            "sha256": self.sha256,
            "n_spots": self.n_spots,
            "temperature_offset_c": self.temperature_offset_c,
            "clock_offset_s": self.clock_offset_s.tolist(),
            "mic_positions_m": np.round(self.mic_positions_m, 4).tolist(),
            "not_identified": self.not_identified,
            "redundancy": self.redundancy,
        }

    def input_uncertainty(self, assumed_temperature_sd_c: float = 0.0) -> CorrelatedInputErrors:
        """What the calibration leaves uncertain, as the radii's input errors (module docstring).

        The posterior covariance, each row and column scaled so that its standard deviation is the
        larger of the posterior's and the jackknife's (a mic's x and y by one factor, the jackknife
        being per mic); parameters not estimated are independent at their prior's. The
        thermometer's variance then gains the playbacks' spread about its offset
        (``temperature_call_sd_c``²): each call's own error, independent of the rest, and
        ``assumed_temperature_sd_c``² (°C) where the calls' temperature is assumed rather than read
        (a season). Where drift was estimated, the clocks' drifts follow the mics'
        (``CorrelatedInputErrors.drifts``).
        """
        m = len(self.mic_positions_m)
        names = ["temperature_offset_c", *(f"clock_{k}_s" for k in range(m)), *(f"mic_{k}_{axis}_m" for k in range(m) for axis in "xy")]
        drifts = any(name.startswith("drift_") for name in self.parameters)
        names += [f"drift_{k}" for k in range(m)] if drifts else []
        index = np.array([self.parameters.index(name) if name in self.parameters else -1 for name in names])
        estimated = np.flatnonzero(index >= 0)
        covariance = np.zeros((len(names), len(names)))
        covariance[np.ix_(estimated, estimated)] = self.covariance[np.ix_(index[estimated], index[estimated])]
        posterior = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
        per_mic = np.sqrt((posterior[1 + m : 1 + 3 * m : 2] ** 2 + posterior[2 + m : 1 + 3 * m : 2] ** 2) / 2)
        posterior = np.r_[posterior[: 1 + m], np.repeat(per_mic, 2), posterior[1 + 3 * m :]]
        larger = np.r_[
            self.temperature_offset_sd_c,
            self.clock_offset_sd_s,
            np.repeat(self.mic_position_sd_m, 2),
            self.clock_drift_sd if drifts else [],
        ]
        scale = np.divide(larger, posterior, out=np.zeros_like(larger), where=posterior > 0)
        covariance *= np.outer(scale, scale)
        loose = posterior <= 0  # not estimated: independent, at the prior's standard deviation
        covariance[loose, :], covariance[:, loose] = 0.0, 0.0
        covariance[loose, loose] = larger[loose] ** 2
        covariance[0, 0] += self.temperature_call_sd_c**2 + assumed_temperature_sd_c**2
        return CorrelatedInputErrors(covariance, drifts=drifts, drift_origin_s=self.drift_origin_s)


def load_calibration(path_text: str, site: Site, quiet: bool = False) -> FieldCalibration:
    """Read and check ``calibration.json`` for ``site`` (one line naming the file and the problem on any fault).

    ``quiet`` leaves out the warnings for a run that uses it (``calibrate`` checks the file it has just written).
    """
    path = Path(path_text).expanduser()
    where = f"calibration={path_text}"
    if not path.is_file():
        raise DataError(f"{where}: no such file (make one with: python -m acoustlab calibrate +site=NAME field=recordings …)")
    if path.stat().st_size > MAX_FILE_BYTES:
        raise DataError(f"{where}: {path.stat().st_size} bytes is larger than a calibration file can be ({MAX_FILE_BYTES} bytes)")
    try:
        body = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise DataError(f"{where}: not a JSON file: {exc}") from None
    except RecursionError:
        raise DataError(f"{where}: nested deeper than any calibration is (not an acoustlab calibration)") from None
    if not isinstance(body, dict) or body.get("format") != FORMAT:
        raise DataError(f"{where}: not an acoustlab calibration (format {FORMAT!r} expected)")
    stated = body.pop("sha256", None)
    if stated != _digest(body):
        raise DataError(f"{where}: its content does not match its sha256 (edited after it was written?); run calibrate again")
    try:
        mics = np.asarray(body["mic_positions_m"], dtype=float)
        jackknife = body.get("jackknife_sd") or {}

        def sd(name: str) -> np.ndarray:  # the posterior's, or the jackknife's over spots where larger
            posterior = np.asarray(body[name], dtype=float)
            return np.maximum(posterior, np.asarray(jackknife[name], dtype=float)) if name in jackknife else posterior

        out = FieldCalibration(
            path=str(path),
            sha256=stated,
            mic_positions_m=mics,
            temperature_offset_c=float(body["temperature_offset_c"]),
            temperature_offset_sd_c=float(sd("temperature_offset_sd_c")),
            clock_offset_s=np.asarray(body["clock_offset_s"], dtype=float),
            clock_offset_sd_s=sd("clock_offset_sd_s"),
            clock_drift=np.asarray(body["clock_drift_s_per_s"], dtype=float),
            drift_origin_s=float(body["drift_origin_s"]),
            clock_drift_sd=sd("clock_drift_sd_s_per_s"),
            mic_position_sd_m=sd("mic_position_sd_m"),
            n_spots=int(body["n_spots"]),
            not_identified=dict(body.get("not_identified", {})),
            parameters=tuple(str(name) for name in body["parameters"]),
            covariance=np.asarray(body["covariance"], dtype=float).reshape(len(body["parameters"]), len(body["parameters"])),
            redundancy=dict(body["redundancy"]) if isinstance(body.get("redundancy"), dict) else None,
            temperature_call_sd_c=float(body["temperature_call_sd_c"]),
            spots_m=np.array([[s[col.TRUE_X], s[col.TRUE_Y]] for s in body["spots"]], dtype=float).reshape(-1, 2)
            if "spots" in body
            else None,
            held_out=_held_out_arrays(body, [str(s[col.POSITION_ID]) for s in body.get("spots", [])], mics.shape),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{where}: field {exc} is missing or not a number") from None
    if mics.shape != site.mic_positions_m.shape:
        raise DataError(f"{where}: calibrates {mics.shape[0]} mics; site {site.name!r} has {site.n_mics}")
    check_values(out, body, where)
    if body.get("site") != site.name and not quiet:
        log.warning("%s was made for site %r; applying it to site %r", where, body.get("site"), site.name)
    if out.redundancy is not None and out.redundancy.get("enough") is False and not quiet:
        log.warning(
            "%s rests on %d spots, fewer than calibrate asks for (%s): its mics and clocks may rest on wrong GCC peaks",
            where,
            out.n_spots,
            out.redundancy.get("spots_needed"),
        )
    stated_mics = np.asarray(body.get("stated_mic_positions_m", mics), dtype=float)
    moved = np.abs(stated_mics - site.mic_positions_m).max()
    if moved > 1e-3:
        raise DataError(f"{where}: was made from mic positions up to {moved:.3g} m from the site's: calibrate again for this array")
    return out


#: Physical bounds of a calibration's values: (field, largest magnitude, unit, why). A file beyond them is refused.
VALUE_BOUNDS = (
    ("temperature_offset_c", 25.0, "°C", "a thermometer that far off is broken"),
    ("temperature_offset_sd_c", 25.0, "°C", "no playback leaves the thermometer that uncertain"),
    ("temperature_call_sd_c", 10.0, "°C", "the air does not vary that much between playbacks"),
    ("clock_offset_s", 1.0, "s", "beyond any lag window a playback is searched in"),
    ("clock_offset_sd_s", 1.0, "s", "beyond any lag window a playback is searched in"),
    ("clock_drift", 1e-3, "s/s", "1,000 ppm, beyond any recorder's crystal"),
    ("clock_drift_sd", 1e-3, "s/s", "1,000 ppm, beyond any recorder's crystal"),
    ("mic_position_sd_m", 50.0, "m", "beyond any GPS's error"),
)
#: A calibrated mic may lie at most this many times its stated σ (``prior_sd``) from its stated position.
MAX_SHIFT_SIGMAS = 8.0


def check_values(calibration: FieldCalibration, body: dict[str, Any], where: str) -> None:
    """Refuse, in one line naming the file and field, a calibration whose values are not finite, of the wrong shape, or
    beyond physical bounds (``VALUE_BOUNDS``; a mic moved more than ``MAX_SHIFT_SIGMAS`` of its stated σ).

    The file's digest proves only that it was not edited by accident: whoever edits it can recompute it.
    """
    m = len(calibration.mic_positions_m)
    if not np.isfinite(calibration.mic_positions_m).all():
        raise DataError(f"{where}: field mic_positions_m holds a value that is not finite")
    for name, bound, unit, why in VALUE_BOUNDS:
        value = np.atleast_1d(np.asarray(getattr(calibration, name), dtype=float))
        if value.ndim != 1 or (value.size != m and value.size != 1):
            raise DataError(f"{where}: field {name} has {value.size} values; {m} (one per mic) or 1 expected")
        if not np.isfinite(value).all():
            raise DataError(f"{where}: field {name} holds a value that is not finite")
        if np.abs(value).max() > bound:
            raise DataError(f"{where}: field {name} = {np.abs(value).max():.6g} {unit} in size, beyond {bound:g} {unit} ({why})")
    if (calibration.temperature_offset_sd_c < 0) or (calibration.mic_position_sd_m < 0).any() or (calibration.clock_offset_sd_s < 0).any():
        raise DataError(f"{where}: a standard deviation is negative")
    if not np.isfinite(calibration.covariance).all():
        raise DataError(f"{where}: field covariance holds a value that is not finite")
    for k in range(len(calibration.held_out)):  # the refits without some spots are used as the file's own values are
        check_values(calibration.without_spots(k), body, f"{where}: held_out_arrays[{k}]")
    prior = dict(zip(calibration.parameters, np.asarray(body.get("prior_sd", []), dtype=float), strict=False))
    stated = np.asarray(body.get("stated_mic_positions_m", calibration.mic_positions_m), dtype=float)
    shift = np.hypot(*(calibration.mic_positions_m - stated)[:, :2].T)
    for k in range(m):
        sigma = max(prior.get(f"mic_{k}_x_m", np.inf), prior.get(f"mic_{k}_y_m", np.inf))
        if shift[k] > MAX_SHIFT_SIGMAS * sigma + 1e-6:
            raise DataError(
                f"{where}: field mic_positions_m moves mic {k} {shift[k]:.3g} m from its stated position, beyond "
                f"{MAX_SHIFT_SIGMAS:g} × its stated σ ({sigma:.3g} m)"
            )


def calibrated_site(site: Site, calibration: FieldCalibration) -> Site:
    """The site with its mics at their calibrated positions."""
    return dataclasses.replace(site, mic_positions_m=calibration.mic_positions_m.copy())


def field_solver_columns(
    features: pd.DataFrame,
    events: pd.DataFrame,
    site: Site,
    solver: Any,
    plausible_margin_fraction: float | None,
    calibration: FieldCalibration | None,
    min_gcc_peak: float | None = None,
    min_gcc_peak_relative: float | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The solver stage of field recordings (``localize`` and every season chunk alike): the calibration, then the solver's columns.

    ``min_gcc_peak`` (``features.gcc.min_peak``): a mic without a GCC peak that high with any other
    mic is left out of its event's solve (``drop_weakly_correlated_mics``), as is one below
    ``min_gcc_peak_relative`` (``features.gcc.min_peak_relative``) × its event's strongest pair peak; None keeps every mic.
    """
    if min_gcc_peak is not None or min_gcc_peak_relative is not None:
        events = drop_weakly_correlated_mics(features, events, site, min_gcc_peak, min_gcc_peak_relative)
    group = calibration.held_out_group(events) if calibration is not None else np.full(len(events), -1)
    if (group < 0).all():
        return _solved(features, events, site, solver, plausible_margin_fraction, calibration)
    # an event at a playback spot is solved with the array calibrated without that spot: its fix (and radii calibrated
    # on it) then carries the array's error at a spot the array was not fitted on, as a new call's does
    parts, order = [], []
    for k in np.unique(group):
        rows = np.flatnonzero(group == k)
        used = calibration if k < 0 else calibration.without_spots(int(k))
        parts.append(_solved(features.iloc[rows], events.iloc[rows], calibrated_site(site, used), solver, plausible_margin_fraction, used))
        order.append(rows)
    back = np.argsort(np.concatenate(order), kind="stable")
    return tuple(pd.concat([part[i] for part in parts]).iloc[back] for i in (0, 1))  # type: ignore[return-value]


def _solved(
    features: pd.DataFrame,
    events: pd.DataFrame,
    site: Site,
    solver: Any,
    plausible_margin_fraction: float | None,
    calibration: FieldCalibration | None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Features with the solver's columns and events with ``mics_used``, the calibration's clocks and thermometer applied."""
    if calibration is not None:  # the thermometer's offset and the recorders' clocks, before the solver
        features, events = apply_calibration(features, events, site, calibration)
    result = solve_events(features, events, site, solver)
    features = add_solver_columns(features, events, site, solver, plausible_margin_fraction, result=result)
    return features, events.assign(**{col.MICS_USED: mics_used(result, events_dropped_mask(events, site))})


def apply_calibration(
    features: pd.DataFrame, events: pd.DataFrame, site: Site, calibration: FieldCalibration
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Field features and events with the thermometer's offset and the recorders' clocks corrected (module docstring)."""
    features, events = features.copy(), events.copy()
    if col.TEMPERATURE in events:
        events[col.TEMPERATURE] = events[col.TEMPERATURE].to_numpy(float) + calibration.temperature_offset_c
        humidity = events[col.HUMIDITY].to_numpy(float) if col.HUMIDITY in events else np.zeros(len(events))
        speed = speed_of_sound_m_s(events[col.TEMPERATURE].to_numpy(float), humidity)
        if col.SPEED_OF_SOUND in events:
            events[col.SPEED_OF_SOUND] = speed
        if col.ENV_TEMPERATURE in features:
            features[col.ENV_TEMPERATURE] = events[col.TEMPERATURE].to_numpy(float)
        if col.ENV_SPEED_OF_SOUND in features:
            features[col.ENV_SPEED_OF_SOUND] = speed
    clock = clock_errors_s(calibration.clock_offset_s, calibration.clock_drift, calibration.drift_origin_s, event_time_s(events))
    for i, j in site.mic_pairs:
        k = 1
        while col.tdoa_lag(i, j, k) in features:
            features[col.tdoa_lag(i, j, k)] = features[col.tdoa_lag(i, j, k)].to_numpy(float) - (clock[:, j] - clock[:, i])
            k += 1
    return features, events
