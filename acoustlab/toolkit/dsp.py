"""Signal maths shared by plugins: fractional delays, GCC, coloured noise (NumPy/SciPy FFTs)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import scipy.fft as sfft
import scipy.signal as ss

from acoustlab.core import columns as col


def next_fast_len(n: int) -> int:
    """FFT-friendly length >= n (real transforms)."""
    return int(sfft.next_fast_len(int(n), real=True))


def clip_samples(start_s: float, length_s: float, sample_rate_hz: float) -> tuple[int, int]:
    """Where a clip lies in its recording: its first sample and its length, in samples, the window extended at its end
    to an FFT-friendly length (its features are computed at that length).

    One rule for every job that cuts clips (``localize``'s recordings, a season's long files), so
    the same window of the same audio gives the same clip and the same features whichever job cuts
    it: the start rounded to the nearest sample, the length the window's own rounded up to the next
    length the FFT handles fast (a function of the window alone, never of its batch-mates'). The
    extension is read from the recording, not zero-padded: zeros change a PHAT-weighted correlation
    (on the shipped real array one pair's peak moved 20 ms), a few more samples of the same audio do
    not; and arbitrary lengths made a season's features a third slower.
    """
    return int(round(start_s * sample_rate_hz)), next_fast_len(int(round(length_s * sample_rate_hz)))


def delay_and_scale(signal: np.ndarray, delays_s: np.ndarray, gains: np.ndarray, sample_rate_hz: float, n_out: int) -> np.ndarray:
    """Copies of a signal delayed by fractional amounts and scaled, via an FFT phase ramp.

    The signal is zero-padded to cover ``n_out`` plus the largest delay, so the phase ramp's
    circular wrap never reaches the output window.

    Parameters
    ----------
    signal : numpy.ndarray
        (S,) source signal.
    delays_s : numpy.ndarray
        (K,) delays in s (non-negative).
    gains : numpy.ndarray
        (K,) amplitude factors.
    sample_rate_hz : float
        Sampling rate in Hz.
    n_out : int
        Output length in samples.

    Returns
    -------
    numpy.ndarray
        (K, n_out) delayed, scaled copies (float64).
    """
    delays_s = np.asarray(delays_s, dtype=float)
    max_shift = int(np.ceil(delays_s.max() * sample_rate_hz)) if delays_s.size else 0
    n_fft = next_fast_len(max(n_out, signal.size) + max_shift + signal.size)
    spectrum = sfft.rfft(signal, n=n_fft)
    freqs = sfft.rfftfreq(n_fft, d=1.0 / sample_rate_hz)
    ramp = np.exp(-2j * np.pi * freqs[None, :] * delays_s[:, None])
    out = sfft.irfft(spectrum[None, :] * ramp * np.asarray(gains, dtype=float)[:, None], n=n_fft, axis=-1)
    return out[:, :n_out]


def gcc(
    audio: np.ndarray,
    pairs: list[tuple[int, int]],
    sample_rate_hz: float,
    weighting: str = "phat",
    band_hz: tuple[float, float] | None = None,
    upsample: int = 1,
    beta: float = 0.8,
    max_lag_s: float | None = None,
    spectra_cache: dict | None = None,
    band_limited: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised cross-correlation of every listed mic pair, for a batch of events.

    For pair (i, j) the peak lies at lag τ = t_j − t_i (arrival at j minus arrival at i).

    Each mic's spectrum is computed once and weighted once: |X_i X_j|^β = |X_i|^β |X_j|^β, so the
    PHAT / β-PHAT weighting of a pair is the product of per-mic weightings (a floor of 10⁻⁶ of
    each mic's largest magnitude keeps empty bins finite). The pairs' cross-spectra are products
    of those, and the inverse transforms run in single precision. With ``max_lag_s`` the
    transform is only as long as the lags need (no circular wrap-around within ±max_lag_s) and only
    those lags are returned.

    Parameters
    ----------
    audio : numpy.ndarray
        (E, M, S) recordings.
    pairs : list of (int, int)
        Mic pairs.
    sample_rate_hz : float
        Sampling rate in Hz.
    weighting : {"phat", "beta_phat", "none"}
        PHAT whitening (unit magnitude cross-spectrum), β-PHAT (the cross-spectrum divided by its
        magnitude to the power ``beta``: between plain and PHAT, so bins with little signal are not
        whitened up to the level of the call's bins), or plain cross-correlation.
    band_hz : tuple of float or numpy.ndarray, optional
        Keep only this (low, high) band of the cross-spectrum, in Hz; an (E, 2) array gives every
        event its own band (see ``event_band_hz``).
    upsample : int
        Lag-resolution factor: the cross-spectrum is zero-padded so lags are spaced by
        1/(upsample × sample_rate_hz), which shrinks the bias of parabolic peak interpolation.
    beta : float
        The exponent of β-PHAT, in [0, 1] (0 is plain cross-correlation, 1 is PHAT).
    max_lag_s : float, optional
        Largest |lag| needed, s; None returns every lag of a transform twice the signal length.
    spectra_cache : dict, optional
        Where the weighted spectra of ``audio`` are kept between calls on the same audio (several
        bands of one batch transform the audio once).
    band_limited : bool
        With ``band_hz``: sample the correlation at ``upsample`` × twice the band's upper edge
        instead of ``upsample`` × the sampling rate (rounded up to an FFT-friendly length). The
        cross-spectrum is zero above the band, so the correlation is the same function sampled
        more coarsely (values scaled to match): a 1–4 kHz band at 24 kHz costs a third.

    Returns
    -------
    cc : numpy.ndarray
        (E, P, L) correlation over lags (float32), from the most negative lag to the most positive.
    lags_s : numpy.ndarray
        (L,) lag of each column in s.
    """
    if weighting not in ("phat", "beta_phat", "none"):
        raise ValueError(f"gcc weighting must be 'phat', 'beta_phat' or 'none'; got {weighting!r}")
    if upsample < 1:
        raise ValueError(f"gcc upsample must be >= 1; got {upsample}")
    size = gcc_lengths(audio.shape[-1], sample_rate_hz, upsample, max_lag_s, band_hz, band_limited)
    n_fft = size.n_fft
    key = ("weighted_spectra", weighting, float(beta))
    if spectra_cache is None:
        spectra = weighted_spectra(audio, weighting, beta)
    else:  # only read below
        if key not in spectra_cache:
            spectra_cache[key] = weighted_spectra(audio, weighting, beta)
        spectra = spectra_cache[key]
    in_band = _band_selection(band_hz, n_fft, sample_rate_hz)
    spectra = spectra.astype(np.complex64, copy=False)  # single precision already when the audio is float32
    n_out, half, rate_hz, scale = size.n_out, size.half, size.rate_hz, size.scale
    n_kept = min(spectra.shape[-1], n_out // 2 + 1)  # bins the inverse transform reads (the rest are zero or padding)
    span, right = _band_spectra(spectra[:, :, :n_kept], in_band)
    left = np.conj(right)  # once per mic, not once per pair
    # one zero-padded cross-spectrum buffer for every pair: the products are written into the band's bins and the
    # rest stays zero, so the inverse transform pads nothing (a copy per pair otherwise)
    cross = np.zeros((audio.shape[0], n_out // 2 + 1), dtype=np.complex64)
    cc = np.empty((audio.shape[0], len(pairs), 2 * half + 1), dtype=np.float32)
    for k, (i, j) in enumerate(pairs):  # one pair at a time: memory of one (E, n_out) transform
        np.multiply(left[:, i], right[:, j], out=cross[:, span])
        full = sfft.irfft(cross, n=n_out, axis=-1)
        if scale is not None:
            full *= np.float32(scale)
        cc[:, k, :half] = full[:, n_out - half :]
        cc[:, k, half:] = full[:, : half + 1]
    lags_s = np.arange(-half, half + 1) / rate_hz
    return cc, lags_s


@dataclass(frozen=True)
class GccLengths:
    """Transform lengths and the lag grid of ``gcc`` (shared with the GPU path, ``acoustlab.toolkit.gcc_torch``).

    Attributes
    ----------
    n_fft : int
        Forward transform length (twice the signal, FFT-friendly).
    n_out : int
        Inverse transform length (``upsample`` × ``n_fft``, or shorter when band-limited).
    half : int
        Lags kept on each side of zero (the correlation has ``2 · half + 1`` columns).
    rate_hz : float
        Sampling rate of the lag grid, Hz.
    scale : float or None
        Factor restoring the amplitude of a shortened inverse transform (None when not shortened).
    """

    n_fft: int
    n_out: int
    half: int
    rate_hz: float
    scale: float | None


def gcc_lengths(
    n_samples: int, sample_rate_hz: float, upsample: int, max_lag_s: float | None, band_hz=None, band_limited: bool = False
) -> GccLengths:
    """The lengths ``gcc`` uses for ``n_samples``-long signals (see its parameters)."""
    max_lag_samples = n_samples if max_lag_s is None else min(n_samples, int(np.ceil(max_lag_s * sample_rate_hz)) + 2)
    # twice the signal length, always: a (β-)PHAT weighting depends on the spectral resolution (a transform
    # only as long as the lags need, signal + largest lag, was tried: more gross first-stage errors on the frozen lake)
    n_fft = next_fast_len(2 * n_samples)
    n_out = n_fft * int(upsample)
    half = min(max_lag_samples * int(upsample), n_out // 2 - 1)
    rate_hz = sample_rate_hz * upsample
    scale = None
    if band_limited and band_hz is not None:
        high_hz = float(np.max(np.asarray(band_hz, dtype=float)[..., 1]))
        reduced = next_fast_len(2 * int(np.ceil(upsample * high_hz / sample_rate_hz * n_fft)) + 2)
        if reduced < n_out:  # bins above n_out/2 are all zero: the shorter inverse transform drops only zeros
            scale = reduced / n_out  # irfft divides by its length
            n_out = reduced
            rate_hz = sample_rate_hz * n_out / n_fft
            half = min(int(np.ceil(max_lag_samples * n_out / n_fft)), n_out // 2 - 1)
    return GccLengths(n_fft, n_out, half, rate_hz, scale)


def _band_selection(band_hz: tuple[float, float] | np.ndarray | None, n_fft: int, sample_rate_hz: float) -> slice | np.ndarray | None:
    """Which bins of an ``n_fft``-point real spectrum lie in ``band_hz`` (inclusive edges).

    None for no band, a slice for one band (its bins are contiguous), an (E, F) boolean mask
    for one band per event.
    """
    if band_hz is None:
        return None
    freqs = sfft.rfftfreq(n_fft, d=1.0 / sample_rate_hz)
    band = np.asarray(band_hz, dtype=float)
    if band.ndim == 1:
        inside = np.flatnonzero((freqs >= band[0]) & (freqs <= band[1]))
        return slice(0, 0) if inside.size == 0 else slice(int(inside[0]), int(inside[-1]) + 1)
    return (freqs >= band[:, :1]) & (freqs <= band[:, 1:])


def _band_spectra(spectra: np.ndarray, in_band: slice | np.ndarray | None) -> tuple[slice, np.ndarray]:
    """The bins of (E, M, F) spectra that any event's band holds, as a slice, and the spectra there, zero outside each event's band.

    ``in_band`` as ``_band_selection`` gives it. conj(X_i) X_j of these is the cross-spectrum of
    pair (i, j) on the slice's bins (the same products as the whole spectra's, masked); every other
    bin of it is zero.
    """
    n_bins = spectra.shape[-1]
    if in_band is None:
        return slice(0, n_bins), spectra
    if isinstance(in_band, slice):
        span = slice(*in_band.indices(n_bins)[:2])
        return span, spectra[..., span]
    mask = in_band[:, :n_bins]
    inside = np.flatnonzero(mask.any(axis=0))
    span = slice(0, 0) if inside.size == 0 else slice(int(inside[0]), int(inside[-1]) + 1)
    return span, np.where(mask[:, None, span], spectra[..., span], np.complex64(0)).astype(spectra.dtype, copy=False)


def weighted_spectra(audio: np.ndarray, weighting: str, beta: float) -> np.ndarray:
    """(E, M, F) spectra of ``audio`` over twice its length, (β-)PHAT weighted per mic (see ``gcc``)."""
    spectra = sfft.rfft(audio, n=next_fast_len(2 * audio.shape[-1]), axis=-1)
    if weighting != "none":  # in place: the same operations as out-of-place ones, without three spectrum-sized temporaries
        magnitude = np.abs(spectra)
        np.maximum(magnitude, 1e-6 * magnitude.max(axis=-1, keepdims=True) + 1e-30, out=magnitude)
        if weighting != "phat":
            np.power(magnitude, float(beta), out=magnitude)
        # the same values as np.divide(spectra, magnitude), at a fifth of its cost: numpy divides a complex by a real
        # c + 0j as both parts times 1 / c, and this product is (a·s − b·0) + (a·0 + b·s)j with s = 1 / c
        np.divide(1, magnitude, out=magnitude)
        np.multiply(spectra, magnitude, out=spectra)
    return spectra


def event_band_hz(
    events: pd.DataFrame, default: tuple[float, float] | None, sample_rate_hz: float
) -> tuple[float, float] | np.ndarray | None:
    """The GCC band of every event: its own detection band (``band_low_hz``, ``band_high_hz``) where given, else ``default``.

    Returns ``default`` unchanged when no event has a band of its own (so batches without
    detection bands compute exactly what they did before); else an (E, 2) array in Hz, each
    band clipped to [0, Nyquist], ``default`` (or the full band) where an event has none.
    """
    if col.BAND_LOW not in events or col.BAND_HIGH not in events:
        return default
    own = events[[col.BAND_LOW, col.BAND_HIGH]].to_numpy(float)
    given = np.isfinite(own).all(axis=1) & (own[:, 1] > own[:, 0])
    if not given.any():
        return default
    fallback = np.array(default if default is not None else (0.0, sample_rate_hz / 2), dtype=float)
    band = np.where(given[:, None], own, fallback[None, :])
    return np.clip(band, 0.0, sample_rate_hz / 2)


def local_maxima(values: np.ndarray) -> np.ndarray:
    """(E, L) True at the local maxima along the last axis: ≥ the left neighbour, > the right one, edges allowed (the GCC's peak rule)."""
    is_peak = np.ones_like(values, dtype=bool)
    is_peak[:, 1:] &= values[:, 1:] >= values[:, :-1]
    is_peak[:, :-1] &= values[:, :-1] > values[:, 1:]
    return is_peak


def parabolic_peak(values: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-sample peak offset and height by fitting a parabola through a peak and its neighbours.

    Parameters
    ----------
    values : numpy.ndarray
        (..., L) sampled curve; its leading axes broadcast against ``index`` (one curve, several peaks).
    index : numpy.ndarray
        (...) integer index of the peak along the last axis (interior or at an edge).

    Returns
    -------
    offset : numpy.ndarray
        (...) offset in samples in [−0.5, 0.5] to add to ``index``.
    height : numpy.ndarray
        (...) interpolated peak height.
    """
    n = values.shape[-1]
    left = np.take_along_axis(values, np.clip(index - 1, 0, n - 1)[..., None], -1)[..., 0]
    mid = np.take_along_axis(values, index[..., None], -1)[..., 0]
    right = np.take_along_axis(values, np.clip(index + 1, 0, n - 1)[..., None], -1)[..., 0]
    denom = left - 2 * mid + right
    safe = np.abs(denom) > 1e-15
    offset = np.where(safe, 0.5 * (left - right) / np.where(safe, denom, 1.0), 0.0)
    offset = np.clip(offset, -0.5, 0.5)
    height = mid - 0.25 * (left - right) * offset
    return offset, height


def coloured_noise(
    rng: np.random.Generator, shape: tuple[int, ...], kind: str, sample_rate_hz: float, band_hz: tuple[float, float] | None = None
) -> np.ndarray:
    """Unit-variance Gaussian noise: ``white``, ``pink`` (1/f power) or ``band`` (band-limited white).

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    shape : tuple of int
        Output shape; the last axis is time.
    kind : {"white", "pink", "band"}
        Spectral shape.
    sample_rate_hz : float
        Sampling rate in Hz (for ``band``).
    band_hz : tuple of float, optional
        (low, high) in Hz for ``band``; a 4th-order Butterworth band-pass, zero phase.

    Returns
    -------
    numpy.ndarray
        Noise with unit variance along the last axis.
    """
    white = rng.standard_normal(shape)
    if kind == "white":
        out = white
    elif kind == "pink":
        n = shape[-1]
        spectrum = sfft.rfft(white, axis=-1)
        freqs = sfft.rfftfreq(n)
        scale = np.ones_like(freqs)
        scale[1:] = 1.0 / np.sqrt(freqs[1:] / freqs[1])
        scale[0] = 0.0
        out = sfft.irfft(spectrum * scale, n=n, axis=-1)
    elif kind == "band":
        if band_hz is None:
            raise ValueError("band noise needs band_hz=(low, high)")
        nyq = sample_rate_hz / 2
        sos = ss.butter(4, [band_hz[0] / nyq, min(band_hz[1] / nyq, 0.999)], btype="bandpass", output="sos")
        out = ss.sosfiltfilt(sos, white, axis=-1)
    else:
        raise ValueError(f"noise kind must be white, pink or band; got {kind!r}")
    return out / np.maximum(out.std(axis=-1, keepdims=True), 1e-30)
