"""Atmospheric acoustics shared by simulators, features and solvers (SI units, vectorised).

Formulas: speed of sound in humid air by the virtual-temperature form, saturation vapour
pressure and absorption from ISO 9613-1:1993 (see the project's physics notes).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

REFERENCE_PRESSURE_KPA = 101.325
REFERENCE_TEMPERATURE_K = 293.15
TRIPLE_POINT_K = 273.16
KELVIN_OFFSET = 273.15
_GAS_CONSTANT_DRY_AIR_FACTOR = 20.05  # c = 20.05 * sqrt(T_v) m/s, T_v in K


def _check_temperature(temperature_c: np.ndarray) -> None:
    if np.any(~np.isfinite(temperature_c)) or np.any(temperature_c <= -KELVIN_OFFSET):
        raise ValueError(f"temperature_c must be finite and above absolute zero (-273.15 °C); got {temperature_c}")


def _check_humidity(relative_humidity_pct: np.ndarray) -> None:
    if np.any(~np.isfinite(relative_humidity_pct)) or np.any((relative_humidity_pct < 0) | (relative_humidity_pct > 100)):
        raise ValueError(f"relative_humidity_pct must lie in [0, 100] %; got {relative_humidity_pct}")


def saturation_vapour_pressure_ratio(temperature_c: ArrayLike) -> np.ndarray:
    """Saturation vapour pressure over the reference pressure, ISO 9613-1 (B.3).

    Parameters
    ----------
    temperature_c : array_like
        Air temperature in °C.

    Returns
    -------
    numpy.ndarray
        p_sat / p_r (dimensionless).
    """
    t_k = np.asarray(temperature_c, dtype=float) + KELVIN_OFFSET
    c = -6.8346 * (TRIPLE_POINT_K / t_k) ** 1.261 + 4.6151
    return 10.0**c


def speed_of_sound_m_s(
    temperature_c: ArrayLike,
    relative_humidity_pct: ArrayLike = 0.0,
    pressure_kpa: ArrayLike = REFERENCE_PRESSURE_KPA,
) -> np.ndarray | float:
    """Speed of sound in humid air.

    Uses c = 20.05 √T_v with the virtual temperature T_v = T / (1 − 0.378 e/p), where e is the
    water-vapour partial pressure from the ISO 9613-1 saturation pressure. Dry air at 20 °C gives
    343.2 m/s; 100 % RH adds about 1.5 m/s at 20 °C and less than 0.3 m/s below 0 °C.

    Parameters
    ----------
    temperature_c : array_like
        Air temperature in °C.
    relative_humidity_pct : array_like, default 0
        Relative humidity in % (0–100).
    pressure_kpa : array_like, default 101.325
        Static pressure in kPa.

    Returns
    -------
    float or numpy.ndarray
        Speed of sound in m/s, broadcast over the inputs.
    """
    t_c = np.asarray(temperature_c, dtype=float)
    rh = np.asarray(relative_humidity_pct, dtype=float)
    p = np.asarray(pressure_kpa, dtype=float)
    _check_temperature(t_c)
    _check_humidity(rh)
    if np.any(p <= 0):
        raise ValueError(f"pressure_kpa must be positive; got {p}")
    vapour_fraction = (rh / 100.0) * saturation_vapour_pressure_ratio(t_c) * REFERENCE_PRESSURE_KPA / p
    t_virtual = (t_c + KELVIN_OFFSET) / (1.0 - 0.378 * vapour_fraction)
    c = _GAS_CONSTANT_DRY_AIR_FACTOR * np.sqrt(t_virtual)
    return float(c) if c.ndim == 0 else c


def air_absorption_db_per_m(
    frequency_hz: ArrayLike,
    temperature_c: ArrayLike,
    relative_humidity_pct: ArrayLike,
    pressure_kpa: ArrayLike = REFERENCE_PRESSURE_KPA,
) -> np.ndarray | float:
    """Pure-tone atmospheric absorption coefficient, ISO 9613-1:1993 eq. (5).

    Parameters
    ----------
    frequency_hz : array_like
        Frequency in Hz (non-negative).
    temperature_c : array_like
        Air temperature in °C.
    relative_humidity_pct : array_like
        Relative humidity in % (0–100).
    pressure_kpa : array_like, default 101.325
        Static pressure in kPa.

    Returns
    -------
    float or numpy.ndarray
        Absorption in dB/m, broadcast over the inputs; the pressure amplitude after a path of
        r metres is multiplied by 10^(−α r / 20).
    """
    f = np.asarray(frequency_hz, dtype=float)
    t_c = np.asarray(temperature_c, dtype=float)
    rh = np.asarray(relative_humidity_pct, dtype=float)
    p = np.asarray(pressure_kpa, dtype=float)
    _check_temperature(t_c)
    _check_humidity(rh)
    if np.any(f < 0):
        raise ValueError(f"frequency_hz must be non-negative; got {f}")
    t_k = t_c + KELVIN_OFFSET
    p_rel = p / REFERENCE_PRESSURE_KPA
    h = rh * saturation_vapour_pressure_ratio(t_c) / p_rel
    t_rel = t_k / REFERENCE_TEMPERATURE_K
    f_ro = p_rel * (24.0 + 4.04e4 * h * (0.02 + h) / (0.391 + h))
    f_rn = p_rel * t_rel**-0.5 * (9.0 + 280.0 * h * np.exp(-4.170 * (t_rel ** (-1.0 / 3.0) - 1.0)))
    alpha = (
        8.686
        * f**2
        * (
            1.84e-11 / p_rel * t_rel**0.5
            + t_rel**-2.5 * (0.01275 * np.exp(-2239.1 / t_k) / (f_ro + f**2 / f_ro) + 0.1068 * np.exp(-3352.0 / t_k) / (f_rn + f**2 / f_rn))
        )
    )
    return float(alpha) if alpha.ndim == 0 else alpha
