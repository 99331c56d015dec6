"""Physics-informed feature groups: columns match the catalog, known answers on clean data."""

import numpy as np
import pandas as pd
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
            cfg = compose(
                config_name="config",
                overrides=[
                    f"+site={site_name}",
                    "site.noise.snr_db=[60,60]",
                    "simulator.trunks.enabled=false",
                    "simulator.ground=false",
                    "simulator.occlusion=false",
                ],
            )
        site = site_from_config(cfg.site)
        sim = build(cfg.simulator, "simulator")
        out[site_name] = (site, sim.simulate(site, np.arange(12), np.arange(12), 4), build_feature_sets(cfg.features))
    GlobalHydra.instance().clear()
    return out


@pytest.mark.parametrize(
    "site_name,expected", [("frozen_lake", 73), ("forest", 3 * 15 + 4 * 15 + 3 * 15 + 4 * 6 + (3 * 6 + 15) + 15 + (15 + 1) + (3 + 3 * 6))]
)
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


@pytest.mark.slow
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


def test_windowed_reverberation_summaries_equal_their_full_length_definitions(clean_batches):
    """The ``ir`` group computes on the 100 / 300 ms after each peak / onset only; every summary equals the definition
    on the full envelope (masks over every sample), to rounding, including a silent channel."""
    import pandas as pd
    import scipy.signal as ss

    from acoustlab.core.types import RecordingBatch
    from plugins.features.waveform_groups import BlindIrSummaries, envelope

    site, batch, _ = clean_batches["forest"]
    audio = batch.audio.copy()
    audio[0, 1] = 0.0
    fresh = RecordingBatch(audio, batch.sample_rate_hz, batch.events)
    group = BlindIrSummaries()
    ours = group.transform(fresh, site)
    fs = batch.sample_rate_hz
    env = envelope(fresh, group.band_hz)
    win = int(0.005 * fs)
    raw = fresh.derived(("hilbert_magnitude", group.band_hz), lambda: None)
    np.testing.assert_allclose(env, ss.oaconvolve(raw, np.ones((1, 1, win)) / win, mode="same", axes=-1), rtol=1e-9, atol=1e-12)
    peak = np.argmax(env, axis=-1)
    peak_val = np.take_along_axis(env, peak[..., None], -1)[..., 0]
    t = np.arange(env.shape[-1]) / fs
    env_db = 20 * np.log10(np.maximum(env, 1e-12) / np.maximum(peak_val, 1e-12)[..., None])
    rel = t[None, None, :] - t[peak][..., None]
    w = ((rel >= 0) & (rel <= 0.1)).astype(float)
    cnt = np.maximum(w.sum(-1), 2)
    mt, my = (w * rel).sum(-1) / cnt, (w * env_db).sum(-1) / cnt
    slope = (w * (rel - mt[..., None]) * (env_db - my[..., None])).sum(-1) / np.maximum((w * (rel - mt[..., None]) ** 2).sum(-1), 1e-12)
    onset = np.argmax(env >= 0.1 * peak_val[..., None], axis=-1)
    rise = np.maximum(np.argmax(env >= 0.9 * peak_val[..., None], axis=-1) - onset, 0) / fs
    rel_on = t[None, None, :] - t[onset][..., None]
    early = (env**2 * ((rel_on >= 0) & (rel_on < 0.05))).sum(-1)
    late = (env**2 * ((rel_on >= 0.05) & (rel_on < 0.3))).sum(-1)
    early_late = 10 * np.log10(np.maximum(early, 1e-20) / np.maximum(late, 1e-20))
    spread = (env_db > -10).sum(-1) / fs
    for k in range(site.n_mics):
        reference = pd.DataFrame(
            {
                f"ir__decay_{k}_db_s": slope[:, k],
                f"ir__early_late_{k}_db": early_late[:, k],
                f"ir__rise_time_{k}_s": rise[:, k],
                f"ir__spread_{k}_s": spread[:, k],
            }
        )
        for name in reference:
            np.testing.assert_allclose(ours[name], reference[name], rtol=1e-9, atol=1e-9, err_msg=name)
    assert ours["ir__spread_1_s"][0] == env.shape[-1] / fs  # a silent channel is "within 10 dB" everywhere, as defined


def test_envelope_lags_equal_the_full_length_correlation(clean_batches):
    """Transforms only as long as the lag window needs give the lags of the correlation over twice the signal length."""
    from acoustlab.core.types import RecordingBatch
    from acoustlab.toolkit.gcc_candidates import lag_windows_s
    from plugins.features.waveform_groups import EnvelopeDelays, envelope

    for site_name in ("frozen_lake", "forest"):
        site, batch, _ = clean_batches[site_name]
        fresh = RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events)
        group = EnvelopeDelays()
        ours = group.transform(fresh, site)
        env = envelope(fresh, group.band_hz, smooth_s=0.002)
        env = env - env.mean(-1, keepdims=True)
        n_fft = 2 * env.shape[-1]
        spec = np.fft.rfft(env, n=n_fft, axis=-1)
        lags = (np.arange(n_fft) - n_fft // 2) / batch.sample_rate_hz
        for (i, j), max_lag in zip(site.mic_pairs, lag_windows_s(site, group.max_lag_margin_s), strict=True):
            cc = np.fft.fftshift(np.fft.irfft(np.conj(spec[:, i]) * spec[:, j], n=n_fft, axis=-1), axes=-1)
            window = np.abs(lags) <= max_lag
            np.testing.assert_array_equal(ours[f"envelope__lag_{i}_{j}_s"], lags[window][np.argmax(cc[:, window], axis=-1)])


def test_peak_to_sidelobe_rms_is_that_of_the_lag_window_bit_for_bit(clean_batches):
    """The candidates' sidelobe RMS equals the RMS over each pair's lag window, each event's row summed by itself (float32
    sums depend on the memory layout: a batch laid out with events along the fast axis sums each row in sequence, one event
    alone pairwise, so a feature would depend on its batch)."""
    from acoustlab.core.types import RecordingBatch
    from acoustlab.toolkit.dsp import gcc
    from acoustlab.toolkit.gcc_candidates import lag_windows_s, pair_candidates

    site, batch, _ = clean_batches["forest"]
    windows = lag_windows_s(site, 0.002)
    ours = pair_candidates(
        RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events), site, 3, 0.002, (300.0, 10000.0), "beta_phat", 2, 0.8
    )
    cc, lags = gcc(batch.audio, site.mic_pairs, batch.sample_rate_hz, "beta_phat", (300.0, 10000.0), 2, 0.8, max_lag_s=float(windows.max()))
    for k, max_lag in enumerate(windows):
        window = np.abs(lags) <= max_lag
        each = [np.sqrt(np.mean(cc[e, k, window] ** 2)) for e in range(len(cc))]  # one contiguous row at a time
        np.testing.assert_array_equal(ours.sidelobe[:, k], np.array(each, dtype=np.float32))


def test_one_transform_envelope_equals_filtfilt_then_hilbert_away_from_the_edges(clean_batches):
    """The band-passed Hilbert magnitude from one transform is sosfiltfilt + scipy.signal.hilbert except near the clip's ends."""
    import scipy.signal as ss

    from plugins.features.waveform_groups import ENVELOPE_PAD_S, _hilbert_magnitude

    for site_name in ("frozen_lake", "forest"):
        _, batch, _ = clean_batches[site_name]
        fs, band = batch.sample_rate_hz, (1000.0, 8000.0)
        sos = ss.butter(4, [band[0] / (fs / 2), band[1] / (fs / 2)], btype="bandpass", output="sos")
        textbook = np.abs(ss.hilbert(ss.sosfiltfilt(sos, batch.audio, axis=-1), axis=-1))
        ours = _hilbert_magnitude(batch.audio, fs, band)
        edge = int(ENVELOPE_PAD_S * fs)
        peak = textbook.max(axis=-1, keepdims=True)
        assert np.max(np.abs(ours - textbook)[..., edge:-edge] / peak) < 2e-3
        np.testing.assert_array_equal(np.argmax(ours, axis=-1), np.argmax(textbook, axis=-1))


def test_an_event_s_features_do_not_depend_on_the_longer_events_beside_it(clean_batches):
    """Recordings of events of different lengths are zero-padded to the longest; with each clip's own length given
    (``clip_samples``), an event's features are those it has alone, bit for bit, whatever else is in the table."""
    import pandas as pd

    from acoustlab.core import columns as col
    from acoustlab.core.types import RecordingBatch

    site, batch, sets = clean_batches["frozen_lake"]
    short = int(batch.audio.shape[-1] * 0.7)
    audio = batch.audio[:4].copy()
    audio[1:3, :, short:] = 0.0  # events 1 and 2 end early; 0 and 3 fill the batch
    events = batch.events.iloc[:4].reset_index(drop=True).assign(**{col.CLIP_SAMPLES: [audio.shape[-1], short, short, audio.shape[-1]]})
    together = extract_features(RecordingBatch(audio, batch.sample_rate_hz, events), site, sets)
    alone = extract_features(
        RecordingBatch(audio[1:2, :, :short], batch.sample_rate_hz, batch.events.iloc[1:2].reset_index(drop=True)), site, sets
    )
    pd.testing.assert_frame_equal(together.iloc[[1]].reset_index(drop=True), alone)
    padded = extract_features(RecordingBatch(audio, batch.sample_rate_hz, events.drop(columns=[col.CLIP_SAMPLES])), site, sets)
    assert not padded.iloc[[1]].reset_index(drop=True).equals(alone)  # the padding would have changed it
    first_alone = extract_features(
        RecordingBatch(audio[:1], batch.sample_rate_hz, batch.events.iloc[:1].reset_index(drop=True)), site, sets
    )
    pd.testing.assert_frame_equal(together.iloc[[0]].reset_index(drop=True), first_alone)


@pytest.mark.slow
@pytest.mark.parametrize("features", ["physics", "physics_lean_coarse", "physics_srp"])
def test_an_event_s_features_do_not_depend_on_the_events_computed_with_it(compose_cfg, features):
    """Every feature of an event computed alone is bit for bit the one it gets among 11 others of the same clip length (no
    reduction whose order follows the batch's memory layout), so chunking the recordings never changes a position."""
    from acoustlab.core.types import RecordingBatch

    cfg = compose_cfg(["+site=forest", "simulator=free_field", f"features={features}"])
    site = site_from_config(cfg.site)
    ids = np.arange(1000, 1012)
    batch = build(cfg.simulator, "simulator").simulate(site, ids, ids, 7)
    feature_sets = build_feature_sets(cfg.features)
    together = extract_features(batch, site, feature_sets)
    for k in range(len(ids)):
        alone = RecordingBatch(
            audio=batch.audio[k : k + 1], sample_rate_hz=batch.sample_rate_hz, events=batch.events.iloc[k : k + 1].reset_index(drop=True)
        )
        pd.testing.assert_frame_equal(
            extract_features(alone, site, feature_sets), together.iloc[k : k + 1].reset_index(drop=True), check_exact=True
        )
