"""Real recordings as input: acoustlab and OpenSoundscape layouts, and clear errors."""

import shutil

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.resources import PACKAGE_DATA
from acoustlab.run.registry import build, build_feature_sets
from acoustlab.stages.dataset import extract_features
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import tdoa_matrix

EXAMPLE = PACKAGE_DATA / "examples" / "loca2021"
UPSTREAM_TDOA_S = [0.0, 0.0325, -0.002, 0.0316, -0.0086, 0.024]
BAND = ["features.gcc.band_hz=[6000,10500]"]  # one GCC band for the tdoa, xcorr and uncertainty groups


def test_shipped_real_array_gives_the_reference_tdoas(compose_cfg):
    cfg = compose_cfg(["+site=loca2021", "field=recordings", *BAND])
    site = site_from_config(cfg.site)
    batch = build(cfg.field, "field").load(site)
    assert batch.audio.shape[:2] == (1, 6) and np.isnan(batch.true_position_m).all()
    table = extract_features(batch, site, build_feature_sets(cfg.features))
    np.testing.assert_allclose(tdoa_matrix(table, 6)[0], UPSTREAM_TDOA_S, atol=1e-3)


def copy_example_audio(folder):
    """The shipped LOCA recordings copied into ``folder``; the example's mics table."""
    mics = pd.read_csv(EXAMPLE / "mics.csv")
    for f in mics["file"]:
        shutil.copy(EXAMPLE / f, folder / f)
    return mics


def load_opensoundscape_layout(compose_cfg, folder, coords_csv, detections_csv, site=(), extra=()):
    """The LOCA example read from OpenSoundscape-layout tables: the batch, and the features' TDOA matrix (``site``, ``extra``: overrides)."""
    cfg = compose_cfg(
        [
            "+site=loca2021",
            "field=recordings",
            f"field.audio_dir={folder}",
            "field.mics_csv=null",
            "field.events_csv=null",
            f"field.coords_csv={coords_csv}",
            f"field.detections_csv={detections_csv}",
            *BAND,
            *site,
            *extra,
        ]
    )
    site = site_from_config(cfg.site)
    batch = build(cfg.field, "field").load(site)
    return batch, tdoa_matrix(extract_features(batch, site, build_feature_sets(cfg.features)), site.n_mics)


def test_opensoundscape_layout(tmp_path, compose_cfg):
    mics = copy_example_audio(tmp_path)
    pd.DataFrame({"file": mics["file"], "x": mics["x_m"], "y": mics["y_m"], "z": mics["z_m"]}).to_csv(tmp_path / "coords.csv", index=False)
    det = pd.DataFrame({"file": mics["file"], "start_time": 0.2, "end_time": 0.5, "zeep": 1})
    det = pd.concat([det, pd.DataFrame({"file": mics["file"][:2], "start_time": 0.6, "end_time": 0.8, "zeep": 1})])
    det.to_csv(tmp_path / "detections.csv", index=False)
    batch, tdoa = load_opensoundscape_layout(compose_cfg, tmp_path, tmp_path / "coords.csv", tmp_path / "detections.csv")
    assert batch.n_events == 1  # the second window has only 2 receivers (< min_receivers=3)
    np.testing.assert_allclose(tdoa[0], UPSTREAM_TDOA_S, atol=1e-3)


def test_the_peers_own_coordinates_table_with_its_index_and_an_unused_recorder(tmp_path, compose_cfg):
    """OpenSoundscape writes aru_coords.csv with the file as pandas' unnamed index column; a recorder no detection names
    (whose row may lack a z) is not a mic."""
    mics = copy_example_audio(tmp_path)
    coords = pd.DataFrame(mics[["x_m", "y_m", "z_m"]].to_numpy(), columns=["x", "y", "z"], index=mics["file"].tolist())
    coords.loc["unused_recorder.wav"] = [5.0, 5.0, np.nan]  # listed, never detected, no z
    coords.to_csv(tmp_path / "aru_coords.csv")  # the peer's way: the index as an unnamed first column
    assert (tmp_path / "aru_coords.csv").read_text().startswith(",x,y,z")
    pd.DataFrame({"file": mics["file"], "start_time": 0.2, "end_time": 0.5, "zeep": 1}).to_csv(tmp_path / "det.csv", index=False)
    batch, tdoa = load_opensoundscape_layout(compose_cfg, tmp_path, tmp_path / "aru_coords.csv", tmp_path / "det.csv")
    assert batch.audio.shape[:2] == (1, 6)
    np.testing.assert_allclose(tdoa[0], UPSTREAM_TDOA_S, atol=1e-3)


def test_bad_inputs_are_named(tmp_path, compose_cfg):
    cfg = compose_cfg(["+site=loca2021", "field=recordings", "field.mics_csv=null"])
    with pytest.raises(ConfigError, match="mics_csv and events_csv"):
        build(cfg.field, "field")
    events = tmp_path / "events.csv"
    events.write_text("event_id,start\n0,0.2\n")
    cfg = compose_cfg(["+site=loca2021", "field=recordings", f"field.events_csv={events}"])
    with pytest.raises(DataError, match=r"events.csv lacks columns \['start_s', 'end_s'\]"):
        build(cfg.field, "field").load(site_from_config(cfg.site))
    cfg = compose_cfg(["+site=frozen_lake", "field=recordings"])
    with pytest.raises(DataError, match="do not match site 'frozen_lake'"):
        build(cfg.field, "field").load(site_from_config(cfg.site))


def test_an_events_table_with_its_own_bands_runs_each_gcc_in_its_band(tmp_path, compose_cfg):
    """low_hz/high_hz per event (as in a detector table): checked against the files' Nyquist, and the GCC runs in the band."""
    from acoustlab.run.registry import build_feature_sets
    from acoustlab.stages.dataset import extract_features

    audio = "acoustlab://examples/loca2021"
    wide, narrow, bad = (tmp_path / f"{name}.csv" for name in ("wide", "narrow", "bad"))
    wide.write_text("event_id,start_s,end_s\n0,0.2,0.5\n")
    narrow.write_text("event_id,start_s,end_s,low_hz,high_hz\n0,0.2,0.5,6000,10500\n")
    bad.write_text("event_id,start_s,end_s,low_hz,high_hz\n0,0.2,0.5,6000,60000\n")
    site = site_from_config(compose_cfg(["+site=loca2021"]).site)
    lags = {}
    for table in (wide, narrow):
        cfg = compose_cfg(
            [
                "+site=loca2021",
                "field=recordings",
                f"field.audio_dir={audio}",
                f"field.events_csv={table}",
                "features.gcc.band_hz=[300,10000]",
            ]
        )
        batch = build(cfg.field, "field").load(site)
        lags[table.stem] = extract_features(batch, site, build_feature_sets(cfg.features))["tdoa__lag_0_1_s"].iloc[0]
    assert lags["narrow"] != lags["wide"]  # the insect band at 4.5 kHz no longer dominates the GCC
    cfg = compose_cfg(["+site=loca2021", "field=recordings", f"field.audio_dir={audio}", f"field.events_csv={bad}"])
    with pytest.raises(DataError, match=r"line 2, column 'high_hz': 60000 is not a number or empty in \[0.0, 12000.0\]"):
        build(cfg.field, "field").validate(site)


def late_copy(folder, mics, late_s=0.1):
    """The LOCA example with mic 2's file starting ``late_s`` later (its first samples cut), as a recorder switched on late."""
    import soundfile as sf

    late = mics["file"].iloc[2]
    audio, fs = sf.read(folder / late)
    sf.write(folder / late, audio[int(round(late_s * fs)) :], fs)
    return late


@pytest.mark.parametrize("where", ["coords", "detections", "opso_metadata"])
def test_per_file_start_times_of_the_peers_tables_are_honoured(tmp_path, compose_cfg, where):
    """A file that starts 0.1 s late, its detection window in its own time (0.1–0.4 s where the others say 0.2–0.5 s): with
    its start time in the coordinates table, the detections' absolute start_timestamp, or (as OpenSoundscape writes it)
    each WAV's ``opso_metadata`` comment with no start column in any table, the clip is cut at the same moment and the
    time differences are the reference ones; without, they would be 0.1 s off (−35 ms where +24 ms is right)."""
    mics = copy_example_audio(tmp_path)
    late = late_copy(tmp_path, mics)
    start = pd.Series(pd.Timestamp("2021-05-01T06:00:00"), index=mics["file"])
    start[late] += pd.Timedelta(seconds=0.1)
    coords = pd.DataFrame({"file": mics["file"], "x": mics["x_m"], "y": mics["y_m"], "z": mics["z_m"]})
    det = pd.DataFrame({"file": mics["file"], "start_time": 0.2, "end_time": 0.5, "zeep": 1})
    det.loc[det["file"] == late, ["start_time", "end_time"]] = [0.1, 0.4]
    if where == "coords":
        coords["start_timestamp"] = start.dt.strftime("%Y-%m-%dT%H:%M:%S.%f").to_numpy()
    elif where == "opso_metadata":
        for f in mics["file"]:
            _with_opso_start(tmp_path / f, start[f].tz_localize("-04:00").isoformat())
    else:
        absolute = start[det["file"]].to_numpy() + pd.to_timedelta(det["start_time"], unit="s").to_numpy()
        det["start_timestamp"] = pd.Series(absolute).dt.strftime("%Y-%m-%dT%H:%M:%S.%f").to_numpy()
    coords.to_csv(tmp_path / "coords.csv", index=False)
    det.to_csv(tmp_path / "det.csv", index=False)
    batch, tdoa = load_opensoundscape_layout(compose_cfg, tmp_path, tmp_path / "coords.csv", tmp_path / "det.csv")
    assert batch.n_events == 1 and not batch.events["quality_flags"].iloc[0]
    np.testing.assert_allclose(tdoa[0], UPSTREAM_TDOA_S, atol=1e-3)


def test_start_times_written_by_the_recorders_are_read(tmp_path):
    """AudioMoth's comment (with its zone), a GUANO Timestamp and a Broadcast WAV TimeReference give each file's start."""
    import struct

    import soundfile as sf

    from acoustlab.toolkit.file_start import file_start_time, start_from_metadata

    def with_chunk(path, name, body):
        data = path.read_bytes()
        chunk = name + struct.pack("<I", len(body)) + body + b"\x00" * (len(body) % 2)
        data = data[:12] + chunk + data[12:]
        path.write_bytes(data[:4] + struct.pack("<I", len(data) - 8) + data[8:])

    tone = np.zeros(800, dtype=np.float32)
    moth = tmp_path / "moth.wav"
    with sf.SoundFile(moth, "w", samplerate=8000, channels=1) as f:
        f.comment = "Recorded at 05:30:00 01/05/2026 (UTC+2) by AudioMoth 24F319 at medium gain"
        f.write(tone)
    assert start_from_metadata(moth) == pd.Timestamp("2026-05-01T03:30:00")
    guano = tmp_path / "guano.wav"
    sf.write(guano, tone, 8000)
    with_chunk(guano, b"guan", b"GUANO|Version: 1.0\nTimestamp: 2026-05-01T05:30:00.250-04:00\n")
    assert start_from_metadata(guano) == pd.Timestamp("2026-05-01T09:30:00.250")
    bwf = tmp_path / "bwf.wav"
    sf.write(bwf, tone, 8000)
    body = bytearray(602)
    body[320:330], body[330:338] = b"2026-05-01", b"05:30:00"
    body[338:346] = struct.pack("<II", 5 * 3600 * 8000 + 30 * 60 * 8000 + 4, 0)  # 05:30:00 and 4 samples (0.5 ms)
    with_chunk(bwf, b"bext", bytes(body))
    assert start_from_metadata(bwf) == pd.Timestamp("2026-05-01T05:30:00.0005")
    named = tmp_path / "20260501_053000.wav"
    sf.write(named, tone, 8000)
    assert start_from_metadata(named) is None and file_start_time(named) == pd.Timestamp("2026-05-01T05:30:00")
    assert file_start_time(tmp_path / "moth.wav") == pd.Timestamp("2026-05-01T03:30:00")  # metadata before the name
    sf.write(tmp_path / "plain.wav", tone, 8000)
    assert file_start_time(tmp_path / "plain.wav") is None


def test_windows_of_files_starting_apart_link_without_chaining():
    """Fixed 3-s windows of two files 0.1 s apart: each call's windows link across files; consecutive windows stay apart."""
    from plugins.fields.recordings import linked_windows

    files = np.array(["a", "a", "a", "b", "b", "b"])
    start = np.array([0.0, 3.0, 6.0, 0.1, 3.1, 6.1])
    windows = linked_windows(files, start, start + 3.0)
    assert windows["n_files"].tolist() == [2, 2, 2] and windows["start_s"].tolist() == [0.0, 3.0, 6.0]


def _linked_windows_by_every_pair(recorders: np.ndarray, start_s: np.ndarray, end_s: np.ndarray) -> list[tuple]:
    """The rule of ``linked_windows`` written out plainly: each anchor against every window (the reference)."""
    order = np.lexsort((end_s, start_s))
    linked = np.zeros(len(recorders), dtype=bool)
    rows = []
    for anchor in order:
        if linked[anchor]:
            continue
        linked[anchor] = True
        members = {recorders[anchor]}
        lo, hi = start_s[anchor], end_s[anchor]
        overlap = np.minimum(end_s, hi) - np.maximum(start_s, lo)
        enough = ~linked & (overlap >= 0.5 * np.minimum(end_s - start_s, hi - lo)) & (overlap > 0)
        for k in np.flatnonzero(enough)[np.argsort(-overlap[enough], kind="stable")]:
            if recorders[k] not in members:
                members.add(recorders[k])
                linked[k] = True
        rows.append((lo, hi, len(members)))
    return rows


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 60), st.sampled_from([0.5, 1.0, 3.0]))
def test_linked_windows_sweep_links_as_every_pair_would(seed, n, grid_s):
    """Windows on a coarse grid (many ties of start, end and overlap) from 4 recorders: the sweep gives the reference's events."""
    from plugins.fields.recordings import linked_windows

    rng = np.random.default_rng(seed)
    recorders = rng.integers(0, 4, n)
    start = rng.integers(0, 20, n) * grid_s / 2
    end = start + rng.integers(1, 5, n) * grid_s / 2
    got = linked_windows(recorders, start, end)
    assert list(got.itertuples(index=False, name=None)) == _linked_windows_by_every_pair(recorders, start, end)


def test_a_mics_table_with_each_files_start_time(tmp_path, compose_cfg):
    """acoustlab's layout: ``start_time`` per mic file, events in seconds from the earliest file's start."""
    mics = copy_example_audio(tmp_path)
    late = late_copy(tmp_path, mics)
    mics["start_time"] = np.where(mics["file"] == late, "2021-05-01T06:00:00.100", "2021-05-01T06:00:00")
    mics.to_csv(tmp_path / "mics.csv", index=False)
    cfg = compose_cfg(
        ["+site=loca2021", "field=recordings", f"field.audio_dir={tmp_path}", f"field.mics_csv={tmp_path / 'mics.csv'}", *BAND]
    )
    site = site_from_config(cfg.site)
    batch = build(cfg.field, "field").load(site)
    np.testing.assert_allclose(
        tdoa_matrix(extract_features(batch, site, build_feature_sets(cfg.features)), 6)[0], UPSTREAM_TDOA_S, atol=1e-3
    )
    mics.loc[0, "start_time"] = "yesterday"
    mics.to_csv(tmp_path / "mics.csv", index=False)
    with pytest.raises(DataError, match=r"line 2, column start_time: 'yesterday' is not an ISO 8601 time"):
        build(cfg.field, "field").load(site)


def test_a_file_whose_header_misstates_its_rate_is_named_by_its_duration(tmp_path, compose_cfg):
    """One mic's file holds its samples under twice their rate (a 48 kHz header on 24 kHz samples would last half as long):
    the preflight names it by comparing the array's durations; a file that is merely a little shorter passes."""
    import soundfile as sf

    mics = copy_example_audio(tmp_path)
    mics.to_csv(tmp_path / "mics.csv", index=False)
    wrong = mics["file"].iloc[3]
    audio, fs = sf.read(tmp_path / wrong)
    sf.write(tmp_path / wrong, audio, 2 * fs)
    cfg = compose_cfg(["+site=loca2021", "field=recordings", f"field.audio_dir={tmp_path}", f"field.mics_csv={tmp_path / 'mics.csv'}"])
    with pytest.raises(DataError, match=rf"{wrong} lasts .* header's {2 * fs:g} Hz is likely wrong \({fs:g} Hz would make it"):
        build(cfg.field, "field").validate(site_from_config(cfg.site))
    sf.write(tmp_path / wrong, audio[: int(0.9 * len(audio))], fs)  # cut short: a recorder that stopped early
    build(cfg.field, "field").validate(site_from_config(cfg.site))


def test_a_localize_too_large_for_the_memory_available_is_refused_before_it_starts(tmp_path, compose_cfg, monkeypatch):
    """The preflight compares the features' expected peak (8 × the audio array) with the memory available: one line."""
    from plugins.fields import recordings

    cfg = compose_cfg(["+site=loca2021", "field=recordings"])
    site = site_from_config(cfg.site)
    monkeypatch.setattr(recordings, "available_memory_bytes", lambda: 1000)
    with pytest.raises(DataError, match=r"need about .* GiB while their features are computed, and 0.0 GiB is available"):
        build(cfg.field, "field").validate(site)
    monkeypatch.setattr(recordings, "available_memory_bytes", lambda: None)  # unknown (not Linux): no refusal
    build(cfg.field, "field").validate(site)


def test_the_tables_are_read_once_until_a_table_file_changes(tmp_path, compose_cfg, monkeypatch):
    from plugins.fields.recordings import RecordingFolder

    mics = copy_example_audio(tmp_path)
    mics.to_csv(tmp_path / "mics.csv", index=False)
    cfg = compose_cfg(["+site=loca2021", "field=recordings", f"field.audio_dir={tmp_path}", f"field.mics_csv={tmp_path / 'mics.csv'}"])
    folder = build(cfg.field, "field")
    reads = []
    original = RecordingFolder._read_tables
    monkeypatch.setattr(RecordingFolder, "_read_tables", lambda self: reads.append(1) or original(self))
    first, _ = folder.tables()
    first.loc[0, "file"] = "changed by the caller"  # a copy: the next call is unaffected
    again, _ = folder.tables()
    assert len(reads) == 1 and again.loc[0, "file"] != "changed by the caller"
    mics.assign(mic_id=[f"m{k}" for k in range(len(mics))]).to_csv(tmp_path / "mics.csv", index=False)
    assert folder.tables()[0]["mic_id"].iloc[0] == "m0" and len(reads) == 2


def test_the_peers_start_timestamps_mixing_naive_and_zoned_times_stop_in_one_line(tmp_path, compose_cfg):
    """Read as UTC, a naive time beside zoned ones would be off by the zone (2 h here) and every clip lost without a
    word: the column is refused, naming the line."""
    mics = copy_example_audio(tmp_path)
    coords = pd.DataFrame({"file": mics["file"], "x": mics["x_m"], "y": mics["y_m"], "z": mics["z_m"]})
    det = pd.DataFrame({"file": mics["file"], "start_time": 0.2, "end_time": 0.5, "zeep": 1})
    det["start_timestamp"] = "2021-05-01T06:00:00.200000+02:00"
    det.loc[2, "start_timestamp"] = "2021-05-01T06:00:00.200000"
    coords.to_csv(tmp_path / "coords.csv", index=False)
    det.to_csv(tmp_path / "det.csv", index=False)
    with pytest.raises(DataError, match="line 4, column start_timestamp: '2021-05-01T06:00:00.200000' lacks a UTC offset and line 2 does"):
        load_opensoundscape_layout(compose_cfg, tmp_path, tmp_path / "coords.csv", tmp_path / "det.csv")


def _with_opso_start(path, start: str) -> None:
    """Rewrite ``path`` with OpenSoundscape's comment (``Audio.save``'s opso_metadata v0.1) giving ``start``."""
    import json

    import soundfile as sf

    audio, fs = sf.read(path)
    with sf.SoundFile(path, "w", samplerate=fs, channels=1 if audio.ndim == 1 else audio.shape[1]) as f:
        f.comment = "opso_metadata" + json.dumps({"opso_metadata_version": "v0.1", "recording_start_time": start})
        f.write(audio)


def test_an_opso_comment_gives_its_start_in_utc_and_a_broken_one_is_named(tmp_path):
    import soundfile as sf

    from acoustlab.core.errors import DataError
    from acoustlab.toolkit.file_start import opso_start, start_from_metadata

    assert opso_start('opso_metadata{"opso_metadata_version": "v0.1", "recording_start_time": "2021-05-01T06:00:00-04:00"}') == (
        pd.Timestamp("2021-05-01T10:00:00")
    )
    assert opso_start("Recorded at 05:30:00 01/05/2026 (UTC) by AudioMoth") is None
    assert opso_start('opso_metadata{"opso_metadata_version": "v0.1"}') is None  # no start given: the file's name may say
    broken = tmp_path / "broken.wav"
    sf.write(broken, np.zeros(800), 8000)
    with sf.SoundFile(broken, "w", samplerate=8000, channels=1) as f:
        f.comment = 'opso_metadata{"recording_start_time": "yesterday"}'
        f.write(np.zeros(800))
    with pytest.raises(DataError, match=r"broken\.wav: an OpenSoundscape comment's recording_start_time 'yesterday'"):
        start_from_metadata(broken)
