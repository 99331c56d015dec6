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

With J the (M × 3) Jacobian of (r_i) in (x, y, c·τ₀) and Σ_r the covariance of those range
errors, the least-squares estimate's covariance is (JᵀJ)⁻¹ Jᵀ Σ_r J (JᵀJ)⁻¹; its horizontal
block gives an RMS error σ = √(trace / 2) per axis, and the radius that holds a circular 2-D
Gaussian error at level ℓ is σ √(−2 ln(1 − ℓ)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.physics import speed_of_sound_m_s


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
    """

    temperature_c: float = 1.0
    mic_position_m: float = 0.0
    clock_offset_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("temperature_c", "mic_position_m", "clock_offset_s"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ConfigError(f"conformal.input_uncertainty.{name} must be a finite number >= 0; got {value}")

    @property
    def is_zero(self) -> bool:
        """True where nothing is stated (no allowance)."""
        return self.temperature_c == 0 and self.mic_position_m == 0 and self.clock_offset_s == 0


def position_sigma_m(
    mic_positions_m: np.ndarray,
    source_m: np.ndarray,
    temperature_c: np.ndarray,
    relative_humidity_pct: np.ndarray,
    stated: InputUncertainty,
) -> np.ndarray:
    """(B,) per-axis RMS horizontal position error (m) from the stated input errors (module docstring).

    Parameters
    ----------
    mic_positions_m : numpy.ndarray
        (M, 3) mic positions, m.
    source_m : numpy.ndarray
        (B, 3) estimated source positions, m (NaN rows give NaN).
    temperature_c, relative_humidity_pct : numpy.ndarray
        (B,) the events' weather.
    stated : InputUncertainty
        The standard deviations.
    """
    mics = np.asarray(mic_positions_m, dtype=float)
    src = np.asarray(source_m, dtype=float)
    temperature_c = np.asarray(temperature_c, dtype=float)
    c = np.asarray(speed_of_sound_m_s(temperature_c, relative_humidity_pct), dtype=float)
    dc_dt = np.asarray(speed_of_sound_m_s(temperature_c + 0.5, relative_humidity_pct), dtype=float) - np.asarray(
        speed_of_sound_m_s(temperature_c - 0.5, relative_humidity_pct), dtype=float
    )
    sigma_c = np.abs(dc_dt) * stated.temperature_c
    offset = src[:, None, :] - mics[None, :, :]
    r = np.sqrt((offset**2).sum(-1))  # (B, M)
    u = offset[..., :2] / np.maximum(r, 1e-9)[..., None]  # horizontal unit vectors mic → source
    jac = np.concatenate([u, np.ones((*r.shape, 1))], axis=-1)  # (B, M, 3): d r_i / d (x, y, c τ₀)
    independent = (c * stated.clock_offset_s) ** 2 + stated.mic_position_m**2  # per mic, per unit-direction projection
    cov_r = independent[:, None, None] * np.eye(r.shape[1])[None] + ((sigma_c / c) ** 2)[:, None, None] * r[:, :, None] * r[:, None, :]
    ok = np.isfinite(src).all(axis=1)
    out = np.full(len(src), np.nan)
    if ok.any():
        j = jac[ok]
        pinv = np.linalg.pinv(j)  # (B, 3, M): (JᵀJ)⁻¹ Jᵀ
        cov = pinv @ cov_r[ok] @ np.swapaxes(pinv, 1, 2)
        out[ok] = np.sqrt(np.maximum(cov[:, 0, 0] + cov[:, 1, 1], 0.0) / 2)
    return out


def level_factor(level: float) -> float:
    """√(−2 ln(1 − level)): the radius, in per-axis standard deviations, that holds a circular 2-D Gaussian error at ``level``."""
    return float(np.sqrt(-2 * np.log(1 - level)))
