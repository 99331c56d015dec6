"""Least-squares TDOA solver: exact on noise-free TDOAs, invariant to translation and rotation."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.core.contracts import SolverInputs
from acoustlab.toolkit.geometry import gdop, sample_in_expanded_hull
from plugins.solvers.least_squares import LeastSquaresSolver

TRIANGLE = np.array([[0.0, 0.0, 1.2], [50.0, 0.0, 1.2], [24.0, 44.0, 1.2]])
HEXAGON = np.array([[0, 0, 1.5], [55, -5, 1.5], [90, 25, 1.5], [75, 70, 1.5], [25, 75, 1.5], [-10, 35, 1.5]], float)


def exact_tdoa(mics, src, c):
    d = np.sqrt(((src[:, None, :] - mics[None]) ** 2).sum(-1))
    return (d - d[:, :1]) / c


@pytest.mark.parametrize("mics", [TRIANGLE, HEXAGON])
def test_noise_free_tdoas_give_the_exact_position_inside_the_hull(mics):
    rng = np.random.default_rng(0)
    xy = sample_in_expanded_hull(rng, mics, 0.0, 300)
    src = np.column_stack([xy, np.full(len(xy), mics[0, 2])])
    res = LeastSquaresSolver().solve(SolverInputs(mics, exact_tdoa(mics, src, 340.0), 340.0))
    err = np.linalg.norm(res.position_m - xy, axis=1)
    assert np.percentile(err, 99) < 1e-6
    assert res.converged.mean() > 0.99
    assert np.nanmax(res.residual_m) < 1e-6


@settings(max_examples=25, deadline=None)
@given(
    shift=st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3)),
    angle=st.floats(0, 2 * np.pi),
    u=st.floats(0.05, 0.9),
    v=st.floats(0.05, 0.9),
)
def test_solver_is_invariant_to_translation_and_rotation(shift, angle, u, v):
    if u + v > 0.95:
        u, v = u / 2, v / 2
    mics = HEXAGON
    xy = mics[0, :2] + u * (mics[2, :2] - mics[0, :2]) + v * (mics[4, :2] - mics[0, :2])
    src = np.array([[xy[0], xy[1], 1.5]])
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    moved = mics.copy()
    moved[:, :2] = mics[:, :2] @ rot.T + np.array(shift)
    moved_src = src.copy()
    moved_src[:, :2] = src[:, :2] @ rot.T + np.array(shift)
    solver = LeastSquaresSolver()
    a = solver.solve(SolverInputs(mics, exact_tdoa(mics, src, 343.0), 343.0)).position_m
    b = solver.solve(SolverInputs(moved, exact_tdoa(moved, moved_src, 343.0), 343.0)).position_m
    np.testing.assert_allclose(b, a @ rot.T + np.array(shift), atol=1e-5)


def test_non_finite_tdoas_give_nan_not_garbage():
    tdoa = np.array([[0.0, np.nan, 0.01]])
    res = LeastSquaresSolver().solve(SolverInputs(TRIANGLE, tdoa, 340.0))
    assert np.isnan(res.position_m).all() and not res.converged[0]


def test_gdop_is_low_inside_and_grows_outside():
    inside = gdop(TRIANGLE, np.array([[24.0, 15.0]]))[0]
    outside = gdop(TRIANGLE, np.array([[24.0, 300.0]]))[0]
    assert 0.5 < inside < 3 and outside > 10 * inside
