"""GCC peak candidates searched on the 1/fs lag grid and refined on the default 1/(2 fs) grid (``features.gcc.search=coarse``).

The default GCC (``acoustlab.toolkit.gcc_candidates.pair_candidates``, ``upsample=2``) inverse
transforms every pair's cross-spectrum at twice the sampling rate and picks the K highest local
maxima of that grid. Here the inverse transforms run at the sampling rate (half as long), and only
the neighbourhoods of likely peaks are brought to the finer grid:

1. the correlation on the 1/fs grid (``acoustlab.toolkit.dsp.gcc`` with ``upsample=1``), halved
   to the default's amplitude (an inverse transform half as long);
2. per pair window, the M highest local maxima, and the M highest local maxima of the sums of
   neighbouring samples (a peak half-way between two samples, neither of them a maximum), each
   centred on a sample, with the window's sum of squares, in one compiled pass
   (``acoustlab.toolkit.window_peaks.window_peaks``; ties go to the lower lag);
3. the two half-sample values beside each centre by band-limited interpolation: a Kaiser-windowed
   sinc (the cross-spectrum is zero above the band, so the correlation is a band-limited function
   of lag); with the centre and its two neighbours that gives the five samples of the fine grid
   around it;
4. the fine-grid local maximum among the three central samples (≥ its left neighbour, > its right
   one, the default's rule) and its parabolic refinement; the K candidates with the highest
   fine-grid sample, best first (the default's ranking), with their parabolic heights (all pairs'
   centres refined together); the RMS of the window on the 1/fs grid as the sidelobe level.

It can miss a narrow peak half-way between two samples when both samples lie far below it (a
component near the band's upper edge loses up to three quarters of its height there). Written by
hand: no library picks peaks of a band-limited sequence between its samples.
"""

from __future__ import annotations

import functools
import logging
import sys

import numpy as np
import scipy.signal as ss
from numpy.lib.stride_tricks import sliding_window_view

from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.dsp import gcc, parabolic_peak

log = logging.getLogger(__name__)

#: Coarse maxima refined per pair window and kind (maxima of the samples, maxima of the two-sample sums).
SEARCHED = 16

#: Taps of the half-sample interpolation kernel (an error of about 3e-5 of the peak on the forest).
TAPS = 32


def check_search(search: str, upsample: int, band_limited: bool = False, device: str = "cpu") -> str:
    """``search`` if the GCC can search that way with these settings, else a ``ConfigError`` naming ``features.gcc.search``.

    ``fine`` always works; ``coarse`` refines on the grid of ``upsample=2``, with the CPU path and
    the main band (not band-limited).
    """
    if search not in ("fine", "coarse"):
        raise ConfigError(f"features.gcc.search must be 'fine' or 'coarse'; got {search!r}")
    if search == "coarse" and (device != "cpu" or int(upsample) != 2 or band_limited):
        raise ConfigError(
            f"features.gcc.search=coarse refines on the grid of upsample=2 with the CPU path; got upsample={upsample}, "
            f"device={device}, band_limited={band_limited} (use search=fine there)"
        )
    return search


@functools.lru_cache(maxsize=4)
def half_sample_kernel(taps: int = TAPS, kaiser_beta: float = 8.6) -> np.ndarray:
    """Weights (taps,) giving x(m + ½) from x(m − taps/2 + 1) … x(m + taps/2): a Kaiser-windowed sinc (read-only)."""
    offsets = np.arange(-taps // 2 + 1, taps // 2 + 1) - 0.5
    kernel = (np.sinc(offsets) * ss.windows.kaiser(taps, kaiser_beta)).astype(np.float32)
    kernel.setflags(write=False)
    return kernel


def half_samples(values: np.ndarray, index: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Interpolated values(index + ½) along the last axis of ``values`` (..., L) for integer ``index`` (..., C); samples beyond the ends
    are clamped."""
    taps = kernel.size
    around = index[..., None] + np.arange(-taps // 2 + 1, taps // 2 + 1)
    gathered = np.take_along_axis(values[..., None, :], np.clip(around, 0, values.shape[-1] - 1), -1)
    return np.einsum("...t,t->...", gathered, kernel)  # not @: BLAS would round a row by its batch-mates


def coarse_pair_candidates(
    audio: np.ndarray,
    pairs: list[tuple[int, int]],
    sample_rate_hz: float,
    windows_s: np.ndarray,
    n_candidates: int,
    weighting: str,
    band_hz,
    beta: float,
    spectra_cache: dict | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K best peaks of every pair on the default's 1/(2 fs) grid, searched on the 1/fs grid (module docstring).

    Parameters
    ----------
    audio : numpy.ndarray
        (E, M, S) recordings.
    pairs : list of (int, int)
        Mic pairs; the peak of pair (i, j) lies at t_j − t_i.
    sample_rate_hz : float
        Sampling rate, Hz.
    windows_s : numpy.ndarray
        (P,) largest |lag| of each pair, s.
    n_candidates : int
        Peaks kept per pair (K).
    weighting, band_hz, beta
        As ``acoustlab.toolkit.dsp.gcc``.
    spectra_cache : dict, optional
        Shared weighted spectra of ``audio`` (see ``acoustlab.toolkit.dsp.gcc``).

    Returns
    -------
    lags_s : numpy.ndarray
        (E, P, K) candidate lags in s, best first (NaN where fewer peaks exist).
    heights : numpy.ndarray
        (E, P, K) parabolic heights on the fine grid (NaN likewise).
    sidelobe : numpy.ndarray
        (E, P) RMS of the correlation within each pair's window.
    """
    windows_s = np.asarray(windows_s, dtype=float)
    cc, lags = gcc(audio, pairs, sample_rate_hz, weighting, band_hz, 1, beta, max_lag_s=float(windows_s.max()), spectra_cache=spectra_cache)
    # an inverse transform half as long as the default's has half its amplitude: the heights and the sidelobe level are halved at the
    # end (exactly: a factor of 2 changes no rounding), not the whole correlation
    fine_step = (lags[1] - lags[0]) / 2
    e, p = cc.shape[:2]
    lags_out, heights_out = np.full((e, p, n_candidates), np.nan), np.full((e, p, n_candidates), np.nan)
    sidelobe = np.empty((e, p))
    centres, valid = np.zeros((e, p, 2 * SEARCHED), dtype=np.int64), np.zeros((e, p, 2 * SEARCHED), dtype=bool)
    firsts = np.empty(p, dtype=np.int64)
    for k, max_lag in enumerate(windows_s):  # the peaks of every window, then one refinement for all pairs
        inside = np.flatnonzero(np.abs(lags) <= max_lag)
        firsts[k] = inside[0]
        seg = cc[:, k, inside[0] : inside[-1] + 1]
        centre, is_peak, sum_of_squares = _centres(seg)
        sidelobe[:, k] = np.sqrt(sum_of_squares / seg.shape[-1]) * 0.5
        centres[:, k, : centre.shape[-1]], valid[:, k, : centre.shape[-1]] = centre + firsts[k], is_peak
    fine_peak, offset, value, height = _refine(cc, centres, half_sample_kernel())
    rank = np.where(valid & np.isfinite(value), value, -np.inf)
    fine_peak = fine_peak - 2 * firsts[:, None]  # fine steps from each window's first lag
    rank = np.where(_repeated(fine_peak, rank > -np.inf), -np.inf, rank)  # one candidate per fine peak
    order = np.argsort(-rank, axis=-1, kind="stable")[..., :n_candidates]
    ok = np.take_along_axis(rank, order, -1) > -np.inf
    chosen = np.take_along_axis(fine_peak + offset, order, -1)
    lags_out[..., : order.shape[-1]] = np.where(ok, lags[firsts][:, None] + chosen * fine_step, np.nan)
    heights_out[..., : order.shape[-1]] = np.where(ok, np.take_along_axis(height, order, -1) * height.dtype.type(0.5), np.nan)
    return lags_out, heights_out, sidelobe


def _centres(seg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples (E, C) of a window to refine around (the top local maxima, then the top maxima of two-sample sums on their
    higher sample), which of them are maxima, and the window's sum of squares (E,) (``window_peaks``)."""
    if "acoustlab.toolkit.window_peaks" not in sys.modules:  # say why the first coarse search may pause
        log.info("loading the compiled GCC peak search (numba): the first use on a machine compiles it once, then it is cached")
    from acoustlab.toolkit.window_peaks import window_peaks  # numba: imported by the first coarse search only

    n = seg.shape[-1]
    m, m_sum = max(1, min(SEARCHED, n - 1)), (max(1, min(SEARCHED, n - 2)) if n >= 2 else 0)
    found = window_peaks(seg, m, m_sum)
    valid = np.arange(m) < found.n_top[:, None]
    if m_sum == 0:
        return found.top, valid, found.sum_of_squares
    top_sum = found.top_sum + (np.take_along_axis(seg, found.top_sum + 1, -1) > np.take_along_axis(seg, found.top_sum, -1))
    valid_sum = np.arange(m_sum) < found.n_sum[:, None]
    return np.concatenate([found.top, top_sum], axis=-1), np.concatenate([valid, valid_sum], axis=-1), found.sum_of_squares


def _refine(rows: np.ndarray, centre: np.ndarray, kernel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fine-grid peak near each centre (E, P, C) of ``rows`` (E, P, L): its fine index (2 × row index ± 1), parabolic offset, sample
    value and height.

    The value is −inf where none of the three central fine samples is a local maximum.
    """
    fine = _fine_samples(rows, centre, kernel)  # (E, P, C, 5)
    central = fine[..., 1:4]
    peak_ok = (central >= fine[..., 0:3]) & (central > fine[..., 2:5])
    best = np.argmax(np.where(peak_ok, central, -np.inf), axis=-1)  # 0, 1, 2: fine offsets −1, 0, +1 from the centre
    offset, height = parabolic_peak(fine, best + 1)  # the peak's neighbours are always among the five samples
    mid = np.take_along_axis(fine, (best + 1)[..., None], -1)[..., 0]
    value = np.where(peak_ok.any(-1), mid, -np.inf)
    return 2 * centre + best - 1, offset, value, height


def _fine_samples(rows: np.ndarray, centre: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """(E, P, C, 5) the fine grid around each centre of ``rows`` (E, P, L): values at centre − 1, − ½, 0, + ½, + 1 (samples beyond the
    ends clamped, as ``half_samples``).

    Both half samples and the three samples lie in the taps + 1 samples from centre − taps/2 on: one gather of those windows (a view
    of every window, indexed), not three gathers through index arrays; centres whose window crosses an end are gathered with clamping.
    """
    taps, n = kernel.size, rows.shape[-1]
    if n < taps + 1:
        return _assemble(_clamped_windows(rows, centre, taps), kernel)
    start = centre - taps // 2
    clamped = (start < 0) | (start > n - taps - 1)
    e, p = np.ogrid[: rows.shape[0], : rows.shape[1]]
    windows = sliding_window_view(rows, taps + 1, axis=-1)[e[..., None], p[..., None], np.clip(start, 0, n - taps - 1)]
    fine = _assemble(windows, kernel)
    if clamped.any():  # whole rows of centres again, clamped: the products then run in the same blocks as everywhere else
        crossing = clamped.any(-1)
        fine[crossing] = _assemble(_clamped_windows(rows[crossing], centre[crossing], taps), kernel)
    return fine


def _clamped_windows(rows: np.ndarray, centre: np.ndarray, taps: int) -> np.ndarray:
    """(..., C, taps + 1) samples centre − taps/2 … centre + taps/2 of ``rows`` (..., L), positions beyond the ends clamped."""
    around = np.clip(centre[..., None] + np.arange(-(taps // 2), taps // 2 + 1), 0, rows.shape[-1] - 1)
    return np.take_along_axis(rows[..., None, :], around, -1)


def _assemble(windows: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """(..., 5) fine samples from windows (..., taps + 1) of samples centre − taps/2 … centre + taps/2."""
    taps, mid = kernel.size, kernel.size // 2
    # values at centre − ½ and centre + ½ (einsum, not @: BLAS would round a row by its batch-mates)
    left, right = np.einsum("...t,t->...", windows[..., :taps], kernel), np.einsum("...t,t->...", windows[..., 1:], kernel)
    return np.stack([windows[..., mid - 1], left, windows[..., mid], right, windows[..., mid + 1]], axis=-1)


def _repeated(index: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """(..., C) True where a kept entry's value already occurred at an earlier kept position of its row (others: False)."""
    key = np.where(kept, index, np.iinfo(np.int64).min + np.arange(index.shape[-1]))  # entries not kept: unique keys
    order = np.argsort(key, axis=-1, kind="stable")
    ordered = np.take_along_axis(key, order, -1)
    repeated = np.zeros(ordered.shape, dtype=bool)
    repeated[..., 1:] = ordered[..., 1:] == ordered[..., :-1]
    out = np.zeros_like(repeated)
    np.put_along_axis(out, order, repeated, -1)
    return out & kept
