"""Calibrate an array from playbacks at known spots: thermometer offset, recorder clocks, mic positions.

A playback n from the surveyed spot s_n at time t_n reaches mic m at
τ_n + ‖s_n − p_m‖ / c_n + δ_m + ρ_m·t_n (τ_n the emission time, p_m the mic, c_n the speed of
sound at the event's temperature plus the thermometer's offset ΔT, δ_m and ρ_m the recorder's clock
offset and drift). The time difference of a pair (i, j) removes τ_n:

    Δ_{n,ij} = (‖s_n − p_j‖ − ‖s_n − p_i‖) / c_n + (δ_j − δ_i) + (ρ_j − ρ_i)·t_n.

Every pair measured is used, not only the pairs with mic 0: the GCC of two distant recorders often
lacks the direct path among its peaks, and each mic's neighbours then still tie it down.

Gauge: only differences of clocks are observable, so mic 0's clock is the reference (δ_0 = ρ_0 = 0).
The mic positions need no gauge: the spots are surveyed in the site's frame.

Every parameter has a prior: ΔT = 0 ± the thermometer's σ, clocks 0 ± σ, mic positions at the
table's coordinates ± their stated GPS σ (horizontal). The priors enter as Gaussian residuals, the
time differences as residuals in units of the timing noise σ_t, iteratively reweighted (Huber,
k = ``HUBER_K``, for the first pass from the stated array, then Cauchy, scale ``CAUCHY_K``, which
gives a wrong GCC peak milliseconds off next to no weight where Huber's would still pull a mic), minimised by
``scipy.optimize.least_squares``; σ_t is re-estimated from the residuals' MAD. The reweighting
repeats until the estimates hold (a pass moves none by more than ``CONVERGED_PRIORS`` of its
prior σ): each pass lowers σ_t and with it the weight of the wrong peaks, and a fit stopped after
a fixed few passes keeps centimetres of their pull (the forest from 5 spots: 5 passes left mics
up to 7 cm off where the converged fit of the same picks is within 3 cm). Written here because no library fits this model; SciPy does the solving.

What the playbacks cannot determine stays at its prior and is said plainly (``ArrayCalibration.not_identified``):
structurally (one spot cannot separate a clock from a position; positions need 3 spots not on a
line; drift needs spots spread over time) and numerically (a parameter is *identified* where the
playbacks shrink its standard deviation to at most ``IDENTIFIED_RATIO`` of its prior's).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import brentq, least_squares, minimize

from acoustlab.core.errors import DataError
from acoustlab.toolkit.ground_reflection import peak_shift_per_fraction_s, reflection_delay_s
from acoustlab.toolkit.physics import speed_of_sound_m_s
from acoustlab.toolkit.recorder_clocks import clock_errors_s, seconds_since_origin

log = logging.getLogger(__name__)

#: A parameter counts as identified where the playbacks shrink its prior standard deviation to this fraction or less.
IDENTIFIED_RATIO = 0.5
#: Huber's constant, in units of the timing noise: larger residuals are down-weighted (a wrong GCC peak, an echo).
HUBER_K = 2.5
#: Cauchy's scale, in units of the timing noise (95 % efficiency under Gaussian noise).
CAUCHY_K = 2.385
#: A calibration should rest on at least this many independent time differences per unknown: with fewer, a set of
#: wrong GCC peaks can fit as tightly as the right one (the measurements behind it: docs/calibrate_results.md).
MIN_REDUNDANCY = 2.0
#: The reweighting stops when no estimate moves by more than this fraction of its prior standard deviation in a pass.
CONVERGED_PRIORS = 1e-4
#: The largest fraction of a ground reflection's delay by which a merged GCC peak moves (two equal peaks merge halfway).
REFLECTION_FRACTION_MAX = 0.5
#: A spot's leverage in any direction is capped here in the cluster-robust σ (``by_spot_covariance``): at most a 33× residual.
MAX_LEVERAGE = 0.97
#: A residual beyond this many timing-noise units counts as an outlier in the report.
OUTLIER_K = 5.0
#: What the calibration's σ covers, in calibration.json (``sd_unit``).
SD_UNIT = (
    "each estimate's sd counts a playback's m - 1 independent time differences (not its m(m - 1)/2 pairs, which share mics), "
    "at least the cluster-robust sd by spot (a spot's playbacks share its multipath), and in a run the larger of that and the "
    "jackknife's over spots; where shared_bias is given it also carries a ground reflection within the direct path's "
    "peak, up to half its delay at every spot alike; it does not cover other biases every spot shares (e.g. a speaker "
    "stand surveyed off in the same direction everywhere); sd_over_per_pair: each sd over the posterior's with every pair "
    "independent"
)
#: The thermometer's offset is bounded to this many prior standard deviations (±30 °C for the default 3 °C).
MAX_TEMPERATURE_PRIORS = 10.0
#: The annealed search's mixture widths, s: from where every candidate within a few ms pulls (the stated array's
#: GPS error moves a pair's lag by ms) down to a clean peak's timing noise (tens of µs).
ANNEALING_WIDTHS_S = np.geomspace(2e-3, 3e-5, 10)
#: The likelihood floor of a time difference none of whose candidates is the direct path (relative to one candidate
#: at zero residual among K = 1): about what a residual of 2.8 widths costs.
ANNEALING_FLOOR = 0.02
#: Each candidate's share of its pair's mixture grows as its GCC peak height to this power (its energy share): a peak
#: that stands well above the others is the direct path far more often than not, yet a lower one must keep some pull
#: (a higher power lets one strong echo decide; docs/calibrate_results.md gives the comparison of powers).
ANNEALING_HEIGHT_POWER = 2.0
#: What can be estimated.
PARAMETER_KINDS = ("temperature", "clocks", "drift", "positions")
#: Names of the spots' position parameters (``spot_<k>_x_m``: the k-th spot in order of its first playback).
SPOT_PREFIX = "spot_"


@dataclass
class Playbacks:
    """Playbacks at known spots and their measured time differences.

    Attributes
    ----------
    source_m : numpy.ndarray
        (N, 3) surveyed playback positions, m.
    tdoa_s : numpy.ndarray
        (N, P) measured arrival-time differences t_j − t_i of ``pairs``, s (NaN where not measured).
    temperature_c, relative_humidity_pct : numpy.ndarray
        (N,) the thermometer's reading and the humidity at each playback.
    time_s : numpy.ndarray
        (N,) when each playback was made, s from any fixed origin (drift is per second of it).
    spot : numpy.ndarray
        (N,) the spot (position id) of each playback.
    pairs : list of tuple of int
        (P,) the mic pairs (i, j), i < j, of the columns of ``tdoa_s``.
    candidates_s : numpy.ndarray or None
        (N, P, K) every pair's GCC candidate lags t_j − t_i, s (NaN where fewer than K), of which
        ``tdoa_s`` holds one pick per pair; None where only the picks are known.
    source_sigma_m : numpy.ndarray or None
        (N,) the horizontal standard deviation per axis of each playback's surveyed spot, m (one
        value per spot; 0 or None: surveyed exactly). A spot off its survey moves every time
        difference of its playbacks alike; such spots' positions are estimated with the array and
        their uncertainty widens the array's (``calibrate_array``).
    """

    source_m: np.ndarray
    tdoa_s: np.ndarray
    temperature_c: np.ndarray
    relative_humidity_pct: np.ndarray
    time_s: np.ndarray
    spot: np.ndarray
    pairs: list[tuple[int, int]]
    candidates_s: np.ndarray | None = None
    source_sigma_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.pairs = [(int(i), int(j)) for i, j in self.pairs]
        index = np.array(self.pairs, dtype=int).reshape(-1, 2)
        self._first, self._second = index[:, 0], index[:, 1]
        if self.tdoa_s.shape[1:] != (len(self.pairs),):
            raise DataError(f"calibration: {self.tdoa_s.shape[1:]} time-difference columns for {len(self.pairs)} mic pairs")

    @property
    def n_spots(self) -> int:
        return int(np.unique(self.spot).size)

    def subset(self, rows: np.ndarray) -> Playbacks:
        """The playbacks of ``rows`` (a boolean mask or indices)."""
        return Playbacks(
            self.source_m[rows],
            self.tdoa_s[rows],
            self.temperature_c[rows],
            self.relative_humidity_pct[rows],
            self.time_s[rows],
            self.spot[rows],
            self.pairs,
            None if self.candidates_s is None else self.candidates_s[rows],
            None if self.source_sigma_m is None else self.source_sigma_m[rows],
        )

    def picked(self, expected_tdoa_s: np.ndarray) -> Playbacks:
        """These playbacks with each pair's candidate nearest the lag ``expected_tdoa_s`` ((N, M) t_m − t_0, s) predicts.

        NaN where a pair has no candidate. Needs ``candidates_s``.
        """
        if self.candidates_s is None:
            raise ValueError("Playbacks.picked needs the candidates (candidates_s)")
        lags = self.candidates_s
        gap = np.abs(lags - self.pair_differences_s(expected_tdoa_s)[:, :, None])
        gap = np.where(np.isfinite(gap), gap, np.inf)
        best = np.take_along_axis(lags, np.argmin(gap, axis=2)[:, :, None], axis=2)[:, :, 0]
        return dataclasses.replace(self, tdoa_s=np.where(np.isfinite(gap.min(axis=2)), best, np.nan))

    def travel_times_s(self, mics_m: np.ndarray, temperature_offset_c: float = 0.0) -> np.ndarray:
        """(N, M) travel time from each playback's spot to each mic at ``mics_m`` ((M, 3), m), s.

        At the speed of sound of the thermometer's reading plus ``temperature_offset_c`` (°C) and the humidity.
        """
        speed = speed_of_sound_m_s(self.temperature_c + temperature_offset_c, self.relative_humidity_pct)
        distance = np.sqrt(((self.source_m[:, None, :] - np.asarray(mics_m, dtype=float)[None]) ** 2).sum(-1))
        return distance / speed[:, None]

    def pair_differences_s(self, arrival_s: np.ndarray) -> np.ndarray:
        """(N, P) t_j − t_i of each pair (i, j) from (N, M) arrival times (any offset common to a row), s."""
        return arrival_s[:, self._second] - arrival_s[:, self._first]

    def reference_tdoa_s(self, n_mics: int) -> np.ndarray:
        """(N, M) time differences t_m − t_0 from the pairs (0, m) (column 0 is 0; NaN where that pair is not measured), s."""
        out = np.full((len(self.source_m), n_mics), np.nan)
        out[:, 0] = 0.0
        for k, (i, j) in enumerate(self.pairs):
            if i == 0:
                out[:, j] = self.tdoa_s[:, k]
        return out


@dataclass
class Priors:
    """What is known before the playbacks, with standard deviations.

    Attributes
    ----------
    mic_positions_m : numpy.ndarray
        (M, 3) the stated mic positions, m.
    position_sigma_m : numpy.ndarray
        (M,) their horizontal standard deviation per axis, m (0: surveyed exactly, not estimated).
    temperature_sigma_c : float
        The thermometer's error, °C.
    clock_sigma_s : float
        Clock offsets between recorders, s.
    drift_sigma : float
        Clock drift between recorders, s per s.
    """

    mic_positions_m: np.ndarray
    position_sigma_m: np.ndarray
    temperature_sigma_c: float = 3.0
    clock_sigma_s: float = 0.01
    drift_sigma: float = 1e-5


@dataclass
class ArrayCalibration:
    """The calibrated array and how well the playbacks determined it (``to_json`` for calibration.json)."""

    mic_ids: list[str]
    mic_positions_m: np.ndarray
    mic_position_shift_m: np.ndarray
    temperature_offset_c: float
    clock_offset_s: np.ndarray
    clock_drift: np.ndarray
    drift_origin_s: float
    timing_sigma_s: float
    #: parameter name → index into ``covariance``
    parameters: list[str]
    covariance: np.ndarray
    prior_sd: np.ndarray
    identified: dict[str, bool]
    not_identified: dict[str, str]
    #: (N, P) predicted − measured time difference of each playback and pair, before and after, s
    residual_before_s: np.ndarray
    residual_after_s: np.ndarray
    pairs: list[tuple[int, int]]
    spot: np.ndarray
    n_spots: int
    priors: Priors
    #: how far the thermometer's error moves from playback to playback about its calibrated offset, °C (``playback_temperature_spread_c``)
    temperature_call_sd_c: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def sd(self, name: str) -> float:
        """Posterior standard deviation of one parameter (its prior's where it was not estimated)."""
        if name in self.parameters:
            return float(np.sqrt(self.covariance[self.parameters.index(name), self.parameters.index(name)]))
        if name == "temperature_offset_c":
            return float(self.priors.temperature_sigma_c)
        if name.startswith("clock_"):
            return 0.0 if name == "clock_0_s" else float(self.priors.clock_sigma_s)
        if name.startswith("drift_"):
            return 0.0
        return float(self.priors.position_sigma_m[int(name.split("_")[1])])

    def predicted_tdoa_s(self, playbacks: Playbacks) -> np.ndarray:
        """(N, M) the time differences t_m − t_0 this calibrated array predicts for the playbacks, s (a pair (i, j): column j − column i)."""
        clock = clock_errors_s(self.clock_offset_s, self.clock_drift, self.drift_origin_s, playbacks.time_s)
        arrival = playbacks.travel_times_s(self.mic_positions_m, self.temperature_offset_c) + clock
        return arrival - arrival[:, :1]

    def position_sd_m(self) -> np.ndarray:
        """(M,) per-axis posterior standard deviation of each mic's horizontal position, m."""
        return np.array([np.sqrt((self.sd(f"mic_{m}_x_m") ** 2 + self.sd(f"mic_{m}_y_m") ** 2) / 2) for m in range(len(self.mic_ids))])

    def to_json(self) -> dict[str, Any]:
        def median_abs(r: np.ndarray) -> float | None:
            r = r[np.isfinite(r)]
            return None if r.size == 0 else float(np.median(np.abs(r)))

        return {
            "mic_ids": self.mic_ids,
            "mic_positions_m": np.round(self.mic_positions_m, 6).tolist(),
            "mic_position_shift_m": np.round(self.mic_position_shift_m, 6).tolist(),
            "mic_position_sd_m": np.round(self.position_sd_m(), 6).tolist(),
            "temperature_offset_c": self.temperature_offset_c,
            "temperature_offset_sd_c": self.sd("temperature_offset_c"),
            "temperature_call_sd_c": self.temperature_call_sd_c,
            "clock_offset_s": self.clock_offset_s.tolist(),
            "clock_offset_sd_s": [self.sd(f"clock_{m}_s") for m in range(len(self.mic_ids))],
            "clock_drift_s_per_s": self.clock_drift.tolist(),
            "clock_drift_sd_s_per_s": [0.0 if m == 0 else self.sd(f"drift_{m}") for m in range(len(self.mic_ids))],
            "drift_origin_s": self.drift_origin_s,
            "timing_sigma_s": self.timing_sigma_s,
            "parameters": self.parameters,
            "covariance": self.covariance.tolist(),
            "prior_sd": self.prior_sd.tolist(),
            "identified": self.identified,
            "not_identified": self.not_identified,
            "pairs": [list(pair) for pair in self.pairs],
            "n_playbacks": int(len(self.spot)),
            "n_spots": self.n_spots,
            "residual_median_abs_before_s": median_abs(self.residual_before_s),
            "residual_median_abs_after_s": median_abs(self.residual_after_s),
            "n_outliers": int(np.sum(np.abs(self.residual_after_s[np.isfinite(self.residual_after_s)]) > OUTLIER_K * self.timing_sigma_s)),
            **self.extra,
        }


def speed_of_sound_slope(temperature_c: np.ndarray, humidity: np.ndarray) -> np.ndarray:
    """d c / d T at each playback, m/s per °C (central difference)."""
    return (speed_of_sound_m_s(temperature_c + 0.05, humidity) - speed_of_sound_m_s(temperature_c - 0.05, humidity)) / 0.1


def redundancy(playbacks: Playbacks, n_unknowns: int) -> dict[str, Any]:
    """How many independent time differences the playbacks give per unknown, and the spots ``MIN_REDUNDANCY`` needs.

    A spot gives (mics heard there − 1) independent time differences whatever the number of its
    playbacks or pairs (repeats average the noise; they add no geometry). ``spots_needed`` assumes
    further spots heard as well as the average one.
    """
    spots = np.asarray(playbacks.spot)
    first, second = np.array(playbacks.pairs).T
    independent = 0
    for spot in np.unique(spots):
        heard = np.isfinite(playbacks.tdoa_s[spots == spot]).any(axis=0)
        independent += max(len(np.unique(np.r_[first[heard], second[heard]])) - 1, 0)
    per_spot = independent / max(len(np.unique(spots)), 1)
    return {
        "independent_time_differences": int(independent),
        "unknowns": int(n_unknowns),
        "per_unknown": round(independent / max(n_unknowns, 1), 3),
        "enough": bool(independent >= MIN_REDUNDANCY * n_unknowns),
        "spots_needed": spots_for(n_unknowns, per_spot),
    }


def spots_for(n_unknowns: int, per_spot: float) -> int | None:
    """Spots giving ``per_spot`` independent time differences each that ``MIN_REDUNDANCY`` asks for ``n_unknowns`` (None if 0)."""
    return int(np.ceil(MIN_REDUNDANCY * n_unknowns / per_spot)) if per_spot > 0 else None


def _structural_limits(playbacks: Playbacks, priors: Priors, wanted: set[str], min_drift_span_s: float) -> dict[str, str]:
    """Parameters the playbacks cannot determine whatever their values, with the reason."""
    out: dict[str, str] = {}
    spots = playbacks.n_spots
    xy = np.unique(np.round(playbacks.source_m[:, :2], 3), axis=0)
    if spots < 2:
        for kind in ("temperature", "positions", "drift"):
            if kind in wanted:
                out[kind] = (
                    "one playback spot cannot separate a recorder's clock from its position or the speed of sound; give 3 or more spots"
                )
    if "positions" in wanted and "positions" not in out:
        if len(xy) < 3 or np.linalg.matrix_rank(xy - xy.mean(axis=0), tol=1e-6 * max(1.0, np.abs(xy).max())) < 2:
            out["positions"] = f"mic positions need 3 or more playback spots not on one line (got {len(xy)})"
        elif not np.any(priors.position_sigma_m > 0):
            out["positions"] = "every mic's position_sigma_m is 0 (surveyed exactly): nothing to estimate"
    if "drift" in wanted and "drift" not in out:
        span = float(np.nanmax(playbacks.time_s) - np.nanmin(playbacks.time_s)) if np.isfinite(playbacks.time_s).any() else 0.0
        if span < min_drift_span_s:
            out["drift"] = f"the playbacks span {span:.0f} s; clock drift needs them spread over at least {min_drift_span_s:.0f} s"
    return out


class _Model:
    """Residuals and their Jacobian in normalised parameters u (θ = θ₀ + σ ⊙ u)."""

    def __init__(self, playbacks: Playbacks, priors: Priors, kinds: set[str], drift_origin_s: float) -> None:
        self.pb, self.pr = playbacks, priors
        n_mics = priors.mic_positions_m.shape[0]
        names, sd = [], []
        if "temperature" in kinds:
            names.append("temperature_offset_c")
            sd.append(priors.temperature_sigma_c)
        if "clocks" in kinds:
            names += [f"clock_{m}_s" for m in range(1, n_mics)]
            sd += [priors.clock_sigma_s] * (n_mics - 1)
        if "drift" in kinds:
            names += [f"drift_{m}" for m in range(1, n_mics)]
            sd += [priors.drift_sigma] * (n_mics - 1)
        self.moved = [m for m in range(n_mics) if priors.position_sigma_m[m] > 0] if "positions" in kinds else []
        for m in self.moved:
            names += [f"mic_{m}_x_m", f"mic_{m}_y_m"]
            sd += [float(priors.position_sigma_m[m])] * 2
        # spots surveyed with an error: nuisance parameters, estimated with the array and marginalised out of its covariance
        self.spot_rows: dict[str, np.ndarray] = {}
        if playbacks.source_sigma_m is not None:
            spots = np.asarray(playbacks.spot)
            for k, spot in enumerate(spots[np.sort(np.unique(spots, return_index=True)[1])]):  # in order of first playback
                rows = np.flatnonzero(spots == spot)
                sigma = float(np.max(playbacks.source_sigma_m[rows]))
                if sigma > 0:
                    names += [f"{SPOT_PREFIX}{k}_x_m", f"{SPOT_PREFIX}{k}_y_m"]
                    sd += [sigma] * 2
                    self.spot_rows[f"{SPOT_PREFIX}{k}"] = rows
        self.names, self.sd = names, np.asarray(sd, dtype=float)
        # the thermometer's offset stays within MAX_TEMPERATURE_PRIORS of its prior σ: wrong peaks must not
        # take the air below absolute zero (the speed-of-sound formula refuses it) on the way to a fit
        limit = np.where(np.array([n == "temperature_offset_c" for n in names], dtype=bool), MAX_TEMPERATURE_PRIORS, np.inf)
        self.bounds = (-limit, limit)
        self.t = seconds_since_origin(playbacks.time_s, drift_origin_s)
        self.measured = np.isfinite(playbacks.tdoa_s)
        self.dcdt = speed_of_sound_slope(playbacks.temperature_c, playbacks.relative_humidity_pct)

    def unpack(self, u: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        theta = dict(zip(self.names, self.sd * u, strict=True))
        n_mics = self.pr.mic_positions_m.shape[0]
        clocks = np.array([0.0] + [theta.get(f"clock_{m}_s", 0.0) for m in range(1, n_mics)])
        drift = np.array([0.0] + [theta.get(f"drift_{m}", 0.0) for m in range(1, n_mics)])
        mics = self.pr.mic_positions_m.astype(float).copy()
        for m in self.moved:
            mics[m, 0] += theta[f"mic_{m}_x_m"]
            mics[m, 1] += theta[f"mic_{m}_y_m"]
        return float(theta.get("temperature_offset_c", 0.0)), clocks, drift, mics

    def sources_m(self, u: np.ndarray) -> np.ndarray:
        """(N, 3) each playback's spot, moved off its survey by the spot parameters."""
        if not self.spot_rows:
            return self.pb.source_m
        theta = dict(zip(self.names, self.sd * u, strict=True))
        source = self.pb.source_m.astype(float).copy()
        for name, rows in self.spot_rows.items():
            source[rows, 0] += theta[f"{name}_x_m"]
            source[rows, 1] += theta[f"{name}_y_m"]
        return source

    def arrival_s(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(N, M) arrival times less the emission's, and the (N, M) distances, (N, M, 3) spot − mic vectors and (N,) speeds."""
        offset, clocks, drift, mics = self.unpack(u)
        speed = speed_of_sound_m_s(self.pb.temperature_c + offset, self.pb.relative_humidity_pct)
        diff = self.sources_m(u)[:, None, :] - mics[None]
        dist = np.sqrt((diff**2).sum(-1))
        return dist / speed[:, None] + clocks[None, :] + drift[None, :] * self.t[:, None], dist, diff, speed

    def predicted_s(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(N, P) predicted pair time differences, and ``arrival_s``'s distances, spot − mic vectors and speeds."""
        arrival, dist, diff, speed = self.arrival_s(u)
        return self.pb.pair_differences_s(arrival), dist, diff, speed

    def residuals(self, u: np.ndarray, sigma_t: float, weights: np.ndarray) -> np.ndarray:
        pred, *_ = self.predicted_s(u)
        r = (pred - self.pb.tdoa_s)[self.measured] / sigma_t * np.sqrt(weights)
        return np.concatenate([r, u])

    def jacobian(self, u: np.ndarray, sigma_t: float, weights: np.ndarray) -> np.ndarray:
        _, dist, diff, speed = self.predicted_s(u)
        # d arrival_m / d θ for each mic m, then pair (i, j) = column j − column i
        cols = []
        for name in self.names:
            d_arrival = np.zeros(dist.shape)
            if name == "temperature_offset_c":
                d_arrival = -dist / speed[:, None] ** 2 * self.dcdt[:, None]
            elif name.startswith("clock_"):
                d_arrival[:, int(name.split("_")[1])] = 1.0
            elif name.startswith("drift_"):
                d_arrival[:, int(name.split("_")[1])] = self.t
            elif name.startswith(SPOT_PREFIX):  # d‖s − p_m‖/ds / c for every mic of that spot's playbacks
                rows, axis = self.spot_rows[name.rsplit("_", 2)[0]], 0 if name.split("_")[-2] == "x" else 1
                d_arrival[rows] = diff[rows, :, axis] / dist[rows] / speed[rows, None]
            else:
                m, axis = int(name.split("_")[1]), 0 if name.split("_")[2] == "x" else 1
                d_arrival[:, m] = -diff[:, m, axis] / dist[:, m] / speed  # d‖s − p_m‖/dp_m / c
            cols.append(self.pb.pair_differences_s(d_arrival)[self.measured])
        data = np.stack(cols, axis=1) * self.sd / sigma_t * np.sqrt(weights)[:, None] if cols else np.zeros((self.measured.sum(), 0))
        return np.vstack([data, np.eye(len(self.names))])


def lag_margin_needed_s(priors: Priors, speed_of_sound_m_s: float = 343.0) -> float:
    """The margin a pair's GCC lag window needs beyond its stated distance / c for a playback's direct path to lie in it, s.

    Three standard deviations of what the stated array and clocks may shift a pair's time
    difference by: 3 √2 (σ_position / c + σ_clock), the √2 for the two mics of a pair. A spot on a
    pair's endfire has the largest lag the stated distance allows; a real array off by its GPS error
    moves that lag out of a window with a smaller margin, and the calibration then fits a wrong peak.
    """
    return float(3.0 * np.sqrt(2.0) * (np.max(priors.position_sigma_m) / speed_of_sound_m_s + priors.clock_sigma_s))


def linearised_rows(
    playbacks: Playbacks, priors: Priors, kinds: tuple[str, ...], timing_sigma_s: float
) -> tuple[np.ndarray, list[str], np.ndarray]:
    """The model's Jacobian at the stated array: what each playback tells about each parameter (for planning spots).

    Returns
    -------
    rows : numpy.ndarray
        (N, P, p) d Δ_{n,pair} / d u in units of ``timing_sigma_s``, with u the parameters in units
        of their prior standard deviations (so the prior's information is the identity).
    names : list of str
        The p parameters' names.
    sd : numpy.ndarray
        (p,) their prior standard deviations (°C, s, m).
    """
    if not np.isfinite(playbacks.tdoa_s).all():
        raise ValueError("linearised_rows needs every pair of every playback measured")
    model = _Model(playbacks, priors, set(kinds), 0.0)
    n_rows = int(model.measured.sum())
    data = model.jacobian(np.zeros(len(model.names)), timing_sigma_s, np.ones(n_rows))[:n_rows]
    return data.reshape(len(playbacks.source_m), len(playbacks.pairs), len(model.names)), model.names, model.sd


def annealed_prediction_s(
    playbacks: Playbacks,
    candidate_lags_s: np.ndarray,
    priors: Priors,
    estimate: tuple[str, ...] = PARAMETER_KINDS,
    widths_s: np.ndarray = ANNEALING_WIDTHS_S,
    min_drift_span_s: float = 3600.0,
    candidate_heights: np.ndarray | None = None,
    height_power: float = ANNEALING_HEIGHT_POWER,
) -> np.ndarray:
    """(N, M) time differences t_m − t_0 predicted by the array that best explains every pair's GCC candidates at once.

    Picking one candidate per pair and fitting (``calibrate_array``) from a few spots settles where
    the first picks lead, and wrong picks that agree with each other hold a mic centimetres to
    decimetres off. Here no pick is made: each time difference's likelihood is a mixture over its
    pair's K candidates, Σ_k π_k exp(−r_k² / 2w²), with a floor ``ANNEALING_FLOOR`` for a pair none
    of whose candidates is the direct path, and the parameters (in units of their priors, with
    their Gaussian priors) maximise the product over all playbacks. The width w is annealed from
    ms, where every candidate within a few ms pulls and the objective has one broad basin, down to
    the timing noise of a clean peak, each step starting where the last ended (deterministic
    annealing; Rose 1998, Proc. IEEE 86: 2210–2239). L-BFGS-B minimises each step with the model's
    analytic Jacobian. The result is a start for the picks, not a calibration: it has no robust
    timing σ, covariance or residuals.

    The weights π_k are the prior probabilities that candidate k is the direct path: equal (1/K)
    without ``candidate_heights``, else proportional to the GCC peak's height to ``height_power``.
    With equal weights, from few spots a set of echoes that agree with each other can explain the
    candidates as well as the direct paths (a 3-mic array from 5 spots: 10 time differences for 9
    unknowns); the peaks' heights are the evidence the lags alone lack.

    Parameters
    ----------
    playbacks : Playbacks
        The playbacks (spots, weather, times, pairs); their ``tdoa_s`` is not used.
    candidate_lags_s : numpy.ndarray
        (N, P, K) each pair's GCC candidate lags t_j − t_i, s (NaN where fewer than K).
    priors, estimate, min_drift_span_s
        As for ``calibrate_array``.
    widths_s : numpy.ndarray
        The mixture's widths, s, from wide to narrow.
    candidate_heights : numpy.ndarray, optional
        (N, P, K) the candidates' GCC peak heights (the ``xcorr`` feature group; NaN or ≤ 0 where
        unknown, which weighs that pair's candidates equally).
    height_power : float
        The power of the heights in the weights (0: equal weights).
    """
    lags = np.asarray(candidate_lags_s, dtype=float)
    usable = np.isfinite(lags)
    measured = dataclasses.replace(playbacks, tdoa_s=np.where(usable.any(axis=2), 0.0, np.nan))
    kinds = set(estimate) - set(_structural_limits(measured, priors, set(estimate), min_drift_span_s))
    origin = float(np.nanmin(playbacks.time_s)) if np.isfinite(playbacks.time_s).any() else 0.0
    model = _Model(measured, priors, kinds, origin)
    observed = np.where(usable, lags, 0.0)[model.measured]  # (R, K)
    share = _candidate_shares(usable, candidate_heights, height_power)[model.measured]
    n_rows = int(model.measured.sum())

    def objective(u: np.ndarray, width_s: float) -> tuple[float, np.ndarray]:
        predicted = model.predicted_s(u)[0][model.measured]
        r = observed - predicted[:, None]
        e = share * np.exp(-0.5 * (r / width_s) ** 2)
        total = e.sum(axis=1) + ANNEALING_FLOOR
        d_predicted = -(e * r).sum(axis=1) / width_s**2 / total  # d(−log likelihood)/d prediction
        d_u = model.jacobian(u, 1.0, np.ones(n_rows))[:n_rows]
        return float(-np.log(total).sum() + 0.5 * u @ u), d_u.T @ d_predicted + u

    u = np.zeros(len(model.names))
    bounds = list(zip(*model.bounds, strict=True))
    for width in widths_s:
        u = minimize(objective, u, args=(float(width),), jac=True, method="L-BFGS-B", bounds=bounds).x
    arrival = model.arrival_s(u)[0]
    return arrival - arrival[:, :1]


def _candidate_shares(usable: np.ndarray, heights: np.ndarray | None, power: float) -> np.ndarray:
    """(N, P, K) each usable candidate's prior weight in its pair's mixture, summing to 1 over the pair's candidates."""
    weight = usable.astype(float)
    if heights is not None:
        h = np.where(usable, np.asarray(heights, dtype=float), np.nan)
        positive = np.isfinite(h) & (h > 0)  # usable candidates with a height
        known = positive.sum(axis=2, keepdims=True) == usable.sum(axis=2, keepdims=True)  # pairs with every height
        weight = np.where(known & usable, np.where(positive, h, 1.0) ** power, weight)
    total = weight.sum(axis=2, keepdims=True)
    return np.divide(weight, total, out=np.zeros_like(weight), where=total > 0)


def calibrate_array(
    playbacks: Playbacks,
    priors: Priors,
    mic_ids: list[str],
    estimate: tuple[str, ...] = PARAMETER_KINDS,
    timing_sigma_s: float = 1e-4,
    min_drift_span_s: float = 3600.0,
    max_reweight: int = 50,
    reflection_band_hz: tuple[float, float] | None = None,
) -> ArrayCalibration:
    """Estimate the thermometer offset, clock offsets and drifts, and mic positions from playbacks (module docstring).

    Parameters
    ----------
    playbacks : Playbacks
        Playbacks at known spots with their measured time differences.
    priors : Priors
        The stated array and the standard deviations of what may be off.
    mic_ids : list of str
        The mics' names, in the order of the arrays.
    estimate : tuple of str
        Which of ``PARAMETER_KINDS`` to estimate (those the playbacks cannot determine are left at
        their priors and listed in ``not_identified``).
    timing_sigma_s : float
        Starting value of the timing noise, s (re-estimated from the residuals).
    min_drift_span_s : float
        Drift is estimated only from playbacks spread over at least this long, s.
    max_reweight : int
        At most this many reweighting passes (they stop when the estimates hold; a warning if they do not).
    reflection_band_hz : (float, float), optional
        The band the playbacks' GCC peaks were measured in, Hz: the covariance then also carries a
        ground reflection within the direct path's peak, a bias every spot shares
        (``shared_reflection_response``); None: it does not.

    Raises
    ------
    DataError
        With fewer than 1 playback measured on 2 or more mics.
    """
    unknown = set(estimate) - set(PARAMETER_KINDS)
    if unknown:
        raise DataError(f"calibration: cannot estimate {sorted(unknown)}; choose from {list(PARAMETER_KINDS)}")
    if not np.isfinite(playbacks.tdoa_s).any():
        raise DataError("calibration: no playback has a measured time difference on 2 or more mics")
    not_identified = _structural_limits(playbacks, priors, set(estimate), min_drift_span_s)
    kinds = set(estimate) - set(not_identified)
    origin = float(np.nanmin(playbacks.time_s)) if np.isfinite(playbacks.time_s).any() else 0.0
    model = _Model(playbacks, priors, kinds, origin)
    u = np.zeros(len(model.names))
    before, *_ = model.predicted_s(u)
    weights = np.ones(int(model.measured.sum()))
    sigma_t = float(timing_sigma_s)
    for k in range(max(1, max_reweight)):
        fit = least_squares(
            model.residuals, u, jac=model.jacobian, args=(sigma_t, weights), method="trf", x_scale="jac", bounds=model.bounds
        )
        moved, u = float(np.max(np.abs(fit.x - u), initial=0.0)), fit.x
        if k > 1 and moved <= CONVERGED_PRIORS:
            break
        r = (model.predicted_s(u)[0] - playbacks.tdoa_s)[model.measured]
        sigma_t = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-6)
        z = np.abs(r) / sigma_t
        # Huber until the fit has left the stated array, then Cauchy: a wrong peak ms off gets next to no weight
        weights = np.minimum(1.0, HUBER_K / np.maximum(z, 1e-12)) if k == 0 else 1.0 / (1.0 + (z / CAUCHY_K) ** 2)
    else:
        log.warning("calibration: the robust fit still moved after %d reweighting passes; its estimates may not have settled", max_reweight)
    jac = model.jacobian(u, sigma_t, weights)
    cov_u = np.linalg.pinv(jac.T @ jac)  # every pair independent: what the geometry identifies
    by_spot, shared = _spot_level_covariance(model, _Solution(u, jac, cov_u, sigma_t, weights), reflection_band_hz)
    # each σ over the per-pair posterior's: the playback's share, the spots' spread and a shared reflection together
    factor = np.sqrt(np.divide(np.diag(by_spot), np.diag(cov_u), out=np.ones(len(cov_u)), where=np.diag(cov_u) > 0))
    covariance = by_spot * np.outer(model.sd, model.sd)
    ratio = np.sqrt(np.clip(np.diag(cov_u), 0, None))  # identification is the geometry's: the per-pair posterior's
    identified = {name: bool(q <= IDENTIFIED_RATIO) for name, q in zip(model.names, ratio, strict=True)}
    for kind, label in (("temperature", "temperature_offset_c"), ("clocks", "clock_"), ("drift", "drift_"), ("positions", "mic_")):
        weak = [n for n in model.names if n.startswith(label) and not identified[n]]
        if kind in kinds and weak:
            not_identified[kind] = (
                f"the playbacks leave {len(weak)} of these parameters near their prior ({', '.join(weak[:4])}"
                f"{', …' if len(weak) > 4 else ''}): more spots, spread around the array, would determine them"
            )
    offset, clocks, drift, mics = model.unpack(u)
    after, dist, _, speed = model.predicted_s(u)
    loading = playbacks.pair_differences_s(-dist / speed[:, None] ** 2 * model.dcdt[:, None])
    # the spots are nuisance parameters: the array's covariance is the Gaussian marginal (its block), their shifts reported
    keep = np.array([not n.startswith(SPOT_PREFIX) for n in model.names], dtype=bool)
    names = [n for n, k in zip(model.names, keep, strict=True) if k]
    return ArrayCalibration(
        mic_ids=list(mic_ids),
        mic_positions_m=mics,
        mic_position_shift_m=mics - priors.mic_positions_m,
        temperature_offset_c=offset,
        clock_offset_s=clocks,
        clock_drift=drift,
        drift_origin_s=origin,
        timing_sigma_s=sigma_t,
        parameters=names,
        covariance=covariance[np.ix_(keep, keep)],
        prior_sd=model.sd[keep],
        identified={n: identified[n] for n in names},
        not_identified=not_identified,
        residual_before_s=before - playbacks.tdoa_s,
        residual_after_s=after - playbacks.tdoa_s,
        pairs=playbacks.pairs,
        spot=np.asarray(playbacks.spot),
        n_spots=playbacks.n_spots,
        priors=priors,
        temperature_call_sd_c=playback_temperature_spread_c(after - playbacks.tdoa_s, loading, model.measured, sigma_t, playbacks.spot),
        extra={
            "redundancy": redundancy(playbacks, len(model.names)),
            "sd_unit": SD_UNIT,
            "sd_over_per_pair": {name: round(float(f), 4) for name, f, k in zip(model.names, factor, keep, strict=True) if k},
            **_spot_shifts(model, u),
            **_reflection_summary(model, shared, reflection_band_hz, keep),
        },
    )


@dataclass(frozen=True)
class _Solution:
    """Where the robust fit ended: parameters u (units of the priors), its Jacobian there and (JᵀJ)⁻¹, timing σ and weights."""

    u: np.ndarray
    jac: np.ndarray
    cov_u: np.ndarray
    sigma_t: float
    weights: np.ndarray


def _spot_level_covariance(
    model: _Model, fit: _Solution, reflection_band_hz: tuple[float, float] | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The covariance a calibration reports (units of the priors), and the shared reflection's response (None without one).

    A playback's m − 1 independent differences (``independent_share``), at least the cluster-robust
    spread by spot (``by_spot_covariance``), plus a ground reflection every spot shares where its band
    is given (``shared_reflection_response``, at most ``REFLECTION_FRACTION_MAX`` of it, either sign).
    """
    playbacks = model.pb
    rows = model.measured.sum()
    by_playback = fit.jac.copy()
    by_playback[:rows] *= np.sqrt(independent_share(playbacks.pairs, model.measured))[:, None]
    spot_of_row = np.broadcast_to(np.asarray(playbacks.spot)[:, None], model.measured.shape)[model.measured]
    residual = model.residuals(fit.u, fit.sigma_t, fit.weights)
    by_spot = by_spot_covariance(np.linalg.pinv(by_playback.T @ by_playback), by_playback, residual, spot_of_row)
    if reflection_band_hz is None:
        return by_spot, None
    shared = shared_reflection_response(model, fit, reflection_band_hz)
    return by_spot + REFLECTION_FRACTION_MAX**2 / 3 * np.outer(shared, shared), shared


def shared_reflection_response(model: _Model, fit: _Solution, band_hz: tuple[float, float]) -> np.ndarray:
    """(K,) how the fit's estimates move (units of their priors) if every arrival sits one reflection's worth late.

    Each arrival's peak moves by a fraction a of ``peak_shift_per_fraction_s`` of its ground
    reflection's delay at the fitted array and spots (``acoustlab.toolkit.ground_reflection``);
    the least-squares fit, linearised at its solution, answers a pattern b of its pairs' time
    differences with (JᵀJ)⁻¹ Jᵀ b. The fraction a is one for the whole calibration (one ground),
    unknown in sign (a soft ground at grazing incidence reflects with the phase inverted) and at
    most ``REFLECTION_FRACTION_MAX`` (two equal peaks merge halfway); taken as uniform over that
    range, its variance is REFLECTION_FRACTION_MAX² / 3.
    """
    *_, mics = model.unpack(fit.u)
    *_, speed = model.predicted_s(fit.u)
    shift = peak_shift_per_fraction_s(reflection_delay_s(model.sources_m(fit.u), mics, speed), band_hz)  # (N, M) s
    rows = int(model.measured.sum())
    pattern = model.pb.pair_differences_s(shift)[model.measured] / fit.sigma_t * np.sqrt(fit.weights)
    return fit.cov_u @ fit.jac[:rows].T @ pattern


def _reflection_summary(model: _Model, response: np.ndarray | None, band_hz: tuple[float, float] | None, keep: np.ndarray) -> dict:
    """``{"shared_bias": …}``: the reflection allowance's band and what it adds at its largest, per estimate; {} without one."""
    if response is None:
        return {}
    at_most = response * model.sd * REFLECTION_FRACTION_MAX  # in the estimates' own units, at a = REFLECTION_FRACTION_MAX
    return {
        "shared_bias": {
            "kind": "a ground reflection within the direct path's GCC peak, the same fraction of its delay at every spot",
            "band_hz": [float(band_hz[0]), float(band_hz[1])],
            "fraction_max": REFLECTION_FRACTION_MAX,
            "shift_at_fraction_max": {n: float(v) for n, v, k in zip(model.names, at_most, keep, strict=True) if k},
        }
    }


def _spot_shifts(model: _Model, u: np.ndarray) -> dict[str, Any]:
    """``{"spot_shift_m": {spot: [dx, dy]}}`` of the spots estimated with the array (m), or {} where none was."""
    if not model.spot_rows:
        return {}
    shift = (model.sources_m(u) - model.pb.source_m)[:, :2]
    spots = np.asarray(model.pb.spot)
    return {"spot_shift_m": {str(spots[rows[0]]): [round(float(v), 4) for v in shift[rows[0]]] for rows in model.spot_rows.values()}}


def independent_share(pairs: list[tuple[int, int]], measured: np.ndarray) -> np.ndarray:
    """(R,) per measured pair, the independent time differences of its playback over the pairs measured: (m − 1) / p.

    A playback heard on m mics gives m − 1 independent time differences however many of its pairs
    are measured: pairs share mics, and an arrival's error enters every pair it is in. With all
    p = m(m − 1)/2 pairs and white noise per mic, the pairs' information is m/2 times what independent
    pairs would give (the pairs' difference matrix D has DᵀD = mI − 11ᵀ); weighting each pair by
    (m − 1)/p gives the playback its m − 1 (exact for all pairs, as ``calibrate`` measures them).
    """
    first, second = np.array(pairs, dtype=int).reshape(-1, 2).T
    n_mics = int(max(first.max(initial=-1), second.max(initial=-1))) + 1
    heard = np.zeros((measured.shape[0], n_mics), dtype=bool)
    for k in range(measured.shape[1]):
        heard[measured[:, k], first[k]] = heard[measured[:, k], second[k]] = True
    share = np.divide(
        np.maximum(heard.sum(axis=1) - 1, 0), measured.sum(axis=1), out=np.zeros(measured.shape[0]), where=measured.any(axis=1)
    )
    return np.broadcast_to(share[:, None], measured.shape)[measured]


def by_spot_covariance(posterior: np.ndarray, jac: np.ndarray, residual: np.ndarray, spot_of_row: np.ndarray) -> np.ndarray:
    """The posterior covariance with each parameter's variance at least the cluster-robust one by spot (scaled units).

    A spot's multipath delays every playback from it alike, so its playbacks move the estimates
    together (a mic's σ was 1.5–2.9× too small with per-spot multipath). The sandwich
    A (Σ_s g_s g_sᵀ · (G − 1)/G + I) A, with A = ``posterior`` = (JᵀJ)⁻¹ and
    g_s = J_sᵀ (I − H_ss)⁻¹ r_s the leverage-corrected score of spot s's rows (H_ss = J_s A J_sᵀ),
    takes the spot as the unit: the CR3 form, which approximates the delete-one-spot jackknife
    (Bell & McCaffrey 2002, Survey Methodology 28:169–181; MacKinnon & White 1985). The plain
    Liang–Zeger form uses the fitted residuals as they are; from 10 spots with 9 unknowns each spot
    pulls the fit towards itself, its residuals shrink, and 16 % of a 3-mic array's estimates lay
    beyond 3 σ. I stands for the prior rows, whose score has unit variance; each parameter's σ is the
    larger of the two, correlations kept from the posterior (the sandwich's meat has rank at most
    G + its prior's, too few to carry them from 10 spots).

    Parameters
    ----------
    posterior : numpy.ndarray
        (K, K) (JᵀJ)⁻¹ of ``jac`` in the fit's scaled units (``calibrate_array`` weighs each pair by
        ``independent_share`` first).
    jac, residual : numpy.ndarray
        (R + K, K) and (R + K,) the scaled Jacobian and the fit's residuals: R data rows, then K prior rows.
    spot_of_row : numpy.ndarray
        (R,) the spot of each data row.

    Returns
    -------
    numpy.ndarray
        (K, K) the covariance, each variance at least ``posterior``'s.
    """
    n_prior = posterior.shape[0]
    data_j, data_r = jac[: len(jac) - n_prior], residual[: len(residual) - n_prior]
    spots = np.unique(spot_of_row)
    if spots.size < 2 or n_prior == 0:
        return posterior
    scores = np.stack([_corrected_score(data_j[spot_of_row == s], data_r[spot_of_row == s], posterior) for s in spots])  # (G, K)
    meat = scores.T @ scores * (spots.size - 1) / spots.size + np.eye(n_prior)
    robust = posterior @ meat @ posterior
    variance = np.diag(posterior)
    grow = np.sqrt(np.divide(np.diag(robust), variance, out=np.ones_like(variance), where=variance > 0))
    factor = np.maximum(1.0, grow)
    return posterior * np.outer(factor, factor)


def _corrected_score(jac_s: np.ndarray, residual_s: np.ndarray, posterior: np.ndarray) -> np.ndarray:
    """(K,) J_sᵀ (I − H_ss)⁻¹ r_s: one spot's score with its residuals as they would be without the spot (CR3).

    A direction in which the spot alone determines the fit (leverage near 1) would divide by
    nearly 0; its share of the residual is capped at ``MAX_LEVERAGE``.
    """
    hat = jac_s @ posterior @ jac_s.T
    leverage, vectors = np.linalg.eigh((hat + hat.T) / 2)
    inverse = (vectors / (1.0 - np.clip(leverage, 0.0, MAX_LEVERAGE))) @ vectors.T
    return jac_s.T @ (inverse @ residual_s)


def playback_temperature_spread_c(
    residual_s: np.ndarray, loading_s_per_c: np.ndarray, measured: np.ndarray, timing_sigma_s: float, spot: np.ndarray | None = None
) -> float:
    """How far the thermometer's error varies from playback to playback about the calibrated offset, °C.

    The calibration fits one offset for the season; a thermometer in the sun, or air between the
    mics warmer than at the logger, is off by a different amount at each call, and the radii must
    carry that spread too (``FieldCalibration.input_uncertainty``). Each playback n's own offset
    about the fitted one is the least-squares ΔT_n = −Σ a r / Σ a² over its pairs (r the calibrated
    residual, a its change per °C), over the pairs within ``OUTLIER_K`` timing-noise units of the
    fit and again once each playback's own offset is removed (a wrong GCC peak would set it; the
    fit's robust weights would not do, as they fall with the very residuals a varying thermometer
    makes, and bias the spread low). Its variance from the timing noise σ_t alone (the MAD of those residuals) is
    σ_t² / Σ a²; the spread beyond it is the between-playback variance τ² of a random-effects
    model, by the method of moments of DerSimonian & Laird (1986, Controlled Clinical Trials
    7:177–188): τ² = max(0, (Q − (K − 1)) / (Σv − Σv² / Σv)), v_n = 1 / var_n,
    Q = Σ v_n (ΔT_n − ΔT̄)². Where a spot has several playbacks, the moments are taken within
    spots (ΔT̄ each spot's mean, K − 1 summed over spots): the fit's mics and clocks absorb part of
    what differs between spots, so across spots the spread comes out low
    (``experiments/call_spread_per_spot.py``: one playback per spot). It is 0 where the playbacks show no
    spread beyond their timing noise, or fewer than 2 playbacks constrain an offset.

    Parameters
    ----------
    residual_s, loading_s_per_c : numpy.ndarray
        (N, P) each playback's and pair's calibrated residual (predicted − measured, s) and its change
        per °C of thermometer offset (s/°C).
    measured : numpy.ndarray
        (N, P) bool, the pairs measured.
    timing_sigma_s : float
        The fit's timing noise, s (its residuals beyond ``OUTLIER_K`` of it are wrong peaks).
    spot : numpy.ndarray, optional
        (N,) each playback's spot: the moments are taken within spots where one has 2 or more.
    """
    a, r = np.where(measured, loading_s_per_c, 0.0), np.where(measured, residual_s, 0.0)

    def offsets(use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        information = (use * a**2).sum(axis=1)
        return -(use * a * r).sum(axis=1) / np.where(information > 0, information, np.inf), information

    inlier = measured & (np.abs(r) < OUTLIER_K * timing_sigma_s)
    offset, _ = offsets(inlier)
    own = r + a * offset[:, None]  # each playback's residuals with its own offset taken out
    sigma_t = max(1.4826 * float(np.median(np.abs(own[inlier] - np.median(own[inlier])))), 1e-9)
    inlier &= np.abs(own) < OUTLIER_K * sigma_t
    offset, information = offsets(inlier)
    used = information > 0
    groups = np.zeros(len(r), dtype=int)
    if spot is not None and used.any():
        by_spot = np.unique(np.asarray(spot), return_inverse=True)[1].ravel()
        groups = by_spot if np.bincount(by_spot[used]).max() >= 2 else groups
    q = dof = denominator = 0.0
    for g in np.unique(groups[used]):
        k = used & (groups == g)
        if k.sum() < 2:
            continue
        v = information[k] / sigma_t**2
        q += float(np.sum(v * (offset[k] - np.sum(v * offset[k]) / np.sum(v)) ** 2))
        dof += k.sum() - 1
        denominator += float(np.sum(v) - np.sum(v**2) / np.sum(v))
    if dof == 0:
        return 0.0
    return float(np.sqrt(max((q - dof) / denominator, 0.0)))


def calibrate_until_picks_hold(
    playbacks: Playbacks, fit: Callable[[Playbacks], ArrayCalibration], max_rounds: int = 30, quiet: bool = False
) -> tuple[ArrayCalibration, Playbacks]:
    """Calibrate from ``playbacks``' picks, re-pick each pair's candidate with the calibration, and repeat until the picks repeat.

    A stated array 2–3 m off predicts lags several ms off, so the first picks take a ground
    reflection or another wrong peak for the direct path on most pairs; each calibration predicts
    the lags more closely and corrects some picks, and a fit stopped before the picks hold keeps
    centimetres of error that are not noise (the forest needed up to 10 rounds). The rounds stop
    when the picks repeat (they hold, or they cycle) or after ``max_rounds``; the log says how many
    rounds it took, and warns when they did not settle (``quiet``: neither). ``fit`` is the
    calibration (``calibrate_array`` with its priors); the playbacks need their ``candidates_s``.
    """
    calibration = fit(playbacks)
    seen = {_picks_key(playbacks)}
    for rounds in range(2, max_rounds + 1):
        repicked = playbacks.picked(calibration.predicted_tdoa_s(playbacks))
        if _picks_key(repicked) in seen:
            log.log(
                logging.DEBUG if quiet else logging.INFO,
                "calibrate: the GCC picks held after %d rounds of calibrating and re-picking",
                rounds - 1,
            )
            return calibration, playbacks
        seen.add(_picks_key(repicked))
        playbacks = repicked
        calibration = fit(playbacks)
    if not quiet:
        log.warning("calibrate: the GCC picks still changed after %d rounds; the calibration may rest on some wrong peaks", max_rounds)
    return calibration, playbacks


def _picks_key(playbacks: Playbacks) -> bytes:
    """The picked time differences as bytes (NaN included), to tell whether a round changed any pick."""
    return np.ascontiguousarray(playbacks.tdoa_s).tobytes()


def temperature_from_speed_c(speed_m_s: float, relative_humidity_pct: float) -> float:
    """The air temperature (°C) at which sound travels at ``speed_m_s`` (inverse of ``speed_of_sound_m_s``)."""
    return float(brentq(lambda t: float(speed_of_sound_m_s(t, relative_humidity_pct)) - speed_m_s, -60.0, 60.0))
