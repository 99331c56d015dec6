"""The field-playback stand-in delivers what a playback campaign would, deterministically."""

import numpy as np

from acoustlab.run.registry import build
from acoustlab.stages.sites import site_from_config


def small_standin(compose_cfg):
    cfg = compose_cfg(
        [
            "+site=frozen_lake",
            "field=playback_standin",
            "field.n_positions=3",
            "field.failed_position=2",
            "field.stimuli={europe: 3, north_america: 2}",
        ]
    )
    return build(cfg.field, "field"), site_from_config(cfg.site)


def test_positions_settings_stimuli_and_failure(compose_cfg):
    field, site = small_standin(compose_cfg)
    batch = field.load(site)
    ev = batch.events
    assert len(ev) == 3 * 2 * 5 and batch.audio.shape[:2] == (30, 3)
    assert ev.groupby("position_id")[["x_m", "y_m"]].nunique().eq(1).all().all()  # fixed speakers
    assert set(ev["setting"]) == {0, 1} and set(ev["stimulus_region"]) == {"europe", "north_america"}
    failed = ev["hardware_failure"]
    assert set(ev.loc[failed, "position_id"]) == {2}
    assert (ev.loc[failed, "failure_mode"] == "clipping").all() and (ev.loc[~failed, "failed_mic"] == -1).all()
    # the quiet setting is 10 dB quieter
    assert np.allclose(ev[ev.setting == 1]["snr_db"].mean() + 10, ev[ev.setting == 0]["snr_db"].mean(), atol=8)
    assert (ev["source"] == "synthetic_playback_standin").all()


def test_standin_is_deterministic(compose_cfg):
    field, site = small_standin(compose_cfg)
    a, b = field.load(site), field.load(site)
    np.testing.assert_array_equal(a.audio, b.audio)
