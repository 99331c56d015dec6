"""A ground reflection merged with the direct path: the GCC peak's shift it predicts, against a GCC measured on signals."""

from __future__ import annotations

import numpy as np
import pytest

from acoustlab.toolkit.dsp import gcc, parabolic_peak
from acoustlab.toolkit.ground_reflection import peak_shift_per_fraction_s, reflection_delay_s


def test_the_reflection_arrives_later_by_the_image_path_and_not_at_all_on_the_ground():
    source = np.array([[0.0, 0.0, 1.5], [40.0, 0.0, 1.5]])
    mics = np.array([[30.0, 0.0, 1.5], [30.0, 0.0, 0.0]])
    delay = reflection_delay_s(source, mics, np.array([340.0, 340.0]))
    np.testing.assert_allclose(delay[:, 0], [(np.hypot(30, 3) - 30) / 340, (np.hypot(10, 3) - 10) / 340])
    np.testing.assert_allclose(delay[:, 1], 0.0, atol=1e-15)  # a mic on the ground hears both paths at once


def test_a_delay_well_inside_the_peak_moves_it_by_that_delay_per_unit_amplitude():
    np.testing.assert_allclose(peak_shift_per_fraction_s(np.array([1e-6, -2e-6]), (1000.0, 8000.0)), [1e-6, -2e-6], rtol=5e-3)
    with pytest.raises(ValueError, match="band_hz"):
        peak_shift_per_fraction_s(np.zeros(1), (8000.0, 1000.0))


@pytest.mark.parametrize("delay_s", [2e-5, 8e-5, 2e-4, 5e-4])
def test_the_predicted_shift_is_where_a_phat_gcc_finds_the_merged_peak(delay_s):
    """White noise in 1–8 kHz heard directly at one mic and with a reflection (amplitude 0.1, ``delay_s`` later) at the
    other: the PHAT GCC's peak lies 0.1 × ``peak_shift_per_fraction_s`` from the direct path's lag (within 10 %: the
    first-order term; at 0.5 ms beyond the peak, where the shift has turned negative, too)."""
    rate, n, amplitude, lag = 48_000.0, 2**15, 0.1, 1e-3
    rng = np.random.default_rng(0)
    freq = np.fft.rfftfreq(n, 1 / rate)
    spectrum = np.fft.rfft(rng.normal(size=n)) * ((freq >= 1000) & (freq <= 8000))
    direct = np.exp(-2j * np.pi * freq * lag)
    second = np.fft.irfft(spectrum * direct * (1 + amplitude * np.exp(-2j * np.pi * freq * delay_s)), n)
    audio = np.stack([np.fft.irfft(spectrum, n), second])[None]
    cc, lags = gcc(audio, [(0, 1)], rate, "phat", (1000.0, 8000.0), upsample=8, max_lag_s=0.005)
    peak = int(np.argmax(cc[0, 0]))
    offset, _ = parabolic_peak(cc[0, 0][None], np.array([peak]))
    measured = lags[peak] + float(offset[0]) * (lags[1] - lags[0]) - lag
    predicted = amplitude * float(peak_shift_per_fraction_s(np.array(delay_s), (1000.0, 8000.0)))
    assert measured == pytest.approx(predicted, abs=0.05e-6 + 0.1 * abs(predicted))
