"""The compiled solvers (``solver=consistent_set_compiled``, ``solver=hyperbolic_compiled``) against the numpy ones they replace."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.core.contracts import SolverInputs
from plugins.solvers.consistent_select import select_compiled
from plugins.solvers.consistent_set import ConsistentSetSolver
from plugins.solvers.consistent_set_compiled import CompiledConsistentSetSolver
from plugins.solvers.hyperbolic import HyperbolicSolver
from plugins.solvers.hyperbolic_compiled import CompiledHyperbolicSolver
from plugins.solvers.hypothesis_search import LATENESS_WEIGHT
from tests.test_first_stage import HEXAGON, TRIANGLE, pairs, random_candidate_events

C = 343.0
OFF_PLANE = HEXAGON + np.array([0, 0, 1.0]) * np.array([0.0, 2.0, 0.5, 4.0, 1.0, 3.0])[:, None]
#: Outputs of the selection that must be equal, bit for bit (the choice); the least-squares times agree to rounding.
EXACT = ("trusted", "consistent_pairs", "consistency", "score_margin", "n_mics_used")


def assert_same_selection(cands, weights, prior=None, **settings):
    numpy_choice = ConsistentSetSolver(search="exhaustive", **settings).select(cands, weights, prior)
    compiled = CompiledConsistentSetSolver(**settings).select(cands, weights, prior)
    assert compiled.keys() == numpy_choice.keys()
    for key in EXACT:
        np.testing.assert_array_equal(compiled[key], numpy_choice[key], err_msg=key)
    np.testing.assert_array_equal(np.isnan(compiled["times_s"]), np.isnan(numpy_choice["times_s"]))
    np.testing.assert_allclose(compiled["times_s"], numpy_choice["times_s"], rtol=0, atol=1e-14)
    np.testing.assert_allclose(compiled["closure_rms_s"], numpy_choice["closure_rms_s"], rtol=1e-9, atol=1e-16, equal_nan=True)


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31), n_mics=st.sampled_from([3, 4, 5, 6]), k=st.sampled_from([1, 2, 3]),
       missing=st.sampled_from([0.0, 0.1, 0.5]), ties=st.booleans(), with_prior=st.booleans())
def test_compiled_selection_chooses_what_the_numpy_search_chooses(seed, n_mics, k, missing, ties, with_prior):
    """Same winner, runner-up margin (bit for bit), trusted mics and diagnostics: near-duplicate and spurious peaks,
    equal weights (ties broken by index alike), missing peaks up to whole pairs, SRP priors."""
    cands, weights, prior = random_candidate_events(seed, n_mics, k, missing, ties, with_prior)
    cands[1] = np.nan  # an event without any peak: every hypothesis misses an arrival
    weights[2, 0, 0] = np.nan  # a NaN height counts as 0
    assert_same_selection(cands, weights, prior, prior_weight=0.05 if with_prior else 0.0)


def one_pass_and_two_passes(cands, weights, m, k, tolerance_s):
    """Each event's winner times and margin (m mics) from the seeded one-pass search and from the two-pass search
    (which starts from no lower bound), run on the same tables."""
    import plugins.solvers.consistent_select as cs

    bsz, n_pairs, k_all = cands.shape
    i_idx, j_idx, ref_pair, slot_pair = cs._layout(m)
    n_slots = m - 1
    arrival, unary, own = np.empty((m, n_slots, k)), np.empty((m, 1, n_slots, k)), np.empty((n_pairs, k))
    table, free_best, root = np.empty((m, n_pairs, k, k)), np.empty((m, n_slots + 1)), np.empty(m)
    tops, lane_tables, lane_own = np.empty((m, n_pairs, 1)), np.empty((m, n_pairs, k, k, 1)), np.empty((n_pairs, k_all, 1))
    kept_score, kept_times = np.empty(cs._KEPT), np.empty((cs._KEPT, m))
    out = []
    for b in range(bsz):
        w = np.where(np.isfinite(cands[b]), np.nan_to_num(weights[b]), 0.0)
        cs._tables(cands[b], w, np.zeros(n_pairs), False, 0.0, 0.0, tolerance_s, k, k_all, i_idx, ref_pair, slot_pair, own, arrival,
                   unary, table, free_best, root, tops, lane_tables, lane_own, 0, False)
        results = []
        for one_pass in (True, False):
            win_t = np.empty(m)
            scratch = (np.empty(n_slots), np.empty(n_slots), np.empty(m), np.empty(m)) + ((np.empty(m),) if one_pass else ())
            margin = (cs._winner_one_pass if one_pass else cs._winner)(
                arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, LATENESS_WEIGHT, tolerance_s, np.zeros(n_slots, np.int64),
                np.zeros(m, np.int64), np.empty((n_slots, k)), np.empty((n_slots, k, n_slots, k)), np.empty((n_slots, k)), *scratch, win_t,
                kept_score, kept_times)
            results.append((win_t, margin))
        out.append(results)
    return out


@pytest.mark.parametrize("n_mics", [3, 4, 6])
@pytest.mark.parametrize("ties", [True, False])
def test_the_seeded_search_finds_what_the_unseeded_search_finds(n_mics, ties):
    """θ's seed (one-slot variants scored from the first hypothesis, in another order than the exact scores) only
    prunes: the one-pass search gives the winner's times and the margin of the two-pass search, which starts from
    no bound, bit for bit, also with equal heights (exact ties, where the seed's rounding could matter)."""
    tolerance_s = ConsistentSetSolver().tolerance_s
    for seed in range(8):
        cands, weights, _ = random_candidate_events(seed, n_mics, 3, 0.1, ties, False, bsz=40)
        for (one_t, one_margin), (two_t, two_margin) in one_pass_and_two_passes(cands, weights, n_mics, 3, tolerance_s):
            np.testing.assert_array_equal(one_t, two_t)
            np.testing.assert_array_equal(one_margin, two_margin)


@pytest.mark.parametrize("n_mics", [8, 10])
def test_compiled_selection_on_larger_arrays(n_mics):
    """8 and 10 mics, 3 candidates per pair (17,496 and 196,830 hypotheses per event), the true lag at a random rank."""
    rng = np.random.default_rng(n_mics)
    mics, src = rng.uniform(0, 100, size=(n_mics, 2)), rng.uniform(0, 100, size=(12, 2))
    t = np.sqrt(((src[:, None] - mics[None]) ** 2).sum(-1)) / C
    lags = np.stack([t[:, j] - t[:, i] for i, j in pairs(n_mics)], axis=1)
    cands = lags[..., None] + rng.choice([-1, 1], size=(*lags.shape, 3)) * rng.uniform(2e-3, 2e-2, size=(*lags.shape, 3))
    cands[..., 0] = lags + rng.normal(0, 5e-5, lags.shape)
    cands = np.take_along_axis(cands, rng.permuted(np.tile(np.arange(3), (*lags.shape, 1)), axis=-1), -1)
    weights = rng.uniform(0.2, 0.6, size=cands.shape)
    numpy_choice = ConsistentSetSolver(search="pruned").select(cands, weights)
    compiled = CompiledConsistentSetSolver().select(cands, weights)
    for key in EXACT:
        np.testing.assert_array_equal(compiled[key], numpy_choice[key], err_msg=key)
    np.testing.assert_allclose(compiled["times_s"], numpy_choice["times_s"], rtol=0, atol=1e-14)


def test_compiled_selection_with_near_duplicate_peaks_everywhere():
    """Every pair's three peaks within the tolerance of each other: all 1,458 hypotheses of an event score alike, more
    than the one-pass search keeps, so the two-pass search decides; the choice is still numpy's, bit for bit."""
    rng = np.random.default_rng(5)
    arrival = rng.uniform(0, 0.01, size=(8, 6))
    lags = np.stack([arrival[:, j] - arrival[:, i] for i, j in pairs(6)], axis=1)
    cands = lags[..., None] + np.array([0.0, 3e-5, 6e-5])
    assert_same_selection(cands, np.full(cands.shape, 0.5))
    assert_same_selection(cands, rng.uniform(0.4, 0.6, size=cands.shape))


def test_the_lanes_pair_tables_are_each_events_own_bit_for_bit():
    """:func:`_lane_tables` (every lane's event at once) gives each event's pair tables and their largest entries as
    :func:`_pair_table` does for that event alone, and each candidate's own entry as :func:`_entry` does, bit for bit: NaN,
    infinite and missing candidates, NaN and infinite heights, a prior, and a last block with fewer events than lanes (whose
    spare lanes are left as they were)."""
    import plugins.solvers.consistent_select as cs

    m, k = 6, 3
    cands, weights, prior = random_candidate_events(11, m, k, 0.1, False, True, bsz=cs.LANES + 7)
    cands[3, 2, 1], cands[4, 5, 0], weights[5, 1, 2], weights[6, 3, 0] = np.inf, -np.inf, np.nan, np.inf
    i_idx, j_idx, ref_pair, slot_pair = cs._layout(m)
    n_pairs, n_slots, lanes = len(i_idx), m - 1, cs.LANES
    prior_weight, prior_tol, tol = 0.05, 1e-3, 2.5e-4
    for b0 in (0, lanes):
        nb = min(lanes, len(cands) - b0)
        lane_arrival, lane_cands = np.empty((m, n_slots, 3, lanes)), np.empty((n_pairs, k, lanes))
        lane_w, lane_prior = np.empty((n_pairs, k, lanes)), np.empty((n_pairs, lanes))
        tables, tops = np.full((m, n_pairs, k, k, lanes), 7.0), np.full((m, n_pairs, lanes), 7.0)
        lane_own = np.full((n_pairs, k, lanes), 7.0)
        cs._gather_lanes(cands, weights, prior, True, b0, nb, i_idx, ref_pair, lane_arrival, lane_cands, lane_w, lane_prior)
        cs._lane_tables(nb, lane_arrival, lane_cands, lane_w, lane_prior, True, prior_weight, prior_tol, tol, slot_pair, tables, tops,
                        lane_own)
        assert (tables[..., nb:] == 7.0).all() and (tops[..., nb:] == 7.0).all() and (lane_own[..., nb:] == 7.0).all()
        for e in range(nb):
            b = b0 + e
            w = np.where(np.isfinite(cands[b]), np.nan_to_num(weights[b]), 0.0)
            for p in range(n_pairs):
                for q in range(k):
                    x = cands[b, p, q]
                    own = cs._entry.py_func(x, cands[b], w, p, k, tol, True, prior[b, p], prior_weight, prior_tol) if np.isfinite(x) else -np.inf
                    assert lane_own[p, q, e] == own or (np.isnan(own) and np.isnan(lane_own[p, q, e])), f"event {b}, pair {p}, rank {q}"
            arrival = np.where(i_idx[ref_pair][..., None] == np.arange(m)[:, None, None], 1.0, -1.0) * cands[b][ref_pair]
            np.testing.assert_array_equal(lane_arrival[..., e], arrival)
            for r in range(m):
                for s in range(n_slots):
                    for s2 in range(s + 1, n_slots):
                        p = slot_pair[r, s, s2]
                        table = np.full((m, n_pairs, k, k), 7.0)
                        top = cs._pair_table.py_func(cands[b], w, p, k, arrival, r, s, s2, k, tol, True, prior[b, p], prior_weight,
                                                     prior_tol, table)
                        np.testing.assert_array_equal(tables[r, p, :, :, e], table[r, p], err_msg=f"event {b}, reference {r}, pair {p}")
                        assert tops[r, p, e] == top or (np.isnan(top) and np.isnan(tops[r, p, e]))


def test_compiled_selection_of_several_blocks_of_lanes():
    """More events than one block of lanes, the last block partly filled: the choice is still numpy's, bit for bit."""
    import plugins.solvers.consistent_select as cs

    cands, weights, prior = random_candidate_events(12, 6, 3, 0.1, False, True, bsz=2 * cs.LANES + 5)
    assert_same_selection(cands, weights, prior, prior_weight=0.05)


@pytest.mark.parametrize("k_all,max_hypotheses", [(4, 10_000), (4, 1_000), (5, 100)])
def test_compiled_selection_with_more_candidates_than_ranks(k_all, max_hypotheses):
    """K = 4 or 5 peaks per pair, of which the first k = 4, 2 or 1 form hypotheses (max_hypotheses) while every K count
    for consistency: the general pair-table path (the default K = 3 has one of its own), the choice numpy's, bit for bit."""
    rng = np.random.default_rng(k_all + max_hypotheses)
    arrival = rng.uniform(0, 0.01, size=(16, 6))
    lags = np.stack([arrival[:, j] - arrival[:, i] for i, j in pairs(6)], axis=1)
    cands = lags[..., None] + rng.choice([0.0, 1e-4, 3e-3, -4e-3, 9e-3], size=(*lags.shape, k_all))
    cands[rng.random(cands.shape) < 0.1] = np.nan
    assert_same_selection(cands, rng.uniform(0, 1, size=cands.shape), max_hypotheses=max_hypotheses)


@pytest.mark.parametrize("n_mics", [3, 6, 10, 63])
@pytest.mark.parametrize("n_events", [0, 1, 500])
def test_compiled_solver_groups_events_as_numpy_does(n_mics, n_events):
    """Events grouped by their trusted mics with integer keys: the same groups, rows and order as np.unique on the rows
    (63 mics: too many bits for a key, numpy's grouping)."""
    trusted = np.random.default_rng(n_mics).random((n_events, n_mics)) < 0.85
    expected = ConsistentSetSolver._groups_by_trusted(trusted)
    got = CompiledConsistentSetSolver._groups_by_trusted(trusted)
    assert len(got) == len(expected)
    for (mask, rows), (want_mask, want_rows) in zip(got, expected, strict=True):
        np.testing.assert_array_equal(mask, want_mask)
        np.testing.assert_array_equal(rows, want_rows)


def test_compiled_selection_names_what_is_wrong():
    with pytest.raises(ValueError, match="all pairs of M mics"):
        select_compiled(np.zeros((2, 4, 3)), np.ones((2, 4, 3)), None, k=3, tolerance_s=2.5e-4, prior_weight=0.0, prior_tolerance_s=1e-3)
    with pytest.raises(ValueError, match="must cover all 15 pairs of 6 mics"):
        CompiledConsistentSetSolver().select(np.zeros((2, 14, 3)), np.ones((2, 14, 3)))


def hyperbolic_inputs(mics, n, noise_s, seed, levels=False):
    rng = np.random.default_rng(seed)
    lo, hi = mics[:, :2].min(0) - 20, mics[:, :2].max(0) + 20
    src = np.column_stack([rng.uniform(lo, hi, size=(n, 2)), rng.uniform(0.5, 8.0, n)])
    t = np.sqrt(((src[:, None] - mics[None]) ** 2).sum(-1)) / C
    tdoa = t - t[:, :1] + rng.normal(0, noise_s, t.shape)
    tdoa[:5, 1] = np.nan  # events without a fix
    received = -20 * np.log10(np.sqrt(((src[:, None] - mics[None]) ** 2).sum(-1))) + rng.normal(0, 1, t.shape) if levels else None
    return src, SolverInputs(mics, tdoa, C, received_level_db=received, source_height_m=float(mics[:, 2].mean()) + 1.0)


@pytest.mark.parametrize("mics", [HEXAGON, OFF_PLANE, TRIANGLE], ids=["coplanar", "off-plane", "triangle"])
@pytest.mark.parametrize("dimensions,fallback", [(2, True), (3, True), (3, False)])
@pytest.mark.parametrize("levels", [False, True])
def test_compiled_hyperbolic_solver_gives_the_numpy_fixes(mics, dimensions, fallback, levels):
    """Positions, residuals and every diagnostic as the numpy solver reports them, to rounding; the same keys, the
    same events without a fix, the same root counts, mirror flags and modes; noisy TDOAs, sources in the mics' plane."""
    if dimensions == 3 and len(mics) < 4:
        with pytest.raises(ValueError, match="at least 4 mics"):
            CompiledHyperbolicSolver(dimensions=3).solve(hyperbolic_inputs(mics, 4, 0.0, 0)[1])
        return
    _, inputs = hyperbolic_inputs(mics, 400, 2e-5, seed=len(mics), levels=levels)
    expected = HyperbolicSolver(dimensions=dimensions, fallback_2d=fallback).solve(inputs)
    got = CompiledHyperbolicSolver(dimensions=dimensions, fallback_2d=fallback).solve(inputs)
    assert got.diagnostics.keys() == expected.diagnostics.keys()
    np.testing.assert_array_equal(got.converged, expected.converged)
    np.testing.assert_allclose(got.position_m, expected.position_m, rtol=0, atol=1e-5, equal_nan=True)
    np.testing.assert_allclose(got.residual_m, expected.residual_m, rtol=1e-6, atol=1e-9, equal_nan=True)
    for name in ("n_roots", "height_ambiguous", "dimensions_used"):
        if name in expected.diagnostics:
            np.testing.assert_array_equal(got.diagnostics[name], expected.diagnostics[name], err_msg=name)
    # Beyond what rounding resolves, both solvers need only say "ill-conditioned": a source in the mics' plane (height_gdop
    # ~ 1e14), or a Jacobian whose JᵀJ has eigenvalues 10¹² apart (conditioning > 10⁶: the smaller one, half-trace less
    # spread, is then rounding noise of the larger; it moves with where each polish stopped and with the machine: equal
    # to 1e-4 on earlier machines, 7.8e7 against 8.2e11 for one triangle event on an AMD EPYC)
    beyond = {"height_gdop": 1e4, "conditioning": 1e6}
    for name, values in expected.diagnostics.items():
        ill = (values > beyond[name]) if name in beyond else np.zeros(len(values), bool)
        np.testing.assert_allclose(got.diagnostics[name][~ill], values[~ill], rtol=1e-4, atol=1e-6, equal_nan=True, err_msg=name)
        assert (got.diagnostics[name][ill] > beyond.get(name, np.inf)).all(), name


def test_compiled_hyperbolic_solver_is_exact_on_noise_free_tdoas():
    src, inputs = hyperbolic_inputs(HEXAGON, 200, 0.0, seed=1)
    fix = CompiledHyperbolicSolver(dimensions=3, fallback_2d=False).solve(inputs)
    ok = np.isfinite(fix.position_m).all(1)
    assert ok.sum() >= 190
    np.testing.assert_allclose(fix.position_m[ok], src[ok, :2], atol=1e-6)
    upper_image = 1.5 + np.abs(src[ok, 2] - 1.5)  # coplanar mics: the mirror above their plane is reported
    np.testing.assert_allclose(fix.diagnostics["source_height_m"][ok], upper_image, atol=1e-5)


def test_compiled_consistent_set_solver_gives_the_numpy_solution():
    """The whole solver on events with planted reflections and a mic lost to noise (some events then trust 3 mics):
    the same trusted mics and margins, the same fixes to rounding."""
    rng = np.random.default_rng(7)
    xy = rng.uniform([-5, -5], [85, 75], size=(64, 2))
    src = np.column_stack([xy, np.full(len(xy), 1.5)])
    t = np.sqrt(((src[:, None] - HEXAGON[None]) ** 2).sum(-1)) / C
    lags = np.stack([t[:, j] - t[:, i] for i, j in pairs(6)], axis=1)
    cands = np.concatenate([lags[..., None], lags[..., None] + rng.uniform(3e-3, 2e-2, size=(*lags.shape, 2))], axis=-1)
    weights = np.concatenate([np.full((*lags.shape, 1), 0.5), np.full((*lags.shape, 2), 0.3)], axis=-1)
    cands[:16, 3] = cands[:16, 3, ::-1]  # a reflection outranks the direct path of pair (0, 4)
    for p, (i, j) in enumerate(pairs(6)):
        if {i, j} & {4, 5}:
            cands[32:40, p] = rng.uniform(-0.2, 0.2, size=(8, 3))  # mics 4 and 5 hear only noise
    tdoa = t - t[:, :1]
    inputs = SolverInputs(HEXAGON, tdoa, C, pair_lag_candidates_s=cands, pair_lag_weights=weights, source_height_m=1.5)
    expected = ConsistentSetSolver().solve(inputs)
    got = CompiledConsistentSetSolver().solve(inputs)
    assert (expected.diagnostics["n_mics_used"][32:40] <= 4).all()
    assert got.diagnostics.keys() == expected.diagnostics.keys()
    for name in EXACT[1:] + ("n_roots", "dimensions_used"):
        np.testing.assert_array_equal(got.diagnostics[name], expected.diagnostics[name], err_msg=name)
    np.testing.assert_allclose(got.position_m, expected.position_m, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.position_m, xy, atol=1e-3)


@pytest.mark.parametrize("solver_class", [ConsistentSetSolver, CompiledConsistentSetSolver])
def test_infinite_gcc_heights_stop_with_a_line_naming_them(solver_class):
    """An infinite height of an existing candidate would make the scores that contain it infinite (the choice meaningless,
    and the numpy and compiled searches would disagree): both solvers stop with a DataError naming event, pair and rank.
    A NaN height (0) and an infinite height of a missing candidate (not read) are accepted, as are heights of any shape
    only when it is the candidates' shape."""
    from acoustlab.core.errors import DataError

    cands, weights, _ = random_candidate_events(3, 4, 3, 0.0, False, False)
    tdoa = np.zeros((cands.shape[0], 4))
    solve = lambda w, c=cands: solver_class().solve(SolverInputs(HEXAGON[:4], tdoa, C, pair_lag_candidates_s=c, pair_lag_weights=w))  # noqa: E731
    bad = weights.copy()
    bad[2, 1, 0] = np.inf
    with pytest.raises(DataError, match=r"pair_lag_weights must be finite .* got inf at event 2, pair 1, candidate 0 \(1 infinite"):
        solve(bad)
    bad[2, 1, 0] = -np.inf
    with pytest.raises(DataError, match="got -inf at event 2"):
        solve(bad)
    with pytest.raises(DataError, match=r"pair_lag_weights must have the shape of pair_lag_candidates_s \(\d+, 6, 3\) .* got \(\d+, 6, 2\)"):
        solve(weights[..., :2])
    accepted = weights.copy()
    accepted[0, 0, 0] = np.nan  # counts as 0
    missing = cands.copy()
    missing[1, 2, 2] = np.nan
    accepted[1, 2, 2] = np.inf  # the height of a missing candidate is not read
    expected = solver_class().solve(SolverInputs(HEXAGON[:4], tdoa, C, pair_lag_candidates_s=missing,
                                                 pair_lag_weights=np.where(np.isinf(accepted), 0.0, accepted)))
    got = solve(accepted, missing)
    np.testing.assert_array_equal(got.position_m, expected.position_m)


def test_the_scalar_3x3_solve_and_normal_sums_are_the_linear_algebra_they_replace():
    """The compiled fix's scalar pieces: the 3 × 3 Gaussian elimination with partial pivoting (leading zeros and tiny
    pivots included) solves what numpy solves, and the residual sums are Σ r², JᵀJ and Jᵀr of the stored Jacobian."""
    import acoustlab.toolkit.compiled_fix as cf

    rng = np.random.default_rng(7)
    for n in range(200):
        a, b = rng.normal(size=(3, 3)), rng.normal(size=3)
        if n % 4 == 1:
            a[0, 0] = 0.0  # the first pivot must come from another row
        elif n % 4 == 2:
            a[:2, 0] = 1e-14 * a[:2, 0]  # the last row holds the only large first entry
        elif n % 4 == 3:
            a[1, 1] = a[0, 1] * a[1, 0] / a[0, 0]  # zero second pivot after the first elimination: swap rows 1 and 2
        np.testing.assert_allclose(cf._solve3(*a.ravel(), *b), np.linalg.solve(a, b), rtol=1e-9, atol=1e-9)
    mics = np.column_stack([rng.uniform(0, 60, (6, 2)), rng.uniform(0, 3, 6)])
    point, rd = np.array([20.0, 35.0, 2.0]), rng.normal(0, 5, 5)
    d = np.linalg.norm(point - mics, axis=1)
    r = (d[1:] - d[0]) - rd
    jac = (point - mics[1:]) / d[1:, None] - (point - mics[0]) / d[0]
    cost, a00, a01, a02, a11, a12, a22, g0, g1, g2 = cf._residuals_3d(*point, mics, rd)
    jtj = jac.T @ jac
    np.testing.assert_allclose(cost, r @ r, rtol=1e-12)
    np.testing.assert_allclose([a00, a01, a02, a11, a12, a22], jtj[np.triu_indices(3)], rtol=1e-12)
    np.testing.assert_allclose([g0, g1, g2], jac.T @ r, rtol=1e-10, atol=1e-12)
    cost2, j00, j01, j11, h0, h1 = cf._residuals_2d(point[0], point[1], mics, point[2], rd)
    np.testing.assert_allclose([cost2, j00, j01, j11, h0, h1], [r @ r, *jtj[:2, :2][np.triu_indices(2)], *(jac.T @ r)[:2]], rtol=1e-10, atol=1e-12)
