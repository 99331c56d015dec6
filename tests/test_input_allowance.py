"""The input allowance's radii follow the shift's shape and tail: a line for a thermometer, the Monte Carlo's own quantiles."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm

from acoustlab.toolkit.input_uncertainty import (
    InputUncertainty,
    allowance_m,
    fix_shift_m,
    gaussian_radius_factor,
    horizontal_covariance_m2,
    level_factor,
    monte_carlo_shifts_m,
)

MICS = np.array([[0.0, 0, 1], [50, 0, 1], [25, 43, 1], [25, 14, 1]])
LEVELS = (0.5, 0.8, 0.95)


@pytest.mark.parametrize("level", LEVELS)
def test_the_gaussian_factor_spans_a_line_to_a_round_error(level: float) -> None:
    assert gaussian_radius_factor(level, np.array([1.0]))[0] == level_factor(level)
    assert gaussian_radius_factor(level, np.array([0.0]))[0] == pytest.approx(norm.ppf((1 + level) / 2), abs=0.01)


@pytest.mark.parametrize("ratio", [0.0, 0.3, 0.7])
def test_first_order_radii_hold_their_level_of_an_elliptical_gaussian(ratio: float) -> None:
    rng = np.random.default_rng(int(ratio * 10))
    draws = rng.normal(size=(100_000, 2)) * np.array([2.0, 2.0 * ratio])
    for level in LEVELS:
        radius = 2.0 * gaussian_radius_factor(level, np.array([ratio]))[0]
        assert np.mean(np.hypot(*draws.T) <= radius) == pytest.approx(level, abs=0.01)


def test_a_thermometer_error_gets_a_radius_along_its_line() -> None:
    """A speed-of-sound error moves a fix along a line: a round radius of the same σ held 0.917 of it at 0.95."""
    source = np.array([[20.0, 10.0, 1.5]])
    weather = (np.array([10.0]), np.array([60.0]))
    stated = InputUncertainty(temperature_c=1.0)
    cov = horizontal_covariance_m2(MICS, source, *weather, stated)[0]
    minor, major = np.sqrt(np.linalg.eigvalsh(cov))
    assert minor < 1e-6 * major  # one error moves the fix along one direction
    found = allowance_m(MICS, source, *weather, stated, LEVELS)
    assert found.sigma_m[0] < stated.exact_above_m  # the first-order path
    shifts = fix_shift_m(
        MICS, source, *weather, np.random.default_rng(5).normal(0, 1.0, 20_000), np.zeros((20_000, 4)), np.zeros((20_000, 4, 2))
    )
    distance = np.hypot(*shifts[0].T)
    for k, level in enumerate(LEVELS):
        assert np.mean(distance <= found.radius_m[0, k]) == pytest.approx(level, abs=0.01)
    assert np.mean(distance <= found.sigma_m[0] * level_factor(0.95)) == pytest.approx(0.917, abs=0.01)  # the round radius


def test_where_first_order_is_poor_the_radii_are_the_monte_carlo_quantiles_and_capped() -> None:
    source = np.array([[25.0, 15.0, 1.5], [60.0, 20.0, 1.5], [80.0, 0.0, 1.5]])
    weather = (np.full(3, 10.0), np.full(3, 60.0))
    stated = InputUncertainty(temperature_c=0.0, mic_position_m=2.0, max_sigma_m=10.0)  # a cap the baseline extension reaches
    found = allowance_m(MICS, source, *weather, stated, LEVELS)
    shifts = monte_carlo_shifts_m(MICS, source, *weather, stated)
    np.testing.assert_array_equal(
        found.radius_m,
        np.minimum(np.quantile(np.sqrt((shifts**2).sum(-1)), LEVELS, axis=1).T, 10.0 * np.array([level_factor(v) for v in LEVELS])),
    )
    assert (np.diff(found.radius_m, axis=1) >= 0).all()  # a higher level never has a smaller radius
    assert np.isnan(allowance_m(MICS, np.full((1, 3), np.nan), weather[0][:1], weather[1][:1], stated, LEVELS).radius_m).all()
