"""Playback plans: spots chosen for the stated array calibrate it better than spots drawn at random."""

from __future__ import annotations

import numpy as np
import pytest

from acoustlab.api import plan_playbacks as plan_for_site
from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.array_calibration import Priors, calibrate_array
from acoustlab.toolkit.playback_plan import plan_playbacks
from tests.test_field_calibration import array, playbacks, spots_in


def with_spot_bias(pb, sd_s: float, seed: int):
    """Each spot's time differences biased alike in all its playbacks (its multipath), ``sd_s`` per pair."""
    bias = np.random.default_rng(seed).normal(0.0, sd_s, (pb.n_spots, len(pb.pairs)))
    pb.tdoa_s[:] = pb.tdoa_s + bias[pb.spot]
    return pb


def mic_errors(n_spots: int, n_arrays: int = 20) -> dict[str, np.ndarray]:
    """Median horizontal mic error (m) of calibrations from random and from planned spots, per array."""
    out: dict[str, list[float]] = {"random": [], "planned": []}
    for seed in range(n_arrays):
        stated, true = array(6, seed)
        rng = np.random.default_rng(seed + 1)
        clocks = np.r_[0.0, rng.uniform(-1e-3, 1e-3, 5)]
        priors = Priors(stated, np.full(6, 2.0))
        planned = plan_playbacks(priors, n_spots, source_height_m=1.5).spots_m  # planned on the stated array, as a user must
        for design, spots in (("random", spots_in(rng, n_spots)), ("planned", planned)):
            pb = with_spot_bias(playbacks(true, spots, clocks, 3.0, noise_s=5e-5, seed=seed), 1e-4, seed)
            cal = calibrate_array(pb, priors, [str(m) for m in range(6)])
            out[design].append(float(np.median(np.hypot(*(cal.mic_positions_m - true)[:, :2].T))))
    return {k: np.asarray(v) for k, v in out.items()}


@pytest.mark.slow
def test_planned_spots_calibrate_better_than_random_ones_under_per_spot_multipath():
    # 5 spots, 20 arrays of 6 mics 2 m off, clocks ±1 ms, a 3 °C thermometer error, 0.1 ms of bias per spot and pair
    errors = mic_errors(5)
    assert np.median(errors["planned"]) < 0.6 * np.median(errors["random"])  # measured 0.025 vs 0.065 m
    assert np.quantile(errors["planned"], 0.9) < 0.5 * np.quantile(errors["random"], 0.9)  # measured 0.038 vs 0.20 m


@pytest.mark.slow
def test_a_plan_keeps_away_from_where_a_stated_mic_may_really_be():
    # 3-mic arrays, 5 spots: spots 3 m from the stated mics let the fit of one array of 30 run 2 m off
    # (measured 2.17 m); at the default distance (5 GPS errors) the worst is 0.25 m
    worst = {}
    for label, distance in (("beside", 3.0), ("default", None)):
        errors = []
        for seed in range(30):
            stated, true = array(3, seed)
            rng = np.random.default_rng(seed + 1)
            clocks = np.r_[0.0, rng.uniform(-1e-3, 1e-3, 2)]
            priors = Priors(stated, np.full(3, 2.0))
            spots = plan_playbacks(priors, 5, source_height_m=1.5, min_mic_distance_m=distance).spots_m
            pb = with_spot_bias(playbacks(true, spots, clocks, 3.0, noise_s=5e-5, seed=seed), 1e-4, seed)
            cal = calibrate_array(pb, priors, ["0", "1", "2"])
            errors.append(float(np.median(np.hypot(*(cal.mic_positions_m - true)[:, :2].T))))
        worst[label] = max(errors)
    assert worst["beside"] > 1.0
    assert worst["default"] < 0.5


def test_a_plan_keeps_its_distances_and_shrinks_the_mics_uncertainty():
    stated, _ = array(5, 3)
    plan = plan_playbacks(Priors(stated, np.full(5, 2.0)), 8, min_mic_distance_m=4.0, min_separation_m=10.0)
    xy = plan.spots_m[:, :2]
    to_mic = np.sqrt(((xy[:, None] - stated[None, :, :2]) ** 2).sum(-1))
    assert to_mic.min() >= 4.0
    apart = np.sqrt(((xy[:, None] - xy[None]) ** 2).sum(-1))[np.triu_indices(8, 1)]
    assert apart.min() >= 10.0
    assert plan.prior_sd_m == pytest.approx(2.0)
    assert np.all(np.diff(plan.predicted_sd_m) <= 0) and plan.predicted_sd_m[-1] < 0.1 * plan.prior_sd_m
    again = plan_playbacks(Priors(stated, np.full(5, 2.0)), 8, min_mic_distance_m=4.0, min_separation_m=10.0)
    np.testing.assert_array_equal(again.spots_m, plan.spots_m)


def test_a_plan_chooses_among_the_users_candidates():
    stated, _ = array(4, 1)
    candidates = np.array([[5.0, 5.0], [70.0, 10.0], [40.0, 75.0], [10.0, 60.0], [60.0, 60.0], [40.0, 40.0]])
    plan = plan_playbacks(Priors(stated, np.full(4, 2.0)), 4, candidates_xy_m=candidates, min_separation_m=1.0)
    assert {tuple(p) for p in plan.spots_m[:, :2]} <= {tuple(c) for c in candidates}
    assert len({tuple(p) for p in plan.spots_m[:, :2]}) == 4


def test_a_plan_refuses_what_it_cannot_do():
    stated, _ = array(4, 1)
    priors = Priors(stated, np.full(4, 2.0))
    with pytest.raises(ConfigError, match="n_spots must be >= 3"):
        plan_playbacks(priors, 2)
    with pytest.raises(ConfigError, match="2 of 2 candidate spots lie 10.0 m or more from every mic, 3 spots asked for"):
        plan_playbacks(priors, 3, candidates_xy_m=np.array([[-100.0, -100.0], [200.0, 200.0]]))
    beside_a_mic = stated[:3, :2] + 4.0  # within 5 GPS errors of the stated mics: where the real mic is, is unknown
    with pytest.raises(ConfigError, match="0 of 3 candidate spots lie 10.0 m or more"):
        plan_playbacks(priors, 3, candidates_xy_m=beside_a_mic)
    with pytest.raises(ConfigError, match="lie 500.0 m apart"):
        plan_playbacks(priors, 3, min_separation_m=500.0)


def test_a_plan_of_too_few_spots_says_how_many_would_do(caplog):
    stated, _ = array(3, 1)
    plan_playbacks(Priors(stated, np.full(3, 2.0)), 5)  # 10 time differences for 9 unknowns
    assert "plan 9 or more" in caplog.text
    caplog.clear()
    plan_playbacks(Priors(stated, np.full(3, 2.0)), 9)
    plan_playbacks(Priors(stated, np.array([0.0, 0.0, 2.0])), 5)  # two surveyed mics: 5 unknowns, 3 spots do
    assert "too few" not in caplog.text


def test_the_api_plans_for_a_site_as_calibrate_reads_it():
    spots = plan_for_site("frozen_lake", 5, source_height_m=1.5)
    assert list(spots.columns) == [col.POSITION_ID, col.TRUE_X, col.TRUE_Y, col.TRUE_Z, "predicted_mic_sd_m"]
    assert spots[col.POSITION_ID].is_unique and (spots[col.TRUE_Z] == 1.5).all()
    surveyed = plan_for_site("frozen_lake", 5, position_sigma_m=[0.0, 2.0, 2.0])
    assert surveyed["predicted_mic_sd_m"].iloc[-1] > 0
    with pytest.raises(ConfigError, match="position_sigma_m must be one number >= 0 or 3 of them"):
        plan_for_site("frozen_lake", 5, position_sigma_m=[1.0, 2.0])


def test_the_second_simulator_renders_at_the_planned_spots():
    from acoustlab.api import load_site
    from plugins.fields.image_source import ImageSourceField

    site = load_site("forest")
    given = [[10.0, 20.0, 1.5], [30.0, 40.0, 2.0], [50.0, 5.0, 1.0]]
    np.testing.assert_array_equal(ImageSourceField(positions_m=given).source_positions(site), np.asarray(given))
    flat = ImageSourceField(positions_m=[p[:2] for p in given]).source_positions(site)
    np.testing.assert_array_equal(flat[:, :2], np.asarray(given)[:, :2])
    low, high = site.source_height_range_m
    assert ((flat[:, 2] >= low) & (flat[:, 2] <= high)).all()
    with pytest.raises(ConfigError, match="field.positions_m must be a list of 2 or more"):
        ImageSourceField(positions_m=[[1.0, 2.0, 3.0, 4.0]])
