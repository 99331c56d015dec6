"""Closed-form hyperbolic solver: exact on noise-free TDOAs, explicit root choice, invariances."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.core.contracts import SolverInputs
from acoustlab.toolkit.geometry import sample_in_expanded_hull
from acoustlab.toolkit.tdoa import energy_residual_db
from plugins.solvers.hyperbolic import HyperbolicSolver

TRIANGLE = np.array([[0.0, 0.0, 1.2], [50.0, 0.0, 1.2], [24.0, 44.0, 1.2]])
HEXAGON = np.array([[0, 0, 1.5], [55, -5, 1.5], [90, 25, 1.5], [75, 70, 1.5], [25, 75, 1.5], [-10, 35, 1.5]], float)


def exact(mics, xy, c=340.0, height=None):
    z = mics[0, 2] if height is None else height
    src = np.column_stack([xy, np.full(len(xy), z)])
    d = np.sqrt(((src[:, None] - mics[None]) ** 2).sum(-1))
    return (d - d[:, :1]) / c, -20 * np.log10(d)


@pytest.mark.parametrize("mics", [TRIANGLE, HEXAGON])
def test_exact_with_levels_everywhere_in_the_source_region(mics):
    xy = sample_in_expanded_hull(np.random.default_rng(1), mics, 0.2, 2000)
    tdoa, levels = exact(mics, xy)
    res = HyperbolicSolver().solve(SolverInputs(mics, tdoa, 340.0, received_level_db=levels))
    err = np.linalg.norm(res.position_m - xy, axis=1)
    assert err.max() < 1e-4
    assert np.nanmax(res.residual_m) < 1e-6 and res.converged.all()
    assert set(np.unique(res.diagnostics["n_roots"])) <= {1.0, 2.0}


def test_two_roots_are_reported_and_energy_picks_the_right_one():
    xy = np.array([[60.0, -8.0], [-12.0, -6.0], [25.0, 58.0]])  # outside the triangle: two-root region
    tdoa, levels = exact(TRIANGLE, xy)
    solver = HyperbolicSolver(box_margin_fraction=2.0)  # both roots plausible by the box
    cand, valid = solver.roots(TRIANGLE, 340.0 * (tdoa[:, 1:] - tdoa[:, :1]), 1.2)
    two = valid.sum(1) == 2
    assert two.any(), "the constructed sources should have two roots"
    res = solver.solve(SolverInputs(TRIANGLE, tdoa, 340.0, received_level_db=levels))
    np.testing.assert_allclose(res.position_m[two], xy[two], atol=1e-4)
    assert (res.diagnostics["n_roots"][two] == 2).all()
    # the energy residual is what separates them: the wrong root is inconsistent with the levels
    e = energy_residual_db(levels[two], TRIANGLE, cand[two], 1.2)
    wrong = np.nanmax(e, axis=1)
    assert (wrong > 1.0).all()


def test_known_mic_heights_and_assumed_source_height():
    mics = HEXAGON.copy()
    mics[:, 2] = [1.5, 3.0, 1.0, 2.5, 4.0, 1.2]
    xy = sample_in_expanded_hull(np.random.default_rng(2), mics, 0.0, 300)
    tdoa, levels = exact(mics, xy, c=343.0, height=6.0)
    res = HyperbolicSolver(source_height_m=6.0).solve(SolverInputs(mics, tdoa, 343.0, received_level_db=levels))
    assert np.linalg.norm(res.position_m - xy, axis=1).max() < 1e-4


@settings(max_examples=25, deadline=None)
@given(
    shift=st.tuples(st.floats(-500, 500), st.floats(-500, 500)),
    angle=st.floats(0, 2 * np.pi),
    u=st.floats(0.05, 0.45),
    v=st.floats(0.05, 0.45),
)
def test_translation_and_rotation_invariance(shift, angle, u, v):
    xy = HEXAGON[0, :2] + u * (HEXAGON[2, :2] - HEXAGON[0, :2]) + v * (HEXAGON[4, :2] - HEXAGON[0, :2])
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    moved = HEXAGON.copy()
    moved[:, :2] = HEXAGON[:, :2] @ rot.T + np.array(shift)
    a = HyperbolicSolver().solve(SolverInputs(HEXAGON, exact(HEXAGON, xy[None])[0], 343.0)).position_m
    b = HyperbolicSolver().solve(SolverInputs(moved, exact(moved, (xy @ rot.T + np.array(shift))[None])[0], 343.0)).position_m
    np.testing.assert_allclose(b, a @ rot.T + np.array(shift), atol=1e-5)


def test_speed_of_sound_per_event_and_nan_tdoas():
    xy = np.array([[20.0, 10.0], [30.0, 15.0]])
    c = np.array([330.0, 345.0])
    tdoa = np.vstack([exact(TRIANGLE, xy[k : k + 1], c[k])[0] for k in range(2)])
    res = HyperbolicSolver().solve(SolverInputs(TRIANGLE, tdoa, c))
    np.testing.assert_allclose(res.position_m, xy, atol=1e-5)
    bad = HyperbolicSolver().solve(SolverInputs(TRIANGLE, np.array([[0.0, np.nan, 0.01]]), 340.0))
    assert np.isnan(bad.position_m).all() and not bad.converged[0]


def test_input_shapes_are_checked():
    with pytest.raises(ValueError, match=r"tdoa_s must be \(B, 3\)"):
        HyperbolicSolver().solve(SolverInputs(TRIANGLE, np.zeros((2, 4)), 340.0))
    with pytest.raises(ValueError, match="mic_positions_m"):
        HyperbolicSolver().solve(SolverInputs(TRIANGLE[:2], np.zeros((2, 2)), 340.0))


def test_crb_scales_with_snr_bandwidth_and_geometry():
    from acoustlab.toolkit.geometry import gdop, position_crb_m, tdoa_crb_s

    base = tdoa_crb_s(20.0, 3000.0, 0.1, 2000.0)
    assert tdoa_crb_s(40.0, 3000.0, 0.1, 2000.0) == pytest.approx(base / 10, rel=0.01)  # 20 dB more SNR: σ / 10 (high SNR)
    assert tdoa_crb_s(20.0, 6000.0, 0.1, 2000.0) == pytest.approx(base / 2)  # twice the RMS bandwidth
    src = np.array([[24.0, 15.0, 1.2], [24.0, 300.0, 1.2]])
    crb = position_crb_m(TRIANGLE, src, 20.0, 3000.0, 0.1, 2000.0, 340.0)
    np.testing.assert_allclose(crb, gdop(TRIANGLE, src) * 340.0 * base)
    assert crb[1] > 10 * crb[0]


def test_robust_solver_recovers_when_the_true_lag_is_a_lower_candidate():
    from plugins.solvers.robust import ConsistentCandidatesSolver

    rng = np.random.default_rng(0)
    xy = sample_in_expanded_hull(rng, HEXAGON, 0.1, 100)
    src = np.column_stack([xy, np.full(len(xy), 1.5)])
    d = np.sqrt(((src[:, None] - HEXAGON[None]) ** 2).sum(-1))
    pairs = [(i, j) for i in range(6) for j in range(i + 1, 6)]
    true = np.stack([(d[:, j] - d[:, i]) / 340.0 for i, j in pairs], 1)
    cands = np.stack([true + rng.uniform(-0.05, 0.05, true.shape), true, true + rng.uniform(-0.05, 0.05, true.shape)], -1)
    keep = rng.random(true.shape) < 0.5  # half the pairs have the right dominant peak
    cands[keep, 0], cands[keep, 1] = true[keep], cands[keep, 0].copy()
    tdoa = np.column_stack([np.zeros(len(xy)), cands[:, [pairs.index((0, j)) for j in range(1, 6)], 0]])
    robust = ConsistentCandidatesSolver(source_height_m=1.5).solve(SolverInputs(HEXAGON, tdoa, 340.0, pair_lag_candidates_s=cands))
    plain = HyperbolicSolver(source_height_m=1.5).solve(SolverInputs(HEXAGON, tdoa, 340.0))
    assert np.percentile(np.linalg.norm(robust.position_m - xy, axis=1), 95) < 1e-3
    assert np.percentile(np.linalg.norm(plain.position_m - xy, axis=1), 50) > 1.0


@pytest.mark.parametrize("solver_name", ["hyperbolic", "least_squares"])
def test_mics_on_one_line_give_no_fix_with_a_warning_not_a_point_on_the_line(solver_name, caplog):
    """With every mic on one line a source off it has a mirror image; the fit between them lies on the line with an
    infinite GDOP and fits neither. It is reported as no fix, with a warning that says why (the peer returns NaN too)."""
    import logging

    from acoustlab.core.contracts import SolverInputs
    from plugins.solvers.hyperbolic import HyperbolicSolver
    from plugins.solvers.least_squares import LeastSquaresSolver

    mics = np.array([[0.0, 0.0], [20.0, 0.0], [40.0, 0.0], [60.0, 0.0]])
    sources = np.array([[30.0, 15.0], [10.0, -20.0]])
    arrival = np.linalg.norm(mics[None] - sources[:, None], axis=-1) / 343.0
    solver = {"hyperbolic": HyperbolicSolver, "least_squares": LeastSquaresSolver}[solver_name](source_height_m=0.0)
    with caplog.at_level(logging.WARNING):
        result = solver.solve(SolverInputs(mic_positions_m=mics, tdoa_s=arrival - arrival[:, :1], speed_of_sound_m_s=343.0))
    assert np.isnan(result.position_m).all() and not result.converged.any()
    assert "the mics lie on one line" in caplog.text
    off_line = np.vstack([mics, [[30.0, 25.0]]])  # one mic off the line: both sources placed
    arrival = np.linalg.norm(off_line[None] - sources[:, None], axis=-1) / 343.0
    result = solver.solve(SolverInputs(mic_positions_m=off_line, tdoa_s=arrival - arrival[:, :1], speed_of_sound_m_s=343.0))
    np.testing.assert_allclose(result.position_m, sources, atol=1e-6)
