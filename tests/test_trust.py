"""The point model is only trusted where it has seen data; positions never mix estimates; radii stay bounded."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from sklearn.neighbors import KNeighborsRegressor

from acoustlab.core import columns as col
from acoustlab.core.contracts import GateDecision
from acoustlab.core.errors import ConfigError
from acoustlab.method import trust
from acoustlab.method.pipeline import Components, LocalizationPipeline
from acoustlab.method.trust import TrainingSupport, TrustSettings, apply_trust, support_cues
from acoustlab.reporting.positions import positions_table
from plugins.conformal.split import SplitConformal
from plugins.gates.bounding_box import BoundingBoxGate
from plugins.gates.learned import LearnedGate
from tests.test_pipeline_calibration import ExactMedian, site3


def scene(n_positions: int = 100, per: int = 5, seed: int = 0, outside: int = 0) -> tuple[pd.DataFrame, pd.DataFrame]:
    """A 3-mic-like scene with redundant TDOAs: good fixes have small residuals, 20 % gross fixes large ones.

    With ``outside`` > 0 the last ``outside`` positions are sources 15–25 m outside the training
    region (east of the array) with exact, consistent solver fixes.
    """
    rng = np.random.default_rng(seed)
    n = n_positions * per
    position_id = np.repeat(np.arange(n_positions), per)
    source = np.column_stack([rng.uniform(2, 38, n_positions), rng.uniform(2, 33, n_positions)])
    if outside:
        source[-outside:] = np.column_stack([rng.uniform(55, 65, outside), rng.uniform(5, 30, outside)])
    source = source[position_id]
    solver = source + rng.normal(0, 0.1, (n, 2))
    residual = np.abs(rng.normal(0, 1e-5, n))
    gross = (rng.random(n) < 0.2) & (source[:, 0] < 50)
    solver[gross] += rng.uniform(6, 15, (gross.sum(), 2)) * rng.choice([-1, 1], (gross.sum(), 2))
    residual[gross] = rng.uniform(5e-4, 2e-3, gross.sum())
    features = pd.DataFrame(
        {
            "tdoa__hint_x_m": source[:, 0] + rng.normal(0, 2.0, n),
            "tdoa__hint_y_m": source[:, 1] + rng.normal(0, 2.0, n),
            col.SOLVER_X: solver[:, 0],
            col.SOLVER_Y: solver[:, 1],
            col.solver_column("residual_s"): residual,
            col.SOLVER_GDOP: np.ones(n),
        }
    )
    events = pd.DataFrame(
        {"event_id": np.arange(n), "position_id": position_id, "x_m": source[:, 0], "y_m": source[:, 1], "z_m": np.full(n, 1.0)}
    )
    return features, events


def components(gate, settings: TrustSettings | None = None) -> Components:
    return Components(
        site=site3(),
        feature_sets={},
        solver=None,
        point_model=KNeighborsRegressor(n_neighbors=10),
        gate=gate,
        error_model=ExactMedian(),
        scorers={"fixed": SplitConformal()},
        levels=[0.5, 0.8, 0.95],
        calibration_folds=5,
        trust=settings or TrustSettings(),
    )


def test_consistent_solver_fix_outside_the_training_region_is_kept():
    """A speaker 15–25 m outside the array: the box gate would hand over to the model; the solver's exact fix is kept."""
    features, events = scene(outside=10)
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups < 90), np.flatnonzero(groups >= 90)
    out = LocalizationPipeline(components(BoundingBoxGate())).fit_predict(features, events, train, test).predictions
    assert out["substituted"].sum() == 0
    np.testing.assert_allclose(out[list(col.estimate_xy("gate"))].to_numpy(), out[list(col.estimate_xy("solver"))].to_numpy())
    assert out[col.error_m("gate")].max() < 1.0
    assert (out[col.TRUST_REASON] != "").all()
    assert out[col.trust_flag("solver_outside_support")].all()
    # … where without the trust check the model's extrapolated guess replaced every one of them
    plain = (
        LocalizationPipeline(components(BoundingBoxGate(), TrustSettings(enabled=False)))
        .fit_predict(features, events, train, test)
        .predictions
    )
    assert plain["substituted"].all() and plain[col.error_m("gate")].min() > 10


@pytest.mark.slow
def test_inside_the_training_region_the_gate_decides_as_before():
    """On events like the training ones the trust check overrides almost nothing."""
    features, events = scene(seed=1)
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups % 5 != 0), np.flatnonzero(groups % 5 == 0)
    gate = LearnedGate(seed=0, n_threads=1, stakes_cap_m=None)
    trusted = LocalizationPipeline(components(gate)).fit_predict(features, events, train, test).predictions
    plain = LocalizationPipeline(components(gate, TrustSettings(enabled=False))).fit_predict(features, events, train, test).predictions
    assert (trusted[col.TRUST_REASON] != "").mean() <= 0.05
    assert trusted[col.error_m("gate")].quantile(0.95) <= plain[col.error_m("gate")].quantile(0.95) * 1.05


def _support(features: pd.DataFrame, events: pd.DataFrame, settings: TrustSettings | None = None) -> TrainingSupport:
    truth = events[["x_m", "y_m", "z_m"]].to_numpy(float)
    error = np.hypot(*(features[list(col.SOLVER_ESTIMATE_COLUMNS)].to_numpy() - truth[:, :2]).T)
    return TrainingSupport(settings or TrustSettings()).fit(features, truth, error, events["position_id"].to_numpy())


def test_a_model_asked_outside_its_training_support_is_not_used():
    features, events = scene()
    support = _support(features, events)
    novel = features.iloc[:3].copy()
    novel["tdoa__hint_x_m"] = 400.0  # nothing like any training row
    solver_xy = np.array([[10.0, 10.0], [np.nan, np.nan], [20.0, 20.0]])
    model_xy = np.array([[11.0, 11.0], [12.0, 12.0], [21.0, 21.0]])
    novel[list(col.SOLVER_ESTIMATE_COLUMNS)] = solver_xy
    substituted = np.ones(3, dtype=bool)
    out = apply_trust(GateDecision(model_xy.copy(), substituted), solver_xy, support_cues(solver_xy, model_xy, novel, novel, support))
    assert (out.flags["novelty"] > 1).all()
    np.testing.assert_array_equal(out.decision.position_m[[0, 2]], solver_xy[[0, 2]])  # the solver's fix kept
    assert np.isnan(out.decision.position_m[1]).all()  # no solver fix: the method abstains …
    assert out.reason[1] == trust.REASON_ABSTAIN and out.reason[0] == trust.REASON_NOVEL  # … and says why
    assert not out.decision.substituted.any()
    # a row like the training ones: the gate's choice stands
    same = apply_trust(
        GateDecision(model_xy[:1].copy(), substituted[:1]),
        solver_xy[:1],
        support_cues(solver_xy[:1], model_xy[:1], features.iloc[:1], features.iloc[:1], support),
    )
    assert same.decision.substituted.all() and same.reason[0] == trust.REASON_GATE


def test_height_outside_the_training_range_is_outside_the_support():
    """A 3-D fix 100 m up where the site simulated 1 m: outside, whatever its horizontal position."""
    features, events = scene()
    support = _support(features, events)
    xy = np.array([[20.0, 15.0], [20.0, 15.0]])
    assert support.outside_region(xy, np.array([100.0, 1.5])).tolist() == [True, False]
    assert support.outside_region(np.array([[20.0, 15.0], [80.0, 15.0], [np.nan, np.nan]])).tolist() == [False, True, False]


def test_without_redundant_measurements_no_fix_counts_as_consistent():
    """3 mics in 2-D fit any fix exactly (residual 0): consistency cannot be shown, so the residual rule is off."""
    features, events = scene()
    features[col.solver_column("residual_s")] = 0.0
    support = _support(features, events)
    assert support.residual_limit_s_ is None and not support.consistent(features).any()


def test_trust_settings_are_checked():
    with pytest.raises(ConfigError, match="support_margin_m"):
        TrustSettings(support_margin_m=-1)
    with pytest.raises(ConfigError, match="novelty_quantile"):
        TrustSettings(novelty_quantile=0)


def test_learned_gate_with_one_class_almost_absent_falls_back_to_the_solver():
    """Where the solver is (almost) never worse than the model the classifier has nothing to learn: keep the solver."""
    rng = np.random.default_rng(0)
    features, events = scene()
    truth = events[["x_m", "y_m"]].to_numpy()
    solver = truth + rng.normal(0, 0.01, truth.shape)
    model = truth + rng.normal(0, 3.0, truth.shape)
    features[list(col.SOLVER_ESTIMATE_COLUMNS)] = solver
    gate = LearnedGate(seed=0, n_threads=1).fit(solver, model, features, site3(), truth, groups=events["position_id"].to_numpy())
    assert gate.diagnostics()["fallback"]
    decision = gate.decide(solver, model, features, site3())
    np.testing.assert_array_equal(decision.position_m, solver)


def test_learned_gate_with_a_useless_classifier_falls_back():
    """Labels the cues cannot predict (out-of-fold AUC near 0.5 or below): the gate keeps the solver's fix."""
    rng = np.random.default_rng(2)
    features, events = scene()
    truth = events[["x_m", "y_m"]].to_numpy()
    solver = truth + rng.normal(0, 1.0, truth.shape)  # solver and model equally good, independent of every cue
    model = truth + rng.normal(0, 1.0, truth.shape)
    features[list(col.SOLVER_ESTIMATE_COLUMNS)] = solver
    gate = LearnedGate(seed=0, n_threads=1, min_auc=0.75).fit(
        solver, model, features, site3(), truth, groups=events["position_id"].to_numpy()
    )
    assert "AUC" in gate.diagnostics()["fallback"]
    assert not gate.decide(solver, model, features, site3()).substituted.any()


def test_singular_geometry_gives_a_bounded_gdop_scaled_radius():
    rng = np.random.default_rng(0)
    error, predicted, gdop = rng.lognormal(size=500), rng.uniform(0.5, 2, 500), rng.uniform(1, 5, 500)
    scorer = SplitConformal("gdop").fit(error, predicted, gdop, [0.5, 0.95])
    radius = scorer.radius(np.array([1.0, 1.0]), np.array([np.quantile(gdop, 0.95), 1e6]))
    assert np.isfinite(radius).all()
    np.testing.assert_allclose(radius[1], radius[0])  # capped at the calibration 95th percentile
    uncapped = SplitConformal("gdop", gdop_cap_quantile=None).fit(error, predicted, gdop, [0.5, 0.95])
    assert uncapped.radius(np.array([1.0]), np.array([1e6]))[0, 1] > 1e4 * radius[1, 1]


def test_no_positions_row_mixes_estimates():
    """x, y, z of a row come from one estimate: the model's x, y never carry the solver's height."""
    predictions = pd.DataFrame(
        {
            "event_id": [0, 1, 2],
            "substituted": [False, True, False],
            "solver_x_m": [1.0, 2.0, np.nan],
            "solver_y_m": [1.0, 2.0, np.nan],
            "model_x_m": [5.0, 6.0, 7.0],
            "model_y_m": [5.0, 6.0, 7.0],
            "gate_x_m": [1.0, 6.0, np.nan],
            "gate_y_m": [1.0, 6.0, np.nan],
            col.SOLVER_SOURCE_HEIGHT: [100.0, 90.0, np.nan],
            "predicted_error_m": [1.0, 1.0, 1.0],
            col.radius("fixed", 0.95): [2.0, 2.0, 2.0],
            col.TRUST_REASON: ["", "", trust.REASON_ABSTAIN],
        }
    )
    table = positions_table(predictions, [0.95], ["fixed"])
    assert table["z_m"].iloc[0] == 100.0 and np.isnan(table["z_m"].iloc[1])
    assert table["source"].tolist() == ["solver", "model", "none"]
    assert table["solver_z_m"].iloc[1] == 90.0
    np.testing.assert_allclose(table["solver_model_distance_m"].iloc[:2], [np.hypot(4, 4)] * 2)
    assert table["abstain_reason"].iloc[2] == trust.REASON_ABSTAIN and not table["placed"].iloc[2]


# ------------------------------------------------------------------------------- recordings sanity
def _shared_multichannel_folder(root, with_channel: bool, identical: bool = False):
    """3 mics listed against one 3-channel WAV (a mics table that names the same file for every mic)."""
    import soundfile as sf

    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    audio = (0.01 * rng.standard_normal((48000, 3))).astype(np.float32)
    if identical:
        audio[:, 2] = audio[:, 1]
    sf.write(root / "all.wav", audio, 24000, subtype="FLOAT")
    mics = pd.DataFrame({"mic_id": ["a", "b", "c"], "file": "all.wav", "x_m": [0.0, 40.0, 20.0], "y_m": [0.0, 0.0, 35.0], "z_m": 1.5})
    if with_channel:
        mics["channel"] = [0, 1, 2]
    mics.to_csv(root / "mics.csv", index=False)
    pd.DataFrame({"event_id": [0, 1], "start_s": [0.3, 1.0], "end_s": [0.6, 1.3]}).to_csv(root / "events.csv", index=False)
    return audio


def _folder(root, **kwargs):
    from plugins.fields.recordings import RecordingFolder

    return RecordingFolder(
        audio_dir=str(root), mics_csv=str(root / "mics.csv"), events_csv=str(root / "events.csv"), sample_rate_hz=24000, **kwargs
    )


def test_one_multichannel_file_for_every_mic_needs_a_channel_column(tmp_path):
    """Never the channel average for every mic (all events at one point, radius 0): refuse, or read each mic's channel."""
    from acoustlab.core.errors import DataError

    _shared_multichannel_folder(tmp_path / "a", with_channel=False)
    with pytest.raises(DataError, match="add a 'channel' column"):
        _folder(tmp_path / "a").validate()
    audio = _shared_multichannel_folder(tmp_path / "b", with_channel=True)
    batch = _folder(tmp_path / "b", pad_s=0.0).load(None)
    np.testing.assert_allclose(batch.audio[0, :, :100], audio[int(0.3 * 24000) : int(0.3 * 24000) + 100].T, atol=1e-7)
    assert batch.events["quality_ok"].all()


def test_identical_channels_are_flagged(tmp_path):
    _shared_multichannel_folder(tmp_path, with_channel=True, identical=True)
    events = _folder(tmp_path).load(None).events
    assert not events["quality_ok"].any()
    assert events["quality_flags"].str.contains("mic c: duplicate").all()


def test_a_header_rate_other_than_the_recorders_is_refused(tmp_path):
    from acoustlab.core.errors import DataError

    _shared_multichannel_folder(tmp_path, with_channel=True)  # written at 24 kHz
    with pytest.raises(DataError, match="declares 24000 Hz but field.recorder_sample_rate_hz is 48000 Hz"):
        _folder(tmp_path, recorder_sample_rate_hz=48000).validate()
    _folder(tmp_path, recorder_sample_rate_hz=24000).validate()


# ------------------------------------------------------------------------------- the second simulator
def test_image_source_field_renders_direct_path_delays(compose_cfg):
    """pyroomacoustics' renders carry the geometric TDOAs (the delays the method must recover), and sources lie in and around the array."""
    pytest.importorskip("pyroomacoustics")

    from acoustlab.run.registry import build
    from acoustlab.stages.sites import site_from_config

    cfg = compose_cfg(
        [
            "+site=frozen_lake",
            "field=image_source",
            "field.n_positions=4",
            "field.events_per_position=1",
            "field.snr_db=[60,60]",
            "field.outside_share=0.5",
        ]
    )
    site = site_from_config(cfg.site)
    source = build(cfg.field, "field")
    batch = source.load(site)
    assert batch.audio.shape == (4, 3, int(round(cfg.simulator.duration_s * cfg.simulator.sample_rate_hz)))
    assert batch.events["outside_simulated_region"].tolist() == [False, False, True, True]
    assert batch.events["speed_of_sound_m_s"].between(300, 360).all() and np.isfinite(batch.audio).all()
    # an impulse from each source arrives at every mic after distance / c (pyroomacoustics' c for the weather), within
    # 0.3 ms: the ground reflection, 0.1–0.2 ms behind the direct path at these ranges, merges with it (343 m/s would be ~3 ms off)
    fs = batch.sample_rate_hz
    click = np.zeros(64)
    click[0] = 1.0
    for source_m in source.source_positions(site):
        clean, c = source._render(site, site.mic_positions_m, source_m, click, 0.1, -10.0, 80.0)
        distance = np.sqrt(((site.mic_positions_m - source_m) ** 2).sum(axis=1))
        arrival_s = np.argmax(np.abs(clean), axis=1) / fs
        np.testing.assert_allclose(arrival_s - arrival_s[0], (distance - distance[0]) / c, atol=3e-4)


def _calibrated_on_field_spots(n_spots: int):
    """The scene's positions 1..n_spots are field playback spots that calibrate (position 0 is the test); settings and result."""
    features, events = scene(n_positions=60)
    groups = events["position_id"].to_numpy()
    events["is_field"] = groups <= n_spots
    train, test = np.flatnonzero(groups != 0), np.flatnonzero(groups == 0)
    settings = components(BoundingBoxGate())
    settings.calibrate_on = "field"
    return settings, (features, events, train, test)


def test_calibration_on_too_few_positions_for_a_level_warns(caplog):
    """4 field playback spots support 0.5 and 0.8 for a new position, not 0.95 (19 needed): said in the log, the diagnostics and
    every row (no radius at 0.95, radius_note says why)."""
    settings, (features, events, train, test) = _calibrated_on_field_spots(4)
    with caplog.at_level("INFO", logger="acoustlab.method.pipeline"):
        result = LocalizationPipeline(settings).fit_predict(features, events, train, test)
    calibration = result.split_diagnostics[0]["calibration"]
    assert calibration["on"] == "field" and calibration["n_positions"] == 4
    assert calibration["unsupported_levels"] == ["0.95"] and calibration["positions_needed_by_level"]["0.95"] == 19
    assert "cannot support level(s) 0.95" in caplog.text
    # 0.5 and 0.8 have radii; 0.95 (19 spots needed) is empty, with the reason on every row
    p = result.predictions
    assert p[col.radius("fixed", 0.95)].isna().all() and np.isfinite(p[col.radius("fixed", 0.8)]).all()
    assert (p[col.RADIUS_NOTE] == "no radius at 0.95: its guarantee needs 19 calibration positions, 4 given").all()
    assert "exchangeable" in calibration["guarantee"] and "Dunn" in calibration["guarantee"]
    # one set of n = 4 spots covers Beta(k, n + 1 - k), k = ceil((n + 1) level): at 0.8, Beta(4, 1), 5 % quantile 0.05 ** (1 / 4)
    assert calibration["coverage_of_one_set"]["0.8"] == [round(0.05**0.25, 3), round(0.95**0.25, 3)]
    assert set(calibration["coverage_of_one_set"]) == {"0.5", "0.8"}
    # what the user's one set of 4 spots gives, in metrics, on every row and in the log: Beta(4, 1)'s 10 % quantile at 0.8
    one_set = calibration["one_set"]["covers_at_least"]
    assert one_set["0.8"] == pytest.approx(0.1**0.25) and one_set["0.95"] is None
    np.testing.assert_allclose(p[col.one_set_coverage(0.8)], 0.1**0.25)
    assert "with probability 0.9 over your 4 calibration spots, the radii cover at least" in caplog.text
    assert calibration["not_guaranteed_levels"] == []
    # asked for anyway: the simulation's 0.95 radius scaled by field/simulation at 0.8, at least the 0.8 radius, labelled
    settings.unsupported_levels = "rescaled"
    rescaled = LocalizationPipeline(settings).fit_predict(features, events, train, test)
    again = rescaled.split_diagnostics[0]["calibration"]
    assert again["not_guaranteed_levels"] == ["0.95"] and "not guaranteed" in again["not_guaranteed_method"]
    q = rescaled.predictions
    np.testing.assert_array_equal(q[col.radius("fixed", 0.8)], p[col.radius("fixed", 0.8)])  # guaranteed levels untouched
    assert (q[col.radius("fixed", 0.95)] >= q[col.radius("fixed", 0.8)]).all() and np.isfinite(q[col.radius("fixed", 0.95)]).all()
    assert (
        q[col.RADIUS_NOTE]
        == "radius at 0.95 not guaranteed (rescaled from the simulation's): a guarantee needs 19 calibration positions, 4 given"
    ).all()


def test_a_rescaled_radius_with_nothing_to_scale_by_is_unbounded_not_nan():
    """Rescaling the simulation's 0.95 radius by field/simulation at 0.8: where either 0.8 radius is infinite (an empty
    Mondrian bin) or the field's is 0, the 0.95 radius is infinite or finite, never NaN."""
    from types import SimpleNamespace

    from acoustlab.method.fitted import FittedMethod

    class Fixed:  # the simulation's radii, row by row
        def radius(self, predicted, gdop):
            return np.array([[0.2, 1.0, 2.0], [0.2, np.inf, np.inf], [0.2, 1.0, np.inf], [0.2, 1.0, 2.0]])

    fitted = SimpleNamespace(
        pipeline=SimpleNamespace(c=SimpleNamespace(levels=[0.5, 0.8, 0.95])),
        calibration={"unsupported_levels": ["0.95"], "not_guaranteed_levels": ["0.95"]},
        simulation_scorers={"fixed": Fixed()},
    )
    field = np.array([[0.1, 0.5, 9.0], [0.1, 0.5, 9.0], [0.1, np.inf, 9.0], [0.0, 0.0, 9.0]])
    out = FittedMethod._rescale_unsupported(fitted, "fixed", field, np.zeros(4), np.ones(4), {})
    np.testing.assert_array_equal(out[:, 2], [1.0, np.inf, np.inf, 0.0])  # 2 × 0.5/1; no tail; unbounded at 0.8; 2 × 0
    np.testing.assert_array_equal(out[:, :2], field[:, :2])


# ------------------------------------------------------------------------------- measured-input uncertainty
def _solve_xy(mics: np.ndarray, ranges_m: np.ndarray, start: np.ndarray, height: float) -> np.ndarray:
    from scipy.optimize import least_squares

    def residual(p):
        source = np.array([p[0], p[1], height])
        return ranges_m - np.sqrt(((mics - source) ** 2).sum(axis=1)) - p[2]

    return least_squares(residual, [*start, 0.0], xtol=1e-12, ftol=1e-12).x[:2]


@pytest.mark.parametrize(
    "stated",
    [
        dict(temperature_c=1.0, mic_position_m=0.0, clock_offset_s=0.0),
        dict(temperature_c=0.0, mic_position_m=0.0, clock_offset_s=1e-4),
        dict(temperature_c=0.0, mic_position_m=0.2, clock_offset_s=0.0),
    ],
)
def test_input_uncertainty_matches_a_monte_carlo_of_the_solve(stated):
    """The first-order position error from stated input errors equals the spread of exact solves with those errors (±15 %)."""
    from acoustlab.toolkit.input_uncertainty import InputUncertainty, position_sigma_m
    from acoustlab.toolkit.physics import speed_of_sound_m_s

    rng = np.random.default_rng(0)
    mics = np.array([[0.0, 0, 1.2], [50, 0, 1.2], [24, 44, 1.2], [45, 40, 1.5]])
    source = np.array([35.0, 20.0, 1.2])
    temperature, humidity = -10.0, 80.0
    c = float(speed_of_sound_m_s(temperature, humidity))
    sigma_c = (
        float(speed_of_sound_m_s(temperature + 0.5, humidity) - speed_of_sound_m_s(temperature - 0.5, humidity)) * stated["temperature_c"]
    )
    travel_s = np.sqrt(((mics - source) ** 2).sum(axis=1)) / c
    errors = []
    for _ in range(400):
        c_used = c + rng.normal(0, sigma_c) if sigma_c else c
        arrival = travel_s + rng.normal(0, stated["clock_offset_s"], 4) if stated["clock_offset_s"] else travel_s
        surveyed = (
            mics + np.column_stack([rng.normal(0, stated["mic_position_m"], (4, 2)), np.zeros(4)]) if stated["mic_position_m"] else mics
        )
        errors.append(_solve_xy(surveyed, c_used * arrival, source[:2], source[2]) - source[:2])
    monte_carlo = np.sqrt(np.mean(np.square(errors)))
    predicted = position_sigma_m(mics, source[None], np.array([temperature]), np.array([humidity]), InputUncertainty(**stated))[0]
    assert predicted == pytest.approx(monte_carlo, rel=0.15)


def test_a_calibrations_correlated_errors_move_the_fix_as_exact_solves_with_them_do():
    """A calibration's errors drawn from its covariance (a clock that trades off with its mic's position, a thermometer):
    the first-order σ equals the spread of exact solves (±15 %), the package's Monte Carlo too (±25 %: its 64 fixed
    draws), and the trade-off, carried as independent errors of the same size, would count far more than the fix moves."""
    from acoustlab.toolkit.input_uncertainty import CorrelatedInputErrors, monte_carlo_sigma_m, position_sigma_m
    from acoustlab.toolkit.physics import speed_of_sound_m_s

    rng = np.random.default_rng(3)
    mics = np.array([[0.0, 0, 1.2], [50, 0, 1.2], [24, 44, 1.2], [45, 40, 1.5]])
    source = np.array([30.0, 18.0, 1.2])
    temperature, humidity = 12.0, 60.0
    c = float(speed_of_sound_m_s(temperature, humidity))
    # mic 1 is 0.3 m off along its direction to the source, its clock estimated 0.3 m / c late to match (the trade-off
    # few spots leave in that direction), plus small independent errors and a thermometer 0.5 °C off
    toward = (source - mics[1])[:2] / np.linalg.norm((source - mics[1])[:2])
    loading = np.zeros((13, 1))
    loading[1 + 1, 0], loading[1 + 4 + 2 : 1 + 4 + 4, 0] = 0.3 / c, 0.3 * toward  # clock 1, mic 1's x and y
    covariance = loading @ loading.T + np.diag(np.r_[0.5**2, 0.0, np.full(3, 2e-5**2), np.full(8, 0.02**2)])
    errors = []
    travel_s = np.sqrt(((mics - source) ** 2).sum(axis=1)) / c
    for e in rng.multivariate_normal(np.zeros(13), covariance, 400):
        c_used = float(speed_of_sound_m_s(temperature + e[0], humidity))
        arrival = travel_s - e[1:5]  # a clock estimated late by δ leaves its corrected arrival δ early
        surveyed = mics + np.column_stack([e[5:].reshape(4, 2), np.zeros(4)])
        errors.append(_solve_xy(surveyed, c_used * arrival, source[:2], source[2]) - source[:2])
    exact = np.sqrt(np.mean(np.square(errors)))
    weather = (np.array([temperature]), np.array([humidity]))
    stated = CorrelatedInputErrors(covariance)
    assert position_sigma_m(mics, source[None], *weather, stated)[0] == pytest.approx(exact, rel=0.15)
    assert monte_carlo_sigma_m(mics, source[None], *weather, stated)[0] == pytest.approx(exact, rel=0.25)
    independent = CorrelatedInputErrors(np.diag(np.diag(covariance)))
    assert position_sigma_m(mics, source[None], *weather, independent)[0] > 1.5 * exact
    with pytest.raises(ValueError, match=r"a covariance of shape \(13, 13\) for an array of 3 mics"):
        position_sigma_m(mics[:3], source[None], *weather, stated)


def test_radii_of_field_detections_carry_the_stated_input_errors():
    """Field rows (calibrated on simulation) get radii grown in quadrature; simulated rows keep theirs."""
    from acoustlab.toolkit.input_uncertainty import InputUncertainty

    features, events = scene(n_positions=60)
    groups = events["position_id"].to_numpy()
    events["is_field"] = groups < 6
    events["temperature_c"], events["relative_humidity_pct"] = 10.0, 60.0
    train, test = np.flatnonzero(groups >= 6), np.flatnonzero(groups < 12)
    radius = col.radius("fixed", 0.95)
    runs = {}
    for sigma in (0.0, 5.0):
        settings = components(BoundingBoxGate())
        settings.input_uncertainty = InputUncertainty(temperature_c=sigma)
        runs[sigma] = LocalizationPipeline(settings).fit_predict(features, events, train[groups[train] >= 12], test).predictions
    field = runs[5.0]["position_id"].to_numpy() < 6
    assert (runs[5.0][col.INPUT_SIGMA][field] > 0).all() and (runs[5.0][col.INPUT_SIGMA][~field] == 0).all()
    assert (runs[5.0][radius][field] > runs[0.0][radius][field]).all()
    np.testing.assert_allclose(runs[5.0][radius][~field], runs[0.0][radius][~field])


def test_the_input_allowance_is_exact_where_first_order_is_poor_and_capped():
    """Inside the array first order and Monte Carlo agree; on a baseline extension first order is 100× too large and the cap holds."""
    from acoustlab.toolkit.input_uncertainty import InputUncertainty, allowance_sigma_m, monte_carlo_sigma_m, position_sigma_m

    mics = np.array([[0.0, 0, 1], [50, 0, 1], [25, 43, 1]])
    source = np.array([[25.0, 15, 1.5], [80, 0, 1.5], [60, 20, 1.5]])
    stated = InputUncertainty(temperature_c=1.0, mic_position_m=0.5, clock_offset_s=1e-4, max_sigma_m=10.0)
    weather = (np.full(3, 10.0), np.full(3, 60.0))
    first, exact = position_sigma_m(mics, source, *weather, stated), monte_carlo_sigma_m(mics, source, *weather, stated)
    assert exact[0] == pytest.approx(first[0], rel=0.15)  # well inside: the linearisation holds
    assert first[1] > 100 * exact[1]  # beyond mic 1 on the 0–1 baseline: first order explodes
    allowance = allowance_sigma_m(mics, source, *weather, stated)
    assert allowance[0] == first[0] and allowance[1] == stated.max_sigma_m and allowance[2] == pytest.approx(exact[2])
    with pytest.raises(ConfigError, match="max_sigma_m"):
        InputUncertainty(max_sigma_m=-1.0)


def test_radii_are_tested_on_the_calibration_spots_each_held_out():
    """Calibrated on 30 field spots: each spot's radii come from the other 29, and on this exchangeable scene they cover about
    the nominal share of its events; a level the 29 spots cannot guarantee (0.95 needs 19: it can) is reported."""
    from acoustlab.reporting.metrics import held_out_calibration_summary

    settings, (features, events, train, test) = _calibrated_on_field_spots(30)
    result = LocalizationPipeline(settings).fit_predict(features, events, train, test)
    table = result.split_diagnostics[0]["held_out_calibration"]
    assert sorted(table["position_id"].unique()) == list(range(1, 31))
    summary = held_out_calibration_summary(table, settings.levels, list(settings.scorers))
    assert summary["n_spots"] == 30
    for level, cell in summary["coverage"]["fixed"].items():
        assert abs(cell["positions"] - float(level)) < 0.2, (level, cell)
    assert {"gdop", "hull_distance"} <= set(summary["by_condition"])


def test_pac_radii_on_field_spots_state_their_own_guarantee_and_spot_count():
    """``position_method: pac`` on 12 field spots: 0.8 radii (9 spots needed) with a one-set statement of at least 0.75 on
    every row and a guarantee sentence naming the PAC scorer; 0.95 (22 needed) left empty with the count in the note."""
    settings, (features, events, train, test) = _calibrated_on_field_spots(12)
    for scorer in settings.scorers.values():
        scorer.position_method = "pac"
    result = LocalizationPipeline(settings).fit_predict(features, events, train, test)
    calibration, p = result.split_diagnostics[0]["calibration"], result.predictions
    assert calibration["positions_needed_by_level"] == {"0.5": 3, "0.8": 9, "0.95": 22}
    assert calibration["unsupported_levels"] == ["0.95"] and p[col.radius("fixed", 0.95)].isna().all()
    assert (p[col.one_set_coverage(0.8)] >= 0.75).all() and np.isfinite(p[col.radius("fixed", 0.8)]).all()
    assert "PAC scorer's radius (fixed) instead covers at least l − 0.05 with probability 0.9" in calibration["guarantee"]
    assert (p[col.RADIUS_NOTE] == "no radius at 0.95: its guarantee needs 22 calibration positions, 12 given").all()


def test_radii_calibrated_on_field_spots_carry_the_drift_that_grows_after_them():
    """Radii calibrated on playbacks hold the clocks' errors as they were then; a calibration's drift adds, at a call a
    week later, what its allowance has grown beyond the larger of its two values at the playbacks' first and last time,
    and nothing at a call between them; radii calibrated on simulation carry the whole allowance."""
    from acoustlab.toolkit.input_uncertainty import CorrelatedInputErrors, allowance_m

    site = site3()
    m = site.n_mics
    variances = np.r_[0.01, 0.0, np.full(m - 1, 1e-10), np.full(2 * m, 1e-4), 0.0, np.full(m - 1, 1e-18)]  # drifts 1e-9 s/s
    stated = CorrelatedInputErrors(np.diag(variances), drifts=True, drift_origin_s=0.0)
    settings = components(BoundingBoxGate())
    settings.input_uncertainty = stated
    pipeline = LocalizationPipeline(settings)
    week = 7 * 86_400.0
    events = pd.DataFrame({"is_field": True, col.TEMPERATURE: 12.0, col.HUMIDITY: 70.0, "time_s": [1800.0, week], "position_id": [1, 2]})
    features = pd.DataFrame(index=events.index)
    position = np.array([[20.0, 15.0], [20.0, 15.0]])
    on_field = pipeline._input_allowance(position, features, events, calibrated_on_field=True, calibration_times_s=(0.0, 3600.0))
    assert (on_field.radius_m[0] == 0).all() and (on_field.radius_m[1] > 0).all()
    from acoustlab.toolkit.event_physics import source_height_m

    source = np.column_stack([position, source_height_m(features, site)])
    full = allowance_m(
        site.mic_positions_m, source, np.full(2, 12.0), np.full(2, 70.0), stated, settings.levels, time_s=np.array([1800.0, week])
    )
    at_end = allowance_m(
        site.mic_positions_m, source, np.full(2, 12.0), np.full(2, 70.0), stated, settings.levels, time_s=np.full(2, 3600.0)
    )
    np.testing.assert_allclose(on_field.radius_m[1], np.sqrt(full.radius_m[1] ** 2 - at_end.radius_m[1] ** 2), rtol=1e-9)
    on_simulation = pipeline._input_allowance(position, features, events, calibrated_on_field=False)
    np.testing.assert_allclose(on_simulation.radius_m, full.radius_m)
    no_drift = pipeline._input_allowance(position, features, events, calibrated_on_field=True, calibration_times_s=None)
    assert (no_drift.radius_m == 0).all()


def test_a_fix_on_a_subset_of_the_mics_that_fits_worse_than_timing_noise_allows_is_flagged():
    """Flagged exactly where the solver left usable mics out and its residual is above the good fixes' limit: a fix on every
    usable mic, a subset fitting well, a fix whose missing mics were dropped for bad clips, and no fix are not."""
    from types import SimpleNamespace

    from acoustlab.core import columns as col
    from acoustlab.method.localizer import with_support_flags

    features = pd.DataFrame(
        {
            col.SOLVER_X: [1.0, 1.0, 1.0, 1.0, np.nan],
            col.SOLVER_Y: [2.0, 2.0, 2.0, 2.0, np.nan],
            col.solver_column("residual_s"): [3e-3, 3e-3, 5e-5, 3e-3, np.nan],
            col.SOLVER_N_MICS_USED: [5, 9, 5, 6, np.nan],
        }
    )
    predictions = pd.DataFrame(
        {col.MICS_DROPPED: ["", "", "", "1;4;7", ""], col.QUALITY_FLAGS: ["", "", "", "mic 1: dead", ""], col.RADIUS_NOTE: ""}
    )
    out = with_support_flags(predictions, features, SimpleNamespace(residual_limit_s_=1e-4), 9)
    assert out[col.WEAK_SUPPORT].tolist() == [True, False, False, False, False]
    assert (
        out[col.QUALITY_FLAGS]
        .iloc[0]
        .startswith("weak support: the fix rests on 5 of 9 mics with a residual of 3.00 ms, above the 0.10 ms")
    )
    assert "its radius may be too small" in out[col.RADIUS_NOTE].iloc[0] and out[col.RADIUS_NOTE].iloc[1:].eq("").all()
    assert out[col.QUALITY_FLAGS].iloc[3] == "mic 1: dead"
    unknown = with_support_flags(predictions, features, SimpleNamespace(residual_limit_s_=None), 9)  # no redundancy in training
    assert not unknown[col.WEAK_SUPPORT].any() and unknown[col.QUALITY_FLAGS].equals(predictions[col.QUALITY_FLAGS])


def test_each_mic_s_residual_at_the_fix_is_near_zero_where_the_fix_explains_it_and_its_peak_s_error_where_not():
    from acoustlab.core import columns as col
    from acoustlab.method.localizer import mic_residual_column, with_mic_residuals

    mics = np.array([[0.0, 0.0, 1.5], [40.0, 0.0, 1.5], [40.0, 40.0, 1.5], [0.0, 40.0, 1.5]])
    source, speed = np.array([10.0, 20.0, 1.5]), 343.0
    arrival = np.linalg.norm(source - mics, axis=1) / speed
    tdoa = arrival - arrival[0]
    tdoa[3] += 2e-3  # mic 3's peak 2 ms late: the solver left it out
    features = pd.DataFrame(
        {
            col.SOLVER_X: [source[0], np.nan],
            col.SOLVER_Y: [source[1], np.nan],
            col.SOLVER_SOURCE_HEIGHT: [1.5, np.nan],
            col.ENV_SPEED_OF_SOUND: speed,
            **{col.tdoa_lag(0, m): tdoa[m] for m in range(1, 4)},
        }
    )
    out = with_mic_residuals(pd.DataFrame({col.MICS_USED: ["0;1;2", ""]}), features, mics)
    residual = out[[mic_residual_column(m) for m in range(4)]].to_numpy(float)
    np.testing.assert_allclose(residual[0], [0.0, 0.0, 0.0, 2e-3 * speed], atol=1e-9)
    assert np.isnan(residual[1]).all()  # no fix: no residual


def test_the_localization_summary_counts_the_placed_fixes_with_weak_support():
    from acoustlab.core import columns as col
    from acoustlab.reporting.positions import localization_summary

    table = pd.DataFrame(
        {col.PLACED: [True, True, False, True], col.WEAK_SUPPORT: [True, False, True, True], "source": "solver", "radius_fixed_0.8_m": 1.0}
    )
    assert localization_summary(table, [0.8], ["fixed"])["n_weak_support"] == 2  # the unplaced one is not counted
    assert localization_summary(table.drop(columns=col.WEAK_SUPPORT), [0.8], ["fixed"])["n_weak_support"] == 0
