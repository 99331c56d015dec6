"""Free-field simulator: delays equal path length over c, per-event determinism, SNR, positions."""

import numpy as np
import pytest

from acoustlab.run.registry import build
from acoustlab.stages.sites import site_from_config
from plugins.features.gcc_phat import GccPhatTdoa, tdoa_column


@pytest.fixture
def sim_and_site(compose_cfg):
    def _make(site="frozen_lake", *overrides):
        cfg = compose_cfg([f"+site={site}", "simulator=free_field", *overrides])
        return build(cfg.simulator, "simulator"), site_from_config(cfg.site)

    return _make


def test_delays_equal_path_length_over_c(sim_and_site):
    sim, site = sim_and_site("forest", "site.noise.snr_db=[120,120]")
    batch = sim.simulate(site, np.arange(6), np.arange(6), seed=3)
    lags = GccPhatTdoa().transform(batch, site)
    src = batch.true_position_m
    dist = np.sqrt(((src[:, None, :] - site.mic_positions_m[None]) ** 2).sum(-1))
    c = batch.events["speed_of_sound_m_s"].to_numpy()
    for i, j in site.mic_pairs:
        expected = (dist[:, j] - dist[:, i]) / c
        np.testing.assert_allclose(lags[tdoa_column(i, j)], expected, atol=0.05 / sim.sample_rate_hz)


def test_amplitude_follows_spherical_spreading(sim_and_site):
    sim, site = sim_and_site("frozen_lake", "site.noise.snr_db=[120,120]")
    batch = sim.simulate(site, np.arange(4), np.arange(4), seed=1)
    dist = np.sqrt(((batch.true_position_m[:, None, :] - site.mic_positions_m[None]) ** 2).sum(-1))
    rms = np.sqrt((batch.audio.astype(float) ** 2).mean(-1))
    product = rms * dist
    np.testing.assert_allclose(product, np.broadcast_to(product[:, :1], product.shape), rtol=1e-3)


def test_event_audio_does_not_depend_on_chunking(sim_and_site):
    sim, site = sim_and_site()
    together = sim.simulate(site, np.arange(10, 14), np.arange(10, 14) // 2, seed=7)
    apart = [sim.simulate(site, np.array([e]), np.array([e // 2]), seed=7) for e in range(10, 14)]
    for k, one in enumerate(apart):
        np.testing.assert_array_equal(together.audio[k], one.audio[0])
    # events that share a position id share the source position
    pos = together.true_position_m
    np.testing.assert_array_equal(pos[0], pos[1])
    assert not np.allclose(pos[0], pos[2])


def test_snr_at_the_nearest_mic(sim_and_site):
    sim, site = sim_and_site("frozen_lake", "site.noise.snr_db=[10,10]", "site.noise.regimes=[{kind: white}]")
    ids = np.arange(8)
    noisy = sim.simulate(site, ids, ids, seed=2)
    clean_sim, clean_site = sim_and_site("frozen_lake", "site.noise.snr_db=[200,200]", "site.noise.regimes=[{kind: white}]")
    clean = clean_sim.simulate(clean_site, ids, ids, seed=2)
    noise = noisy.audio.astype(float) - clean.audio.astype(float)
    dist = np.sqrt(((clean.true_position_m[:, None, :] - site.mic_positions_m[None]) ** 2).sum(-1))
    nearest = np.argmin(dist, axis=1)
    dur = noisy.events["call_duration_s"].to_numpy()
    n = np.arange(8)
    call_power = (clean.audio[n, nearest].astype(float) ** 2).sum(-1) / (dur * sim.sample_rate_hz)
    snr = 10 * np.log10(call_power / noise[n, nearest].var(-1))
    np.testing.assert_allclose(snr, 10.0, atol=0.3)


def test_sources_lie_in_the_expanded_hull(sim_and_site):
    from acoustlab.toolkit.geometry import distance_to_polygon_m, source_region

    sim, site = sim_and_site()
    batch = sim.simulate(site, np.arange(40), np.arange(40), seed=0)
    polygon, buffer_m = source_region(site.mic_positions_m, site.hull_expansion)
    assert (distance_to_polygon_m(batch.true_position_m[:, :2], polygon) <= buffer_m + 1e-9).all()
    assert batch.events["noise_regime"].isin(["recorded", "white", "pink"]).all()
    assert batch.events["call"].str.startswith("synthetic:").all()
