"""How a ground reflection moves a GCC peak: the bias every playback spot shares.

Over flat ground each mic hears the direct path and, ``reflection_delay_s`` later, the path by the
ground (the mic's image below the ground plane). Where that delay is within the GCC peak's width
the two peaks merge and the measured arrival lies part of the way towards the reflection. The part
is the same for every playback on one ground (its reflection coefficient), so playbacks from many
spots do not average it out: it is a bias all spots share, which neither the fit's σ nor the
jackknife over spots can see.

To first order in the reflection's relative amplitude a, PHAT-weighted over a band of angular
frequencies ω, the peak moves by a · Σ ω sin(ωτ) / Σ ω² (the cross-correlation's slope at the
reflection's delay τ over its curvature at 0; the phase of 1 + a e^{−iωτ} is −a sin ωτ). For τ well
inside the peak this is a · τ: the fraction a of the reflection's delay; for τ beyond it, it
oscillates and falls off as 1/τ. ``peak_shift_per_fraction_s`` is that shape per unit a. Derived
here because no library models a GCC peak's merge with a delayed copy of itself.
"""

from __future__ import annotations

import numpy as np

#: Frequencies the band's sums are taken over (uniform in the band; the shape converges well before this).
N_FREQUENCIES = 256


def reflection_delay_s(source_m: np.ndarray, mics_m: np.ndarray, speed_m_s: np.ndarray) -> np.ndarray:
    """(N, M) how much later the ground reflection arrives than the direct path, s (flat ground at z = 0).

    Parameters
    ----------
    source_m : numpy.ndarray
        (N, 3) sources, m (heights above the ground).
    mics_m : numpy.ndarray
        (M, 3) mics, m.
    speed_m_s : numpy.ndarray
        (N,) speed of sound of each source's air, m/s.
    """
    horizontal = np.hypot(source_m[:, None, 0] - mics_m[None, :, 0], source_m[:, None, 1] - mics_m[None, :, 1])
    direct = np.hypot(horizontal, source_m[:, None, 2] - mics_m[None, :, 2])
    reflected = np.hypot(horizontal, source_m[:, None, 2] + mics_m[None, :, 2])
    return (reflected - direct) / np.asarray(speed_m_s, dtype=float)[:, None]


def peak_shift_per_fraction_s(delay_s: np.ndarray, band_hz: tuple[float, float]) -> np.ndarray:
    """How far a reflection ``delay_s`` later moves the direct path's PHAT peak per unit relative amplitude, s (module docstring).

    Parameters
    ----------
    delay_s : numpy.ndarray
        Reflection delays, s, any shape.
    band_hz : (float, float)
        The band the GCC is PHAT-weighted over, Hz.

    Returns
    -------
    numpy.ndarray
        Σ ω sin(ωτ) / Σ ω², the shape of ``delay_s``: τ for a delay well inside the peak.
    """
    low, high = float(band_hz[0]), float(band_hz[1])
    if not 0 <= low < high:
        raise ValueError(f"band_hz must be 0 <= low < high; got {band_hz}")
    omega = 2 * np.pi * np.linspace(low, high, N_FREQUENCIES)
    delay = np.asarray(delay_s, dtype=float)
    return (np.sin(delay[..., None] * omega) @ omega) / float(omega @ omega)
