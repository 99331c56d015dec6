"""OpenSoundscape's localization test cases, ported: the same inputs and expectations, run against acoustlab.

Ported from the peer's public test suite (``tests/test_localization.py`` of kitzeslab/opensoundscape):
the inputs and the expected answers, not its code. Where acoustlab answers differently on purpose
the test says so: arrival times without a zero are accepted (only differences count) where the
peer raises.
"""

import numpy as np
import pandas as pd
import pytest

import acoustlab
from acoustlab.core.errors import DataError
from acoustlab.toolkit.physics import speed_of_sound_m_s


def test_speed_of_sound_at_20_c_is_343_m_s():
    """The peer's dry-air value; humid air is faster (acoustlab includes humidity: ~344 m/s at 50 %)."""
    assert speed_of_sound_m_s(20.0, 0.0) == pytest.approx(343.0, abs=1.0)
    assert 343.5 < speed_of_sound_m_s(20.0, 50.0) < 345.0


def test_sound_finder_2d_equal_arrivals_are_the_square_s_centre():
    receivers = np.array([[0, 0], [0, 20], [20, 20], [20, 0]], dtype=float)
    fix = acoustlab.solve(receivers, np.ones(4), source_height_m=0.0)
    assert np.hypot(fix["x_m"].iloc[0] - 10, fix["y_m"].iloc[0] - 10) < 0.01


@pytest.mark.parametrize("offset", [0.0, 100.0])  # the peer's centred and not-centred cases
def test_sound_finder_3d_equal_arrivals_at_uneven_heights(offset):
    receivers = np.array([[0, 0, 0], [0, 20, 1], [20, 20, -1], [20, 0, 0.1]], dtype=float) + [offset, 0, 0]
    fix = acoustlab.solve(receivers, np.ones(4), dimensions=3, fallback_2d=False)
    estimate = fix[["x_m", "y_m", "z_m"]].to_numpy()[0]
    assert np.linalg.norm(estimate - [offset + 10, 10, 0]) < 0.1


def test_arrival_times_without_a_zero_give_the_same_fix():
    """The peer's Gillette solver raises when no arrival time is 0; acoustlab takes any reference (only differences count)."""
    receivers = np.array([[100, 0], [100, 20], [120, 20], [120, 0], [110, 10]], dtype=float)
    source = np.array([113.0, 6.0])
    arrival = np.linalg.norm(receivers - source, axis=1) / 343.0
    fixes = [acoustlab.solve(receivers, arrival + shift, source_height_m=0.0)[["x_m", "y_m"]].to_numpy()[0] for shift in (0.0, 1.0)]
    np.testing.assert_allclose(fixes[0], source, atol=1e-6)
    np.testing.assert_allclose(fixes[1], fixes[0], atol=1e-6)


def test_gillette_2d_source_relative_to_the_first_arrival():
    receivers = np.array([[0, 0], [0, 20], [20, 20], [20, 0], [10, 10]], dtype=float)
    source = np.random.default_rng(0).random(2) * 20
    time_of_flight = np.linalg.norm(receivers - source, axis=1) / 343.0
    fix = acoustlab.solve(receivers, time_of_flight - time_of_flight.min(), source_height_m=0.0)
    np.testing.assert_allclose(fix[["x_m", "y_m"]].to_numpy()[0], source, rtol=0.1)


@pytest.mark.parametrize("reference", range(6))
def test_gillette_3d_with_each_receiver_as_reference(reference):
    """Every receiver in turn is the reference mic (mic 0): the 3-D fix is the source (the peer allows 2.5 m; exact here)."""
    receivers = np.array([[0, 0, 10], [0, 20, 1], [20, 20, -1], [20, 0, 0.1], [10, 10, 0], [5, 5, 5]], dtype=float)
    source = np.array([10.0, 12.0, 2.0])
    order = [reference, *[m for m in range(6) if m != reference]]
    time_of_flight = np.linalg.norm(receivers[order] - source, axis=1) / 343.0
    fix = acoustlab.solve(receivers[order], time_of_flight - time_of_flight[0], dimensions=3, fallback_2d=False)
    np.testing.assert_allclose(fix[["x_m", "y_m", "z_m"]].to_numpy()[0], source, atol=2.5)
    np.testing.assert_allclose(fix[["x_m", "y_m", "z_m"]].to_numpy()[0], source, atol=1e-4)


def _loca_folder(tmp_path):
    from tests.test_recordings import copy_example_audio

    mics = copy_example_audio(tmp_path)
    coords = pd.DataFrame(mics[["x_m", "y_m", "z_m"]].to_numpy(), columns=["x", "y", "z"], index=mics["file"].tolist())
    return mics, coords


def test_a_too_short_file_is_dropped_from_the_event_not_the_event(tmp_path, compose_cfg):
    """The peer's real-audio edge case: a seventh receiver whose file is shorter than the call is left out, and the event
    keeps the other six (here: placed from them, ``mics_dropped`` naming it)."""
    import soundfile as sf

    from tests.test_recordings import load_opensoundscape_layout

    mics, coords = _loca_folder(tmp_path)
    audio, fs = sf.read(tmp_path / mics["file"].iloc[0])
    sf.write(tmp_path / "veryshort.wav", audio[: int(0.05 * fs)], fs)
    coords.loc["veryshort.wav"] = [5.0, 5.0, 3.0]
    coords.to_csv(tmp_path / "aru_coords.csv")
    det = pd.DataFrame({"file": coords.index, "start_time": 0.2, "end_time": 0.5, "zeep": 1})
    det.to_csv(tmp_path / "det.csv", index=False)
    cfg_site = ["site.mics_csv=null", f"site.mics={coords.to_numpy().tolist()}".replace(" ", "")]
    batch, _ = load_opensoundscape_layout(compose_cfg, tmp_path, tmp_path / "aru_coords.csv", tmp_path / "det.csv", site=cfg_site)
    assert batch.events["mics_dropped"].iloc[0] == "6" and bool(batch.events["quality_ok"].iloc[0])
    assert "out_of_range" in batch.events["quality_flags"].iloc[0]


def test_the_peers_own_tables_with_a_heightless_too_short_file_place_the_call_without_it(tmp_path, compose_cfg, caplog):
    """The peer's own LOCA tables: a too-short seventh file whose coordinates row has no z, named by a detection. It is left
    out with its recorder, in one warning naming it, for the site (``+site=recordings``) and the field alike, and the call
    keeps the six good recorders and the reference time differences (the table was refused before)."""
    import soundfile as sf

    from acoustlab.stages.sites import site_from_config
    from tests.test_recordings import UPSTREAM_TDOA_S, load_opensoundscape_layout

    mics, coords = _loca_folder(tmp_path)
    audio, fs = sf.read(tmp_path / mics["file"].iloc[0])
    sf.write(tmp_path / "veryshort.wav", audio[: int(0.05 * fs)], fs)
    coords = coords.astype(object)
    coords.loc["veryshort.wav"] = [5.0, 5.0, ""]
    coords.to_csv(tmp_path / "aru_coords.csv")
    pd.DataFrame({"file": coords.index, "start_time": 0.2, "end_time": 0.5, "zeep": 1}).to_csv(tmp_path / "det.csv", index=False)
    tables = [f"field.coords_csv={tmp_path / 'aru_coords.csv'}", f"field.detections_csv={tmp_path / 'det.csv'}"]
    with caplog.at_level("WARNING", logger="acoustlab.toolkit.peer_tables"):
        site = site_from_config(compose_cfg(["+site=recordings", "field=recordings", f"field.audio_dir={tmp_path}", *tables]).site)
        batch, tdoa = load_opensoundscape_layout(
            compose_cfg,
            tmp_path,
            tmp_path / "aru_coords.csv",
            tmp_path / "det.csv",
            site=[f"site.mics={site.mic_positions_m.tolist()}".replace(" ", ""), "site.mics_csv=null"],
        )
    assert site.n_mics == 6 and "give no height (z)" in caplog.text and "veryshort.wav" in caplog.text
    assert batch.n_events == 1
    np.testing.assert_allclose(tdoa[0], UPSTREAM_TDOA_S, atol=1e-3)


def test_too_few_receivers_for_any_window_is_one_clear_line(tmp_path, compose_cfg):
    """The peer returns no events when min_n_receivers exceeds the receivers; acoustlab says so in one line."""
    from tests.test_recordings import load_opensoundscape_layout

    mics, coords = _loca_folder(tmp_path)
    coords.to_csv(tmp_path / "aru_coords.csv")
    pd.DataFrame({"file": coords.index, "start_time": 0.2, "end_time": 0.5, "zeep": 1}).to_csv(tmp_path / "det.csv", index=False)
    with pytest.raises(DataError, match="no time window was detected by at least field.min_receivers=10"):
        load_opensoundscape_layout(
            compose_cfg, tmp_path, tmp_path / "aru_coords.csv", tmp_path / "det.csv", extra=["field.min_receivers=10"]
        )


@pytest.mark.slow
def test_a_switching_users_three_tables_localize_without_editing(tmp_path, compose_cfg):
    """The peer's coordinates table (file as pandas' unnamed index), its detections with per-file absolute start times (one
    recorder started 0.1 s late) and a seventh receiver whose file is too short: localize places the call from the six
    good recorders, 3-D, where the shipped example's reference places it."""
    import soundfile as sf

    from acoustlab.run.app import run_experiment
    from tests.test_recordings import late_copy

    mics, coords = _loca_folder(tmp_path)
    late = late_copy(tmp_path, mics)
    audio, fs = sf.read(tmp_path / mics["file"].iloc[0])
    sf.write(tmp_path / "veryshort.wav", audio[: int(0.05 * fs)], fs)
    coords.loc["veryshort.wav"] = [5.0, 5.0, 3.0]
    coords.to_csv(tmp_path / "aru_coords.csv")
    start = pd.Series(pd.Timestamp("2021-09-24T06:52:00"), index=coords.index)
    start[late] += pd.Timedelta(seconds=0.1)
    det = pd.DataFrame({"file": coords.index, "start_time": 0.2, "end_time": 0.5, "zeep": 1})
    det.loc[det["file"] == late, ["start_time", "end_time"]] = [0.1, 0.4]
    det["start_timestamp"] = (start[det["file"]].to_numpy() + pd.to_timedelta(det["start_time"], unit="s").to_numpy()).astype(str)
    det.to_csv(tmp_path / "detections.csv", index=False)
    site = ["+site=loca2021", "site.mics_csv=null", f"site.mics={coords.to_numpy().tolist()}".replace(" ", "")]
    field = [f"field.audio_dir={tmp_path}", "field.mics_csv=null", "field.events_csv=null"]
    tables = [f"field.coords_csv={tmp_path / 'aru_coords.csv'}", f"field.detections_csv={tmp_path / 'detections.csv'}"]
    quick = ["+experiment=smoke", "tracking=none", "plots=false", "model.n_estimators=20", f"paths.outputs_dir={tmp_path / 'out'}"]
    cfg = compose_cfg(
        [
            *site,
            "protocol=localize",
            "field=recordings",
            *field,
            *tables,
            *quick,
            "features.gcc.band_hz=[6000,10500]",
            "solver.dimensions=3",
        ]
    )
    run_experiment(cfg, tmp_path / "run")
    (row,) = pd.read_parquet(tmp_path / "run" / "positions.parquet").to_dict("records")
    assert row["placed"] and row["mics_dropped"] == "6" and row["source"] == "solver"
    np.testing.assert_allclose([row["x_m"], row["y_m"]], [-2.22, 26.8], atol=1.0)  # the shipped example's fix (docs/localize.md)


def test_several_files_of_one_recorder_are_read_as_that_recorder(tmp_path, compose_cfg):
    """The peer's coordinates table lists one row per file: a recorder that made two files (0.1 s, then the rest) appears twice
    at one position. They are one mic whose clips are cut from the file recording at the time, so the time differences are the
    single-file ones, and ``+site=recordings`` takes the six recorders (not twelve files) from the same tables."""
    import soundfile as sf

    from acoustlab.stages.sites import site_from_config
    from tests.test_recordings import UPSTREAM_TDOA_S, load_opensoundscape_layout

    mics, _ = _loca_folder(tmp_path)
    rows, det = [], []
    origin = pd.Timestamp("2021-09-24T06:52:00")
    for name, x, y, z in mics[["file", "x_m", "y_m", "z_m"]].itertuples(index=False):
        audio, fs = sf.read(tmp_path / name)
        cut = int(0.1 * fs)
        for part, samples, start in (("a", audio[:cut], origin), ("b", audio[cut:], origin + pd.Timedelta(seconds=0.1))):
            file = f"{part}_{name}"
            sf.write(tmp_path / file, samples, fs)
            rows.append({"file": file, "x": x, "y": y, "z": z, "start_timestamp": start.isoformat()})
            det.append(
                {"file": file, "start_time": 0.1 if part == "b" else 0.0, "end_time": 0.4 if part == "b" else 0.1, "zeep": int(part == "b")}
            )
    pd.DataFrame(rows).set_index("file").to_csv(tmp_path / "aru_coords.csv")  # the file as pandas' unnamed index
    pd.DataFrame(det).to_csv(tmp_path / "det.csv", index=False)
    batch, tdoa = load_opensoundscape_layout(compose_cfg, tmp_path, tmp_path / "aru_coords.csv", tmp_path / "det.csv")
    assert batch.n_events == 1 and batch.events["quality_flags"].iloc[0] == ""
    np.testing.assert_allclose(tdoa[0], UPSTREAM_TDOA_S, atol=1e-3)
    cfg = compose_cfg(
        [
            "+site=recordings",
            "field=recordings",
            f"field.coords_csv={tmp_path / 'aru_coords.csv'}",
            f"field.detections_csv={tmp_path / 'det.csv'}",
        ]
    )
    np.testing.assert_allclose(site_from_config(cfg.site).mic_positions_m, mics[["x_m", "y_m", "z_m"]].to_numpy())
