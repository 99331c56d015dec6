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
