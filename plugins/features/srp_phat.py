"""SRP-PHAT grid search (score-based baseline, group ``srp``): steered response power over a grid.

For every grid point the GCC-PHAT of each pair is read at the lag that point implies (linear
interpolation) and summed over pairs; a coarse grid over the plausibility box is followed by a
fine grid around its maximum. It needs the audio, so it lives in the (cached) feature stage;
its estimate is compared with the solvers in ``experiments/solvers.py``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.ndimage import maximum_filter1d

from acoustlab.core import columns as col
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.toolkit.dsp import event_band_hz, gcc
from acoustlab.toolkit.event_physics import assumed_source_height_m, event_speed_of_sound_m_s
from acoustlab.toolkit.geometry import bounding_box


def _steered_power(
    cc: np.ndarray, lag0_s: float, step_s: float, grid: np.ndarray, mics: np.ndarray, pairs, height: float, c: np.ndarray
) -> np.ndarray:
    """(E, G) summed GCC over pairs at the lags implied by grid points (E, G, 2) for sound speeds c (E,)."""
    src = np.concatenate([grid, np.full(grid.shape[:-1] + (1,), height)], axis=-1)
    dist = np.sqrt(((src[..., None, :] - mics) ** 2).sum(-1))  # (E, G, M)
    total = np.zeros(grid.shape[:-1])
    n_lags = cc.shape[-1]
    rows = np.arange(cc.shape[0])[:, None]
    for p, (i, j) in enumerate(pairs):
        pos = ((dist[..., j] - dist[..., i]) / c[:, None] - lag0_s) / step_s
        i0 = np.clip(np.floor(pos).astype(int), 0, n_lags - 2)
        frac = np.clip(pos - i0, 0, 1)
        total += cc[rows, p, i0] * (1 - frac) + cc[rows, p, i0 + 1] * frac
    return total


class SrpPhat:
    """``srp``: SRP-PHAT position estimate (x, y in m) and its normalised peak power.

    Parameters
    ----------
    coarse_step_m, fine_step_m : float
        Grid spacings of the two passes, m.
    fine_half_width_m : float
        Half-width of the fine grid around the coarse maximum, m.
    box_margin_fraction : float
        The search box: the mics' bounding box grown by this fraction of the array extent.
    band_hz : list of float
        Band of the PHAT-weighted cross-spectrum, Hz.
    """

    group = "srp"
    cache_version = "1"

    def __init__(
        self,
        coarse_step_m: float = 2.0,
        fine_step_m: float = 0.2,
        fine_half_width_m: float = 3.0,
        box_margin_fraction: float = 0.25,
        band_hz=(300.0, 10000.0),
    ) -> None:
        self.coarse_step_m = float(coarse_step_m)
        self.fine_step_m = float(fine_step_m)
        self.fine_half_width_m = float(fine_half_width_m)
        self.box_margin_fraction = float(box_margin_fraction)
        self.band_hz = (float(band_hz[0]), float(band_hz[1]))

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        return [
            (col.SRP_X, "m", "SRP-PHAT estimate, x"),
            (col.SRP_Y, "m", "SRP-PHAT estimate, y"),
            (col.SRP_POWER, "1", "steered response power at the estimate over the number of pairs"),
        ]

    @staticmethod
    def _spread(cc: np.ndarray, cell_m: float, step_s: float, c: np.ndarray) -> np.ndarray:
        """Running maximum of the correlation over the lag span (±) of a grid cell of ``cell_m``."""
        width = int(np.ceil(2 * cell_m / np.min(c) / step_s)) | 1
        return maximum_filter1d(cc, size=width, axis=-1, mode="nearest") if width > 1 else cc

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        mics = site.mic_positions_m
        pairs = site.mic_pairs
        cc, lags = gcc(batch.audio, pairs, batch.sample_rate_hz, "phat", event_band_hz(batch.events, self.band_hz, batch.sample_rate_hz), 2)
        c = event_speed_of_sound_m_s(batch.events)
        height = assumed_source_height_m(site)
        low, high = bounding_box(mics, self.box_margin_fraction)
        gx, gy = np.meshgrid(np.arange(low[0], high[0] + 1e-9, self.coarse_step_m), np.arange(low[1], high[1] + 1e-9, self.coarse_step_m))
        coarse = np.broadcast_to(np.column_stack([gx.ravel(), gy.ravel()]), (batch.n_events, gx.size, 2))
        step_s = lags[1] - lags[0]
        # PHAT peaks are a fraction of a millisecond wide, far narrower than a coarse cell: each pass
        # reads the correlation's maximum over the lag span of one cell (as locaR's modified SRP does)
        cc_coarse = self._spread(cc, self.coarse_step_m, step_s, c)
        power = _steered_power(cc_coarse, lags[0], step_s, coarse, mics, pairs, height, c)
        best = coarse[np.arange(batch.n_events), np.argmax(power, axis=1)]
        off = np.arange(-self.fine_half_width_m, self.fine_half_width_m + 1e-9, self.fine_step_m)
        fx, fy = np.meshgrid(off, off)
        fine = best[:, None, :] + np.column_stack([fx.ravel(), fy.ravel()])[None]
        power = _steered_power(self._spread(cc, self.fine_step_m, step_s, c), lags[0], step_s, fine, mics, pairs, height, c)
        k = np.argmax(power, axis=1)
        est = fine[np.arange(batch.n_events), k]
        return pd.DataFrame({col.SRP_X: est[:, 0], col.SRP_Y: est[:, 1], col.SRP_POWER: power[np.arange(batch.n_events), k] / len(pairs)})
