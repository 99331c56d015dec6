"""Physics-informed feature groups: columns match the catalog, known answers on clean data."""

import numpy as np
import pytest

from acoustlab.run.catalog import DOCS, render
from acoustlab.run.registry import build, build_feature_sets, group_options
from acoustlab.stages.dataset import extract_features
from acoustlab.stages.sites import site_from_config


@pytest.fixture(scope="module")
def clean_batches():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from acoustlab.run.registry import CONF_DIR

    out = {}
    for site_name in ("frozen_lake", "forest"):
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=[f"+site={site_name}", "site.noise.snr_db=[60,60]",
                                                            "simulator.trunks.enabled=false", "simulator.ground=false",
                                                            "simulator.occlusion=false"])
        site = site_from_config(cfg.site)
        sim = build(cfg.simulator, "simulator")
        out[site_name] = (site, sim.simulate(site, np.arange(12), np.arange(12), 4), build_feature_sets(cfg.features))
    GlobalHydra.instance().clear()
    return out


@pytest.mark.parametrize("site_name,expected", [("frozen_lake", 73), ("forest", 3 * 15 + 4 * 15 + 3 * 15 + 4 * 6 + (3 * 6 + 15) + 15 + (15 + 1) + (3 + 3 * 6))])
def test_columns_follow_the_catalog(clean_batches, site_name, expected):
    site, batch, sets = clean_batches[site_name]
    table = extract_features(batch, site, sets)
    names = [n for fs in sets.values() for n, _, _ in fs.catalog(site)]
    assert list(table.columns) == names
    assert table.shape == (12, expected)
    assert np.isfinite(table.to_numpy()).all()


def test_dominant_lag_and_envelope_lag_match_the_geometry(clean_batches):
    site, batch, sets = clean_batches["forest"]
    table = extract_features(batch, site, sets)
    src = batch.true_position_m
    dist = np.linalg.norm(src[:, None, :] - site.mic_positions_m[None], axis=2)
    c = batch.events["speed_of_sound_m_s"].to_numpy()
    for i, j in site.mic_pairs:
        true = (dist[:, j] - dist[:, i]) / c
        # periodic calls (trills, harmonic stacks) can put a sidelobe first even on clean data
        close = np.abs(table[f"tdoa__lag_{i}_{j}_s"] - true) < 0.25 / batch.sample_rate_hz
        assert close.mean() >= 0.9
        assert np.median(np.abs(table[f"envelope__lag_{i}_{j}_s"] - true)) < 1e-3


def test_levels_fall_with_distance_and_snr_is_high_on_clean_data(clean_batches):
    site, batch, sets = clean_batches["forest"]
    table = extract_features(batch, site, sets)
    dist = np.linalg.norm(batch.true_position_m[:, None, :] - site.mic_positions_m[None], axis=2)
    levels = table[[f"environment__level_{m}_db" for m in range(site.n_mics)]].to_numpy()
    rho = [np.corrcoef(-np.log(dist[e]), levels[e])[0, 1] for e in range(len(dist))]
    assert np.median(rho) > 0.8
    assert (table[[f"environment__snr_{m}_db" for m in range(site.n_mics)]].to_numpy() > 15).mean() > 0.8
    assert (table["environment__temperature_c"] == batch.events["temperature_c"]).all()


def test_swapping_two_mics_negates_their_lag(clean_batches):
    import dataclasses

    site, batch, sets = clean_batches["frozen_lake"]
    perm = [1, 0, 2]
    swapped_site = dataclasses.replace(site, mic_positions_m=site.mic_positions_m[perm])
    swapped = dataclasses.replace(batch, audio=batch.audio[:, perm])
    a = sets["tdoa"].transform(batch, site)
    b = sets["tdoa"].transform(swapped, swapped_site)
    np.testing.assert_allclose(b["tdoa__lag_0_1_s"], -a["tdoa__lag_0_1_s"], atol=1e-9)
    np.testing.assert_allclose(b["tdoa__lag_1_2_s"], a["tdoa__lag_0_2_s"], atol=1e-9)


def test_feature_catalog_doc_is_current():
    assert DOCS.read_text() == render(), "docs/features.md is stale: run python -m acoustlab.catalog"


def test_every_features_option_has_a_catalog():
    for option in group_options("features"):
        from acoustlab.run.catalog import feature_catalog

        assert len(feature_catalog("frozen_lake", option)) > 3


def test_srp_phat_finds_clean_sources(clean_batches):
    from plugins.features.srp_phat import SrpPhat

    site, batch, _ = clean_batches["frozen_lake"]
    est = SrpPhat().transform(batch, site)[["srp__x_m", "srp__y_m"]].to_numpy()
    err = np.linalg.norm(est - batch.true_position_m[:, :2], axis=1)
    assert np.median(err) < 0.3 and np.mean(err < 1.0) >= 0.8


def test_documented_feature_counts_match_the_catalog():
    """The status page's column counts are the catalog's (the default feature set, solver columns included)."""
    import re

    from acoustlab.run.catalog import PROJECT_ROOT, feature_catalog

    status = (PROJECT_ROOT / "docs" / "status.md").read_text()
    found = re.search(r"\((\d+) columns on the 3-mic frozen lake, (\d+) on the 6-mic forest", status)
    assert found, "docs/status.md no longer states the feature counts"
    assert (int(found[1]), int(found[2])) == (len(feature_catalog("frozen_lake")), len(feature_catalog("forest")))
