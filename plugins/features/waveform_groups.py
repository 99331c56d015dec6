"""Waveform feature groups estimated blindly from the recordings: ``ir``, ``spectral``, ``envelope``.

Nothing here reads the simulator's ground truth, so field recordings get exactly the same features.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import scipy.fft as sfft
import scipy.signal as ss
from scipy import ndimage

from acoustlab.core import columns as col
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.toolkit.gcc_candidates import lag_windows_s

FRAME_S = 0.005


#: Zero padding of the one-transform envelope, s: the band-pass' response decays within it, so nothing wraps around.
ENVELOPE_PAD_S = 0.05


def _hilbert_magnitude(audio: np.ndarray, sample_rate_hz: float, band_hz: tuple[float, float]) -> np.ndarray:
    """|analytic signal| of the zero-phase band-passed signals, (E, M, S), from one forward and one inverse transform.

    The 4th-order Butterworth band-pass applied forward and backward is its squared magnitude
    response; the analytic signal keeps the positive frequencies, doubled. Both are one product
    with the recording's spectrum (zero-padded by ``ENVELOPE_PAD_S``), followed by one inverse
    transform: the same envelope as ``sosfiltfilt`` then ``scipy.signal.hilbert`` away from the
    clip's first and last 50 ms (which those pad differently), at half the cost; in single
    precision, a third of that again.
    """
    n = audio.shape[-1]
    n_fft = sfft.next_fast_len(n + int(ENVELOPE_PAD_S * sample_rate_hz))
    nyq = sample_rate_hz / 2
    sos = ss.butter(4, [band_hz[0] / nyq, min(band_hz[1] / nyq, 0.99)], btype="bandpass", output="sos")
    spectrum = sfft.rfft(audio, n=n_fft, axis=-1)
    _, response = ss.sosfreqz(sos, worN=2 * np.pi * np.arange(spectrum.shape[-1]) / n_fft)
    gain = np.abs(response) ** 2
    gain[1:] *= 2.0  # positive frequencies of the analytic signal, doubled
    if n_fft % 2 == 0:
        gain[-1] /= 2.0  # the Nyquist bin is its own mirror
    # transforms in single precision like the recordings (float32 audio has ~7 digits; the envelope moves by < 1e-6 of its peak)
    analytic = np.zeros((*audio.shape[:-1], n_fft), dtype=np.complex64)
    np.multiply(spectrum, gain.astype(np.float32), out=analytic[..., : spectrum.shape[-1]])
    return np.abs(sfft.ifft(analytic, axis=-1, overwrite_x=True)[..., :n]).astype(np.float64)  # what follows sums over it


def envelope(batch: RecordingBatch, band_hz: tuple[float, float], smooth_s: float = 0.005) -> np.ndarray:
    """Smoothed Hilbert envelope of band-passed signals, (E, M, S).

    The band-passed Hilbert magnitude is computed once per batch and band (the ``ir`` and
    ``envelope`` groups share it); only the smoothing differs.
    """
    fs = batch.sample_rate_hz
    env = batch.derived(("hilbert_magnitude", band_hz), lambda: _hilbert_magnitude(batch.audio, fs, band_hz))
    win = max(int(smooth_s * fs), 1)
    # moving average over samples i − win//2 … i + win − win//2 − 1, zeros beyond the ends: the centred
    # ("same") convolution with a boxcar of win samples, as a running sum (O(S) instead of an FFT)
    return ndimage.uniform_filter1d(env, win, axis=-1, mode="constant", cval=0.0)


def _after(values: np.ndarray, start: np.ndarray, span_s: float, fs: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples of ``values`` (E, M, S) from ``start`` (E, M) on, long enough to hold ``span_s``: (E, M, L) values,
    time after ``start`` in s (as ``t[i] − t[start]`` with ``t = arange(S) / fs``, so masks on it select the same
    samples as masks on full-length arrays) and whether the sample exists."""
    n = values.shape[-1]
    index = start[..., None] + np.arange(int(np.ceil(span_s * fs)) + 2)
    exists = index < n
    index = np.minimum(index, n - 1)
    t = np.arange(n) / fs
    return np.take_along_axis(values, index, -1), t[index] - t[start][..., None], exists


class BlindIrSummaries:
    """``ir``: reverberation summaries of each channel from its band-passed energy envelope.

    Per mic: decay slope of the envelope over 0–100 ms after its peak (dB/s), early-to-late energy
    ratio (0–50 ms vs 50–300 ms after onset, dB), onset sharpness (10 %→90 % rise time, s) and the
    spread of arrivals (time the envelope stays within 10 dB of its peak, s).

    Parameters
    ----------
    band_hz : list of float
        (low, high) analysis band in Hz.
    """

    group = "ir"
    cache_version = "2"  # 2: the band-passed envelope from one transform

    def __init__(self, band_hz=(1000.0, 8000.0)) -> None:
        self.band_hz = (float(band_hz[0]), float(band_hz[1]))

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        rows = []
        for m in range(site.n_mics):
            rows += [
                (f"ir__decay_{m}_db_s", "dB/s", "slope of the envelope (dB) over 0–100 ms after its peak"),
                (f"ir__early_late_{m}_db", "dB", "energy 0–50 ms after onset over 50–300 ms after onset"),
                (f"ir__rise_time_{m}_s", "s", "10 % to 90 % rise time of the envelope before its peak"),
                (col.ir_spread_s(m), "s", "time the envelope stays within 10 dB of its peak"),
            ]
        return rows

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        fs = batch.sample_rate_hz
        env = envelope(batch, self.band_hz)
        e, m, n = env.shape
        peak = np.argmax(env, axis=-1)
        peak_val = np.take_along_axis(env, peak[..., None], -1)[..., 0]
        floor_peak = np.maximum(peak_val, 1e-12)[..., None]
        # decay: least-squares slope of the envelope (dB) over 0–100 ms after the peak, computed on that window only
        after_peak, rel, exists = _after(env, peak, 0.1, fs)
        env_db = 20 * np.log10(np.maximum(after_peak, 1e-12) / floor_peak)
        w = (exists & (rel >= 0) & (rel <= 0.1)).astype(float)
        cnt = np.maximum(w.sum(-1), 2)
        mt = (w * rel).sum(-1) / cnt
        my = (w * env_db).sum(-1) / cnt
        slope = (w * (rel - mt[..., None]) * (env_db - my[..., None])).sum(-1) / np.maximum((w * (rel - mt[..., None]) ** 2).sum(-1), 1e-12)
        onset = np.argmax(env >= 0.1 * peak_val[..., None], axis=-1)  # first sample at 10 % of the peak
        first90 = np.argmax(env >= 0.9 * peak_val[..., None], axis=-1)
        rise = np.maximum(first90 - onset, 0) / fs
        # early (0–50 ms after the onset) and late (50–300 ms) energy, on the 300 ms after the onset only
        after_onset, rel_on, exists = _after(env, onset, 0.3, fs)
        energy = after_onset**2 * exists
        early = (energy * ((rel_on >= 0) & (rel_on < 0.05))).sum(-1)
        late = (energy * ((rel_on >= 0.05) & (rel_on < 0.3))).sum(-1)
        early_late = 10 * np.log10(np.maximum(early, 1e-20) / np.maximum(late, 1e-20))
        # time within 10 dB of the peak, the comparison in dB on the samples above 0.3 × the peak (−10 dB is 0.316 ×)
        near = (env >= 0.3 * peak_val[..., None]) | (peak_val < 1e-12)[..., None]
        channel, sample = np.nonzero(near.reshape(e * m, n))
        within = 20 * np.log10(np.maximum(env.reshape(e * m, n)[channel, sample], 1e-12) / floor_peak.reshape(-1)[channel]) > -10
        spread = np.bincount(channel[within], minlength=e * m).reshape(e, m) / fs
        cols = {}
        for k in range(m):
            cols[f"ir__decay_{k}_db_s"] = slope[:, k]
            cols[f"ir__early_late_{k}_db"] = early_late[:, k]
            cols[f"ir__rise_time_{k}_s"] = rise[:, k]
            cols[col.ir_spread_s(k)] = spread[:, k]
        return pd.DataFrame(cols)


class SpectralSummaries:
    """``spectral``: spectral centroid, bandwidth and 85 % roll-off per mic, and pairwise centroid differences.

    Computed on the 100 ms around each channel's loudest 5 ms frame (the call), in Hz.
    """

    group = "spectral"
    cache_version = "1"

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        rows = []
        for m in range(site.n_mics):
            rows += [
                (col.spectral_centroid_hz(m), "Hz", "power-weighted mean frequency around the loudest frame"),
                (col.spectral_bandwidth_hz(m), "Hz", "power-weighted standard deviation of frequency"),
                (f"spectral__rolloff_{m}_hz", "Hz", "frequency below which 85 % of the power lies"),
            ]
        rows += [(f"spectral__centroid_diff_{i}_{j}_hz", "Hz", f"centroid of mic {i} minus mic {j}") for i, j in site.mic_pairs]
        return rows

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        fs = batch.sample_rate_hz
        frame = max(int(FRAME_S * fs), 1)
        e, m, n = batch.audio.shape
        n_frames = n // frame
        power = (batch.audio[..., : n_frames * frame].astype(float).reshape(e, m, n_frames, frame) ** 2).mean(-1)
        centre = np.argmax(power, axis=-1) * frame + frame // 2
        half = int(0.05 * fs)
        idx = np.clip(centre[..., None] + np.arange(-half, half)[None, None, :], 0, n - 1)
        seg = np.take_along_axis(batch.audio.astype(float), idx, -1) * np.hanning(2 * half)
        spec = np.abs(np.fft.rfft(seg, axis=-1)) ** 2
        f = np.fft.rfftfreq(2 * half, 1 / fs)
        total = np.maximum(spec.sum(-1), 1e-30)
        centroid = (spec * f).sum(-1) / total
        bandwidth = np.sqrt((spec * (f - centroid[..., None]) ** 2).sum(-1) / total)
        cum = np.cumsum(spec, axis=-1) / total[..., None]
        rolloff = f[np.argmax(cum >= 0.85, axis=-1)]
        cols = {}
        for k in range(m):
            cols[col.spectral_centroid_hz(k)] = centroid[:, k]
            cols[col.spectral_bandwidth_hz(k)] = bandwidth[:, k]
            cols[f"spectral__rolloff_{k}_hz"] = rolloff[:, k]
        for i, j in site.mic_pairs:
            cols[f"spectral__centroid_diff_{i}_{j}_hz"] = centroid[:, i] - centroid[:, j]
        return pd.DataFrame(cols)


class EnvelopeDelays:
    """``envelope``: delay of the Hilbert-envelope cross-correlation per pair, within its lag window (s).

    Envelopes ignore the carrier phase, so they are robust where GCC-PHAT locks onto a wrong
    fine-structure peak, at the price of precision.
    """

    group = "envelope"
    cache_version = "2"  # 2: the band-passed envelope from one transform

    def __init__(self, band_hz=(1000.0, 8000.0), max_lag_margin_s: float = 0.002) -> None:
        self.band_hz = (float(band_hz[0]), float(band_hz[1]))
        self.max_lag_margin_s = float(max_lag_margin_s)

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        return [(f"envelope__lag_{i}_{j}_s", "s", "lag t_j − t_i of the envelope cross-correlation maximum") for i, j in site.mic_pairs]

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        fs = batch.sample_rate_hz
        env = envelope(batch, self.band_hz, smooth_s=0.002)
        env = env - env.mean(-1, keepdims=True)
        n = env.shape[-1]
        windows = lag_windows_s(site, self.max_lag_margin_s)
        max_lag = min(int(np.ceil(windows.max() * fs)) + 1, n - 1)
        n_fft = sfft.next_fast_len(n + max_lag, real=True)  # no circular wrap-around within ±max_lag
        spec = sfft.rfft(env, n=n_fft, axis=-1)
        lags = np.arange(-max_lag, max_lag + 1) / fs
        cols = {}
        for (i, j), window_s in zip(site.mic_pairs, windows, strict=True):
            full = sfft.irfft(np.conj(spec[:, i]) * spec[:, j], n=n_fft, axis=-1)
            cc = np.concatenate([full[:, n_fft - max_lag :], full[:, : max_lag + 1]], axis=-1)
            window = np.abs(lags) <= window_s
            cols[f"envelope__lag_{i}_{j}_s"] = lags[window][np.argmax(cc[:, window], axis=-1)]
        return pd.DataFrame(cols)
