"""The GPU (torch) GCC path: the same peaks as the numpy/SciPy path, and clear errors where it cannot run.

The torch code runs here on the CPU (``device="cpu"`` of :func:`pair_candidates_torch`), so every
line of it is tested without a GPU; the ``gpu``-marked test repeats the comparison on CUDA.
"""

import numpy as np
import pytest

from acoustlab.core.errors import ConfigError
from acoustlab.core.types import RecordingBatch
from acoustlab.toolkit.gcc_candidates import lag_windows_s, pair_candidates

torch = pytest.importorskip("torch")
from acoustlab.toolkit import gcc_torch  # noqa: E402
from acoustlab.toolkit.dsp import gcc_lengths  # noqa: E402
from acoustlab.toolkit.gcc_torch import check_device, events_per_pass, pair_candidates_torch, window_bounds  # noqa: E402


@pytest.fixture(scope="module")
def noisy_batches(simulate_site):
    """Default simulation (noise, trunks, ground): several GCC peaks per pair."""
    return {site_name: simulate_site(site_name, n, 3) for site_name, n in (("frozen_lake", 8), ("forest", 4))}


def _assert_same_candidates(ours_lags, ours_heights, ours_sidelobe, reference, sample_rate_hz, upsample):
    """Same peaks (lags far within one lag step, the same NaN pattern), heights and RMS up to float32 rounding."""
    np.testing.assert_array_equal(np.isnan(ours_lags), np.isnan(reference.lags_s))
    assert np.nanmax(np.abs(ours_lags - reference.lags_s)) < 0.01 / (sample_rate_hz * upsample)
    scale = np.nanmax(np.abs(reference.heights))
    assert np.nanmax(np.abs(ours_heights - reference.heights)) < 1e-4 * scale
    np.testing.assert_allclose(ours_sidelobe, reference.sidelobe, rtol=1e-4)


@pytest.mark.parametrize("site_name", ["frozen_lake", "forest"])
@pytest.mark.parametrize(
    "weighting,band,band_limited",
    [("beta_phat", (300.0, 10000.0), False), ("phat", None, False), ("none", (1000.0, 4000.0), True), ("beta_phat", "per_event", True)],
)
def test_torch_gcc_gives_the_numpy_paths_peaks(noisy_batches, site_name, weighting, band, band_limited):
    site, batch = noisy_batches[site_name]
    if band == "per_event":  # one band per event, as detector tables give them
        band = np.tile([[500.0, 8000.0]], (batch.n_events, 1))
        band[::2] = [1500.0, 6000.0]
    reference = pair_candidates(
        RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events), site, 3, 0.002, band, weighting, 2, 0.8, band_limited
    )
    lags, heights, sidelobe = pair_candidates_torch(
        batch.audio,
        site.mic_pairs,
        batch.sample_rate_hz,
        lag_windows_s(site, 0.002),
        3,
        weighting,
        band,
        2,
        0.8,
        band_limited,
        device="cpu",
    )
    _assert_same_candidates(lags, heights, sidelobe, reference, batch.sample_rate_hz, 2)
    assert np.isfinite(lags[..., 0]).all()


def test_a_pair_window_narrower_than_k_peaks_leaves_the_missing_candidates_nan(noisy_batches):
    """A window with fewer local maxima than K gives NaN candidates, as the numpy path does; a peak lies in its window
    (up to the half lag step parabolic refinement may add at the window's edge)."""
    site, batch = noisy_batches["frozen_lake"]
    windows = np.full(len(site.mic_pairs), 1.5 / batch.sample_rate_hz)  # ±1.5 samples: at most a couple of maxima
    lags, heights, _ = pair_candidates_torch(
        batch.audio, site.mic_pairs, batch.sample_rate_hz, windows, 3, "beta_phat", (300.0, 10000.0), 2, 0.8, device="cpu"
    )
    assert np.isnan(lags[..., -1]).any()
    np.testing.assert_array_equal(np.isnan(lags), np.isnan(heights))
    assert np.nanmax(np.abs(lags)) <= windows[0] + 0.5 / (2 * batch.sample_rate_hz) + 1e-15


def test_window_bounds_cut_each_pair_as_boolean_indexing_does():
    lags = np.arange(-7, 8) / 4.0
    first, last = window_bounds(lags, np.array([0.5, 1.0, 10.0]))
    for f, la, w in zip(first, last, (0.5, 1.0, 10.0), strict=True):
        inside = np.flatnonzero(np.abs(lags) <= w)
        assert (f, la) == (inside[0], inside[-1])


def test_feature_groups_route_the_gcc_to_the_configured_device(noisy_batches, monkeypatch):
    """``features.gcc.device`` and its memory bound reach pair_candidates (a stand-in records them; the result is the CPU path's)."""
    import plugins.features.gcc_groups as groups

    seen = []
    monkeypatch.setattr(groups, "check_device", lambda device: device)  # pretend a GPU is there

    def on_cpu(audio, pairs, fs, windows, k, weighting, band, upsample, beta, band_limited=False, device="cuda", memory_gb=4.0):
        seen.append((device, memory_gb))
        return pair_candidates_torch(audio, pairs, fs, windows, k, weighting, band, upsample, beta, band_limited, device="cpu")

    monkeypatch.setattr(gcc_torch, "pair_candidates_torch", on_cpu)
    site, batch = noisy_batches["frozen_lake"]
    on_gpu = groups.TdoaCandidates(gcc={"device": "cuda:0", "device_memory_gb": 1.5}).transform(
        RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events), site
    )
    on_host = groups.TdoaCandidates().transform(RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events), site)
    assert seen == [("cuda:0", 1.5)]
    assert list(on_gpu.columns) == list(on_host.columns)
    np.testing.assert_allclose(on_gpu.to_numpy(), on_host.to_numpy(), rtol=0, atol=1e-7)


@pytest.mark.parametrize("device,message", [("gpu", "must be 'cpu', 'cuda' or 'cuda:N'"), ("cuda:x", "must be 'cpu', 'cuda' or 'cuda:N'")])
def test_an_unknown_device_is_a_config_error_naming_the_setting(device, message):
    with pytest.raises(ConfigError, match="features.gcc.device") as info:
        check_device(device)
    assert message in str(info.value)


@pytest.mark.parametrize("band", ["one", "per_event"])
def test_events_in_several_passes_give_the_peaks_of_one_pass(noisy_batches, band):
    """A memory bound of one event per pass: the same peaks as the whole batch at once (per-event bands cut with their events)."""
    site, batch = noisy_batches["frozen_lake"]
    bands = (
        (300.0, 10000.0) if band == "one" else np.tile([[500.0, 8000.0]], (batch.n_events, 1)) + np.arange(batch.n_events)[:, None] * 100.0
    )
    args = (batch.audio, site.mic_pairs, batch.sample_rate_hz, lag_windows_s(site, 0.002), 3, "beta_phat", bands, 2, 0.8, True)
    size = gcc_lengths(batch.audio.shape[-1], batch.sample_rate_hz, 2, float(lag_windows_s(site, 0.002).max()), bands, True)
    tiny = 1.5 / (events_per_pass(1.0, site.n_mics, len(site.mic_pairs), size) + 1)  # GiB of about 1.5 events
    assert events_per_pass(tiny, site.n_mics, len(site.mic_pairs), size) == 1
    whole = pair_candidates_torch(*args, device="cpu")
    split = pair_candidates_torch(*args, device="cpu", memory_gb=tiny)
    for a, b in zip(whole, split, strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-9)
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))


def test_events_per_pass_grows_with_the_memory_and_refuses_a_non_positive_bound():
    size = gcc_lengths(26_400, 24_000.0, 2, 0.2)
    small, large = events_per_pass(1.0, 6, 15, size), events_per_pass(8.0, 6, 15, size)
    assert small >= 1 and 8 * small <= large < 8 * (small + 1)  # floors of 1 and 8 GiB over one event's bytes
    assert events_per_pass(1e-6, 6, 15, size) == 1
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ConfigError, match="features.gcc.device_memory_gb must be > 0"):
            events_per_pass(bad, 6, 15, size)
    from plugins.features.gcc_groups import TdoaCandidates

    with pytest.raises(ConfigError, match="features.gcc.device_memory_gb must be > 0"):
        TdoaCandidates(gcc={"device_memory_gb": 0})


def test_a_gpu_out_of_memory_stops_with_the_setting_named(noisy_batches, monkeypatch):
    site, batch = noisy_batches["frozen_lake"]

    def out_of_memory(*args, **kwargs):
        raise torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 9.00 GiB")

    monkeypatch.setattr(gcc_torch, "_correlation", out_of_memory)
    with pytest.raises(ConfigError, match=r"ran the GPU out of memory; lower features.gcc.device_memory_gb \(now 4.0 GiB\)"):
        pair_candidates_torch(
            batch.audio,
            site.mic_pairs,
            batch.sample_rate_hz,
            lag_windows_s(site, 0.002),
            3,
            "beta_phat",
            (300.0, 10000.0),
            2,
            0.8,
            device="cpu",
        )


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA GPU is visible")
def test_cuda_without_a_gpu_is_a_config_error_at_construction():
    from plugins.features.gcc_groups import TdoaCandidates

    with pytest.raises(ConfigError, match="sees no CUDA GPU.*features.gcc.device=cpu"):
        TdoaCandidates(gcc={"device": "cuda"})


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA GPU is visible")
def test_a_method_fitted_on_a_gpu_and_run_without_one_stops_with_the_setting_named(noisy_batches):
    """A loaded method does not run its constructors again: the GCC itself checks its device (a shard on a CPU node)."""
    site, batch = noisy_batches["frozen_lake"]
    with pytest.raises(ConfigError, match="features.gcc.device=cuda: torch .* sees no CUDA GPU"):
        pair_candidates(
            RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events),
            site,
            3,
            0.002,
            (300.0, 10000.0),
            "beta_phat",
            2,
            0.8,
            device="cuda",
        )


def test_the_default_config_does_not_name_a_device(compose_cfg):
    """The device is not in the default gcc block: default feature cache keys stay what they were (set, it is part of them)."""
    for features in ("physics", "physics_lean"):
        cfg = compose_cfg(["+site=frozen_lake", f"features={features}"])
        assert "device" not in cfg.features.gcc
    cfg = compose_cfg(["+site=frozen_lake", "+features.gcc.device=cuda"])
    assert cfg.features.gcc.device == "cuda" and cfg.features.groups.tdoa.gcc.device == "cuda"


@pytest.mark.gpu
def test_cuda_gcc_gives_the_numpy_paths_peaks(noisy_batches):
    site, batch = noisy_batches["forest"]
    reference = pair_candidates(
        RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events), site, 3, 0.002, (300.0, 10000.0), "beta_phat", 2, 0.8
    )
    ours = pair_candidates(
        RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events),
        site,
        3,
        0.002,
        (300.0, 10000.0),
        "beta_phat",
        2,
        0.8,
        device="cuda",
    )
    _assert_same_candidates(ours.lags_s, ours.heights, ours.sidelobe, reference, batch.sample_rate_hz, 2)
