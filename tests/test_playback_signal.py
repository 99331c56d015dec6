"""The playback sweep: one sharp correlation peak, a file a speaker can play, and what it buys a calibration from few spots."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.calls import synthetic_call
from acoustlab.toolkit.playback_signal import SWEEP_LABEL, SweepPool, playback_sweep, write_playback_sweep

RATE = 24000.0


def side_peak(signal: np.ndarray, main_lobe_s: float) -> float:
    """The highest |autocorrelation| outside ± ``main_lobe_s`` of zero lag, relative to the zero-lag peak."""
    n = signal.size
    spectrum = np.fft.rfft(signal, 2 * n)
    ac = np.abs(np.fft.irfft(spectrum * np.conj(spectrum)))[: n // 2]
    return float(ac[int(main_lobe_s * RATE) :].max() / ac[0])


def test_the_sweep_covers_its_band_and_correlates_with_itself_at_one_lag_only():
    sweep = playback_sweep(RATE)
    assert sweep.size == int(0.3 * RATE) and np.max(np.abs(sweep)) == pytest.approx(1.0)
    power = np.abs(np.fft.rfft(sweep)) ** 2
    freqs = np.fft.rfftfreq(sweep.size, 1 / RATE)
    assert power[(freqs >= 900) & (freqs <= 8100)].sum() > 0.99 * power.sum()
    # beyond half a millisecond its autocorrelation stays below 0.2 of the peak; a tonal call's repeats at its period
    assert side_peak(sweep, 5e-4) < 0.2
    harmonic = synthetic_call(np.random.default_rng(3), RATE, "harmonic_stack")[1]
    assert side_peak(harmonic, 5e-4) > 0.5


@pytest.mark.parametrize(("band", "duration"), [((8000.0, 1000.0), 0.3), ((1000.0, 12000.0), 0.3), ((1000.0, 8000.0), 0.001)])
def test_a_sweep_that_cannot_be_made_is_refused_in_one_line(band, duration):
    with pytest.raises(ConfigError, match="playback sweep"):
        playback_sweep(RATE, *band, duration_s=duration)


def test_the_sweep_file_is_what_a_speaker_plays(tmp_path: Path):
    path = write_playback_sweep(tmp_path / "sweep.wav", sample_rate_hz=48000.0)
    audio, rate = sf.read(path)
    assert rate == 48000 and audio.ndim == 1 and audio.size == int(0.3 * 48000) + 2 * 24000
    assert np.max(np.abs(audio)) == pytest.approx(10 ** (-1 / 20), abs=1e-3)  # −1 dBFS
    assert not audio[:24000].any() and not audio[-24000:].any()  # half a second of silence each side
    with pytest.raises(ConfigError, match="cannot write"):
        write_playback_sweep(tmp_path / "missing" / "sweep.wav")


def test_a_field_emits_the_sweep_when_asked_and_refuses_an_unknown_signal():
    from plugins.fields.image_source import ImageSourceField

    with pytest.raises(ConfigError, match="field.signal"):
        ImageSourceField(signal="song")
    pool = SweepPool(RATE)
    assert pool.draw(np.random.default_rng(0)).label == SWEEP_LABEL and pool.max_duration_s == pytest.approx(0.3)


@pytest.mark.slow
def test_from_five_spots_a_sweep_recovers_the_3_mic_lake_where_calls_trade_the_thermometer_for_the_arrays_scale(
    compose_cfg, tmp_path, caplog
):
    """acoustlab's own lake (3 mics, ground reflection), mics 2 m off, clocks ±1 ms, thermometer 3 °C high, 5 planned
    spots × 2 playbacks: the calls' GCC peaks repeat at their period and the calibration takes wrong ones; the sweep's do
    not. ``calibrate`` tells the calls by their second GCC peak and warns."""
    from acoustlab.api import plan_playbacks
    from acoustlab.method.protocols.calibration_report import TONAL_PEAK_RATIO
    from acoustlab.run.app import run_experiment
    from acoustlab.stages.sites import site_from_config
    from plugins.fields.image_source import ImageSourceField

    spots = plan_playbacks("frozen_lake", 5)[["x_m", "y_m", "z_m"]].to_numpy()
    positions = "[" + ",".join(f"[{x:.3f},{y:.3f},{z:.3f}]" for x, y, z in spots) + "]"
    impaired = ["field.mic_position_error_m=2.0", "field.clock_offset_max_s=0.001", "field.temperature_error_c=3.0", "field.array_seed=100"]
    errors, ratio, warned = {}, {}, {}
    for signal in ("calls", "sweep"):
        overrides = ["+site=frozen_lake", "protocol=calibrate", "field=outdoor", f"field.positions_m={positions}", "field.seed=9100"]
        overrides += [*impaired, "field.events_per_position=2", f"field.signal={signal}", f"paths.outputs_dir={tmp_path}"]
        cfg = compose_cfg([*overrides, "tracking=none", "plots=false", "cache.enabled=false"])
        caplog.clear()
        with caplog.at_level("WARNING", logger="acoustlab.method.protocols.calibration_report"):
            ratio[signal] = run_experiment(cfg, tmp_path / signal, {})["calibration"]["second_peak_ratio"]
        warned[signal] = "the signal played back is tonal" in caplog.text
        body = json.loads((tmp_path / signal / "calibration.json").read_text())
        true_mics = ImageSourceField(mic_position_error_m=2.0, clock_offset_max_s=0.001, array_seed=100).true_array(
            site_from_config(cfg.site)
        )[0]
        errors[signal] = (np.hypot(*(np.asarray(body["mic_positions_m"]) - true_mics)[:, :2].T).max(), body["temperature_offset_c"])
    assert errors["sweep"][0] < 0.03 and abs(errors["sweep"][1] + 3.0) < 0.3
    assert errors["calls"][0] > 2 * errors["sweep"][0]  # premise: from calls the same spots leave the mics further off
    assert ratio["calls"] >= TONAL_PEAK_RATIO > ratio["sweep"] and warned == {"calls": True, "sweep": False}


def test_no_tonal_warning_without_peak_heights(caplog):
    from acoustlab.method.protocols.calibration_report import warn_if_tonal

    with caplog.at_level("WARNING", logger="acoustlab.method.protocols.calibration_report"):
        warn_if_tonal(None)
        warn_if_tonal(0.5)
    assert not caplog.text
