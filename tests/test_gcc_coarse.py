"""``features.gcc.search=coarse``: peaks searched on the 1/fs grid and refined on the 1/(2 fs) grid give the default's peaks."""

import numpy as np
import pytest

from acoustlab.core.errors import ConfigError
from acoustlab.core.types import RecordingBatch
from acoustlab.run.registry import build, build_feature_sets
from acoustlab.stages.dataset import extract_features
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import tdoa_matrix
from acoustlab.toolkit.dsp import gcc
from acoustlab.toolkit.gcc_candidates import lag_windows_s, pair_candidates
from acoustlab.toolkit.gcc_coarse import half_sample_kernel, half_samples
from plugins.features.gcc_groups import TdoaCandidates

UPSTREAM_LOCA_TDOA_S = [0.0, 0.0325, -0.002, 0.0316, -0.0086, 0.024]  # as tests/test_recordings.py


@pytest.fixture(scope="module")
def batches(simulate_site):
    """Default simulation (noise, trunks, ground) on both sites: several GCC peaks per pair."""
    return {site_name: simulate_site(site_name, n, 5) for site_name, n in (("frozen_lake", 16), ("forest", 8))}


def _fresh(batch):
    return RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events)


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


@pytest.mark.parametrize("settings,message", [({"search": "medium"}, "must be 'fine' or 'coarse'"),
                                              ({"search": "coarse", "upsample": 4}, "upsample=4"),
                                              ({"search": "coarse", "upsample": 1}, "upsample=1")])
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


@pytest.mark.parametrize("scale", [1.0, 1e25])
def test_top_marked_values_equal_the_masked_argpartition(scale):
    """``_top`` ranks marked values without np.where's branches; its indices are argpartition's on the −inf-masked values, in the
    same order (so ties resolve as before), also where values are too large for the finite stand-in (the masked fallback)."""
    from acoustlab.toolkit.gcc_coarse import _top

    rng = np.random.default_rng(11)
    values = (scale * np.round(rng.standard_normal((40, 300)), 1)).astype(np.float32)  # rounded: many exact ties
    marked = rng.random(values.shape) < 0.3
    marked[0] = False  # a row with nothing marked
    for m in (1, 5, 16):
        top, valid = _top(values, marked, m)
        masked = np.where(marked, values, -np.inf)
        expected = np.argpartition(-masked, m - 1, axis=-1)[:, :m]
        np.testing.assert_array_equal(top, expected)
        np.testing.assert_array_equal(valid, np.take_along_axis(masked, expected, -1) > -np.inf)
