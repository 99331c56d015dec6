"""One placement path: ``localize``, ``season`` and ``acoustlab.localize`` give the same positions for the same clips.

A synthetic frozen-lake season (one file per recorder, Raven tables) is localized as a season;
its events' windows, band and assumed weather then become the events table of ``field=recordings``
over the same files, localized by ``python -m acoustlab localize`` (in process) and by the
Python API. All three cut each clip by one rule (``acoustlab.toolkit.dsp.clip_samples``), fit the
same method and place through ``FittedLocalizer``, so every column they share is equal, bit for bit.
"""

from __future__ import annotations

import json

import pandas as pd
import pytest

from acoustlab.run.app import run_experiment
from acoustlab.season.synthetic import SyntheticSeason, write_season
from acoustlab.stages.sites import site_from_config

pytestmark = pytest.mark.slow

METHOD = ["+site=frozen_lake", "+experiment=smoke", "tracking=none", "model.n_estimators=20", "features=physics_lean_coarse"]


def test_localize_season_and_the_api_place_the_same_clips_alike(compose_cfg, tmp_path):
    outputs = f"paths.outputs_dir={tmp_path / 'outputs'}"
    season_cfg = compose_cfg(
        [
            *METHOD,
            outputs,
            "protocol=season",
            f"protocol.recordings.audio_dir={tmp_path / 'audio'}",
            f"protocol.detections.paths=[{tmp_path / 'raven'}]",
            f"protocol.output_dir={tmp_path / 'season'}",
        ]
    )
    site = site_from_config(season_cfg.site)
    settings = SyntheticSeason.for_site(
        site, duration_s=30, file_s=30, n_calls=6, min_spacing_s=2.0, sample_rate_hz=float(season_cfg.simulator.sample_rate_hz)
    )
    write_season(settings, tmp_path)
    run_experiment(season_cfg, tmp_path / "season_run")
    season = pd.read_parquet(tmp_path / "season_run" / "positions.parquet")

    # the season's own clips as an events table of field=recordings over the same files
    events = pd.read_parquet(tmp_path / "season" / "events.parquet")
    manifest = json.loads((tmp_path / "season" / "season.json").read_text())
    files = {path.parent.name: str(path.relative_to(tmp_path / "audio")) for path in (tmp_path / "audio").glob("*/*.wav")}
    mics = pd.DataFrame(
        {
            "mic_id": manifest["recorders"],
            "x_m": site.mic_positions_m[:, 0],
            "y_m": site.mic_positions_m[:, 1],
            "z_m": site.mic_positions_m[:, 2],
            "file": [files[r] for r in manifest["recorders"]],
            "position_sigma_m": 0.0,  # the season's own mics, exactly where it rendered them
        }
    )
    mics.to_csv(tmp_path / "mics.csv", index=False)
    table = pd.DataFrame(
        {
            "event_id": events["event_id"],
            "start_s": events["start_s"],
            "end_s": events["end_s"],
            "temperature_c": manifest["plan"]["temperature_c"],
            "relative_humidity_pct": manifest["plan"]["relative_humidity_pct"],
            "low_hz": events["band_low_hz"],
            "high_hz": events["band_high_hz"],
        }
    )
    table.to_csv(tmp_path / "events.csv", index=False)
    field = {
        "audio_dir": str(tmp_path / "audio"),
        "mics_csv": str(tmp_path / "mics.csv"),
        "events_csv": str(tmp_path / "events.csv"),
        "pad_s": 0,
    }
    run_experiment(
        compose_cfg([*METHOD, outputs, "protocol=localize", "field=recordings", *(f"field.{k}={v}" for k, v in field.items())]),
        tmp_path / "localize_run",
    )
    localized = pd.read_parquet(tmp_path / "localize_run" / "positions.parquet")

    from acoustlab.api import localize

    from_python = localize("frozen_lake", overrides=[*METHOD[1:], outputs], run_dir=tmp_path / "api_run", verbose=False, field=field)

    shared = [c for c in localized.columns if c in season.columns]
    assert {"x_m", "y_m", "solver_x_m", "model_x_m", "radius_gdop_scaled_0.8_m", "tdoa_0_1_s", "placed"} <= set(shared)
    assert len(season) == settings.n_calls and season["placed"].all()
    pd.testing.assert_frame_equal(localized[shared], season[shared], check_exact=True, check_dtype=False)
    pd.testing.assert_frame_equal(from_python[shared], season[shared], check_exact=True, check_dtype=False)
