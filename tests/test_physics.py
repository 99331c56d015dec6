"""Known-answer tests of the atmospheric acoustics (ISO 9613-1 table, speed of sound)."""

import numpy as np
import pytest

from acoustlab.toolkit.physics import air_absorption_db_per_m, speed_of_sound_m_s

FREQS = [500, 1000, 2000, 4000, 8000, 12000]
# ISO 9613-1 reference values (dB/km), as tabulated in the project's physics notes.
TABLE = {
    (20.0, 50.0): [2.73, 4.66, 9.89, 29.7, 105, 221],
    (0.0, 80.0): [1.50, 4.06, 13.9, 49.2, 148, 241],
    (-10.0, 70.0): [2.64, 9.19, 27.9, 58.7, 86.5, 104],
}


@pytest.mark.parametrize("weather", list(TABLE))
def test_air_absorption_matches_iso_table(weather):
    got = air_absorption_db_per_m(np.array(FREQS, float), *weather) * 1000
    np.testing.assert_allclose(got, TABLE[weather], rtol=6e-3)


def test_speed_of_sound_reference_values():
    assert speed_of_sound_m_s(20.0) == pytest.approx(343.2, abs=0.15)
    assert speed_of_sound_m_s(0.0) == pytest.approx(331.3, abs=0.15)
    humid = speed_of_sound_m_s(20.0, 100.0) - speed_of_sound_m_s(20.0, 0.0)
    assert humid == pytest.approx(1.5, abs=0.1)
    assert 0 < speed_of_sound_m_s(-5.0, 100.0) - speed_of_sound_m_s(-5.0, 0.0) < 0.3


def test_speed_of_sound_vectorises_and_rejects_bad_input():
    c = speed_of_sound_m_s(np.array([-10.0, 0.0, 10.0]), np.array([50.0, 50.0, 50.0]))
    assert c.shape == (3,) and np.all(np.diff(c) > 0)
    with pytest.raises(ValueError, match="relative_humidity_pct"):
        speed_of_sound_m_s(10.0, 120.0)
    with pytest.raises(ValueError, match="temperature_c"):
        speed_of_sound_m_s(np.nan)


def test_tdoa_bound_matches_a_monte_carlo_of_the_cross_correlation_estimator():
    """Two noisy copies of a band-limited white signal: the delay estimate's spread equals the two-sensor bound.

    Plain cross-correlation is the maximum-likelihood delay estimator for white signal and noise in
    the same band, so it attains the bound at a large time-bandwidth product; a bound without the
    (1 + 2r)/r factor would be √2 below the measured spread at high SNR.
    """
    from acoustlab.toolkit.dsp import gcc, parabolic_peak
    from acoustlab.toolkit.geometry import tdoa_crb_s

    rng = np.random.default_rng(0)
    fs, duration, lo, hi = 16000.0, 0.25, 1000.0, 5000.0
    n = int(fs * duration)
    band = (np.fft.rfftfreq(n, 1 / fs) >= lo) & (np.fft.rfftfreq(n, 1 / fs) <= hi)

    def band_noise():
        x = np.fft.irfft(np.fft.rfft(rng.normal(size=n)) * band, n)
        return x / x.std()

    rms_bandwidth = np.sqrt((hi**3 - lo**3) / (3 * (hi - lo)))
    for snr_db in (0.0, 20.0):
        amplitude = 10 ** (-snr_db / 20)
        estimates = []
        for _ in range(300):
            s = band_noise()
            x = np.stack([s + amplitude * band_noise(), s + amplitude * band_noise()])[None]
            cc, lags = gcc(x, [(0, 1)], fs, "none", (lo, hi), 16)
            k = int(np.argmax(cc[0, 0]))
            offset, _ = parabolic_peak(cc[0, 0][None, None], np.array([[k]]))
            estimates.append(lags[k] + float(offset.ravel()[0]) * (lags[1] - lags[0]))
        ratio = np.std(estimates) / tdoa_crb_s(snr_db, rms_bandwidth, duration, hi - lo)
        assert 0.85 < ratio < 1.2, f"at {snr_db} dB the estimator's spread is {ratio:.2f} × the bound"
