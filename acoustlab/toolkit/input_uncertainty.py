"""How far the position moves when the inputs a user measures are off: thermometer, mic survey, clocks.

Conformal radii calibrated on simulation know nothing of the user's measurement errors: the
simulation knows its speed of sound and mic positions exactly. A 0.3 % error in the speed of
sound (1.7 °C) moved the frozen lake's median error from 0.08 to 0.24 m, three times the 0.5
radius. This module propagates stated standard deviations through the TDOA equations
(first order, by the Jacobian at the estimate) so the radius can carry them:

* arrival range at mic i: r_i = |s − m_i| + c·τ₀ (s the source, τ₀ the emission time);
* a clock offset δτ_i adds c·δτ_i to r_i (independent between mics);
* a mic position error δm_i adds −u_i·δm_i (u_i the unit vector mic → source; independent);
* a speed-of-sound error δc scales every travel time: it adds r_i·δc/c to all of them at once
  (fully correlated between mics: the part GDOP alone cannot describe).

A field calibration's errors are correlated (``CorrelatedInputErrors``): from few spots a
recorder's clock trades off against its distance to them, so −c·δτ_i + u_i·δm_i, not each term,
is what the playbacks tie down. Σ_r is then G Σ Gᵀ, with Σ the calibration's covariance and G
each input's loading on each range (r_i·(dc/dT)/c for the thermometer, −c for mic i's clock,
u_i for its position). Where the calibration estimated the clocks' drift, the covariance also
holds the M drifts (s per s), and a clock's error at a call t seconds after the drift's origin is
its offset's error plus t times its drift's (``CorrelatedInputErrors.at``): a drift estimated from
playbacks an hour apart, extrapolated over a season, can grow a clock's error by milliseconds.

With J the (M × 3) Jacobian of (r_i) in (x, y, c·τ₀) and Σ_r the covariance of those range
errors, the least-squares estimate's covariance is (JᵀJ)⁻¹ Jᵀ Σ_r J (JᵀJ)⁻¹; its horizontal
block gives an RMS error σ = √(trace / 2) per axis (the ``input_sigma_m`` column).

The radius the allowance adds at level ℓ (``allowance_m``) follows the shift's shape, not a
round error of the same σ: a thermometer error moves every fix along a line, where a round
radius σ √(−2 ln(1 − ℓ)) holds 0.917 at 0.95 instead of 0.95. To first order it is the
ℓ-quantile of a 2-D Gaussian with the horizontal block's two axes (``gaussian_radius_factor``);
where the first-order σ exceeds ``exact_above_m``, the ℓ-quantile of the Monte Carlo's own
shifts, which also carries their tail (mics 2 m off: a round radius held 0.87–0.93 of the
shifts at 0.95 over simulated surveys, the Monte Carlo quantile 0.88–0.94; ``docs/localize.md``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.physics import speed_of_sound_m_s
from acoustlab.toolkit.recorder_clocks import seconds_since_origin


@dataclass
class InputUncertainty:
    """Standard deviations of the inputs a user measures (``conformal.input_uncertainty`` in the config).

    Attributes
    ----------
    temperature_c : float
        Thermometer error, °C (becomes a speed-of-sound error of about 0.6 m/s per °C).
    mic_position_m : float
        Mic survey error per horizontal axis, m.
    clock_offset_s : float
        Recorder clock offset after synchronisation, s.
    exact_above_m : float
        Where the first-order σ exceeds this (m), it is replaced by a Monte Carlo of the fix
        (``monte_carlo_sigma_m``): near a baseline extension the linearisation overstates the shift.
    max_sigma_m : float
        The allowance never exceeds this per axis (m): beyond it the fix is not located by its
        inputs at all. It is large (a 0.95 radius of about 120 m) so that a radius far outside the
        array still says how badly the fix is placed: capped at 10 m, the 0.95 radii of fixes
        beyond 0.3 array extents outside a GPS-surveyed forest array covered 0.86 of them
        (``experiments/field_workflow.py``'s arm without playbacks).
    unsurveyed_mic_position_m : float
        The survey error per axis a field run assumes for mics whose table gives no
        ``position_sigma_m`` and that no calibration fitted, m: a consumer GPS's (2 m per axis
        is about 5 m at 95 % horizontally). Only a mics table reaches it (``acoustlab.stages.mic_survey``).

    The allowance is marginal over thermometers (and surveys, clocks): it is the spread of the fix
    over the errors a user's instruments may have, not the shift of one season-long bias, which
    ``acoustlab calibrate`` removes.
    """

    temperature_c: float = 1.0
    mic_position_m: float = 0.0
    clock_offset_s: float = 0.0
    exact_above_m: float = 0.5
    max_sigma_m: float = 50.0
    unsurveyed_mic_position_m: float = 2.0

    def __post_init__(self) -> None:
        for name in ("temperature_c", "mic_position_m", "clock_offset_s", "exact_above_m", "max_sigma_m", "unsurveyed_mic_position_m"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ConfigError(f"conformal.input_uncertainty.{name} must be a finite number >= 0; got {value}")

    @property
    def is_zero(self) -> bool:
        """True where nothing is stated (no allowance)."""
        return self.temperature_c == 0 and self.mic_position_m == 0 and self.clock_offset_s == 0


@dataclass(frozen=True)
class CorrelatedInputErrors:
    """The errors a field calibration leaves in the inputs, with their correlations (``FieldCalibration.input_uncertainty``).

    From few spots a recorder's clock and its distance to the spots trade off: each alone may be
    hundreds of µs or decimetres off while the time differences they predict together hold to tens
    of µs. Carried as independent errors they would grow every radius by what the playbacks rule
    out; their covariance carries what the playbacks leave.

    Attributes
    ----------
    covariance : numpy.ndarray
        (1 + 3M, 1 + 3M) covariance of the estimates' errors: the thermometer's offset (°C), the M
        recorders' clock offsets (s; the reference's is 0), then each mic's x and y (m), in that
        order; with ``drifts``, (1 + 4M, 1 + 4M), the M clock drifts (s per s) after them.
    exact_above_m, max_sigma_m : float
        As for ``InputUncertainty``.
    drifts : bool
        Whether the covariance holds the clocks' drifts.
    drift_origin_s : float
        The time the clock offsets hold at (the calibration's ``drift_origin_s``), s.
    """

    covariance: np.ndarray
    exact_above_m: float = 0.5
    max_sigma_m: float = 50.0
    drifts: bool = False
    drift_origin_s: float = 0.0

    @property
    def is_zero(self) -> bool:
        """True where the calibration leaves nothing uncertain (no allowance)."""
        return not np.any(self.covariance)

    def check_array(self, n_mics: int) -> None:
        """Raise ValueError unless the covariance is of ``n_mics`` mics (1 + 3 ``n_mics`` rows, 1 + 4 ``n_mics`` with drifts)."""
        if self.covariance.shape != ((4 if self.drifts else 3) * n_mics + 1,) * 2:
            raise ValueError(f"CorrelatedInputErrors: a covariance of shape {self.covariance.shape} for an array of {n_mics} mics")

    def transfer(self, n_mics: int, time_s: np.ndarray | None) -> np.ndarray:
        """(B, 1 + 3M, D) or (1 + 3M, D): each call's inputs from the covariance's: a clock's error at time t is its
        offset's plus (t − ``drift_origin_s``) times its drift's (no time, or no drift: the offset's alone)."""
        self.check_array(n_mics)
        base = np.eye(1 + 3 * n_mics, self.covariance.shape[0])
        if not self.drifts or time_s is None:
            return base
        elapsed = seconds_since_origin(time_s, self.drift_origin_s)  # as the correction applies them
        out = np.broadcast_to(base, (len(elapsed), *base.shape)).copy()
        clocks = np.arange(1, 1 + n_mics)
        out[:, clocks, 1 + 3 * n_mics + np.arange(n_mics)] = elapsed[:, None]
        return out

    def at(self, n_mics: int, time_s: np.ndarray | None = None) -> np.ndarray:
        """(B, 1 + 3M, 1 + 3M) the inputs' covariance at each call's ``time_s`` ((B,), s), or (1 + 3M, 1 + 3M) at the origin."""
        a = self.transfer(n_mics, time_s)
        return a @ self.covariance @ np.swapaxes(a, -1, -2)


#: Stated or calibrated input errors.
InputErrors = InputUncertainty | CorrelatedInputErrors


def range_loadings(distance_m: np.ndarray, direction: np.ndarray, speed_m_s: np.ndarray, dc_dt: np.ndarray) -> np.ndarray:
    """(B, M, 1 + 3M) how far each input's error moves each mic's arrival range, m per °C, s or m (``CorrelatedInputErrors``' order).

    ``distance_m`` (B, M) and ``direction`` (B, M, 2), the horizontal unit vectors mic → source;
    ``speed_m_s`` and ``dc_dt`` (B,), the speed of sound and its change per °C.
    """
    n, m = distance_m.shape
    mic = np.arange(m)
    out = np.zeros((n, m, 1 + 3 * m))
    out[:, :, 0] = distance_m * (dc_dt / speed_m_s)[:, None]
    out[:, mic, 1 + mic] = -speed_m_s[:, None]  # a clock read late by δ: its corrected arrival is δ early
    out[:, mic, 1 + m + 2 * mic] = direction[..., 0]
    out[:, mic, 2 + m + 2 * mic] = direction[..., 1]
    return out


def position_sigma_m(
    mic_positions_m: np.ndarray,
    source_m: np.ndarray,
    temperature_c: np.ndarray,
    relative_humidity_pct: np.ndarray,
    stated: InputErrors,
    time_s: np.ndarray | None = None,
) -> np.ndarray:
    """(B,) per-axis RMS horizontal position error (m) from the stated input errors, first order: √(trace / 2) of
    ``horizontal_covariance_m2`` (same parameters)."""
    cov = horizontal_covariance_m2(mic_positions_m, source_m, temperature_c, relative_humidity_pct, stated, time_s)
    return _per_axis_sigma(cov)


def horizontal_covariance_m2(
    mic_positions_m: np.ndarray,
    source_m: np.ndarray,
    temperature_c: np.ndarray,
    relative_humidity_pct: np.ndarray,
    stated: InputErrors,
    time_s: np.ndarray | None = None,
) -> np.ndarray:
    """(B, 2, 2) covariance of the horizontal fix's shift (m²) under the stated input errors, first order (module docstring).

    Parameters
    ----------
    mic_positions_m : numpy.ndarray
        (M, 3) mic positions, m.
    source_m : numpy.ndarray
        (B, 3) estimated source positions, m (NaN rows give NaN).
    temperature_c, relative_humidity_pct : numpy.ndarray
        (B,) the events' weather.
    stated : InputUncertainty or CorrelatedInputErrors
        The standard deviations, or a calibration's covariance.
    time_s : numpy.ndarray, optional
        (B,) when each call happened, s (a calibration's drift grows its clocks' errors with time since its origin).
    """
    mics = np.asarray(mic_positions_m, dtype=float)
    src = np.asarray(source_m, dtype=float)
    temperature_c = np.asarray(temperature_c, dtype=float)
    c = np.asarray(speed_of_sound_m_s(temperature_c, relative_humidity_pct), dtype=float)
    dc_dt = np.asarray(speed_of_sound_m_s(temperature_c + 0.5, relative_humidity_pct), dtype=float) - np.asarray(
        speed_of_sound_m_s(temperature_c - 0.5, relative_humidity_pct), dtype=float
    )
    offset = src[:, None, :] - mics[None, :, :]
    r = np.sqrt((offset**2).sum(-1))  # (B, M)
    u = offset[..., :2] / np.maximum(r, 1e-9)[..., None]  # horizontal unit vectors mic → source
    jac = np.concatenate([u, np.ones((*r.shape, 1))], axis=-1)  # (B, M, 3): d r_i / d (x, y, c τ₀)
    if isinstance(stated, CorrelatedInputErrors):
        loadings = range_loadings(r, u, c, dc_dt)
        cov_r = loadings @ stated.at(len(mics), time_s) @ np.swapaxes(loadings, 1, 2)
    else:
        sigma_c = np.abs(dc_dt) * stated.temperature_c
        independent = (c * stated.clock_offset_s) ** 2 + stated.mic_position_m**2  # per mic, per unit-direction projection
        cov_r = independent[:, None, None] * np.eye(r.shape[1])[None] + ((sigma_c / c) ** 2)[:, None, None] * r[:, :, None] * r[:, None, :]
    ok = np.isfinite(src).all(axis=1)
    out = np.full((len(src), 2, 2), np.nan)
    if ok.any():
        j = jac[ok]
        pinv = np.linalg.pinv(j)  # (B, 3, M): (JᵀJ)⁻¹ Jᵀ
        out[ok] = (pinv @ cov_r[ok] @ np.swapaxes(pinv, 1, 2))[:, :2, :2]
    return out


@dataclass(frozen=True)
class Allowance:
    """What the stated input errors add to each detection's radii.

    Attributes
    ----------
    sigma_m : numpy.ndarray
        (B,) per-axis RMS shift of the fix, m (``input_sigma_m``).
    radius_m : numpy.ndarray
        (B, L) the radius that holds the shift at each level, m (module docstring).
    """

    sigma_m: np.ndarray
    radius_m: np.ndarray


def allowance_m(
    mic_positions_m: np.ndarray,
    source_m: np.ndarray,
    temperature_c: np.ndarray,
    relative_humidity_pct: np.ndarray,
    stated: InputErrors,
    levels: tuple[float, ...] | list[float] = (),
    time_s: np.ndarray | None = None,
) -> Allowance:
    """The allowance the radii carry at ``levels``: first order, by Monte Carlo where that exceeds ``exact_above_m``.

    To first order the radius at ℓ is the ℓ-quantile of the Gaussian shift with the first-order
    covariance's two axes; where the first-order σ exceeds ``stated.exact_above_m``, σ and the
    radii are the Monte Carlo shifts' RMS and ℓ-quantiles (``monte_carlo_shifts_m``). σ is capped at
    ``max_sigma_m`` and each radius at ``max_sigma_m`` times the round factor of its level.
    ``time_s`` (B,), when each call happened, s: where a calibration estimated drift, its clocks'
    errors grow with it.
    """
    levels = [float(level) for level in levels]
    cov = horizontal_covariance_m2(mic_positions_m, source_m, temperature_c, relative_humidity_pct, stated, time_s)
    sigma = _per_axis_sigma(cov)
    axes = np.sqrt(np.clip(np.linalg.eigvalsh(np.nan_to_num(cov)), 0.0, None))  # (B, 2): minor, major standard deviations
    ratio = np.divide(axes[:, 0], axes[:, 1], out=np.ones(len(axes)), where=axes[:, 1] > 0)
    radius = np.zeros((len(sigma), len(levels)))
    for k, level in enumerate(levels):
        radius[:, k] = axes[:, 1] * gaussian_radius_factor(level, ratio)
    radius[~np.isfinite(sigma)] = np.nan
    poor = np.isfinite(sigma) & (sigma > stated.exact_above_m)
    if poor.any():
        shifts = monte_carlo_shifts_m(
            mic_positions_m,
            np.asarray(source_m)[poor],
            np.asarray(temperature_c)[poor],
            np.asarray(relative_humidity_pct)[poor],
            stated,
            time_s=None if time_s is None else np.asarray(time_s)[poor],
        )
        sigma[poor] = _per_axis_rms(shifts)
        if levels:
            radius[poor] = np.quantile(np.sqrt((shifts**2).sum(-1)), levels, axis=1).T
    round_factors = np.array([level_factor(level) for level in levels])
    return Allowance(np.minimum(sigma, stated.max_sigma_m), np.minimum(radius, stated.max_sigma_m * round_factors))


def allowance_sigma_m(
    mic_positions_m: np.ndarray,
    source_m: np.ndarray,
    temperature_c: np.ndarray,
    relative_humidity_pct: np.ndarray,
    stated: InputErrors,
    time_s: np.ndarray | None = None,
) -> np.ndarray:
    """(B,) the per-axis σ (m) of ``allowance_m`` (first order, by Monte Carlo where that exceeds ``exact_above_m``, capped)."""
    return allowance_m(mic_positions_m, source_m, temperature_c, relative_humidity_pct, stated, (), time_s).sigma_m


def level_factor(level: float) -> float:
    """√(−2 ln(1 − level)): the radius, in per-axis standard deviations, that holds a circular 2-D Gaussian error at ``level``."""
    return float(np.sqrt(-2 * np.log(1 - level)))


#: Axis ratios (minor ÷ major) at which ``gaussian_radius_factor`` is tabulated, and the draws that tabulate it.
_RATIOS = np.linspace(0.0, 1.0, 41)
_TABLE_DRAWS = 200_000


@functools.cache
def _radius_factors(level: float) -> np.ndarray:
    """(41,) the ``level``-quantile of √(z₁² + ρ² z₂²) at each ratio ρ of ``_RATIOS`` (fixed draws, seed 0; exact at ρ = 1)."""
    z = np.random.default_rng(0).normal(size=(2, _TABLE_DRAWS)) ** 2
    table = np.array([np.quantile(np.sqrt(z[0] + ratio**2 * z[1]), level) for ratio in _RATIOS])  # one ratio at a time: 3 MB
    table[-1] = level_factor(level)  # a round error: √(−2 ln(1 − ℓ)), exactly
    return table


def gaussian_radius_factor(level: float, axis_ratio: np.ndarray) -> np.ndarray:
    """Radius ÷ the major axis's σ that holds a 2-D Gaussian error at ``level``, for minor ÷ major σ ``axis_ratio`` in [0, 1].

    A line (ratio 0) needs the 1-D two-sided quantile (1.96 at 0.95), a round error
    √(−2 ln(1 − ℓ)) (2.45 at 0.95); between them, the quantile of √(z₁² + ρ² z₂²), tabulated.
    """
    return np.interp(np.clip(np.asarray(axis_ratio, dtype=float), 0.0, 1.0), _RATIOS, _radius_factors(float(level)))


#: Draws of the Monte Carlo (the same for every detection: a detection's allowance never depends on its batch).
N_DRAWS = 64


def monte_carlo_shifts_m(
    mic_positions_m: np.ndarray,
    source_m: np.ndarray,
    temperature_c: np.ndarray,
    relative_humidity_pct: np.ndarray,
    stated: InputErrors,
    n_iterations: int = 15,
    time_s: np.ndarray | None = None,
) -> np.ndarray:
    """(B, N_DRAWS, 2) shifts (m) of the least-squares fix when the inputs are off by the stated errors, by Monte Carlo.

    ``fix_shift_m`` under ``N_DRAWS`` fixed draws (seed 0) of the errors: a speed of sound off by
    the thermometer's error, mics off by the survey error and clocks off by theirs; with
    ``CorrelatedInputErrors``, drawn together from the calibration's covariance (a clock's drift
    times the call's time since the drift's origin added to its offset, ``time_s`` (B,), s). Near
    a singular geometry some draws have no nearby fix at all: a shift counts at most 3 × ``max_sigma_m``.
    """
    d_temperature, d_clock, d_mics = _input_draws(stated, len(mic_positions_m), time_s)
    shift = fix_shift_m(mic_positions_m, source_m, temperature_c, relative_humidity_pct, d_temperature, d_clock, d_mics, n_iterations)
    return np.clip(np.nan_to_num(shift, nan=np.inf), -3 * stated.max_sigma_m, 3 * stated.max_sigma_m)


def monte_carlo_sigma_m(
    mic_positions_m: np.ndarray,
    source_m: np.ndarray,
    temperature_c: np.ndarray,
    relative_humidity_pct: np.ndarray,
    stated: InputErrors,
    n_iterations: int = 15,
    time_s: np.ndarray | None = None,
) -> np.ndarray:
    """(B,) per-axis RMS of ``monte_carlo_shifts_m``, m."""
    shift = monte_carlo_shifts_m(mic_positions_m, source_m, temperature_c, relative_humidity_pct, stated, n_iterations, time_s)
    return _per_axis_rms(shift)


def fix_shift_m(
    mic_positions_m: np.ndarray,
    source_m: np.ndarray,
    temperature_c: np.ndarray,
    relative_humidity_pct: np.ndarray,
    d_temperature_c: np.ndarray,
    d_arrival_s: np.ndarray,
    d_mics_m: np.ndarray,
    n_iterations: int = 15,
) -> np.ndarray:
    """(B, D, 2) how far the least-squares fix of each source moves under each of D sets of input errors, m (NaN: no fix).

    The arrival ranges are those of the true geometry (``mic_positions_m`` (M, 3), ``source_m``
    (B, 3), the true weather (B,)); the fix is solved by Gauss–Newton in x, y and c·τ₀ from the
    true position with the thermometer off by ``d_temperature_c`` ((D,), or (B, D) per source), °C, the arrival times by
    ``d_arrival_s`` ((D, M), or (B, D, M) per source), s, and the mics by ``d_mics_m`` (D, M, 2), m.
    """
    mics = np.asarray(mic_positions_m, dtype=float)
    src = np.asarray(source_m, dtype=float)
    d_temperature, d_clock, d_mics = (np.asarray(v, dtype=float) for v in (d_temperature_c, d_arrival_s, d_mics_m))
    n_draws, n_mics = d_clock.shape[-2:]
    c_true = np.asarray(speed_of_sound_m_s(temperature_c, relative_humidity_pct), dtype=float)  # (B,)
    c_used = np.asarray(
        speed_of_sound_m_s(
            np.asarray(temperature_c, dtype=float)[:, None] + np.atleast_2d(d_temperature), np.asarray(relative_humidity_pct)[:, None]
        ),
        dtype=float,
    )  # (B, D)
    travel = np.sqrt(((src[:, None, :] - mics[None]) ** 2).sum(-1)) / c_true[:, None]  # (B, M) true travel times, s
    measured = travel[:, None, :] + (d_clock if d_clock.ndim == 3 else d_clock[None])  # (B, D, M) arrival times the recorders report
    used_mics = np.broadcast_to(mics, (n_draws, n_mics, 3)).copy()
    used_mics[..., :2] += d_mics
    p = np.broadcast_to(np.concatenate([src[:, :2], np.zeros((len(src), 1))], axis=1)[:, None, :], (len(src), n_draws, 3)).copy()
    target = measured * c_used[..., None]  # (B, D, M) ranges the user computes, m
    for _ in range(n_iterations):
        offset = np.concatenate([p[..., None, :2] - used_mics[None, :, :, :2], (src[:, None, None, 2:3] - used_mics[None, :, :, 2:3])], -1)
        dist = np.maximum(np.sqrt((offset**2).sum(-1)), 1e-9)  # (B, D, M)
        residual = dist + p[..., 2:3] - target
        jac = np.concatenate([offset[..., :2] / dist[..., None], np.ones((*dist.shape, 1))], -1)  # (B, D, M, 3)
        jtj = np.einsum("bdmi,bdmj->bdij", jac, jac) + 1e-9 * np.eye(3)
        jtr = np.einsum("bdmi,bdm->bdi", jac, residual)
        p = p - np.linalg.solve(jtj, jtr[..., None])[..., 0]
    return p[..., :2] - src[:, None, :2]


def _input_draws(stated: InputErrors, n_mics: int, time_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``N_DRAWS`` fixed draws (seed 0) of the thermometer's error (°C), the clocks' errors in the arrival times (s) and the mics' (m).

    A calibrated clock δ too large leaves the corrected arrival δ early: the draw of a clock
    estimate's error enters the arrival times with its sign flipped (``range_loadings``). With a
    calibration's drifts and ``time_s`` (B,), the clocks' errors are per call: (B, N_DRAWS, M).
    """
    rng = np.random.default_rng(0)
    if isinstance(stated, CorrelatedInputErrors):
        stated.check_array(n_mics)
        # in units of each input's σ: the variances span °C² to (s/s)², and an eigendecomposition's error is relative to the largest
        scale = np.sqrt(np.clip(np.diag(stated.covariance), 0.0, None))
        unit = np.divide(stated.covariance, np.outer(scale, scale), out=np.zeros_like(stated.covariance), where=np.outer(scale, scale) > 0)
        values, vectors = np.linalg.eigh(unit)
        draws = rng.normal(0.0, 1.0, (N_DRAWS, len(values))) @ (vectors * np.sqrt(np.clip(values, 0.0, None))).T * scale
        inputs = draws @ np.swapaxes(stated.transfer(n_mics, time_s), -1, -2)  # (N_DRAWS, 1 + 3M) or (B, N_DRAWS, 1 + 3M)
        return draws[:, 0], -inputs[..., 1 : 1 + n_mics], draws[:, 1 + n_mics : 1 + 3 * n_mics].reshape(N_DRAWS, n_mics, 2)
    d_temperature = rng.normal(0.0, 1.0, N_DRAWS) * stated.temperature_c
    d_mics = rng.normal(0.0, 1.0, (N_DRAWS, n_mics, 2)) * stated.mic_position_m
    d_clock = rng.normal(0.0, 1.0, (N_DRAWS, n_mics)) * stated.clock_offset_s
    return d_temperature, d_clock, d_mics


def _per_axis_sigma(cov: np.ndarray) -> np.ndarray:
    """(B,) per-axis RMS σ, m, of (B, 2, 2) horizontal covariances: √(trace / 2) (``input_sigma_m``)."""
    return np.sqrt(np.maximum(cov[:, 0, 0] + cov[:, 1, 1], 0.0) / 2)


def _per_axis_rms(shifts: np.ndarray) -> np.ndarray:
    """(B,) per-axis RMS, m, of (B, D, 2) Monte Carlo shifts: the same σ as ``_per_axis_sigma`` of their covariance about 0."""
    return np.sqrt(np.mean(shifts**2, axis=(1, 2)))
