"""``features.gcc.search=coarse``: peaks searched on the 1/fs grid and refined on the 1/(2 fs) grid give the default's peaks."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.core.errors import ConfigError
from acoustlab.core.types import RecordingBatch
from acoustlab.run.registry import build, build_feature_sets
from acoustlab.stages.dataset import extract_features
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import tdoa_matrix
from acoustlab.toolkit.dsp import gcc, local_maxima
from acoustlab.toolkit.gcc_candidates import lag_windows_s, pair_candidates
from acoustlab.toolkit.gcc_coarse import half_sample_kernel, half_samples
from acoustlab.toolkit.window_peaks import window_peaks
from plugins.features.gcc_groups import TdoaCandidates
from tests.conftest import examples

UPSTREAM_LOCA_TDOA_S = [0.0, 0.0325, -0.002, 0.0316, -0.0086, 0.024]  # as tests/test_recordings.py


@pytest.fixture(scope="module")
def batches(simulate_site):
    """Default simulation (noise, trunks, ground) on both sites: several GCC peaks per pair."""
    return {site_name: simulate_site(site_name, n, 5) for site_name, n in (("frozen_lake", 16), ("forest", 8))}


def _fresh(batch):
    return RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events)


@pytest.mark.slow
def test_half_sample_interpolation_matches_the_exact_finer_grid(batches):
    """The band-limited interpolation of the 1/fs grid gives the 1/(2 fs) grid's odd samples to 1e-4 of the peak."""
    site, batch = batches["forest"]
    window = float(lag_windows_s(site, 0.002).max())
    fine, _ = gcc(batch.audio, site.mic_pairs, batch.sample_rate_hz, "beta_phat", (300.0, 10000.0), 2, 0.8, max_lag_s=window)
    coarse, _ = gcc(batch.audio, site.mic_pairs, batch.sample_rate_hz, "beta_phat", (300.0, 10000.0), 1, 0.8, max_lag_s=window)
    coarse *= 0.5
    np.testing.assert_allclose(coarse, fine[..., ::2], atol=1e-6 * np.abs(fine).max())  # the coarse grid is every other fine sample
    kernel = half_sample_kernel()
    index = np.arange(kernel.size, coarse.shape[-1] - kernel.size)
    for p in range(len(site.mic_pairs)):
        halves = half_samples(coarse[:, p], np.broadcast_to(index, (batch.n_events, index.size)), kernel)
        assert np.abs(halves - fine[:, p, 2 * index + 1]).max() < 1e-4 * np.abs(fine[:, p]).max()


@pytest.mark.slow
@pytest.mark.parametrize("site_name", ["frozen_lake", "forest"])
def test_coarse_search_gives_the_default_peaks(batches, site_name):
    site, batch = batches[site_name]
    args = (site, 3, 0.002, (300.0, 10000.0), "beta_phat", 2, 0.8)
    fine = pair_candidates(_fresh(batch), *args)
    coarse = pair_candidates(_fresh(batch), *args, search="coarse")
    step = 1.0 / (2 * batch.sample_rate_hz)
    same = np.abs(coarse.lags_s - fine.lags_s) < 0.01 * step
    assert same[..., 0].mean() >= 0.97 and same.all(-1).mean() >= 0.9  # the benchmark: 99.88 % and 99.54 % on 1,100 forest events
    both = same & np.isfinite(fine.heights)
    np.testing.assert_allclose(coarse.heights[both], fine.heights[both], rtol=1e-3, atol=1e-4 * np.nanmax(fine.heights))
    np.testing.assert_allclose(coarse.sidelobe, fine.sidelobe, rtol=0.05)
    assert np.isfinite(coarse.lags_s[..., 0]).all()


def test_coarse_search_is_cached_apart_from_the_default(batches):
    site, batch = batches["frozen_lake"]
    shared = _fresh(batch)
    args = (site, 3, 0.002, (300.0, 10000.0), "beta_phat", 2, 0.8)
    assert pair_candidates(shared, *args, search="coarse") is pair_candidates(shared, *args, search="coarse")
    assert pair_candidates(shared, *args) is not pair_candidates(shared, *args, search="coarse")


def test_the_shipped_real_array_gives_the_reference_tdoas_with_the_coarse_search(compose_cfg):
    """The LOCA 2021 recording's 6–10.5 kHz band, where a plain 1/fs grid picked another peak, keeps the upstream TDOAs."""
    cfg = compose_cfg(["+site=loca2021", "field=recordings", "features.gcc.band_hz=[6000,10500]", "+features.gcc.search=coarse"])
    site = site_from_config(cfg.site)
    batch = build(cfg.field, "field").load(site)
    table = extract_features(batch, site, build_feature_sets(cfg.features))
    np.testing.assert_allclose(tdoa_matrix(table, 6)[0], UPSTREAM_LOCA_TDOA_S, atol=1e-3)


@pytest.mark.parametrize(
    "settings,message",
    [
        ({"search": "medium"}, "must be 'fine' or 'coarse'"),
        ({"search": "coarse", "upsample": 4}, "upsample=4"),
        ({"search": "coarse", "upsample": 1}, "upsample=1"),
    ],
)
def test_bad_search_settings_are_config_errors_naming_the_setting(settings, message):
    with pytest.raises(ConfigError, match=f"features.gcc.search.*{message}"):
        TdoaCandidates(gcc=settings)


def test_pair_candidates_itself_refuses_a_coarse_search_it_cannot_do(batches):
    """A caller of the toolkit (not only the feature groups) gets the error, never the upsample-2 grid under another name."""
    site, batch = batches["frozen_lake"]
    for upsample, band_limited, message in ((4, False, "upsample=4"), (2, True, "band_limited=True")):
        with pytest.raises(ConfigError, match=f"features.gcc.search=coarse.*{message}"):
            pair_candidates(_fresh(batch), site, 3, 0.002, (300.0, 10000.0), "beta_phat", upsample, 0.8, band_limited, search="coarse")
    with pytest.raises(ConfigError, match="must be 'fine' or 'coarse'"):
        pair_candidates(_fresh(batch), site, 3, 0.002, (300.0, 10000.0), "beta_phat", 2, 0.8, search="medium")


def test_the_default_config_does_not_name_the_search(compose_cfg):
    """Not in the default gcc block: the default feature cache keys stay what they were."""
    for features in ("physics", "physics_lean"):
        assert "search" not in compose_cfg(["+site=frozen_lake", f"features={features}"]).features.gcc
    cfg = compose_cfg(["+site=forest", "features=physics_lean", "+features.gcc.search=coarse"])
    assert cfg.features.groups.tdoa.gcc.search == "coarse" and cfg.features.groups.uncertainty.gcc.search == "coarse"


def _reference_top(values: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The m highest local maxima of each row by the textbook route (mask, stable sort), highest first, ties by the lower index."""
    masked = np.where(local_maxima(values), values, -np.inf)
    masked[np.isnan(masked)] = -np.inf
    order = np.argsort(-masked, axis=-1, kind="stable")[:, :m]
    is_peak = np.take_along_axis(masked, order, -1) > -np.inf
    pad = m - order.shape[-1]  # rows shorter than m: slots that can hold no peak
    return np.pad(order, ((0, 0), (0, pad))), np.pad(is_peak, ((0, 0), (0, pad)))


def _assert_same_peaks(values: np.ndarray, m: int, m_sum: int) -> None:
    found = window_peaks(values, m, m_sum)
    top, is_peak = _reference_top(values, m)
    assert found.top.shape == (values.shape[0], m) and found.top_sum.shape == (values.shape[0], m_sum)
    np.testing.assert_array_equal(found.n_top, is_peak.sum(-1))
    np.testing.assert_array_equal(np.where(is_peak, found.top, -1), np.where(is_peak, top, -1))
    if m_sum:
        sums = values[:, :-1] + values[:, 1:]  # in the rows' own precision, as the kernel adds them
        top_sum, is_peak_sum = _reference_top(sums, m_sum)
        np.testing.assert_array_equal(found.n_sum, is_peak_sum.sum(-1))
        np.testing.assert_array_equal(np.where(is_peak_sum, found.top_sum, -1), np.where(is_peak_sum, top_sum, -1))
    np.testing.assert_allclose(found.sum_of_squares, np.sum(np.square(values, dtype=np.float64), axis=-1), rtol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("n", [1, 2, 3, 17, 300])
def test_window_peaks_equal_the_sorted_masked_maxima_with_ties_and_plateaus(dtype, n):
    """One pass gives the m highest local maxima (and of the two-sample sums) that masking and a stable sort give, in the same
    order: highest first, the lower index among equal values; rows with many exact ties, plateaus, NaN and fewer maxima than m."""
    rng = np.random.default_rng(n)
    values = np.round(rng.standard_normal((30, n)), 1).astype(dtype)  # rounded: many exact ties and flat runs
    values[0] = 0.0  # flat: only the last sample is a maximum
    values[1, ::3] = np.nan
    for m, m_sum in ((1, 1), (5, 3), (16, 16), (40, 0)):
        _assert_same_peaks(values, m, min(m_sum, max(n - 1, 0)))


@settings(max_examples=examples(60), deadline=None)
@given(
    st.lists(st.lists(st.floats(-4, 4, width=32), min_size=4, max_size=60), min_size=1, max_size=4).filter(
        lambda rows: len({len(r) for r in rows}) == 1
    ),
    st.integers(1, 20),
)
def test_window_peaks_hold_for_any_rows(rows, m):
    """Arbitrary float32 rows (Hypothesis): the same peaks as the reference, in the same order."""
    _assert_same_peaks(np.array(rows, dtype=np.float32), m, m)


def test_window_peaks_read_strided_windows_and_refuse_bad_input():
    """A window cut from a wider correlation (a strided view) gives what its copy gives; wrong shapes and types are named."""
    rng = np.random.default_rng(3)
    wide = rng.standard_normal((6, 3, 500)).astype(np.float32)
    view = wide[:, 1, 40:460]
    for a, b in zip(window_peaks(view, 16, 16), window_peaks(np.ascontiguousarray(view), 16, 16)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="2-D float32 or float64"):
        window_peaks(wide, 4, 4)
    with pytest.raises(ValueError, match="2-D float32 or float64"):
        window_peaks(view.astype(np.int32), 4, 4)
    with pytest.raises(ValueError, match="m, m_sum >= 0"):
        window_peaks(view, -1, 4)


def test_a_centre_that_is_no_fine_peak_does_not_hide_a_later_one():
    """Only kept entries count as repeats: an entry ranked out (no fine-grid peak) that lands on the same fine index as a later
    genuine peak leaves that peak in place."""
    from acoustlab.toolkit.gcc_coarse import _repeated

    index = np.array([[7, 7, 3, 7, 3]])
    kept = np.array([[False, True, True, True, True]])
    np.testing.assert_array_equal(_repeated(index, kept), [[False, False, False, True, True]])


@pytest.mark.parametrize("length", [20, 33, 400])
def test_fine_samples_from_window_views_equal_the_clamped_gathers(length):
    """The five fine samples around each centre, gathered as windows of a view, equal the clamped gathers (the samples bit for
    bit, the half samples to single-precision rounding) with centres at both ends (clamped) and inside, rows shorter than the
    kernel included."""
    from acoustlab.toolkit.gcc_coarse import _fine_samples

    rng = np.random.default_rng(length)
    rows = rng.standard_normal((3, 4, length)).astype(np.float32)
    centre = rng.integers(0, length, (3, 4, 32))
    centre[..., :2] = [0, length - 1]  # the ends: windows cross them
    centre[0, 0] = length // 2  # a row of centres inside only
    kernel = half_sample_kernel()
    fine = _fine_samples(rows, centre, kernel)
    clamp = np.clip(centre[..., None] + np.array([-1, 0, 1]), 0, length - 1)
    np.testing.assert_array_equal(fine[..., [0, 2, 4]], np.take_along_axis(rows, clamp.reshape(3, 4, -1), -1).reshape(clamp.shape))
    halves = np.stack([half_samples(rows, centre - 1, kernel), half_samples(rows, centre, kernel)], axis=-1)
    np.testing.assert_allclose(fine[..., [1, 3]], halves, rtol=1e-6, atol=1e-6)
