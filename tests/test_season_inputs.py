"""Season inputs: recordings indexed by absolute time, clips stitched across files, detector tables, events."""

import shutil

import numpy as np
import pandas as pd
import pytest
import soundfile as sf
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.core.errors import DataError
from acoustlab.season.detections import read_detections
from acoustlab.season.events import group_detections
from acoustlab.season.recorder_files import RecorderFiles, timestamp_from_name
from acoustlab.season.weather import read_weather, weather_at

FS = 8000


def write_files(folder, recorder, starts, lengths, rng, gap_after=None):
    """Files of one recorder named by their start (seconds after 2026-05-01 05:00:00); returns the samples joined end to end."""
    (folder / recorder).mkdir(parents=True, exist_ok=True)
    joined = []
    for start, n in zip(starts, lengths, strict=True):
        samples = rng.uniform(-0.5, 0.5, n).astype(np.float32)
        name = f"{pd.Timestamp('2026-05-01 05:00:00') + pd.Timedelta(seconds=start):%Y%m%d_%H%M%S}.wav"
        sf.write(folder / recorder / name, samples, FS, subtype="FLOAT")
        joined.append(samples)
    return np.concatenate(joined)


@pytest.fixture(scope="module")
def season_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("audio")
    rng = np.random.default_rng(0)
    joined = write_files(folder, "A", [0, 10, 20], [10 * FS] * 3, rng)
    write_files(folder, "B", [0, 30], [10 * FS, 10 * FS], rng)  # B has a gap from 10 s to 30 s
    return folder, joined


@settings(max_examples=40, deadline=None)
@given(start=st.floats(0.0, 29.0), length=st.floats(0.01, 12.0))
def test_a_clip_across_file_boundaries_equals_the_clip_from_one_joined_file(season_files, start, length):
    folder, joined = season_files
    files = RecorderFiles.from_file_names(folder)
    n = int(round(length * FS))
    clip = files.read("A", start, n)
    first = int(round(start * FS))
    expected = np.zeros(n, np.float32)
    available = joined[first : first + n]
    expected[: available.size] = available
    np.testing.assert_array_equal(clip.samples, expected)
    assert clip.flags == ([] if first + n <= joined.size else ["out_of_range"])
    files.close()


@pytest.mark.parametrize("subtype", ["PCM_16", "PCM_24", "FLOAT"])
def test_clips_read_from_any_wav_subtype_equal_libsndfiles_floats(tmp_path, subtype):
    """16-bit PCM is read as integers and scaled in numpy (the fast path); every subtype gives libsndfile's own floats."""
    rng = np.random.default_rng(4)
    for recorder, start in (("A", 0), ("A", 10), ("B", 0)):
        (tmp_path / recorder).mkdir(exist_ok=True)
        samples = rng.uniform(-1.0, 1.0, (10 * FS, 2)).astype(np.float32)
        samples[:5] = [[-1.0, 1.0]]  # full scale both ways
        name = f"{pd.Timestamp('2026-05-01 05:00:00') + pd.Timedelta(seconds=start):%Y%m%d_%H%M%S}.wav"
        sf.write(tmp_path / recorder / name, samples, FS, subtype=subtype)
    files = RecorderFiles.from_file_names(tmp_path)
    as_float = [sf.read(tmp_path / "A" / f"20260501_0500{s:02d}.wav", dtype="float32")[0] for s in (0, 10)]
    joined = np.concatenate(as_float)[:, 0]
    for start_s, n in ((0.0, 100), (9.5, FS), (3.25, 2 * FS)):  # the second clip crosses the file boundary
        first = int(round(start_s * FS))
        np.testing.assert_array_equal(files.read("A", start_s, n).samples, joined[first : first + n])
    files.close()


def test_gaps_and_times_outside_the_recordings_are_flagged(season_files):
    files = RecorderFiles.from_file_names(season_files[0])
    across_gap = files.read("B", 9.5, FS)  # 9.5–10.5 s: the second half is in B's gap
    assert across_gap.flags == ["gap"] and not across_gap.samples[FS // 2 + 1 :].any() and across_gap.samples[: FS // 2].any()
    assert files.read("B", 45.0, FS).flags == ["out_of_range"]
    assert files.read("A", 5.0, FS).flags == []
    assert files.origin == pd.Timestamp("2026-05-01 05:00:00")
    # a detection at the recordings' very start: the clip's context before it lies outside them and flags nothing, while a
    # clip whose own span (inside the context) is missing still does
    quarter = FS // 4
    assert files.read("A", -0.25, FS + 2 * quarter, context=quarter).flags == []
    assert files.read("A", -0.25, FS + 2 * quarter).flags == ["out_of_range"]
    assert files.read("A", -0.5, FS + 2 * quarter, context=quarter).flags == ["out_of_range"]
    assert files.read("B", 9.9, FS // 5, context=FS // 10).flags == []  # only the context reaches into the gap


def test_a_damaged_stretch_of_a_flac_file_flags_its_clips_and_the_rest_is_read(tmp_path):
    """A decoder error inside a file costs the clips that touch it (flagged ``unreadable``, not placed), not the season."""
    (tmp_path / "A").mkdir()
    rng = np.random.default_rng(3)
    samples = rng.uniform(-0.5, 0.5, 20 * FS).astype(np.float32)
    path = tmp_path / "A" / "20260501_050000.flac"
    sf.write(path, samples, FS)
    files = RecorderFiles.from_file_names(tmp_path)
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 3000] = rng.integers(0, 256, 3000, dtype=np.uint8).tobytes()  # garbage in the middle frames
    path.write_bytes(bytes(data))
    damaged = files.read("A", 9.0, 2 * FS)
    assert len(damaged.flags) == 1 and damaged.flags[0].startswith("unreadable (20260501_050000.flac: ")
    assert not damaged.samples.any()
    early = files.read("A", 0.5, FS)  # before the damage: read as written
    assert early.flags == [] and np.allclose(early.samples, samples[FS // 2 : FS // 2 + FS], atol=1e-4)
    files.close()


def test_bad_timestamps_stop_with_one_line_naming_the_file(tmp_path):
    (tmp_path / "A").mkdir()
    sf.write(tmp_path / "A" / "morning_take.wav", np.zeros(100, np.float32), FS)
    with pytest.raises(DataError, match="morning_take.wav.*holds no start time"):
        RecorderFiles.from_file_names(tmp_path)
    with pytest.raises(DataError, match="20261341_050000.wav"):
        timestamp_from_name("20261341_050000.wav")  # month 13
    table = tmp_path / "files.csv"
    table.write_text("recorder_id,file,start_time\nA,A/morning_take.wav,yesterday at dawn\n")
    with pytest.raises(DataError, match="line 2, column start_time: 'yesterday at dawn'"):
        RecorderFiles.from_table(table)


def test_recorders_at_different_rates_are_read_each_at_its_own(tmp_path):
    """Recorder B runs at twice A's rate: each reads its own samples for a time window (resampled later to the method's
    rate); the index survives a save and load; one recorder's files at two rates stop the run naming one."""
    import scipy.signal as ss

    from acoustlab.season.stream import _clip
    from acoustlab.toolkit.quality import QualityThresholds

    t = np.arange(10 * FS) / FS
    tone = (0.3 * np.sin(2 * np.pi * 440 * t)).astype(np.float32)
    for recorder, rate in (("A", FS), ("B", 2 * FS)):
        (tmp_path / recorder).mkdir()
        signal = tone if rate == FS else ss.resample_poly(tone, 2, 1).astype(np.float32)
        sf.write(tmp_path / recorder / "20260501_050000.wav", signal, rate, subtype="FLOAT")
    files = RecorderFiles.from_file_names(tmp_path)
    assert (files.rate_of("A"), files.rate_of("B"), files.sample_rate_hz) == (FS, 2 * FS, FS)
    assert files.read("B", 2.0, 2 * FS).samples.size == 2 * FS and files.table[files.table["recorder_id"] == "B"]["end_s"].iloc[0] == 10.0
    a, _ = _clip(files, "A", 2.0, 1.0, FS, QualityThresholds())
    b, _ = _clip(files, "B", 2.0, 1.0, FS, QualityThresholds())
    np.testing.assert_allclose(b[200:-200], a[200:-200], atol=0.01)  # the same tone at the method's rate
    files.save(tmp_path / "files.parquet")
    assert RecorderFiles.load(tmp_path / "files.parquet").rate_of("B") == 2 * FS
    sf.write(tmp_path / "A" / "20260501_050010.wav", tone, 2 * FS, subtype="FLOAT")
    with pytest.raises(DataError, match=r"recorder A's files differ in sample rate .*20260501_050010.wav"):
        RecorderFiles.from_file_names(tmp_path)


def test_overlapping_files_of_one_recorder_are_refused(tmp_path):
    rng = np.random.default_rng(1)
    write_files(tmp_path, "A", [0, 5], [10 * FS, 10 * FS], rng)  # the second starts 5 s into the first
    with pytest.raises(DataError, match="recorder A: .* starts at .* before .* ends"):
        RecorderFiles.from_file_names(tmp_path)


def test_files_table_with_iso_times_and_the_saved_index(tmp_path, season_files):
    folder, _ = season_files
    table = tmp_path / "files.csv"
    rows = ["recorder_id,file,start_time"] + [
        f"A,{p},{t}"
        for p, t in (
            (folder / "A" / "20260501_050000.wav", "2026-05-01T05:00:00"),
            (folder / "A" / "20260501_050010.wav", "2026-05-01T05:00:10+00:00"),
        )
    ]
    table.write_text("\n".join(rows) + "\n")
    with pytest.raises(DataError, match="line 3, column start_time: '2026-05-01T05:00:10\\+00:00' has a UTC offset and line 2 does not"):
        RecorderFiles.from_table(table)
    table.write_text("\n".join(rows).replace("+00:00", "") + "\n")
    files = RecorderFiles.from_table(table)
    assert files.table["start_s"].tolist() == [0.0, 10.0]
    files.save(tmp_path / "index.parquet")
    again = RecorderFiles.load(tmp_path / "index.parquet")
    np.testing.assert_array_equal(again.read("A", 9.0, 2 * FS).samples, files.read("A", 9.0, 2 * FS).samples)


@pytest.fixture
def two_recorders(tmp_path):
    rng = np.random.default_rng(2)
    write_files(tmp_path / "audio", "R0", [0, 60], [60 * FS, 60 * FS], rng)
    write_files(tmp_path / "audio", "R1", [0, 60], [60 * FS, 60 * FS], rng)
    return tmp_path, RecorderFiles.from_file_names(tmp_path / "audio")


def raven_table(path, rows):
    header = "Selection\tView\tChannel\tBegin Time (s)\tEnd Time (s)\tLow Freq (Hz)\tHigh Freq (Hz)\tBegin File\tFile Offset (s)\tSpecies"
    lines = [header]
    for k, (begin_file, offset, duration, species) in enumerate(rows, start=1):
        for view in ("Spectrogram 1", "Waveform 1"):  # Raven repeats every selection per view
            lines.append(f"{k}\t{view}\t1\t{offset}\t{offset + duration}\t1000\t3000\t{begin_file}\t{offset}\t{species}")
    path.write_text("\n".join(lines) + "\n")


def test_raven_tables_per_recorder_place_selections_by_file_start_and_offset(two_recorders):
    folder, files = two_recorders
    raven_table(
        folder / "R0.Table.1.selections.txt", [("20260501_050000.wav", 12.0, 0.5, "wren"), ("20260501_050100.wav", 3.0, 0.4, "tit")]
    )
    raven_table(folder / "R1.Table.1.selections.txt", [("20260501_050000.wav", 12.1, 0.5, "wren")])
    det = read_detections([folder / "R0.Table.1.selections.txt", folder / "R1.Table.1.selections.txt"], "raven", files)
    assert det[["recorder_id", "start_s", "label"]].values.tolist() == [["R0", 12.0, "wren"], ["R1", 12.1, "wren"], ["R0", 63.0, "tit"]]
    assert det["low_hz"].tolist() == [1000.0] * 3 and np.allclose(det["end_s"] - det["start_s"], [0.5, 0.5, 0.4])
    only = read_detections([folder / "R0.Table.1.selections.txt"], "raven", files, classes=["tit"])
    assert only["label"].tolist() == ["tit"]


def test_a_selection_beginning_outside_its_file_is_named_and_left_out(two_recorders, caplog):
    """A begin time before its file or 99,999 s into a 60-s file: never a call in it; one warning names the table, the
    first such line and the file's length, and the other selections are kept."""
    folder, files = two_recorders
    rows = [
        ("20260501_050000.wav", 12.0, 0.5, "wren"),
        ("20260501_050000.wav", 99999.0, 0.5, "wren"),
        ("20260501_050100.wav", -3.0, 0.5, "tit"),
    ]
    raven_table(folder / "R0.Table.1.selections.txt", rows)
    with caplog.at_level("WARNING"):
        det = read_detections([folder / "R0.Table.1.selections.txt"], "raven", files)
    assert det["start_s"].tolist() == [12.0]
    assert "2 row(s) of" in caplog.text and "line 4: 99999.000 s into 20260501_050000.wav, which is 60.000 s long" in caplog.text


def test_one_raven_table_for_all_recorders_needs_a_recorder_column(two_recorders):
    folder, files = two_recorders
    raven_table(folder / "all.txt", [("20260501_050000.wav", 12.0, 0.5, "wren")])
    with pytest.raises(DataError, match="file name '20260501_050000.wav' is used by recorders R0, R1"):
        read_detections([folder / "all.txt"], "raven", files)
    table = pd.read_csv(folder / "all.txt", sep="\t").assign(Recorder="R1")
    table.to_csv(folder / "all.txt", sep="\t", index=False)
    assert read_detections([folder / "all.txt"], "raven", files, recorder_column="Recorder")["recorder_id"].tolist() == ["R1"]


def test_birdnet_and_opensoundscape_tables_with_class_and_score_thresholds(two_recorders):
    folder, files = two_recorders
    (folder / "R0").mkdir()
    pd.DataFrame(
        {
            "Start (s)": [0.0, 3.0, 6.0],
            "End (s)": [3.0, 6.0, 9.0],
            "Scientific name": ["Troglodytes troglodytes"] * 3,
            "Common name": ["Eurasian Wren", "Eurasian Wren", "Great Tit"],
            "Confidence": [0.9, 0.3, 0.8],
            "File": ["20260501_050100.wav"] * 3,
        }
    ).to_csv(folder / "R0" / "birdnet.csv", index=False)
    det = read_detections([folder / "R0" / "birdnet.csv"], "birdnet", files, classes=["Eurasian Wren"], min_score=0.5)
    assert det[["recorder_id", "start_s", "end_s", "score"]].values.tolist() == [["R0", 60.0, 63.0, 0.9]]
    bad = pd.read_csv(folder / "R0" / "birdnet.csv").assign(Confidence=[0.9, 1.5, 0.8])
    bad.to_csv(folder / "R0" / "bad.csv", index=False)
    with pytest.raises(DataError, match=r"bad.csv line 3, column 'Confidence': 1.5 is not a score in \[0, 1\]"):
        read_detections([folder / "R0" / "bad.csv"], "birdnet", files)
    pd.DataFrame(
        {"file": ["20260501_050000.wav"] * 2, "start_time": [0.0, 5.0], "end_time": [5.0, 10.0], "wren": [0.2, 4.0], "tit": [3.0, -1.0]}
    ).to_csv(folder / "R1.scores.csv", index=False)
    det = read_detections([folder / "R1.scores.csv"], "opensoundscape", files, classes=["wren", "tit"], min_score=1.0)
    assert sorted(det[["label", "start_s"]].values.tolist()) == [["tit", 0.0], ["wren", 5.0]] and set(det["recorder_id"]) == {"R1"}


@pytest.mark.parametrize(
    "content, message",
    [
        ("Selection\tBegin Time (s)\n1\t3.0\n", r"lacks columns \['End Time \(s\)'\]"),
        ("Selection\tBegin Time (s)\tEnd Time (s)\n1\t3.0\t4.0\n", "names no audio file: add the Begin File or Begin Path column"),
        (
            "Selection\tBegin Time (s)\tEnd Time (s)\tBegin File\n1\tsoon\t4.0\t20260501_050000.wav\n",
            r"line 2, column 'Begin Time \(s\)': 'soon'",
        ),
        (
            "Selection\tBegin Time (s)\tEnd Time (s)\tBegin File\n1\t5.0\t4.0\t20260501_050000.wav\n",
            "line 2: the detection ends before it begins",
        ),
        ("Selection\tBegin Time (s)\tEnd Time (s)\tBegin File\n1\t3.0\t4.0\tother.wav\n", "file 'other.wav' of recorder R0 is not among"),
        (
            "Selection\tBegin Time (s)\tEnd Time (s)\tLow Freq (Hz)\tHigh Freq (Hz)\tBegin File\n1\t3.0\t4.0\t2000\t60000\t20260501_050000.wav\n",
            r"line 2: High Freq \(Hz\) is above the recordings' Nyquist frequency, 4000 Hz \(low 2000 Hz, high 60000 Hz\)",
        ),
        (
            "Selection\tBegin Time (s)\tEnd Time (s)\tLow Freq (Hz)\tHigh Freq (Hz)\tBegin File\n1\t3.0\t4.0\t3000\t1000\t20260501_050000.wav\n",
            r"line 2: Low Freq \(Hz\) is not below High Freq \(Hz\)",
        ),
        (
            "Selection\tBegin Time (s)\tEnd Time (s)\tLow Freq (Hz)\tHigh Freq (Hz)\tBegin File\n1\t3.0\t4.0\t-5\t1000\t20260501_050000.wav\n",
            r"line 2: Low Freq \(Hz\) is negative",
        ),
    ],
)
def test_malformed_raven_tables_stop_with_one_line(two_recorders, content, message):
    folder, files = two_recorders
    (folder / "R0.txt").write_text(content)
    with pytest.raises(DataError, match=message):
        read_detections([folder / "R0.txt"], "raven", files)


def detections(rows):
    return pd.DataFrame(
        [
            {"recorder_id": r, "start_s": s, "end_s": e, "low_hz": lo, "high_hz": hi, "label": lab, "score": np.nan, "source": f"t:{k}"}
            for k, (r, s, e, lo, hi, lab) in enumerate(rows)
        ]
    )


def test_detections_are_grouped_into_events_heard_by_enough_recorders():
    det = detections(
        [
            ("R0", 10.0, 10.5, 2000, 5000, "wren"),
            ("R1", 10.2, 10.7, 2500, 6000, "wren"),
            ("R2", 10.25, 10.75, np.nan, np.nan, "wren"),
            ("R0", 10.1, 10.4, 1000, 2000, "tit"),  # another species at the same time: its own event, heard once
            ("R1", 20.0, 20.5, 2000, 5000, "wren"),
            ("R2", 20.1, 20.6, 2000, 5000, "wren"),
            ("R0", 40.0, 52.0, 2000, 5000, "wren"),
            ("R1", 40.1, 52.1, 2000, 5000, "wren"),  # too long to read
        ]
    )
    events = group_detections(det, margin_s=0.3, min_recorders=2, max_event_s=10.0)
    assert events["event_id"].tolist() == [0, 1, 2]
    assert events["n_recorders"].tolist() == [3, 2, 2] and events["recorders"].iloc[0] == "R0;R1;R2"
    np.testing.assert_allclose(events[["start_s", "end_s"]].iloc[0], [9.7, 11.05])
    np.testing.assert_allclose(events[["band_low_hz", "band_high_hz"]].iloc[0], [2000, 6000])
    assert events["too_long"].tolist() == [False, False, True]


def test_repeats_of_one_detection_are_one_detection(caplog):
    """The same table read twice (every row twice on every recorder): the events of reading it once, each naming both
    source rows, and one warning; without merging, each repeat opened an event of its own."""
    rows = [(f"R{r}", 5.0 * k + 0.01 * r, 5.0 * k + 0.5, 2000, 5000, "wren") for k in range(30) for r in range(4)]
    once = group_detections(detections(rows), margin_s=0.3, min_recorders=2)
    twice = detections(rows + rows)
    twice["source"] = [f"t.txt:{k + 2}" for k in range(len(twice))]
    with caplog.at_level("WARNING"):
        events = group_detections(twice, margin_s=0.3, min_recorders=2)
    assert "120 repeat(s) of a detection on the same recorder" in caplog.text
    pd.testing.assert_frame_equal(events.drop(columns="detections"), once.drop(columns="detections"))
    assert events["detections"].iloc[0].split(";")[:2] == ["t.txt:2", "t.txt:122"]


def test_consecutive_fixed_windows_of_a_singing_bird_stay_separate_events():
    """BirdNET's 3-s windows of a bird singing on and on, on three recorders: one event per window (each recorder once),
    not one chained event too long to read (single linkage chained all 20 into one 60-s event)."""
    rows = [(f"R{r}", 3.0 * k, 3.0 * k + 3.0, np.nan, np.nan, "wren") for k in range(20) for r in range(3)]
    events = group_detections(detections(rows), margin_s=0.3, min_recorders=2, max_event_s=10.0)
    assert len(events) == 20 and not events["too_long"].any() and (events["n_recorders"] == 3).all()
    np.testing.assert_allclose(events["start_s"], 3.0 * np.arange(20) - 0.3)


def test_a_files_table_reads_only_inside_its_audio_dir(tmp_path, season_files):
    """As field=recordings: an absolute path elsewhere, '..' and a linked recorder folder are refused in one line naming
    the line and where it resolves; allow_outside_audio_dir reads them."""
    folder, _ = season_files
    audio = tmp_path / "audio"
    (audio / "B").mkdir(parents=True)
    (audio / "A").symlink_to(folder / "A")  # a recorder folder linked from elsewhere
    shutil.copy(folder / "B" / "20260501_050000.wav", audio / "B" / "20260501_050000.wav")
    table = tmp_path / "files.csv"
    for named in ("A/20260501_050000.wav", str(folder / "A" / "20260501_050000.wav"), "../audio0/A/20260501_050000.wav"):
        table.write_text(f"recorder_id,file,start_time\nB,B/20260501_050000.wav,2026-05-01T05:00:00\nA,{named},2026-05-01T05:00:00\n")
        with pytest.raises(DataError, match="line 3, column file: .* outside recordings.audio_dir .*allow_outside_audio_dir=true"):
            RecorderFiles.from_table(table, audio)
    table.write_text(
        "recorder_id,file,start_time\nB,B/20260501_050000.wav,2026-05-01T05:00:00\nA,A/20260501_050000.wav,2026-05-01T05:00:00\n"
    )
    assert len(RecorderFiles.from_table(table, audio, allow_outside_audio_dir=True).table) == 2


def _jittered_season(seed: int, n_calls: int = 300, false_share: float = 0.03, miss: float = 0.05) -> tuple[pd.DataFrame, float]:
    """Raven-like boxes of ``n_calls`` calls on 5 recorders within 70 m: ±20 ms jitter, ``miss`` of the boxes missing,
    ``false_share`` more false boxes (half just before a real call on one recorder); ``source`` is ``call<k>`` or
    ``false``. Returns the detections and the linkage margin."""
    rng = np.random.default_rng(seed)
    mics = rng.uniform(0, 50, (5, 2))
    emission = np.cumsum(rng.uniform(2.0, 6.0, n_calls))
    arrival = emission[:, None] + np.linalg.norm(rng.uniform(-10, 60, (n_calls, 2))[:, None] - mics[None], axis=-1) / 343.0
    rows = [
        (f"R{r}", arrival[c, r] + rng.uniform(-0.02, 0.02), f"call{c}") for c in range(n_calls) for r in range(5) if rng.random() >= miss
    ]
    for k in range(int(false_share * len(rows))):
        r, c = int(rng.integers(5)), int(rng.integers(n_calls))
        rows.append((f"R{r}", arrival[c, r] - rng.uniform(0.05, 0.4) if k % 2 == 0 else rng.uniform(0, emission[-1]), "false"))
    table = pd.DataFrame(
        [
            {
                "recorder_id": r,
                "start_s": s,
                "end_s": s + 0.6,
                "low_hz": 2e3,
                "high_hz": 5e3,
                "label": "wren",
                "score": np.nan,
                "source": src,
            }
            for r, s, src in rows
        ]
    )
    return table, float(np.hypot(50, 50) / 343 + 0.01)


def test_one_call_is_one_event_whatever_false_boxes_come_before_it(caplog):
    """A false box on R2 0.35 s before a call whose first arrival is R4's: linking alone made {R2 false, R4} an event
    beside {R0, R1, R2, R3}, two positions for one bird. Now one event of all five, and the false box a row of its own,
    not read, naming that event. Over 1,500 calls with jitter, misses and false boxes, at most 2 calls give two placed
    events (69 did before); two calls of one bird 0.3 s apart on every recorder stay two."""
    arrivals = {"R0": 10.06, "R1": 10.08, "R2": 10.01, "R3": 10.03, "R4": 10.0}
    rows = [(r, t, t + 0.6, 2000, 5000, "wren") for r, t in arrivals.items()] + [("R2", 9.66, 10.26, 2000, 5000, "wren")]
    with caplog.at_level("WARNING"):
        events = group_detections(detections(rows), margin_s=0.22, min_recorders=2)
    read = events[events["not_read"] == ""]
    assert len(read) == 1 and read["n_recorders"].iloc[0] == 5
    (flagged,) = events.loc[events["not_read"] != "", "not_read"]
    assert flagged == f"a second detection on recorder R2 within event {read['event_id'].iloc[0]}'s call (a false positive or an echo)"
    assert "1 detection(s) fell within another event's call" in caplog.text
    split = 0
    for seed in range(5):
        table, margin = _jittered_season(seed)
        placed = group_detections(table, margin, 2)
        placed = placed[(placed["not_read"] == "") & ~placed["too_long"]]
        calls = pd.Series([c for cell in placed["detections"] for c in set(cell.split(";")) if c != "false"])
        split += int((calls.value_counts() > 1).sum())
    assert split <= 2
    twice = [(f"R{r}", t + 0.01 * r, t + 0.01 * r + 0.25, 2000, 5000, "wren") for t in (20.0, 20.3) for r in range(5)]
    assert (group_detections(detections(twice), margin_s=0.22, min_recorders=2)["n_recorders"] == 5).sum() == 2


def test_a_clip_reaches_past_its_detections_only_as_far_as_a_recorder_without_one_needs():
    """Every recorder detected the call: the clip is its detections plus the pad. One did not: widened on both sides by that
    recorder's shortest travel time to one that did (its arrival lies within that of theirs), not the array's largest."""
    travel = pd.DataFrame([[0.0, 0.1, 0.3], [0.1, 0.0, 0.25], [0.3, 0.25, 0.0]], index=["R0", "R1", "R2"], columns=["R0", "R1", "R2"])  # s
    rows = [("R0", 10.0, 10.5, 2000, 5000, "wren"), ("R1", 10.05, 10.55, 2000, 5000, "wren"), ("R2", 10.2, 10.7, 2000, 5000, "wren")]
    rows += [("R0", 20.0, 20.5, 2000, 5000, "wren"), ("R1", 20.05, 20.55, 2000, 5000, "wren")]  # R2 missed it
    events = group_detections(detections(rows), margin_s=0.31, min_recorders=2, travel_s=travel, pad_s=0.01)
    np.testing.assert_allclose(events["widening_s"], [0.01, 0.26])
    np.testing.assert_allclose(events[["start_s", "end_s"]], [[9.99, 10.71], [19.74, 20.81]])
    old_rule = group_detections(detections(rows), margin_s=0.31, min_recorders=2)
    np.testing.assert_allclose(old_rule["widening_s"], 0.31)
    assert (events["event_id"] == old_rule["event_id"]).all() and (events["recorders"] == old_rule["recorders"]).all()


def write_weather(path, rows, header="time,temperature_c,relative_humidity_pct"):
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    return path


def test_a_weather_table_gives_each_event_its_air_interpolated_in_time(tmp_path, caplog):
    path = write_weather(tmp_path / "w.csv", ["2026-05-01T05:10:00,10.0,80", "2026-05-01T05:00:00,4.0,90", "2026-05-01T05:20:00,16,70"])
    weather = read_weather(path)
    assert weather["time"].is_monotonic_increasing
    origin = pd.Timestamp("2026-05-01T05:00:00")
    with caplog.at_level("WARNING"):
        air = weather_at(weather, np.array([0.0, 300.0, 900.0, 3600.0]), origin, path)
    np.testing.assert_allclose(air["temperature_c"], [4.0, 7.0, 13.0, 16.0])
    np.testing.assert_allclose(air["relative_humidity_pct"], [90.0, 85.0, 75.0, 70.0])
    assert "1 of 4 events lie outside w.csv's readings" in caplog.text
    # a zoned logger reads in UTC, as the files' zoned start times do (the recordings' origin is naive UTC then)
    zoned = read_weather(
        write_weather(tmp_path / "t.csv", ["2026-05-01T07:00:00+02:00,4.0", "2026-05-01T06:00:00Z,10.0"], "time,temperature_c")
    )
    air = weather_at(zoned, np.array([1800.0]), origin, tmp_path / "t.csv")
    assert list(air.columns) == ["temperature_c"] and air["temperature_c"].iloc[0] == pytest.approx(7.0)
    with pytest.raises(DataError, match=r"t.csv, line 3, column time: '2026-05-01T06:00:00' lacks a UTC offset"):
        read_weather(write_weather(tmp_path / "t.csv", ["2026-05-01T05:00:00Z,4.0", "2026-05-01T06:00:00,5.0"], "time,temperature_c"))


@pytest.mark.parametrize(
    ("header", "rows", "message"),
    [
        ("time,temp", ["2026-05-01T05:00:00,4"], "has no 'temperature_c' column"),
        ("time,temperature_c", ["yesterday,4"], r"line 2, column time: 'yesterday' is not an ISO 8601 time"),
        ("time,temperature_c", ["2026-05-01T05:00:00,4", "2026-05-01T05:01:00,277.1"], r"line 3, column 'temperature_c': '277.1' is not"),
        ("time,temperature_c,relative_humidity_pct", ["2026-05-01T05:00:00,4,"], r"column 'relative_humidity_pct': '' is not a number"),
        ("time,temperature_c", ["2026-05-01T05:00:00,4", "2026-05-01T05:00:00,5"], r"line 3: time '2026-05-01T05:00:00' is given twice"),
    ],
)
def test_a_bad_weather_table_stops_with_one_line_naming_file_line_and_column(tmp_path, header, rows, message):
    with pytest.raises(DataError, match=r"protocol.weather_csv: .*w.csv.*" + message):
        read_weather(write_weather(tmp_path / "w.csv", rows, header))


def test_an_empty_missing_or_undecodable_weather_table_stops_with_one_line(tmp_path):
    (tmp_path / "empty.csv").write_text("")
    (tmp_path / "binary.csv").write_bytes(b"\xff\xfe\x00time\x00")
    for name, message in (("empty.csv", "cannot read"), ("missing.csv", "cannot read"), ("binary.csv", "")):
        with pytest.raises(DataError, match=r"protocol.weather_csv: .*" + message) as info:
            read_weather(tmp_path / name)
        assert "\n" not in str(info.value)


def test_a_season_with_a_weather_table_carries_each_event_s_air_and_without_one_none(tmp_path):
    from types import SimpleNamespace

    from acoustlab.season.protocol import SeasonLocalize

    path = write_weather(tmp_path / "w.csv", ["2026-05-01T05:00:00,4.0,90", "2026-05-01T05:00:20,14.0,70"])
    events = pd.DataFrame({"event_id": [0, 1], "start_s": [4.0, 14.0], "end_s": [6.0, 16.0]})
    recordings = SimpleNamespace(origin=pd.Timestamp("2026-05-01T05:00:00"))
    with_air = SeasonLocalize({}, {"format": "raven"}, {}, weather_csv=str(path)).with_weather(events, recordings)
    np.testing.assert_allclose(with_air[["temperature_c", "relative_humidity_pct"]], [[6.5, 85.0], [11.5, 75.0]])
    assert SeasonLocalize({}, {"format": "raven"}, {}).with_weather(events, recordings) is events
    with pytest.raises(Exception, match="protocol.events.pad_s must be a number >= 0"):
        SeasonLocalize({}, {"format": "raven"}, {"pad_s": -1}).pad_s()


def test_a_site_table_edited_in_place_keys_another_method(tmp_path):
    """The season reuses a fitted method only for the same config; the site's mics table edited under the same path is
    another array (other mics, another survey error), so it is another method."""
    from acoustlab.season.protocol import SeasonLocalize

    path = tmp_path / "mics.csv"
    path.write_text("x_m,y_m,z_m\n0,0,1.5\n40,0,1.5\n20,35,1.5\n")
    config = {"site": {"mics_csv": str(path)}, "protocol": {}}
    season = SeasonLocalize({}, {"format": "raven"}, {})
    first = season.method_key(config)
    assert season.method_key(config) == first
    path.write_text("x_m,y_m,z_m\n0,0,1.5\n40,0,1.5\n20,36,1.5\n")
    assert season.method_key(config) != first
