"""Field impairments applied to rendered recordings (off in training simulations).

Timing impairments (clock offsets, path-wise sound-speed perturbations) enter the propagation
model itself; the functions here act on the recorded signals: gain mismatch, non-acoustic
interference at one sensor, and failed channels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.signal as ss

from acoustlab.core.errors import ConfigError

FAILURE_MODES = ("dead", "clipping", "dc")
INTERFERENCE_KINDS = ("clicks", "rubbing")


@dataclass(frozen=True)
class ImpairmentConfig:
    """Knobs of the field impairments (all zero/off = a clean training simulation).

    Attributes
    ----------
    clock_offset_std_s : float
        Standard deviation of each mic's clock error per event, in s (≈1 cm of propagation is 29 µs).
    sound_speed_perturbation : float
        Relative standard deviation of the sound speed along each path (near-surface gradients).
    gain_mismatch_db_std : float
        Standard deviation of each recorder's gain error in dB (fixed per deployment).
    interference_probability : float
        Probability that an event has clicks or rubbing at one sensor.
    failure_probability : float
        Probability that an event has one failed channel (dead, clipping or DC).
    """

    clock_offset_std_s: float = 0.0
    sound_speed_perturbation: float = 0.0
    gain_mismatch_db_std: float = 0.0
    interference_probability: float = 0.0
    failure_probability: float = 0.0

    def __post_init__(self) -> None:
        for name in ("clock_offset_std_s", "sound_speed_perturbation", "gain_mismatch_db_std"):
            if getattr(self, name) < 0:
                raise ConfigError(f"impairments.{name} must be >= 0; got {getattr(self, name)}")
        for name in ("interference_probability", "failure_probability"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"impairments.{name} must be in [0, 1]; got {getattr(self, name)}")


def add_interference(rng: np.random.Generator, channel: np.ndarray, sample_rate_hz: float, kind: str) -> np.ndarray:
    """Non-acoustic interference on one channel: impulsive clicks or a rubbing/handling burst.

    Amplitudes are relative to the channel's peak, so the disturbance dominates where it occurs.
    """
    out = channel.copy()
    peak = max(float(np.max(np.abs(channel))), 1e-12)
    n = channel.size
    if kind == "clicks":
        for _ in range(int(rng.integers(1, 6))):
            at = int(rng.integers(n - 8))
            width = int(rng.integers(1, 6))
            out[at : at + width] += rng.choice([-1, 1]) * rng.uniform(2, 8) * peak
    elif kind == "rubbing":
        length = int(rng.uniform(0.05, 0.3) * sample_rate_hz)
        at = int(rng.integers(max(n - length, 1)))
        nyq = sample_rate_hz / 2
        sos = ss.butter(2, [100 / nyq, min(1500 / nyq, 0.99)], btype="bandpass", output="sos")
        burst = ss.sosfilt(sos, rng.standard_normal(length)) * ss.windows.tukey(length, 0.3)
        burst *= rng.uniform(1, 4) * peak / max(np.max(np.abs(burst)), 1e-12)
        out[at : at + length] += burst[: n - at]
    else:
        raise ConfigError(f"interference kind must be one of {INTERFERENCE_KINDS}; got {kind!r}")
    return out


def fail_channel(rng: np.random.Generator, channel: np.ndarray, mode: str) -> np.ndarray:
    """A failed channel: ``dead`` (near-silent), ``clipping`` (hard clip at 5–30 % of peak) or ``dc``.

    ``dc`` adds a large offset with slow drift, as a failing preamplifier does.
    """
    peak = max(float(np.max(np.abs(channel))), 1e-12)
    if mode == "dead":
        return 1e-4 * peak * rng.standard_normal(channel.size)
    if mode == "clipping":
        level = rng.uniform(0.05, 0.3) * peak
        return np.clip(channel, -level, level)
    if mode == "dc":
        drift = np.linspace(0, rng.uniform(-1, 1), channel.size) * peak
        return channel + rng.uniform(2, 10) * peak + drift
    raise ConfigError(f"failed-channel mode must be one of {FAILURE_MODES}; got {mode!r}")
