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
