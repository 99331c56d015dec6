"""Context feature groups: ``geometry`` (the array) and ``environment`` (weather, levels, SNR)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.toolkit.physics import speed_of_sound_m_s

FRAME_S = 0.01


class ArrayGeometry:
    """``geometry``: mic spacing per pair and the array aperture, in m (constant within a site)."""

    group = "geometry"
    cache_version = "1"

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        return [(f"geometry__spacing_{i}_{j}_m", "m", f"distance between mics {i} and {j}") for i, j in site.mic_pairs] + [
            ("geometry__aperture_m", "m", "largest mic-to-mic distance")
        ]

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        mics = site.mic_positions_m
        cols = {f"geometry__spacing_{i}_{j}_m": np.full(batch.n_events, np.linalg.norm(mics[i] - mics[j])) for i, j in site.mic_pairs}
        cols["geometry__aperture_m"] = np.full(batch.n_events, site.max_mic_distance_m)
        return pd.DataFrame(cols)


def frame_levels_db(audio: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    """(E, M, F) RMS level of 10 ms frames in dB (re 1)."""
    frame = max(int(FRAME_S * sample_rate_hz), 1)
    e, m, n = audio.shape
    k = n // frame
    samples = audio[..., : k * frame].astype(float)
    np.square(samples, out=samples)  # in place: one double-precision copy of the audio, not two
    power = samples.reshape(e, m, k, frame).mean(-1)
    return 10 * np.log10(np.maximum(power, 1e-30))


class Environment:
    """``environment``: measured weather, the speed of sound, and per-mic received level, noise level and SNR.

    Received level: mean power of the loudest 10 % of 10 ms frames (the call); noise level: mean
    power of the quietest 20 %; SNR their difference, all in dB.
    """

    group = "environment"
    cache_version = "1"

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        rows = [
            (col.ENV_TEMPERATURE, "°C", "air temperature recorded with the event"),
            (col.ENV_HUMIDITY, "%", "relative humidity recorded with the event"),
            (col.ENV_SPEED_OF_SOUND, "m/s", "speed of sound from temperature and humidity"),
        ]
        for m in range(site.n_mics):
            rows += [
                (col.level_db(m), "dB", "received level: power of the loudest 10 % of 10 ms frames"),
                (col.noise_db(m), "dB", "noise level: power of the quietest 20 % of 10 ms frames"),
                (col.snr_db(m), "dB", "received level minus noise level"),
            ]
        return rows

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        ev = batch.events
        t = ev[col.TEMPERATURE].to_numpy(float)
        rh = ev[col.HUMIDITY].to_numpy(float)
        cols = {
            col.ENV_TEMPERATURE: t,
            col.ENV_HUMIDITY: rh,
            col.ENV_SPEED_OF_SOUND: np.where(
                np.isfinite(t) & np.isfinite(rh), speed_of_sound_m_s(np.nan_to_num(t, nan=10.0), np.nan_to_num(rh, nan=50.0)), np.nan
            ),
        }
        levels = np.sort(frame_levels_db(batch.audio, batch.sample_rate_hz), axis=-1)
        k = levels.shape[-1]
        loud = 10 * np.log10(np.mean(10 ** (levels[..., -max(k // 10, 1) :] / 10), axis=-1))
        quiet = 10 * np.log10(np.mean(10 ** (levels[..., : max(k // 5, 1)] / 10), axis=-1))
        for m in range(site.n_mics):
            cols[col.level_db(m)] = loud[:, m]
            cols[col.noise_db(m)] = quiet[:, m]
            cols[col.snr_db(m)] = loud[:, m] - quiet[:, m]
        return pd.DataFrame(cols)
