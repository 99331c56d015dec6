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


@pytest.mark.parametrize("solver", ["consistent_set", "hyperbolic", "least_squares", "baseline_robust", "baseline_per_reference_mic"])
@pytest.mark.parametrize("site_name", ["frozen_lake", "forest"])
def test_a_fix_does_not_depend_on_the_events_solved_with_it(compose_cfg, solver, site_name):
    """Each event alone gives bit for bit the fix, residual and diagnostics it gets among 30 others: nothing couples the events
    of a batch (a BLAS matrix product rounds a row by its batch-mates; the solvers avoid it), so a season's answer cannot
    depend on its batch size."""
    from acoustlab.run.registry import build
    from acoustlab.stages.sites import site_from_config

    cfg = compose_cfg([f"+site={site_name}", f"solver={solver}"])
    site, fit = site_from_config(cfg.site), build(cfg.solver, "solver")
    rng = np.random.default_rng(1)
    n = 30
    sources = np.column_stack([rng.uniform(-10, 60, n), rng.uniform(-10, 60, n), np.full(n, 1.5)])
    arrival = np.linalg.norm(sources[:, None] - site.mic_positions_m[None], axis=-1) / 343.0
    tdoa = arrival - arrival[:, :1] + rng.normal(0, 2e-5, arrival.shape)
    tdoa[:, 0] = 0.0
    candidates = np.stack(
        [np.stack([tdoa[:, j] - tdoa[:, i], rng.uniform(-0.1, 0.1, n), rng.uniform(-0.1, 0.1, n)], -1) for i, j in site.mic_pairs], 1
    )

    def solved(rows):
        return fit.solve(
            SolverInputs(
                site.mic_positions_m, tdoa[rows], np.full(len(rows), 343.0), pair_lag_candidates_s=candidates[rows], source_height_m=1.5
            )
        )

    together = solved(np.arange(n))
    for k in range(n):
        alone = solved(np.array([k]))
        np.testing.assert_array_equal(alone.position_m[0], together.position_m[k])
        np.testing.assert_array_equal(alone.residual_m[0], together.residual_m[k])
        for name, values in together.diagnostics.items():
            np.testing.assert_array_equal(alone.diagnostics[name][0], values[k], err_msg=name)
