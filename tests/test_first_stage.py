"""The robust first stage: consistent candidate sets, bounded output, failures counted, the peer heuristic."""

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.core import columns as col
from acoustlab.core.contracts import SolverInputs
from acoustlab.core.types import NoiseRegime, Site
from acoustlab.reporting.metrics import error_summary
from acoustlab.stages.solver_columns import FAILURE_IMPLAUSIBLE, FAILURE_NO_FIX, add_solver_columns, bound_fixes
from plugins.solvers.consistent_set import ConsistentSetSolver
from plugins.solvers.hyperbolic import HyperbolicSolver
from plugins.solvers.per_reference_mic import PerReferenceMicSolver
from tests.conftest import examples

C = 340.0
TRIANGLE = np.array([[0.0, 0.0, 1.2], [50.0, 0.0, 1.2], [24.0, 44.0, 1.2]])
HEXAGON = np.array([[0, 0, 1.5], [55, -5, 1.5], [90, 25, 1.5], [75, 70, 1.5], [25, 75, 1.5], [-10, 35, 1.5]], float)


def pairs(m):
    return [(i, j) for i in range(m) for j in range(i + 1, m)]


def random_candidate_events(seed, n_mics, k, missing, ties, with_prior, bsz=24):
    """(B, P, k) candidate lags around true ones (near-duplicate peaks within and just inside the tolerance, spurious
    ones ms away), a share ``missing`` of them NaN and the first event's first pair without any, GCC heights (two
    values when ``ties``) and SRP prior lags 1 ms off (None without ``with_prior``)."""
    rng = np.random.default_rng(seed)
    n_pairs = n_mics * (n_mics - 1) // 2
    arrival = rng.uniform(0, 0.01, size=(bsz, n_mics))
    lags = np.stack([arrival[:, j] - arrival[:, i] for i, j in pairs(n_mics)], axis=1)
    cands = lags[..., None] + rng.choice([0.0, 0.0, 1e-4, 2.4e-4, 3e-3, -4e-3, 9e-3], size=(bsz, n_pairs, k))
    cands[rng.random(cands.shape) < missing] = np.nan
    cands[0, 0] = np.nan  # a pair without any peak
    weights = rng.choice([0.5, 1.0], size=cands.shape) if ties else rng.uniform(0, 1, size=cands.shape)
    prior = lags + rng.normal(0, 1e-3, size=lags.shape) if with_prior else None
    return cands, weights, prior


def scene(mics, xy, k=3, seed=0):
    """Exact lags of every pair as rank 1, two spurious lower peaks per pair; TDOAs to mic 0 from rank 1."""
    rng = np.random.default_rng(seed)
    src = np.column_stack([xy, np.full(len(xy), mics[0, 2])])
    t = np.sqrt(((src[:, None] - mics[None]) ** 2).sum(-1)) / C
    lags = np.stack([t[:, j] - t[:, i] for i, j in pairs(len(mics))], axis=1)  # (E, P)
    cands = np.concatenate([lags[..., None], lags[..., None] + rng.uniform(3e-3, 2e-2, size=(*lags.shape, k - 1))], axis=-1)
    weights = np.concatenate([np.full((*lags.shape, 1), 0.5), np.full((*lags.shape, k - 1), 0.3)], axis=-1)
    return t - t[:, :1], cands, weights


def plant_reflection(cands, weights, pair_index, delay_s=1.5e-2):
    """Make a delayed copy the highest peak of one pair and push the direct path to rank 2."""
    cands, weights = cands.copy(), weights.copy()
    cands[:, pair_index, 1] = cands[:, pair_index, 0]
    cands[:, pair_index, 0] = cands[:, pair_index, 1] + delay_s
    weights[:, pair_index, 0], weights[:, pair_index, 1] = 0.6, 0.5
    return cands, weights


def inputs_from(mics, cands, weights):
    top = cands[:, :, 0]
    m = len(mics)
    tdoa = np.column_stack([np.zeros(len(top))] + [top[:, pairs(m).index((0, j))] for j in range(1, m)])
    return SolverInputs(mics, tdoa, C, pair_lag_candidates_s=cands, pair_lag_weights=weights, source_height_m=float(mics[0, 2]))


@pytest.mark.parametrize("mics,pair", [(HEXAGON, (0, 2)), (HEXAGON, (3, 4)), (TRIANGLE, (0, 1))])
def test_a_planted_reflection_is_rejected_by_consistency(mics, pair):
    xy = np.array([[30.0, 30.0], [20.0, 10.0], [40.0, 25.0]]) if len(mics) == 6 else np.array([[25.0, 15.0], [20.0, 20.0]])
    _, cands, weights = scene(mics, xy)
    cands, weights = plant_reflection(cands, weights, pairs(len(mics)).index(pair))
    inputs = inputs_from(mics, cands, weights)
    chosen = ConsistentSetSolver().solve(inputs)
    assert np.linalg.norm(chosen.position_m - xy, axis=1).max() < 1e-3
    assert (chosen.diagnostics["consistency"] == 1.0).all() and (chosen.diagnostics["n_mics_used"] == len(mics)).all()
    assert (chosen.diagnostics["score_margin"] > 0).all()
    if pair[0] == 0:  # the reflection sits in a pair with mic 0: the top-peak solver is fooled
        assert np.linalg.norm(HyperbolicSolver().solve(inputs).position_m - xy, axis=1).min() > 1.0


def test_a_mic_with_no_consistent_peak_is_left_out():
    xy = np.array([[30.0, 30.0], [45.0, 40.0]])
    _, cands, weights = scene(HEXAGON, xy)
    for p, (i, j) in enumerate(pairs(6)):
        if 5 in (i, j):  # mic 5 hears only noise: every one of its peaks is random
            cands[:, p, :] = np.random.default_rng(p).uniform(-0.2, 0.2, size=(2, 3))
    result = ConsistentSetSolver().solve(inputs_from(HEXAGON, cands, weights))
    assert (result.diagnostics["n_mics_used"] == 5).all()
    assert np.linalg.norm(result.position_m - xy, axis=1).max() < 1e-3


@settings(max_examples=examples(25), deadline=None)
@given(order=st.permutations(range(6)), x=st.floats(0, 80), y=st.floats(0, 70), reflected=st.integers(0, 14))
def test_selection_does_not_depend_on_mic_order(order, x, y, reflected):
    xy = np.array([[x, y]])
    _, cands, weights = scene(HEXAGON, xy, seed=reflected)
    cands, weights = plant_reflection(cands, weights, reflected)
    base = ConsistentSetSolver().solve(inputs_from(HEXAGON, cands, weights))
    order = list(order)
    mics = HEXAGON[order]
    index = {p: n for n, p in enumerate(pairs(6))}
    perm_c, perm_w = np.empty_like(cands), np.empty_like(weights)
    for n, (a, b) in enumerate(pairs(6)):
        i, j = order[a], order[b]
        src = index[(min(i, j), max(i, j))]
        perm_c[:, n] = cands[:, src] if i < j else -cands[:, src]
        perm_w[:, n] = weights[:, src]
    permuted = ConsistentSetSolver().solve(inputs_from(mics, perm_c, perm_w))
    np.testing.assert_allclose(permuted.position_m, base.position_m, atol=1e-6)
    assert permuted.diagnostics["consistent_pairs"] == pytest.approx(base.diagnostics["consistent_pairs"])


def test_the_peer_heuristic_keeps_the_lowest_residual_reference():
    xy = np.array([[30.0, 30.0], [50.0, 20.0]])
    _, cands, weights = scene(HEXAGON, xy)
    cands, weights = plant_reflection(cands, weights, pairs(6).index((0, 2)))  # spoils reference mics 0 and 2 only
    result = PerReferenceMicSolver().solve(inputs_from(HEXAGON, cands, weights))
    assert np.linalg.norm(result.position_m - xy, axis=1).max() < 1e-3
    assert not set(result.diagnostics["reference_mic"]) & {0.0, 2.0}


def site_of(mics):
    return Site(
        name="t",
        mic_positions_m=mics,
        tree_positions_m=np.zeros((0, 2)),
        trunk_diameters_m=np.zeros(0),
        temperature_range_c=(10.0, 10.0),
        relative_humidity_range_pct=(50.0, 50.0),
        ground_type="grass",
        ground_flow_resistivity_kpa_s_m2=200.0,
        ground_impedance_model="miki",
        ground_layer_thickness_m=None,
        noise_regimes=(NoiseRegime("white"),),
        snr_range_db=(10.0, 20.0),
        species_pool=("synthetic",),
        source_height_range_m=(1.2, 1.2),
        hull_expansion=0.2,
    )


def test_bounded_output_on_a_degenerate_geometry():
    """TDOAs no source can produce (larger than the mic spacing allows) never come out as a far-away number."""
    site = site_of(TRIANGLE)
    features = pd.DataFrame({col.tdoa_lag(0, 1): [0.5, 0.01, np.nan], col.tdoa_lag(0, 2): [-0.49, 0.02, 0.0]})
    events = pd.DataFrame({"speed_of_sound_m_s": [C, C, C]})
    unbounded = add_solver_columns(features, events, site, HyperbolicSolver())
    bounded = add_solver_columns(features, events, site, HyperbolicSolver(), plausible_margin_fraction=1.0)
    assert np.abs(unbounded.loc[0, [col.SOLVER_X, col.SOLVER_Y]].to_numpy(float)).max() > 200  # what it used to emit
    assert bounded.loc[0, [col.SOLVER_X, col.SOLVER_Y]].isna().all() and bounded.loc[0, col.SOLVER_FAILURE] == FAILURE_IMPLAUSIBLE
    assert bounded.loc[2, col.SOLVER_FAILURE] == FAILURE_NO_FIX
    assert np.isfinite(bounded.loc[1, [col.SOLVER_X, col.SOLVER_Y]].to_numpy(float)).all() and bounded.loc[1, col.SOLVER_FAILURE] == 0


def test_bound_keeps_fixes_inside_and_none_means_unbounded():
    site = site_of(TRIANGLE)
    fixes = np.array([[25.0, 20.0], [1e5, 0.0], [np.nan, 1.0]])
    kept, failure = bound_fixes(fixes, site, None)
    assert np.isfinite(kept[1]).all() and list(failure) == [0, 0, FAILURE_NO_FIX]
    kept, failure = bound_fixes(fixes, site, 1.0)
    assert np.isnan(kept[1]).all() and list(failure) == [0, FAILURE_IMPLAUSIBLE, FAILURE_NO_FIX]


def test_failures_count_in_every_percentile():
    errors = np.concatenate([np.linspace(0.1, 1.0, 90), np.full(10, np.inf)])
    summary = error_summary(errors)
    assert summary["n_failed"] == 10 and summary["n"] == 100
    assert summary["p50"] == pytest.approx(np.percentile(errors[:90], 50 * 100 / 90), rel=0.02)  # the failures shift the median
    assert summary["p95"] == np.inf and summary["p99"] == np.inf
    assert np.isfinite(summary["p90"]) or summary["p90"] == np.inf
    dropped = error_summary(errors[:90])
    assert summary["p50"] > dropped["p50"]  # counting failures never flatters
    assert error_summary(np.array([1.0, np.nan]))["n_failed"] == 1


# --- 3-D fixes ------------------------------------------------------------------------------

OFF_PLANE = HEXAGON.copy()
OFF_PLANE[:, 2] = [1.5, 3.0, 8.0, 1.2, 5.0, 2.5]  # mics strapped at different heights


def exact_tdoa(mics, src):
    t = np.sqrt(((src[:, None] - mics[None]) ** 2).sum(-1)) / C
    return t - t[:, :1]


@pytest.mark.parametrize("mics", [HEXAGON, OFF_PLANE, HEXAGON[:4]])
def test_a_noise_free_3d_case_is_exact(mics):
    rng = np.random.default_rng(3)
    src = np.column_stack([rng.uniform(0, 80, 40), rng.uniform(0, 70, 40), rng.uniform(4.0, 40.0, 40)])  # above every mic
    result = HyperbolicSolver(dimensions=3).solve(SolverInputs(mics, exact_tdoa(mics, src), C))
    assert np.abs(result.position_m - src[:, :2]).max() < 1e-6
    assert np.abs(result.diagnostics["source_height_m"] - src[:, 2]).max() < 1e-6
    assert (result.diagnostics["height_ambiguous"] == 0).all()


def test_the_exact_root_of_random_3d_arrays_is_never_beaten_by_its_mirror():
    """Exact time differences from 200 random 3-D arrays: the root that fits to numerical precision is reported, never a
    second root a few cm worse that a coplanar tie rule would prefer for being higher; the other root's misfit is given."""
    rng = np.random.default_rng(11)
    errors, other = [], []
    for _ in range(200):
        mics = np.column_stack([rng.uniform(0, 60, 5), rng.uniform(0, 60, 5), rng.uniform(0.5, 12, 5)])
        src = np.array([[rng.uniform(0, 60), rng.uniform(0, 60), rng.uniform(0.5, 20)]])
        result = HyperbolicSolver(dimensions=3, fallback_2d=False).solve(SolverInputs(mics, exact_tdoa(mics, src), C))
        errors.append(np.hypot(*(result.position_m[0] - src[0, :2])))
        other.append(result.diagnostics["other_root_residual_m"][0])
    assert max(errors) < 1e-4, sorted(errors)[-3:]
    assert np.nanmin(other) >= 0 and np.isfinite(other).any()


def test_coplanar_mics_flag_the_mirror_height_and_its_poor_precision():
    src = np.array([[30.0, 30.0, 1.0], [30.0, 30.0, 20.0]])  # 0.5 m below the mics' plane (its mirror is above ground); far above it
    result = HyperbolicSolver(dimensions=3).solve(SolverInputs(HEXAGON, exact_tdoa(HEXAGON, src), C))
    np.testing.assert_allclose(result.position_m, src[:, :2], atol=1e-6)
    assert result.diagnostics["height_ambiguous"].tolist() == [1.0, 0.0]
    assert result.diagnostics["source_height_m"][0] == pytest.approx(2.0, abs=1e-6)  # the upper image is reported
    assert result.diagnostics["height_gdop"][0] > 10 * result.diagnostics["height_gdop"][1]  # near the plane the height is poor


def test_3d_needs_four_mics_and_says_so():
    with pytest.raises(ValueError, match="at least 4 mics"):
        HyperbolicSolver(dimensions=3).solve(SolverInputs(TRIANGLE, np.zeros((1, 3)), C))


def test_consistent_set_solves_3d_through_a_planted_reflection():
    src = np.array([[30.0, 30.0, 12.0], [20.0, 10.0, 25.0]])
    t = np.sqrt(((src[:, None] - OFF_PLANE[None]) ** 2).sum(-1)) / C
    lags = np.stack([t[:, j] - t[:, i] for i, j in pairs(6)], axis=1)
    cands = np.concatenate([lags[..., None], lags[..., None] + np.array([4e-3, 9e-3])], axis=-1)
    weights = np.concatenate([np.full((*lags.shape, 1), 0.5), np.full((*lags.shape, 2), 0.3)], axis=-1)
    cands, weights = plant_reflection(cands, weights, pairs(6).index((0, 2)))
    result = ConsistentSetSolver(dimensions=3).solve(inputs_from(OFF_PLANE, cands, weights))
    np.testing.assert_allclose(result.position_m, src[:, :2], atol=1e-6)
    np.testing.assert_allclose(result.diagnostics["source_height_m"], src[:, 2], atol=1e-6)


def brute_force_selection(cands, weights, tol):
    """The consistent-set choice by visiting every hypothesis one by one (the definition; slow)."""
    import itertools

    bsz, n_pairs, k = cands.shape
    m = int(round((1 + np.sqrt(1 + 8 * n_pairs)) / 2))
    prs = pairs(m)
    out = []
    for b in range(bsz):
        scored = []
        for ref in range(m):
            others = [n for n in range(m) if n != ref]
            for combo in itertools.product(range(k), repeat=m - 1):
                t = np.zeros(m)
                for n, c in zip(others, combo, strict=True):
                    p = prs.index((min(ref, n), max(ref, n)))
                    t[n] = cands[b, p, c] if ref < n else -cands[b, p, c]
                if not np.isfinite(t).all():
                    continue
                score = 0.0
                for p, (i, j) in enumerate(prs):
                    close = np.abs((t[j] - t[i]) - cands[b, p]) < tol
                    score += max([weights[b, p, r] for r in range(k) if close[r]], default=0.0)
                score -= 1e-3 * (t - t.min()).sum()
                scored.append((score, t - t[0]))
        best = max(range(len(scored)), key=lambda h: scored[h][0])  # first of equal maxima, as argmax
        rivals = [s for s, rel in scored if np.abs(rel - scored[best][1]).max() > tol]
        out.append((scored[best][0] - max(rivals)) if rivals else np.nan)
    return np.array(out)


@settings(max_examples=examples(15), deadline=None)
@given(seed=st.integers(0, 2**31), n_mics=st.sampled_from([3, 4, 5]))
def test_pruned_search_equals_the_exhaustive_definition(seed, n_mics):
    """The table-and-sparse-product scoring with its bounded top-hypothesis search picks what visiting every
    hypothesis picks (score margins equal), including near-ties and missing peaks."""
    rng = np.random.default_rng(seed)
    tol = 2.5e-4
    n_pairs = n_mics * (n_mics - 1) // 2
    arrival = rng.uniform(0, 0.01, size=(6, n_mics))
    lags = np.stack([arrival[:, j] - arrival[:, i] for i, j in pairs(n_mics)], axis=1)
    cands = lags[..., None] + rng.choice([0.0, 0.0, 3e-3, -4e-3, 1e-4], size=(6, n_pairs, 3))  # true lags, near-duplicates, spurious
    cands[rng.random(cands.shape) < 0.05] = np.nan
    weights = rng.choice([0.3, 0.5, 0.5, 0.6], size=cands.shape)
    chosen = ConsistentSetSolver(tolerance_s=tol).select(cands, weights)
    np.testing.assert_allclose(chosen["score_margin"], brute_force_selection(cands, weights, tol), rtol=1e-9, atol=1e-12, equal_nan=True)


def assert_same_selection(cands, weights, prior=None, **settings):
    """Branch and bound and the exhaustive search choose the same consistent set, bit for bit, every output."""
    pruned = ConsistentSetSolver(search="pruned", **settings).select(cands, weights, prior)
    exhaustive = ConsistentSetSolver(search="exhaustive", **settings).select(cands, weights, prior)
    assert pruned.keys() == exhaustive.keys()
    for key in pruned:
        np.testing.assert_array_equal(pruned[key], exhaustive[key], err_msg=key)


@settings(max_examples=examples(60), deadline=None)
@given(
    seed=st.integers(0, 2**31),
    n_mics=st.sampled_from([3, 4, 5, 6]),
    k=st.sampled_from([1, 2, 3]),
    missing=st.sampled_from([0.0, 0.1, 0.5]),
    ties=st.booleans(),
    with_prior=st.booleans(),
)
def test_branch_and_bound_equals_the_exhaustive_search(seed, n_mics, k, missing, ties, with_prior):
    """The fast candidate search gives the exhaustive search's choice, margins and trusted mics exactly: near-duplicate
    and spurious peaks, equal weights (ties broken by index alike), missing peaks up to whole pairs, SRP priors."""
    cands, weights, prior = random_candidate_events(seed, n_mics, k, missing, ties, with_prior)
    assert_same_selection(cands, weights, prior, prior_weight=0.05 if with_prior else 0.0)


@pytest.mark.slow
def test_branch_and_bound_keeps_every_candidate_on_larger_arrays():
    """8 and 10 mics with 3 candidates per pair (17,496 and 196,830 hypotheses per event): the pruned search
    gives the exhaustive choice; with 12 mics (2.1 million, beyond the exhaustive search) the default still
    keeps 3 candidates and finds the true arrival pattern through planted reflections."""
    rng = np.random.default_rng(3)
    for n_mics in (8, 10, 12):
        mics = np.column_stack([rng.uniform(0, 80, size=(n_mics, 2)), np.full(n_mics, 1.5)])
        truth, cands, weights = scene(mics, rng.uniform(10, 70, size=(6, 2)), k=3, seed=n_mics)
        cands, weights = plant_reflection(cands, weights, pair_index=2)
        if n_mics < 12:
            assert_same_selection(cands, weights)
        chosen = ConsistentSetSolver().select(cands, weights)
        times = chosen["times_s"] - chosen["times_s"][:, :1]
        np.testing.assert_allclose(times, truth, atol=1e-9)


def test_srp_disagreement_is_reported_beside_the_fix():
    """With an SRP-PHAT estimate among the features the solver stage reports how far apart the two fixes are."""
    site = site_of(TRIANGLE)
    src = np.array([[25.0, 15.0], [20.0, 20.0]])
    tdoa = exact_tdoa(TRIANGLE, np.column_stack([src, np.full(2, TRIANGLE[0, 2])]))
    features = pd.DataFrame(
        {col.tdoa_lag(0, 1): tdoa[:, 1], col.tdoa_lag(0, 2): tdoa[:, 2], "srp__x_m": [25.0, 23.0], "srp__y_m": [15.0, 24.0]}
    )
    events = pd.DataFrame({"speed_of_sound_m_s": [C, C]})
    out = add_solver_columns(features, events, site, HyperbolicSolver(source_height_m=float(TRIANGLE[0, 2])), 1.0)
    np.testing.assert_allclose(out["solver__srp_disagreement_m"], [0.0, 5.0], atol=1e-6)
    without = add_solver_columns(features.drop(columns=["srp__x_m", "srp__y_m"]), events, site, HyperbolicSolver(), 1.0)
    assert without["solver__srp_disagreement_m"].isna().all()


def test_a_prior_position_breaks_a_tie_between_candidate_sets():
    """Two candidate sets fit equally well (a pair's two peaks tie); SRP-PHAT's peak near the true source picks the right one,
    and without the prior (or with prior_weight 0) the choice is the tie-break's."""
    _, cands, weights = scene(TRIANGLE, np.array([[25.0, 15.0]]))
    # on the triangle every pair has a twin set: shift all three lags consistently by a mirror solution's lags
    mirror = np.array([[10.0, 30.0]])
    _, mirror_cands, _ = scene(TRIANGLE, mirror)
    cands[:, :, 1] = mirror_cands[:, :, 0]
    weights[:, :, 1] = weights[:, :, 0]  # the two sets tie
    inputs = inputs_from(TRIANGLE, cands, weights)
    for prior, expected in (([25.0, 15.0], [25.0, 15.0]), ([10.0, 30.0], [10.0, 30.0])):
        with_prior = SolverInputs(**{**inputs.__dict__, "prior_position_m": np.array([prior])})
        fix = ConsistentSetSolver(prior_weight=0.05).solve(with_prior).position_m[0]
        np.testing.assert_allclose(fix, expected, atol=1e-3)
    ignored = ConsistentSetSolver(prior_weight=0.0).solve(SolverInputs(**{**inputs.__dict__, "prior_position_m": np.array([[10.0, 30.0]])}))
    np.testing.assert_allclose(ignored.position_m, ConsistentSetSolver().solve(inputs).position_m)
