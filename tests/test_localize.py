"""Localizing recordings without ground truth: positions.csv from the shipped LOCA example and from a synthetic folder."""

import json

import numpy as np
import pandas as pd
import pytest
import soundfile as sf

from acoustlab.core.errors import DataError
from acoustlab.run.app import run_experiment

LEVELS = ["0.5", "0.8", "0.95"]


def localize(compose_cfg, tmp_path, *overrides):
    cfg = compose_cfg(
        [
            *overrides,
            "protocol=localize",
            "field=recordings",
            "+experiment=smoke",
            "tracking=none",
            "model.n_estimators=20",
            "conformal=all",
            f"paths.outputs_dir={tmp_path / 'outputs'}",
        ]
    )
    run_dir = tmp_path / "run"
    metrics = run_experiment(cfg, run_dir)
    return pd.read_csv(run_dir / "positions.csv"), metrics, run_dir


def check_radii(table):
    for scorer in ("fixed", "gdop_scaled", "gdop_only"):
        radii = table[[f"radius_{scorer}_{lv}_m" for lv in LEVELS]].to_numpy(float)[table["placed"].to_numpy(bool)]
        assert np.isfinite(radii).all() and (np.diff(radii, axis=1) >= 0).all(), scorer


@pytest.mark.slow
def test_localize_the_shipped_loca_example(compose_cfg, tmp_path):
    table, metrics, run_dir = localize(compose_cfg, tmp_path, "+site=loca2021", "features.gcc.band_hz=[6000,10500]", "solver.dimensions=3")
    assert len(table) == 1 and {
        "x_m",
        "y_m",
        "z_m",
        "solver_x_m",
        "model_x_m",
        "source",
        "predicted_error_m",
        "placed",
        "abstain_reason",
        "gate_reason",
        "solver__failure",
        "solver__height_gdop",
        "solver__n_mics_used",
    } <= set(table.columns)
    # the time differences the solver worked from, as measured (OpenSoundscape's reference for recorder 4 vs 3: 32.5 ms)
    assert [c for c in table.columns if c.startswith("tdoa_0_")] == [f"tdoa_0_{j}_s" for j in range(1, 6)]
    assert table["tdoa_0_1_s"].iloc[0] == pytest.approx(0.0325, abs=0.002)
    check_radii(table)
    assert metrics["localization"]["n_detections"] == 1
    assert "errors" not in metrics  # no truth, no error metrics
    assert (run_dir / "plots" / "positions_map.png").exists()
    assert json.loads((run_dir / "metrics.json").read_text())["localization"]["n_detections"] == 1


def simulated_folder(compose_cfg, folder, n_events, known=0, rotation_deg=None, site_name="frozen_lake", dead=None, noise=None):
    """Simulated frozen-lake events written as one WAV per event with a mics and an events table; the first ``known``
    events carry their true position (calibration playbacks). With ``rotation_deg`` the mics table also has projected
    coordinates (the local frame rotated and shifted into UTM-like numbers). ``dead``: {event: [mics]} written as silent channels;
    ``noise``: {event: [mics]} written as white noise of the channel's own RMS (a recorder that hears nothing of the call)."""
    from acoustlab.run.registry import build
    from acoustlab.stages.sites import site_from_config

    cfg = compose_cfg([f"+site={site_name}", "simulator=free_field"])
    site = site_from_config(cfg.site)
    ids = np.arange(1000, 1000 + n_events)
    batch = build(cfg.simulator, "simulator").simulate(site, ids, ids, 7)
    folder.mkdir()
    rows = []
    for k, audio in enumerate(batch.audio):
        audio = audio.copy()
        audio[(dead or {}).get(k, [])] = 0.0
        for m in (noise or {}).get(k, []):
            audio[m] = np.random.default_rng([k, m]).normal(0.0, audio[m].std(), audio.shape[-1])
        sf.write(folder / f"event_{k}.wav", audio.T, int(batch.sample_rate_hz))
        row = {
            "event_id": k,
            "start_s": 0.0,
            "end_s": audio.shape[-1] / batch.sample_rate_hz,
            "file": f"event_{k}.wav",
            "temperature_c": batch.events["temperature_c"].iloc[k],
            "relative_humidity_pct": batch.events["relative_humidity_pct"].iloc[k],
            "position_id": k,
        }
        if k < known:
            row.update(x_m=batch.events["x_m"].iloc[k], y_m=batch.events["y_m"].iloc[k])
        rows.append(row)
    pd.DataFrame(rows).to_csv(folder / "events.csv", index=False)
    mics = pd.DataFrame(
        {
            "mic_id": range(site.n_mics),
            "x_m": site.mic_positions_m[:, 0],
            "y_m": site.mic_positions_m[:, 1],
            "z_m": site.mic_positions_m[:, 2],
        }
    )
    if rotation_deg is not None:
        a = np.deg2rad(rotation_deg)
        rotation = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        projected = site.mic_positions_m[:, :2] @ rotation.T + [500000.0, 4100000.0]
        mics = mics.assign(easting_m=projected[:, 0], northing_m=projected[:, 1], crs="EPSG:32617")
    mics.to_csv(folder / "mics.csv", index=False)
    overrides = [
        f"+site={site_name}",
        "simulator=free_field",
        f"field.audio_dir={folder}",
        f"field.mics_csv={folder / 'mics.csv'}",
        f"field.events_csv={folder / 'events.csv'}",
        f"field.sample_rate_hz={batch.sample_rate_hz}",
    ]
    return batch, overrides


@pytest.mark.slow
def test_localize_a_folder_of_recordings_without_truth(compose_cfg, tmp_path):
    """Simulated frozen-lake events written as files with a mics and an events table but no positions: every detection
    gets a row, and (the truth being known here) the positions are where the sources were."""
    batch, overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 8)
    table, _, run_dir = localize(compose_cfg, tmp_path, *overrides)
    assert len(table) == 8 and table["event_id"].tolist() == list(range(8))
    check_radii(table)
    placed = table["placed"].to_numpy(bool)
    err = np.hypot(table["x_m"] - batch.events["x_m"].to_numpy(), table["y_m"] - batch.events["y_m"].to_numpy())[placed]
    assert placed.mean() >= 0.75 and np.median(err) < 2.0
    # the clips of a placed event, aligned by its time differences, cut again from the run's own recordings
    import soundfile as sf

    from acoustlab.api import aligned_clips

    event = int(table["event_id"][placed].iloc[0])
    (wav,) = aligned_clips(run_dir, [event])
    audio, _ = sf.read(wav)
    per_mic = pd.read_csv(wav.with_suffix(".csv"))
    assert audio.shape[1] == batch.audio.shape[1] == len(per_mic)
    row = table[table["event_id"] == event].iloc[0]
    arrival = np.r_[0.0, [row[f"tdoa_0_{m}_s"] for m in range(1, len(per_mic))]]
    np.testing.assert_array_equal(per_mic["shift_samples"], np.round(arrival * batch.sample_rate_hz).astype(int))
    used = per_mic["fix_uses_mic"].to_numpy(bool)
    assert used.sum() >= 3 and (per_mic["residual_m"][used].abs() < 1.0).all(), per_mic


@pytest.mark.slow
def test_calibration_playbacks_join_training_and_positions_are_projected(compose_cfg, tmp_path):
    """Events with known positions (calibration playbacks) are added to the training rows, not localized; the others are
    placed and also written in the mics table's projected coordinates."""
    batch, overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 10, known=4, rotation_deg=30.0)
    table, metrics, run_dir = localize(compose_cfg, tmp_path, *overrides)
    assert table["event_id"].tolist() == [4, 5, 6, 7, 8, 9]
    assert metrics["training"]["n_calibration_playbacks"] == 4 and metrics["training"]["n_simulated"] > 0
    a = np.deg2rad(30.0)
    expected_e = table["x_m"] * np.cos(a) - table["y_m"] * np.sin(a) + 500000.0
    expected_n = table["x_m"] * np.sin(a) + table["y_m"] * np.cos(a) + 4100000.0
    np.testing.assert_allclose(table["easting_m"], expected_e, atol=1e-6)
    np.testing.assert_allclose(table["northing_m"], expected_n, atol=1e-6)
    assert (table["crs"] == "EPSG:32617").all()
    # the map layer a GIS opens: the positions in the mics' CRS, every column of positions.csv, the radii as circles
    import geopandas as gpd

    layer = gpd.read_file(run_dir / "positions.gpkg", layer="positions")
    assert layer.crs.to_epsg() == 32617 and set(table.columns) <= set(layer.columns)
    placed = table["placed"].to_numpy(bool)
    np.testing.assert_allclose(layer.geometry.x[placed], table["easting_m"][placed], atol=1e-6)
    radii = gpd.read_file(run_dir / "positions.gpkg", layer="radii")
    assert radii.crs.to_epsg() == 32617 and len(radii) > 0


@pytest.mark.slow
def test_playbacks_that_calibrate_the_radii_also_test_them_held_out_by_spot(compose_cfg, tmp_path):
    """20 playback spots calibrate the radii on the field: metrics.json gives their coverage with each spot's radii calibrated
    on the other 19, per scorer and by GDOP / hull-distance bin."""
    _, overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 24, known=20)
    table, metrics, run_dir = localize(compose_cfg, tmp_path, *overrides, "conformal.calibrate_on=field")
    held = json.loads((run_dir / "metrics.json").read_text())["held_out_calibration"]
    assert held == json.loads(json.dumps(metrics["held_out_calibration"]))
    assert held["n_playbacks"] == 20 and held["n_spots"] == 20 and len(table) == 4
    fixed = held["coverage"]["fixed"]
    assert all(0 <= fixed[lv]["detections"] <= 1 and fixed[lv]["detections"] == fixed[lv]["positions"] for lv in ("0.5", "0.8", "0.95"))
    assert held["coverage"]["cqr"]["0.8"] is None  # a quantile scorer's own model is not refitted per spot
    assert sum(entry["n"] for entry in held["by_condition"]["hull_distance"]) == 20


@pytest.mark.slow
def test_a_dead_recorder_costs_that_recorder_not_the_event(compose_cfg, tmp_path):
    """On the 6-mic forest a silent channel is left out of that event's solve (placed from the other mics, near the truth,
    the solver's fix kept); with four silent channels too few remain and the event is not placed."""
    batch, overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 8, site_name="forest", dead={1: [2], 3: [0], 5: [0, 1, 2, 3]})
    _, _, run_dir = localize(compose_cfg, tmp_path, *overrides)
    by_event = pd.read_parquet(run_dir / "positions.parquet").set_index("event_id")
    assert by_event.loc[1, "mics_dropped"] == "2" and by_event.loc[3, "mics_dropped"] == "0"
    assert "mic 2: dead" in by_event.loc[1, "quality_flags"]
    # the mics each fix rests on: never a dropped one, and as many as the solver says it used
    for event, row in by_event.iterrows():
        used = [int(m) for m in str(row["mics_used"]).split(";") if m]
        assert not set(used) & {int(m) for m in str(row["mics_dropped"]).split(";") if m}, event
        assert not row["placed"] or len(used) == row["solver__n_mics_used"], event
    assert by_event.loc[0, "mics_used"] != "" and "2" not in by_event.loc[1, "mics_used"].split(";")
    truth = batch.events.set_index("event_id")
    for event in (1, 3):  # mic 0, the usual reference, may be the one dropped
        row = by_event.loc[event]
        assert row["placed"] and row["source"] == "solver" and row["solver__n_mics_used"] <= 5
        error = np.hypot(row["x_m"] - truth.loc[1000 + event, "x_m"], row["y_m"] - truth.loc[1000 + event, "y_m"])
        assert error < 2.0, (event, error)
    assert not by_event.loc[5, "placed"] and by_event.loc[5, "abstain_reason"].startswith("quality:")
    assert by_event.loc[0, "mics_dropped"] == ""


@pytest.mark.slow
def test_a_recorder_without_a_gcc_peak_is_left_out_when_min_peak_is_set(compose_cfg, tmp_path):
    """``features.gcc.min_peak``: a channel of pure noise (no peak with any mic, about 0.01 against 0.05–0.3 for the
    call) is dropped from its event's solve and flagged ``weak_gcc``; four such channels leave too few mics and the event is
    not placed. Off (the default), every channel is used."""
    batch, overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 6, site_name="forest", noise={1: [2], 4: [0, 1, 2, 3]})
    _, _, run_dir = localize(compose_cfg, tmp_path, *overrides, "features.gcc.min_peak=0.03")
    by_event = pd.read_parquet(run_dir / "positions.parquet").set_index("event_id")
    assert by_event.loc[1, "mics_dropped"] == "2" and "mic 2: weak_gcc" in by_event.loc[1, "quality_flags"]
    row, truth = by_event.loc[1], batch.events.set_index("event_id").loc[1001]
    assert row["placed"] and row["source"] == "solver" and row["solver__n_mics_used"] == 5
    assert np.hypot(row["x_m"] - truth["x_m"], row["y_m"] - truth["y_m"]) < 2.0
    assert not by_event.loc[4, "placed"] and "weak_gcc" in by_event.loc[4, "abstain_reason"]
    assert (by_event.drop(index=[1, 4])["mics_dropped"] == "").all()
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["quality_flags"]["weak_gcc"] == 2
    _, _, default_run = localize(compose_cfg, tmp_path / "default", *overrides)
    assert (pd.read_parquet(default_run / "positions.parquet")["mics_dropped"] == "").all()


@pytest.mark.slow
def test_text_event_ids_come_back_as_given(compose_cfg, tmp_path):
    """An events table whose ids are text (``call00``, …) is read, and positions.csv names each row by its own id; two rows
    with one id stop the run naming it."""
    _, overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 4)
    events = pd.read_csv(tmp_path / "recordings" / "events.csv")
    events["event_id"] = [f"call{k:02d}" for k in range(len(events))]
    events.to_csv(tmp_path / "recordings" / "events.csv", index=False)
    table, _, _ = localize(compose_cfg, tmp_path, *overrides)
    assert table["event_id"].tolist() == ["call00", "call01", "call02", "call03"]
    events.loc[3, "event_id"] = "call00"
    events.to_csv(tmp_path / "recordings" / "events.csv", index=False)
    with pytest.raises(DataError, match="column 'event_id': 'call00' appears more than once"):
        localize(compose_cfg, tmp_path / "again", *overrides)


@pytest.mark.slow
def test_your_own_array_from_the_recordings_mics_table_alone(compose_cfg, tmp_path):
    """``+site=recordings`` takes the simulation's mics from ``field.mics_csv``: one CSV describes the array, and the calls are
    placed where they were."""
    batch, overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 6)
    overrides = ["+site=recordings" if o == "+site=frozen_lake" else o for o in overrides]
    cfg = compose_cfg([*overrides, "field=recordings"])
    from acoustlab.stages.sites import site_from_config

    mics = pd.read_csv(tmp_path / "recordings" / "mics.csv")
    np.testing.assert_allclose(site_from_config(cfg.site).mic_positions_m, mics[["x_m", "y_m", "z_m"]].to_numpy())
    table, _, _ = localize(compose_cfg, tmp_path, *overrides)
    placed = table["placed"].to_numpy(bool)
    err = np.hypot(table["x_m"] - batch.events["x_m"].to_numpy(), table["y_m"] - batch.events["y_m"].to_numpy())[placed]
    assert placed.mean() >= 0.5 and np.median(err) < 2.0


@pytest.mark.slow
def test_localize_streams_the_recordings_and_the_answer_does_not_depend_on_the_chunks(compose_cfg, tmp_path):
    """``field.chunk_events``: the recordings are read and turned into features a few events at a time (peak memory: one
    chunk's audio); two events at a time gives every column of every row the whole table gives, bit for bit."""
    _, overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 7, dead={3: [1]})
    _, _, whole = localize(compose_cfg, tmp_path / "whole", *overrides)
    _, _, chunked = localize(compose_cfg, tmp_path / "chunked", *overrides, "field.chunk_events=2")
    pd.testing.assert_frame_equal(
        pd.read_parquet(chunked / "positions.parquet"), pd.read_parquet(whole / "positions.parquet"), check_exact=True
    )
    with pytest.raises(DataError, match="lower field.chunk_events"):  # one chunk too large for memory: said before any work
        localize(compose_cfg, tmp_path / "huge", *overrides, "field.chunk_events=100000", "field.max_event_s=100000", "field.pad_s=40000")


def test_the_console_positions_summary_names_events_gives_a_radius_and_only_determined_heights():
    """The log's view of positions: the event id, x, y, a radius, and ``z_m`` only where a 3-D fix determined the height
    (a flat array's, an ambiguous mirror's or the model's estimate shows ``—``)."""
    from acoustlab.reporting.positions import positions_summary_text

    table = pd.DataFrame(
        {
            "event_id": ["call00", "call01", "call02", "call03"],
            "x_m": [1.0, 2.0, 3.0, np.nan],
            "y_m": [4.0, 5.0, 6.0, np.nan],
            "z_m": [1.5, 7.25, np.nan, np.nan],
            "source": ["solver", "solver", "model", "none"],
            "radius_gdop_scaled_0.5_m": [0.4, 0.5, 0.6, np.nan],
            "radius_gdop_scaled_0.95_m": [2.0, 3.0, 4.0, np.nan],
            "placed": [True, True, True, False],
            "solver__height_gdop": [3.0, 2.0, np.nan, np.nan],
            "solver__height_ambiguous": [0.0, 1.0, np.nan, np.nan],
        }
    )
    lines = positions_summary_text(table, [0.5, 0.95], ["gdop_scaled"]).splitlines()
    assert lines[0].split() == ["event_id", "x_m", "y_m", "z_m", "source", "radius_gdop_scaled_0.95_m", "placed"]
    assert lines[1].split() == ["call00", "1.00", "4.00", "1.50", "solver", "2.00", "True"]
    assert lines[2].split()[3] == "—" and lines[3].split()[3] == "—"  # ambiguous mirror; the model's estimate has no height
    assert lines[4].split()[0] == "call03" and lines[4].split()[-1] == "False"


def test_an_uncalibrated_array_s_radii_carry_the_mics_table_s_survey_error(caplog):
    """Without a calibration the mics table's ``position_sigma_m`` becomes the radii's mic allowance (the largest mic's);
    a table without it is taken as a consumer GPS's (2 m per axis) and says so with the figure; a surveyed table (0s), a stated
    ``mic_position_m`` and a simulated field keep theirs."""
    from acoustlab.core.errors import ConfigError
    from acoustlab.stages.mic_survey import survey_allowance
    from acoustlab.toolkit.input_uncertainty import InputUncertainty

    stated = InputUncertainty()
    mics = pd.DataFrame({"x_m": [0.0, 30.0, 0.0], "y_m": [0.0, 0.0, 30.0], "z_m": [1.0, 1.0, 1.0]})
    surveyed = mics.assign(position_sigma_m=[0.0, 0.0, 0.0])
    gps = mics.assign(position_sigma_m=[1.5, 2.5, 2.0])
    with caplog.at_level("INFO", logger="acoustlab.stages.mic_survey"):
        assert survey_allowance(stated, gps, 3).mic_position_m == 2.5
        assert "up to 2.50 m" in caplog.text
        caplog.clear()
        assert survey_allowance(stated, surveyed, 3) == stated  # surveyed mics keep today's radii
        assert survey_allowance(stated, mics, 3).mic_position_m == 2.0 and "consumer GPS puts them, 2.00 m off per axis" in caplog.text
        assert survey_allowance(InputUncertainty(unsurveyed_mic_position_m=4.0), mics, 3).mic_position_m == 4.0
        caplog.clear()
        assert survey_allowance(stated, None, 3) == stated and not caplog.text  # a simulated field has no table
    given = InputUncertainty(mic_position_m=0.3)
    assert survey_allowance(given, gps, 3) == given  # the config's own statement is kept
    with pytest.raises(ConfigError, match=r"line 3, column 'position_sigma_m': .* is not a number >= 0"):
        survey_allowance(stated, mics.assign(position_sigma_m=[1.0, -2.0, 1.0]), 3)


@pytest.mark.slow
def test_localize_on_gps_surveyed_mics_widens_the_radii_and_records_the_allowance(compose_cfg, tmp_path):
    """Surveyed mics (``position_sigma_m`` 0) keep the simulation's radii; GPS-placed ones (3 m) widen them; a table without
    the column is taken as a consumer GPS's 2 m, recorded in ``metrics.json``."""
    _, overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 6)
    mics_csv = next(o.split("=", 1)[1] for o in overrides if o.startswith("field.mics_csv="))
    table = pd.read_csv(mics_csv)
    runs = {}
    for name, sigma in (("surveyed", 0.0), ("gps", 3.0), ("unsurveyed", None)):
        (table if sigma is None else table.assign(position_sigma_m=sigma)).to_csv(tmp_path / f"{name}.csv", index=False)
        given = [f"field.mics_csv={tmp_path / f'{name}.csv'}" if o.startswith("field.mics_csv=") else o for o in overrides]
        runs[name] = localize(compose_cfg, tmp_path / name, *given)
    allowance = {name: metrics["input_allowance"]["mic_position_m"] for name, (_, metrics, _) in runs.items()}
    assert allowance == {"surveyed": 0.0, "gps": 3.0, "unsurveyed": 2.0}
    exact, gps, unsurveyed = (runs[name][0] for name in ("surveyed", "gps", "unsurveyed"))
    placed = exact["placed"].to_numpy(bool) & gps["placed"].to_numpy(bool)
    radius = "radius_gdop_scaled_0.95_m"
    assert placed.any() and (gps[radius][placed] > unsurveyed[radius][placed]).all()
    assert (unsurveyed[radius][placed] > exact[radius][placed]).all()
    pd.testing.assert_series_equal(gps["x_m"], exact["x_m"])  # the positions themselves do not move


@pytest.mark.slow
def test_text_spot_ids_from_plan_playbacks_calibrate_the_radii_as_numbers_do(compose_cfg, tmp_path):
    """``plan_playbacks`` names its spots ``spot_01`` …: an events table with those ids places every detection exactly as
    the same table with numbered spots."""
    _, overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 10, known=6)
    events_csv = tmp_path / "recordings" / "events.csv"
    numbered, _, _ = localize(compose_cfg, tmp_path / "numbers", *overrides)
    events = pd.read_csv(events_csv)
    events["position_id"] = [f"spot_{k + 1:02d}" if k < 6 else "" for k in range(len(events))]
    events.to_csv(events_csv, index=False)
    named, metrics, _ = localize(compose_cfg, tmp_path / "names", *overrides)
    assert metrics["training"]["n_calibration_playbacks"] > 0
    pd.testing.assert_frame_equal(named, numbered)
