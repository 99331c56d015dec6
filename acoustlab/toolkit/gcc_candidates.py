"""GCC peak candidates per mic pair, shared by the ``tdoa``, ``xcorr`` and ``uncertainty`` groups.

For each pair (i, j) the correlation is searched only within that pair's physical lag window
±(d_ij / c_max + margin); the K highest local maxima are kept (sub-sample lag by parabolic
interpolation on an upsampled correlation), with their heights and the peak-to-sidelobe ratio.
Results are kept in the batch's own cache (``RecordingBatch.derived``), so several feature
groups on one batch compute the GCC once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acoustlab.core.types import RecordingBatch, Site
from acoustlab.toolkit.dsp import gcc, local_maxima, parabolic_peak
from acoustlab.toolkit.gcc_coarse import check_search, coarse_pair_candidates
from acoustlab.toolkit.physics import speed_of_sound_m_s


@dataclass
class PairCandidates:
    """Peak candidates of every pair of a batch.

    Attributes
    ----------
    lags_s : numpy.ndarray
        (E, P, K) candidate lags t_j − t_i in s, best first (NaN where fewer peaks exist).
    heights : numpy.ndarray
        (E, P, K) GCC heights of the candidates.
    sidelobe : numpy.ndarray
        (E, P) RMS of the correlation within the lag window (for peak-to-sidelobe ratios).
    """

    lags_s: np.ndarray
    heights: np.ndarray
    sidelobe: np.ndarray


def lag_windows_s(site: Site, margin_s: float) -> np.ndarray:
    """(P,) maximum |lag| of each pair in s: distance over the fastest sound speed plus a margin."""
    c_max = speed_of_sound_m_s(site.temperature_range_c[1], site.relative_humidity_range_pct[1])
    mics = site.mic_positions_m
    return np.array([np.linalg.norm(mics[i] - mics[j]) / c_max + margin_s for i, j in site.mic_pairs])


def pair_candidates(
    batch: RecordingBatch,
    site: Site,
    n_candidates: int = 3,
    margin_s: float = 0.002,
    band_hz: tuple[float, float] | np.ndarray | None = None,
    weighting: str = "phat",
    upsample: int = 4,
    beta: float = 0.8,
    band_limited: bool = False,
    device: str = "cpu",
    device_memory_gb: float = 4.0,
    search: str = "fine",
) -> PairCandidates:
    """The K best GCC peaks of every mic pair of every event (see the module docstring).

    ``band_limited`` samples the correlation at ``upsample`` × twice the band's upper edge (see
    ``acoustlab.toolkit.dsp.gcc``). ``device="cuda"`` computes the same on a GPU with torch
    (``acoustlab.toolkit.gcc_torch``: equal up to single-precision rounding); ``"cpu"`` is the
    numpy/SciPy path; ``device_memory_gb`` bounds the GPU memory of one pass of events there.
    ``search="coarse"`` (CPU, ``upsample=2``, not band-limited) searches the peaks on the 1/fs grid
    and refines them on the 1/(2 fs) grid (``acoustlab.toolkit.gcc_coarse``: cheaper, and nearly always the
    same dominant lag).
    """
    check_search(search, upsample, band_limited, device)
    band_key = band_hz.tobytes() if isinstance(band_hz, np.ndarray) else band_hz
    key = ("pair_candidates", n_candidates, margin_s, band_key, weighting, upsample, beta, band_limited, site.mic_positions_m.tobytes())
    if search == "coarse":
        key = (*key, "coarse")
        return batch.derived(key, lambda: _coarse_pair_candidates(batch, site, n_candidates, margin_s, band_hz, weighting, beta))
    if device != "cpu":
        key = (*key, device)
        return batch.derived(
            key,
            lambda: _torch_pair_candidates(
                batch, site, n_candidates, margin_s, band_hz, weighting, upsample, beta, band_limited, device, device_memory_gb
            ),
        )
    return batch.derived(
        key, lambda: _compute_pair_candidates(batch, site, n_candidates, margin_s, band_hz, weighting, upsample, beta, band_limited)
    )


def _torch_pair_candidates(
    batch: RecordingBatch,
    site: Site,
    n_candidates: int,
    margin_s: float,
    band_hz,
    weighting: str,
    upsample: int,
    beta: float,
    band_limited: bool,
    device: str,
    memory_gb: float,
) -> PairCandidates:
    from acoustlab.toolkit.gcc_torch import pair_candidates_torch

    lags, heights, sidelobe = pair_candidates_torch(
        batch.audio,
        site.mic_pairs,
        batch.sample_rate_hz,
        lag_windows_s(site, margin_s),
        n_candidates,
        weighting,
        band_hz,
        upsample,
        beta,
        band_limited,
        device,
        memory_gb,
    )
    return PairCandidates(lags, heights, sidelobe)


def _coarse_pair_candidates(
    batch: RecordingBatch, site: Site, n_candidates: int, margin_s: float, band_hz, weighting: str, beta: float
) -> PairCandidates:
    shared = batch.derived("gcc_spectra", dict)  # the weighted spectra, shared with the other bands of the batch
    lags, heights, sidelobe = coarse_pair_candidates(
        batch.audio,
        site.mic_pairs,
        batch.sample_rate_hz,
        lag_windows_s(site, margin_s),
        n_candidates,
        weighting,
        band_hz,
        beta,
        spectra_cache=shared,
    )
    return PairCandidates(lags, heights, sidelobe)


def _compute_pair_candidates(
    batch: RecordingBatch,
    site: Site,
    n_candidates: int,
    margin_s: float,
    band_hz: tuple[float, float] | None,
    weighting: str,
    upsample: int,
    beta: float,
    band_limited: bool = False,
) -> PairCandidates:
    windows = lag_windows_s(site, margin_s)
    shared = batch.derived("gcc_spectra", dict)  # one transform of the audio for every band and candidate count
    cc, lags = gcc(
        batch.audio,
        site.mic_pairs,
        batch.sample_rate_hz,
        weighting,
        band_hz,
        upsample,
        beta,
        max_lag_s=float(windows.max()),
        spectra_cache=shared,
        band_limited=band_limited,
    )
    step = lags[1] - lags[0]
    e, p = cc.shape[:2]
    out_lags = np.full((e, p, n_candidates), np.nan)
    out_heights = np.full((e, p, n_candidates), np.nan)
    sidelobe = np.empty((e, p))
    for k, max_lag in enumerate(windows):
        inside = np.flatnonzero(np.abs(lags) <= max_lag)  # one contiguous run of lags
        # lags along the fast axis: numpy sums a contiguous row pairwise, whatever the number of events, while events along
        # it (Fortran order) summed each row in sequence unless there was one event, so a feature depended on its batch
        seg = np.ascontiguousarray(cc[:, k, inside[0] : inside[-1] + 1])
        first_lag = lags[inside[0]]
        sidelobe[:, k] = np.sqrt(np.mean(seg**2, axis=-1))
        masked = np.where(local_maxima(seg), seg, -np.inf)  # local maxima (edges allowed), then the K highest
        top = np.argpartition(-masked, min(n_candidates, masked.shape[-1] - 1), axis=-1)[:, :n_candidates]
        order = np.take_along_axis(top, np.argsort(-np.take_along_axis(masked, top, -1), axis=-1), -1)
        valid = np.take_along_axis(masked, order, -1) > -np.inf
        offset, height = parabolic_peak(seg[:, None, :], order)  # broadcast over the K candidates, no copies
        out_lags[:, k] = np.where(valid, first_lag + (order + offset) * step, np.nan)
        out_heights[:, k] = np.where(valid, height, np.nan)
    return PairCandidates(out_lags, out_heights, sidelobe)
