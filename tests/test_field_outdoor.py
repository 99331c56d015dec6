"""``field=outdoor``: acoustlab's own simulator renders at the recorders' true positions, with a field study's errors."""

from __future__ import annotations

import numpy as np
import pytest

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.physics import speed_of_sound_m_s


def test_the_own_simulator_renders_at_the_true_array_with_a_wrong_thermometer(compose_cfg):
    from acoustlab.run.app import build_run

    spots = [[30.0, 30.0, 2.0], [60.0, 40.0, 4.0]]
    cfg = compose_cfg(
        [
            "+site=forest",
            "protocol=field_eval",
            "field=outdoor",
            f"field.positions_m={spots}",
            "field.events_per_position=1",
            "field.mic_position_error_m=2.0",
            "field.clock_offset_max_s=0.001",
            "field.temperature_error_c=3.0",
            "field.array_seed=7",
        ]
    )
    built = build_run(cfg)
    field, site = built.field_source, built.site
    batch = field.load(site)
    events = batch.events
    assert (events["source"] == "acoustlab_outdoor_simulator").all()
    np.testing.assert_allclose(events[[col.TRUE_X, col.TRUE_Y, col.TRUE_Z]].to_numpy(), spots)
    # the thermometer reads 3 °C high: the table's speed of sound is not the one the sound travelled at
    air = events["simulator_speed_of_sound_m_s"].to_numpy()
    np.testing.assert_allclose(speed_of_sound_m_s(events[col.TEMPERATURE].to_numpy() - 3.0, events[col.HUMIDITY].to_numpy()), air)
    # a click from the first spot arrives at each recorder's true position (the direct path is the strongest arrival)
    true_mics, _ = field.true_array(site)
    rate = batch.sample_rate_hz
    click = np.zeros(64)
    click[0] = 1.0
    clean, c = field._render(site, true_mics, np.asarray(spots[0]), click, 0.05, 15.0, 60.0)
    arrival_s = np.argmax(np.abs(clean), axis=1) / rate
    expected_s = 0.05 + np.sqrt(((np.asarray(spots[0]) - true_mics) ** 2).sum(-1)) / c
    np.testing.assert_allclose(arrival_s, expected_s, atol=2.0 / rate)
    as_stated_s = 0.05 + np.sqrt(((np.asarray(spots[0]) - site.mic_positions_m) ** 2).sum(-1)) / c
    assert np.abs(arrival_s - as_stated_s).max() > 20 / rate  # the stated array would put them elsewhere


def test_the_image_source_renderers_ground_is_refused_not_ignored():
    from plugins.fields.outdoor import OutdoorField

    with pytest.raises(ConfigError, match="ground_energy_absorption is field=image_source's"):
        OutdoorField(ground_energy_absorption=0.4)
