"""GCC-PHAT dominant-peak TDOA per mic pair (feature group ``tdoa``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.toolkit.dsp import event_band_hz, gcc, parabolic_peak
from acoustlab.toolkit.physics import speed_of_sound_m_s


def tdoa_column(i: int, j: int) -> str:
    """Name of the pair (i, j) lag column: arrival at mic j minus arrival at mic i, in s."""
    return col.tdoa_lag(i, j)


class GccPhatTdoa:
    """Dominant GCC-PHAT peak per mic pair, searched within that pair's physical lag window.

    The window of pair (i, j) is ±(d_ij / c_max + margin), with c_max the fastest sound speed of
    the site's weather range; the peak is refined to sub-sample precision by a parabola.

    Parameters
    ----------
    max_lag_margin_s : float
        Extra lag allowed beyond the pair's distance over c, in s.
    band_hz : list of float, optional
        (low, high) band of the cross-spectrum in Hz; None for the full band.
    upsample : int
        Lag-resolution factor of the correlation before parabolic peak refinement.
    """

    group = "tdoa"
    cache_version = "1"

    def __init__(self, max_lag_margin_s: float = 0.002, band_hz: Sequence[float] | None = (300.0, 10000.0), upsample: int = 4) -> None:
        if max_lag_margin_s < 0:
            raise ConfigError(f"features tdoa.max_lag_margin_s must be >= 0; got {max_lag_margin_s}")
        self.max_lag_margin_s = float(max_lag_margin_s)
        self.band_hz = None if band_hz is None else (float(band_hz[0]), float(band_hz[1]))
        self.upsample = int(upsample)

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        """(name, unit, definition) of every column, in table order."""
        return [(tdoa_column(i, j), "s", f"lag t_{j} − t_{i} of the dominant GCC-PHAT peak") for i, j in site.mic_pairs]

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        """One row per event: ``tdoa__lag_i_j_s`` for every pair i < j."""
        pairs = site.mic_pairs
        band = event_band_hz(batch.events, self.band_hz, batch.sample_rate_hz)
        cc, lags_s = gcc(batch.audio, pairs, batch.sample_rate_hz, "phat", band, self.upsample)
        c_max = speed_of_sound_m_s(site.temperature_range_c[1], site.relative_humidity_range_pct[1])
        mics = site.mic_positions_m
        out = {}
        for p, (i, j) in enumerate(pairs):
            max_lag = np.linalg.norm(mics[i] - mics[j]) / c_max + self.max_lag_margin_s
            window = np.abs(lags_s) <= max_lag
            segment = cc[:, p, window]
            peak = np.argmax(segment, axis=-1)
            offset, _ = parabolic_peak(segment, peak)
            lag_step_s = lags_s[1] - lags_s[0]
            out[tdoa_column(i, j)] = lags_s[window][0] + (peak + offset) * lag_step_s
        return pd.DataFrame(out)
