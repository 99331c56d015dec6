"""Fractional delays and GCC-PHAT recover known delays."""

import numpy as np
import pytest

from acoustlab.toolkit.dsp import coloured_noise, delay_and_scale, gcc, parabolic_peak
from plugins.simulators.free_field import synthetic_chirp

FS = 16000.0


@pytest.mark.parametrize("delay_s", [0.0, 0.01234, 0.05 + 0.37 / FS])
def test_gcc_phat_recovers_fractional_delay(delay_s):
    call = synthetic_chirp(1500, 6000, 0.2, FS)
    rng = np.random.default_rng(1)
    sig = delay_and_scale(call, np.array([0.01, 0.01 + delay_s]), np.array([1.0, 0.5]), FS, 4000)
    sig = sig + 0.01 * rng.standard_normal(sig.shape)
    cc, lags = gcc(sig[None], [(0, 1)], FS)
    peak = np.argmax(cc[0, 0])
    offset, _ = parabolic_peak(cc[0, 0], np.array(peak))
    est = lags[peak] + float(offset) / FS
    assert est == pytest.approx(delay_s, abs=0.1 / FS)


def test_swapping_a_pair_negates_its_lag():
    call = synthetic_chirp(2000, 5000, 0.1, FS)
    sig = delay_and_scale(call, np.array([0.002, 0.007]), np.ones(2), FS, 3000)
    cc, lags = gcc(sig[None], [(0, 1), (1, 0)], FS)
    a, b = lags[np.argmax(cc[0, 0])], lags[np.argmax(cc[0, 1])]
    assert a == pytest.approx(0.005, abs=1 / FS) and b == pytest.approx(-a)


@pytest.mark.parametrize("kind", ["white", "pink", "band"])
def test_coloured_noise_is_unit_variance_and_shaped(kind):
    x = coloured_noise(np.random.default_rng(0), (2, 32000), kind, FS, (300.0, 3000.0))
    np.testing.assert_allclose(x.std(axis=-1), 1.0, rtol=1e-6)
    spec = np.abs(np.fft.rfft(x[0])) ** 2
    f = np.fft.rfftfreq(x.shape[-1], 1 / FS)
    low, high = spec[(f > 100) & (f < 200)].mean(), spec[(f > 5000) & (f < 6000)].mean()
    if kind == "white":
        assert 0.7 < low / high < 1.4
    elif kind == "pink":
        assert low / high > 10  # 1/f: ~30x between these bands
    else:
        in_band = spec[(f > 500) & (f < 2500)].mean()
        assert in_band > 100 * high


def test_band_limited_gcc_samples_the_same_correlation():
    """With ``band_limited`` the correlation of a 1–4 kHz band is sampled at 2 × 2 × 4 kHz instead of 2 × 24 kHz: on
    the lags both grids share its values are the full-rate values, and the lags lie on its own grid."""
    rng = np.random.default_rng(0)
    fs = 24000.0
    audio = rng.standard_normal((3, 3, 2400)).astype(np.float32)
    audio[:, 1] = np.roll(audio[:, 0], 7, axis=-1) + 0.3 * audio[:, 1]
    pairs = [(0, 1), (0, 2), (1, 2)]
    full, full_lags = gcc(audio, pairs, fs, "beta_phat", (1000.0, 4000.0), upsample=2, max_lag_s=0.01)
    coarse, coarse_lags = gcc(audio, pairs, fs, "beta_phat", (1000.0, 4000.0), upsample=2, max_lag_s=0.01, band_limited=True)
    step = np.diff(coarse_lags)[0]
    assert step > 2 * np.diff(full_lags)[0]  # a coarser grid: fewer lags to transform
    assert coarse_lags.max() >= 0.01
    shared = np.isclose(np.mod(coarse_lags * 48000.0 + 1e-9, 1.0), 0.0, atol=1e-6) & (np.abs(coarse_lags) <= full_lags.max())
    assert shared.sum() > 10
    index = np.rint(coarse_lags[shared] * 48000.0).astype(int) + len(full_lags) // 2
    np.testing.assert_allclose(coarse[..., shared], full[..., index], rtol=1e-4, atol=1e-5 * np.abs(full).max())
    np.testing.assert_array_equal(
        gcc(audio, pairs, fs, "beta_phat", None, 2, max_lag_s=0.01, band_limited=True)[0],
        gcc(audio, pairs, fs, "beta_phat", None, 2, max_lag_s=0.01)[0],
    )  # no band: nothing changes


@pytest.mark.parametrize("weighting", ["phat", "beta_phat", "none"])
def test_weighted_spectra_in_place_equals_the_textbook_weighting_bit_for_bit(weighting):
    """The in-place weighting computes exactly |X|-floored (β-)PHAT as written out here (cached features stay valid)."""
    import scipy.fft as sfft

    from acoustlab.toolkit.dsp import next_fast_len, weighted_spectra

    audio = np.random.default_rng(3).standard_normal((4, 3, 1000)).astype(np.float32)
    audio[1, 2] = 0.0  # a silent channel: the floor decides
    spectra = sfft.rfft(audio, n=next_fast_len(2 * audio.shape[-1]), axis=-1)
    expected = spectra
    if weighting != "none":
        magnitude = np.maximum(np.abs(spectra), 1e-6 * np.abs(spectra).max(axis=-1, keepdims=True) + 1e-30)
        expected = spectra / (magnitude if weighting == "phat" else magnitude**0.8)
    np.testing.assert_array_equal(weighted_spectra(audio, weighting, 0.8), expected)


def _textbook_gcc(audio, pairs, fs, weighting, band, upsample, max_lag_s, band_limited=False):
    """The GCC as written out: mask both weighted spectra, multiply, one zero-padded inverse transform per pair."""
    import scipy.fft as sfft

    from acoustlab.toolkit.dsp import next_fast_len, weighted_spectra

    n_fft = next_fast_len(2 * audio.shape[-1])
    spectra = weighted_spectra(audio, weighting, 0.8)
    if band is not None:
        freqs = sfft.rfftfreq(n_fft, d=1.0 / fs)
        band = np.asarray(band, dtype=float)
        mask = (freqs >= band[..., :1]) & (freqs <= band[..., 1:])
        spectra = spectra * (mask if band.ndim == 1 else mask[:, None, :])
    spectra = spectra.astype(np.complex64)
    max_lag = min(audio.shape[-1], int(np.ceil(max_lag_s * fs)) + 2)
    n_out, half, scale = n_fft * upsample, max_lag * upsample, None
    if band_limited and band is not None:
        reduced = next_fast_len(2 * int(np.ceil(upsample * float(np.max(band[..., 1])) / fs * n_fft)) + 2)
        if reduced < n_out:
            n_out, scale = reduced, reduced / (n_fft * upsample)
            half = int(np.ceil(max_lag * n_out / n_fft))
    rows = []
    for i, j in pairs:
        full = sfft.irfft(np.conj(spectra[:, i]) * spectra[:, j], n=n_out, axis=-1)
        if scale is not None:
            full *= np.float32(scale)
        rows.append(np.concatenate([full[:, n_out - half :], full[:, : half + 1]], axis=-1))
    return np.stack(rows, axis=1)


@pytest.mark.parametrize("band", ["none", "one", "per_event"])
@pytest.mark.parametrize("band_limited", [False, True])
def test_gcc_equals_the_textbook_masked_cross_spectra_bit_for_bit(band, band_limited):
    """The GCC multiplies only in-band bins into one zero-padded buffer; its correlation is exactly the textbook one
    (masked spectra, their products, padded inverse transforms), so features computed before and after agree bit for bit."""
    rng = np.random.default_rng(5)
    fs = 24000.0
    audio = rng.standard_normal((5, 4, 1500)).astype(np.float32)
    audio[:, 1] = np.roll(audio[:, 0], 9, axis=-1) + 0.2 * audio[:, 1]
    pairs = [(0, 1), (0, 2), (1, 3), (2, 3), (3, 0)]
    band_hz = {
        "none": None,
        "one": (300.0, 7000.0),
        "per_event": np.stack([rng.uniform(200, 2000, 5), rng.uniform(3000, 9000, 5)], axis=1),
    }[band]
    for weighting, upsample in (("beta_phat", 2), ("phat", 1), ("none", 3)):
        cc, _ = gcc(audio, pairs, fs, weighting, band_hz, upsample, 0.8, max_lag_s=0.02, band_limited=band_limited)
        expected = _textbook_gcc(audio, pairs, fs, weighting, band_hz, upsample, 0.02, band_limited)
        assert cc.dtype == np.float32
        np.testing.assert_array_equal(cc, expected)


def test_parabolic_peak_broadcasts_one_curve_over_several_peaks():
    curve = np.random.default_rng(4).standard_normal((5, 50))
    index = np.array([[3, 17, 49], [0, 20, 33], [1, 2, 3], [10, 11, 12], [48, 25, 6]])
    offset, height = parabolic_peak(curve[:, None, :], index)
    offset_r, height_r = parabolic_peak(curve[:, None, :].repeat(3, 1), index)
    np.testing.assert_array_equal(offset, offset_r)
    np.testing.assert_array_equal(height, height_r)
