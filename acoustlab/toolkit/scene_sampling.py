"""Random draws shared by simulators: source positions, weather, noise (per-event seeded).

Every draw of event ``e`` comes from ``numpy.random.default_rng([seed, stream, e])``, so an
event's data never depends on chunking, sharding or the number of workers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acoustlab.core.types import Site
from acoustlab.toolkit.audio import load_mono
from acoustlab.toolkit.dsp import coloured_noise
from acoustlab.toolkit.geometry import sample_in_expanded_hull

POSITION_STREAM = 0
EVENT_STREAM = 1


def position_rng(seed: int, position_id: int) -> np.random.Generator:
    """The generator of a source position's draws."""
    return np.random.default_rng([int(seed), POSITION_STREAM, int(position_id)])


def event_rng(seed: int, event_id: int) -> np.random.Generator:
    """The generator of an event's draws."""
    return np.random.default_rng([int(seed), EVENT_STREAM, int(event_id)])


def draw_source(site: Site, seed: int, position_id: int) -> np.ndarray:
    """(3,) source position in m: uniform in the expanded hull, height uniform in the site's range."""
    rng = position_rng(seed, position_id)
    xy = sample_in_expanded_hull(rng, site.mic_positions_m, site.hull_expansion, 1)[0]
    return np.array([xy[0], xy[1], rng.uniform(*site.source_height_range_m)])


@dataclass(frozen=True)
class Weather:
    """Air state of one event: temperature in °C and relative humidity in %."""

    temperature_c: float
    relative_humidity_pct: float


def draw_weather(rng: np.random.Generator, site: Site) -> Weather:
    """Temperature and humidity uniform in the site's ranges."""
    return Weather(rng.uniform(*site.temperature_range_c), rng.uniform(*site.relative_humidity_range_pct))


def noise_matrix(
    rng: np.random.Generator, site: Site, regime_index: int, n_samples: int, sample_rate_hz: float, diffuse_fraction: float = 0.0
) -> np.ndarray:
    """(M, n_samples) unit-variance background noise of one regime.

    Each mic gets an independent segment (wind and local sources are incoherent between mics);
    ``diffuse_fraction`` of the power is one shared segment (a distant, spatially diffuse part).
    """
    regime = site.noise_regimes[regime_index]
    m = site.n_mics

    def draw(count: int) -> np.ndarray:
        if regime.kind != "recorded":
            return coloured_noise(rng, (count, n_samples), regime.kind, sample_rate_hz, regime.band_hz)
        out = np.empty((count, n_samples))
        for k in range(count):
            rec = load_mono(regime.files[int(rng.integers(len(regime.files)))], sample_rate_hz)
            if rec.size <= n_samples:
                rec = np.tile(rec, n_samples // max(rec.size, 1) + 2)
            start = int(rng.integers(rec.size - n_samples))
            seg = rec[start : start + n_samples].astype(float)
            seg = seg - seg.mean()
            out[k] = seg / max(seg.std(), 1e-12)
        return out

    local = draw(m)
    if diffuse_fraction <= 0:
        return local
    shared = draw(1)
    return np.sqrt(1 - diffuse_fraction) * local + np.sqrt(diffuse_fraction) * shared


def noise_std_for_snr(clean_nearest: np.ndarray, call_duration_s: float, sample_rate_hz: float, snr_db: float) -> float:
    """Noise standard deviation giving ``snr_db`` at the nearest mic.

    SNR = received call power (energy of the clean signal over the call's duration) / noise power.
    """
    power = float(np.sum(clean_nearest.astype(float) ** 2)) / max(call_duration_s * sample_rate_hz, 1.0)
    return float(np.sqrt(power / 10 ** (snr_db / 10)))
