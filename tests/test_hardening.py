"""Bad input, damaged caches and full disks: a one-line error naming what is wrong, or a flagged row; never a traceback,
a silent NaN or lost results. Tables and audio are generated (Hypothesis where it fits)."""

from __future__ import annotations

import errno
import json
import logging
import shutil
import stat

import numpy as np
import pandas as pd
import pytest
import soundfile as sf
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from acoustlab.core.errors import AcoustlabError, ConfigError, DataError
from acoustlab.core.files import StorageError, atomic_save_npy, atomic_write_bytes
from acoustlab.core.resources import PACKAGE_DATA
from acoustlab.run.app import build_run, run_experiment
from acoustlab.run.registry import build, build_feature_sets, to_plain
from acoustlab.stages.cache import StageCache
from acoustlab.stages.dataset import SimulationPlan, load_or_build_field, load_or_build_simulated
from acoustlab.stages.sites import site_from_config
from acoustlab.toolkit.quality import QualityThresholds, clip_quality
from plugins.fields.recordings import RecordingFolder

EXAMPLE = PACKAGE_DATA / "examples" / "loca2021"
RATE = 24000
FUZZ = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


# ------------------------------------------------------------------------------------------- helpers
def lake_folder(root, n_events=3, duration_s=2.0, seed=0):
    """A 3-mic multichannel recordings folder matching the frozen-lake site: noise plus a chirp per event."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    mics = pd.DataFrame({"mic_id": ["a", "b", "c"], "x_m": [0.0, 40.0, 20.0], "y_m": [0.0, 0.0, 35.0], "z_m": [1.5, 1.5, 1.5]})
    rows = []
    for k in range(n_events):
        audio = (0.01 * rng.standard_normal((int(duration_s * RATE), 3))).astype(np.float32)
        sf.write(root / f"ev{k}.wav", audio, RATE, subtype="FLOAT")
        rows.append({"event_id": k, "start_s": 0.5, "end_s": 1.0, "file": f"ev{k}.wav", "position_id": k // 2})
    mics.to_csv(root / "mics.csv", index=False)
    pd.DataFrame(rows).to_csv(root / "events.csv", index=False)
    return mics, pd.DataFrame(rows)


def folder(root, **kwargs) -> RecordingFolder:
    return RecordingFolder(
        audio_dir=str(root), mics_csv=str(root / "mics.csv"), events_csv=str(root / "events.csv"), sample_rate_hz=RATE, **kwargs
    )


@pytest.fixture
def lake_site(compose_cfg, tmp_path):
    mics, _ = lake_folder(tmp_path / "rec")
    cfg = compose_cfg(["+site=from_csv", f"site.mics_csv={tmp_path / 'rec' / 'mics.csv'}"])
    return site_from_config(cfg.site)


# ------------------------------------------------------------------------------------- config values
@pytest.mark.parametrize(
    ("override", "named"),
    [
        ("data.n_jobs=0", "data.n_jobs"),
        ("seed=-1", "seed"),
        ("site.relative_humidity_pct=[70,250]", "site.relative_humidity_pct"),
        ("site.temperature_c=[10,400]", "site.temperature_c"),
        ("cache.file_mode=abc", "cache.file_mode"),
        ("cache.file_mode=0200", "cache.file_mode"),
        ("data.n_events=0", "data.n_events"),
    ],
)
def test_bad_config_values_stop_in_the_preflight_naming_the_key(compose_cfg, tmp_path, override, named):
    cfg = compose_cfg(["+site=frozen_lake", "+experiment=smoke", "tracking=none", f"paths.outputs_dir={tmp_path}", override])
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        build_run(cfg)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("data.n_events=abc", "data.n_events must be an integer; got 'abc'"),
        ("seed=1.5", "seed must be an integer; got '1.5'"),
        ("pipeline.plausible_margin_fraction=wide", "must be a number; got 'wide'"),
    ],
)
def test_a_wrong_type_is_one_line_before_hydra_and_still_fails_when_composing(compose_cfg, override, message):
    from hydra.errors import ConfigCompositionException

    from acoustlab.run.preflight import check_argv

    with pytest.raises(ConfigError, match=message):
        check_argv(["+site=frozen_lake", override])
    with pytest.raises(ConfigCompositionException, match=override.split("=")[0]):  # and the schema too, for compose API users
        compose_cfg(["+site=frozen_lake", override])


# -------------------------------------------------------------------------------------------- tables
BAD_CELLS = st.sampled_from(["abc", "", "nan", "inf", "-inf", "1e400", "1,5", "--3", "None", "é"])


def folder_with_bad_cell(root, table: str, column: str, row: int, value: str):
    """A generated recordings folder whose ``table`` (``mics`` or ``events``) holds ``value`` at (row, column)."""
    mics, events = lake_folder(root)
    frame = {"mics": mics, "events": events}[table]
    frame[column] = frame[column].astype(object)
    frame.loc[row, column] = value
    frame.to_csv(root / f"{table}.csv", index=False)


@FUZZ
@given(column=st.sampled_from(["event_id", "start_s", "end_s"]), value=BAD_CELLS, row=st.integers(0, 2))
def test_events_table_cells_that_are_not_finite_numbers_are_named(tmp_path_factory, column, value, row):
    root = tmp_path_factory.mktemp("fuzz")
    folder_with_bad_cell(root, "events", column, row, value)
    with pytest.raises(DataError) as info:
        folder(root).validate()
    message = str(info.value)
    assert "events.csv" in message and "\n" not in message
    assert column in message or "end_s" in message  # a cell, or an end not after its start


@FUZZ
@given(column=st.sampled_from(["x_m", "y_m", "z_m"]), value=BAD_CELLS, row=st.integers(0, 2))
def test_mics_table_coordinates_that_are_not_numbers_are_named(tmp_path_factory, column, value, row):
    root = tmp_path_factory.mktemp("fuzz")
    folder_with_bad_cell(root, "mics", column, row, value)
    with pytest.raises(DataError, match=rf"mics.csv, line {row + 2}, column '{column}'"):
        folder(root).validate()


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda e: e.iloc[:0], "has a header but no rows"),
        (lambda e: e.assign(event_id=[0, 0, 1]), "appears more than once"),
        (lambda e: e.assign(end_s=[1.0, 3600.0, 1.0]), "lasts 3599.5 s, more than field.max_event_s"),
        (lambda e: e.assign(end_s=[0.2, 1.0, 1.0]), "end_s 0.2 is not after start_s 0.5"),
        (lambda e: e.assign(file=["ev0.wav", "../../../../etc/passwd", "ev2.wav"]), "outside field.audio_dir"),
        (lambda e: e.assign(file=["ev0.wav", "/etc/passwd", "ev2.wav"]), "outside field.audio_dir"),
        (lambda e: e.assign(file=["ev0.wav", "missing.wav", "ev2.wav"]), "missing.wav does not exist"),
        (lambda e: e.assign(relative_humidity_pct=[50, 140, 50]), "relative_humidity_pct"),
        (lambda e: e.assign(position_id=[0, 0.5, 1]), "not a whole number"),
    ],
)
def test_bad_events_tables_stop_in_the_preflight(tmp_path, edit, message):
    _, events = lake_folder(tmp_path)
    edit(events).to_csv(tmp_path / "events.csv", index=False)
    with pytest.raises(DataError, match=message):
        folder(tmp_path).validate()


def test_unreadable_audio_and_too_few_channels_are_named(tmp_path):
    lake_folder(tmp_path)
    (tmp_path / "ev1.wav").write_bytes(b"RIFF not really a wave file")
    with pytest.raises(DataError, match="cannot read the audio header of .*ev1.wav"):
        folder(tmp_path).validate()
    sf.write(tmp_path / "ev1.wav", np.zeros((100, 2), np.float32), RATE)
    with pytest.raises(DataError, match="ev1.wav has 2 channels but the mics table lists 3 mics"):
        folder(tmp_path).validate()


def test_opensoundscape_tables_with_text_classes_or_unknown_files(tmp_path):
    pd.DataFrame({"file": ["a.wav", "b.wav", "c.wav"], "x": [0, 40, 20], "y": [0, 0, 35]}).to_csv(tmp_path / "coords.csv", index=False)
    for k in "abc":
        sf.write(tmp_path / f"{k}.wav", np.zeros(RATE, np.float32), RATE)
    make = lambda: RecordingFolder(
        audio_dir=str(tmp_path),
        coords_csv=str(tmp_path / "coords.csv"),  # noqa: E731
        detections_csv=str(tmp_path / "det.csv"),
        sample_rate_hz=RATE,
    )
    pd.DataFrame({"file": ["a.wav", "b.wav", "c.wav"], "start_time": 0.1, "end_time": 0.4, "zeep": ["yes", "no", "yes"]}).to_csv(
        tmp_path / "det.csv", index=False
    )
    with pytest.raises(DataError, match="det.csv, line 2, column 'zeep'"):
        make().validate()
    pd.DataFrame({"file": ["x.wav", "y.wav", "z.wav"], "start_time": 0.1, "end_time": 0.4, "zeep": 1}).to_csv(
        tmp_path / "det.csv", index=False
    )
    with pytest.raises(DataError, match="none of its files .* is in the coords table"):
        make().validate()
    pd.DataFrame({"file": ["a.wav", "b.wav"], "start_time": 0.1, "end_time": 0.4, "zeep": 1}).to_csv(tmp_path / "det.csv", index=False)
    with pytest.raises(DataError, match="no time window was detected by at least field.min_receivers=3"):
        make().validate()


# --------------------------------------------------------------------------------------------- audio
@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 400), start=st.integers(-500, 500), length=st.integers(1, 300), margin=st.integers(0, 20), seed=st.integers(0, 2**16)
)
def test_clip_quality_places_samples_at_their_true_offset(n, start, length, margin, seed):
    signal = np.random.default_rng(seed).uniform(-0.5, 0.5, n).astype(np.float32)
    length += 2 * margin  # the event itself is never empty
    clip, reasons = clip_quality(signal, start, length, QualityThresholds(), margin=margin)
    expected = np.array([signal[i] if 0 <= i < n else 0.0 for i in range(start, start + length)], np.float32)
    np.testing.assert_array_equal(clip, expected)  # never shifted, never clamped
    inner = range(start + margin, start + length - margin)
    covered = [0 <= i < n for i in inner]
    if not any(covered):
        assert reasons == ["out_of_range"]
    else:
        assert ("truncated" in reasons) == (not all(covered))


@settings(max_examples=40, deadline=None)
@given(kind=st.sampled_from(["nan", "inf", "zeros", "constant", "clipped", "fine"]), seed=st.integers(0, 2**16))
def test_clip_quality_names_what_is_wrong(kind, seed):
    rng = np.random.default_rng(seed)
    signal = (0.05 * rng.standard_normal(1000)).astype(np.float32)
    where = rng.integers(0, 1000, size=20)
    if kind == "nan":
        signal[where] = np.nan
    elif kind == "inf":
        signal[where] = np.inf * rng.choice([-1, 1], size=20)
    elif kind == "zeros":
        signal[:] = 0.0
    elif kind == "constant":
        signal[:] = 0.3
    elif kind == "clipped":
        signal[where] = 1.0
    clip, reasons = clip_quality(signal, 0, 1000, QualityThresholds())
    assert np.isfinite(clip).all()
    assert (
        reasons
        == {"nan": ["nonfinite"], "inf": ["nonfinite"], "zeros": ["dead"], "constant": ["dead"], "clipped": ["clipped"], "fine": []}[kind]
    )


def test_damaged_recordings_are_flagged_not_localized_from_zeros(tmp_path, lake_site):
    root = tmp_path / "rec"
    _, events = lake_folder(root, n_events=6)
    audio = sf.read(root / "ev1.wav", dtype="float32")[0]
    audio[:, 2] = 0.0  # dead channel
    sf.write(root / "ev1.wav", audio, RATE, subtype="FLOAT")
    audio = sf.read(root / "ev0.wav", dtype="float32")[0]
    audio[:, 2] = 0.0  # the same mic dead at the same position (0): a hardware failure there
    sf.write(root / "ev0.wav", audio, RATE, subtype="FLOAT")
    audio = sf.read(root / "ev2.wav", dtype="float32")[0]
    audio[RATE // 2 + 100, 0] = np.nan
    sf.write(root / "ev2.wav", audio, RATE, subtype="FLOAT")
    sf.write(root / "ev3.wav", sf.read(root / "ev3.wav", dtype="float32")[0][: int(0.7 * RATE)], RATE, subtype="FLOAT")  # cut short
    events.loc[4, ["start_s", "end_s"]] = [5.0, 5.4]  # past the end of its file
    events.loc[5, ["start_s", "end_s"]] = [-0.2, 0.3]  # begins before its file
    events.to_csv(root / "events.csv", index=False)
    batch = folder(root).load(lake_site)
    flags = batch.events["quality_flags"].tolist()
    assert flags == [
        "mic c: dead",
        "mic c: dead",
        "mic a: nonfinite",
        "mic a: truncated; mic b: truncated; mic c: truncated",
        "mic a: out_of_range; mic b: out_of_range; mic c: out_of_range",
        "mic a: truncated; mic b: truncated; mic c: truncated",
    ]
    assert batch.events["hardware_failure"].tolist() == [True, True, False, False, False, False]
    assert np.isfinite(batch.audio).all()
    # read one event at a time (localize streams chunks): the same clips and flags, and the position's failure once joined
    from acoustlab.toolkit.quality import failed_positions

    one_at_a_time = folder(root)
    one_at_a_time.chunk_events = 1
    parts = list(one_at_a_time.load_chunks(lake_site))
    assert len(parts) == 6 and all(not p.events["hardware_failure"].any() for p in parts)  # no chunk sees a whole position
    joined = pd.concat([p.events for p in parts], ignore_index=True)
    assert failed_positions(joined).tolist() == [True, True, False, False, False, False]
    assert joined["quality_flags"].tolist() == flags
    for k, part in enumerate(parts):
        length = int(batch.events["clip_samples"].iloc[k])
        np.testing.assert_array_equal(part.audio[0, :, :length], batch.audio[k, :, :length])
    # the event that begins before its file keeps its samples at their true times: the file's first sample lands 0.2 s + pad in
    pad = int(0.05 * RATE)
    first = sf.read(root / "ev5.wav", dtype="float32")[0][0, 0]
    assert batch.audio[5, 0, pad + int(0.2 * RATE) - 1] == 0.0 and batch.audio[5, 0, pad + int(0.2 * RATE)] == first


@pytest.mark.slow
def test_flagged_detections_are_kept_unplaced_with_their_reason(compose_cfg, tmp_path):
    """localize on simulated frozen-lake recordings, one of them with a dead channel: kept, not placed, reason given, counted."""
    cfg = compose_cfg(["+site=frozen_lake", "simulator=free_field"])
    site = site_from_config(cfg.site)
    batch = build(cfg.simulator, "simulator").simulate(site, np.arange(500, 504), np.arange(500, 504), 3)
    root = tmp_path / "rec"
    root.mkdir()
    rows = []
    for k, audio in enumerate(batch.audio):
        audio = audio / np.abs(batch.audio).max() * 0.5
        if k == 2:
            audio[1] = 0.0
        sf.write(root / f"e{k}.wav", audio.T, int(batch.sample_rate_hz), subtype="FLOAT")
        rows.append({"event_id": k, "start_s": 0.05, "end_s": audio.shape[-1] / batch.sample_rate_hz - 0.05, "file": f"e{k}.wav"})
    pd.DataFrame(rows).to_csv(root / "events.csv", index=False)
    pd.DataFrame({"x_m": site.mic_positions_m[:, 0], "y_m": site.mic_positions_m[:, 1], "z_m": site.mic_positions_m[:, 2]}).to_csv(
        root / "mics.csv", index=False
    )
    cfg = compose_cfg(
        [
            "+site=frozen_lake",
            "simulator=free_field",
            "protocol=localize",
            "field=recordings",
            "+experiment=smoke",
            "tracking=none",
            "model.n_estimators=20",
            "plots=false",
            f"paths.outputs_dir={tmp_path / 'out'}",
            f"field.audio_dir={root}",
            f"field.mics_csv={root / 'mics.csv'}",
            f"field.events_csv={root / 'events.csv'}",
            f"field.sample_rate_hz={batch.sample_rate_hz}",
        ]
    )
    metrics = run_experiment(cfg, tmp_path / "run")
    table = pd.read_csv(tmp_path / "run" / "positions.csv", keep_default_na=False)
    assert len(table) == 4 and not bool(table["placed"].iloc[2])
    assert table["abstain_reason"].iloc[2] == "quality: mic 1: dead"
    assert metrics["quality_flags"]["flagged"] == 1 and metrics["quality_flags"]["dead"] == 1


# --------------------------------------------------------------------------------------------- cache
def tiny_dataset(compose_cfg, cache_dir):
    cfg = compose_cfg(["+site=frozen_lake", "simulator=free_field", "features=physics"])
    site = site_from_config(cfg.site)
    simulator = build(cfg.simulator, "simulator")
    features = build_feature_sets(cfg.features)
    plan = SimulationPlan(n_events=12, events_per_position=4, seed=5, chunk_size=6)
    cache = StageCache(cache_dir)
    return lambda: load_or_build_simulated(site, simulator, to_plain(cfg.simulator), features, to_plain(cfg.features.groups), plan, cache)


def flip_bytes(path, offset_fraction=0.5, n=3):
    data = bytearray(path.read_bytes())
    at = int(len(data) * offset_fraction)
    for k in range(n):
        data[at + k] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    "damage", ["truncate features", "flip features", "flip chunk", "truncate chunk", "delete manifest", "bad parquet metadata"]
)
def test_a_damaged_cache_entry_is_discarded_and_rebuilt_identically(compose_cfg, tmp_path, caplog, damage):
    load = tiny_dataset(compose_cfg, tmp_path / "cache")
    clean = load()
    features_dir = next(p for p in (tmp_path / "cache" / "features").iterdir() if p.is_dir())
    sim_dir = next(p for p in (tmp_path / "cache" / "simulation").iterdir() if p.is_dir())
    if damage == "truncate features":
        target = features_dir / "features.parquet"
        target.write_bytes(target.read_bytes()[: target.stat().st_size // 3])
    elif damage == "flip features":
        flip_bytes(features_dir / "features.parquet")
    elif damage == "bad parquet metadata":
        flip_bytes(features_dir / "events.parquet", offset_fraction=0.97, n=2)
    elif damage == "delete manifest":
        (features_dir / "manifest.json").unlink()
    else:  # a simulation chunk: read only when the features are rebuilt, so drop the feature entry too
        chunk = sorted(sim_dir.glob("*.npy"))[1]
        if damage == "flip chunk":
            flip_bytes(chunk, 0.8)
        else:
            chunk.write_bytes(chunk.read_bytes()[:200])
        shutil.rmtree(features_dir)
    caplog.set_level(logging.WARNING)
    again = load()
    assert any("corrupt or incomplete" in r.message and "discarded, rebuilding" in r.message for r in caplog.records), damage
    pd.testing.assert_frame_equal(again.features, clean.features)
    assert again.dataset_hash == clean.dataset_hash and again.features_sha256 == clean.features_sha256
    caplog.clear()
    load()  # and the rebuilt entry is trusted again
    assert not any("corrupt" in r.message for r in caplog.records)


def test_cache_files_are_group_readable_and_the_mode_is_configurable(compose_cfg, tmp_path):
    tiny_dataset(compose_cfg, tmp_path / "cache")()
    entry = next(p for p in (tmp_path / "cache" / "features").iterdir() if p.is_dir())
    assert stat.S_IMODE((entry / "features.parquet").stat().st_mode) == 0o644
    assert stat.S_IMODE(entry.stat().st_mode) == 0o755
    cache = StageCache(tmp_path / "c2", file_mode="0640")
    work = cache.partial_dir("x", "k")
    atomic_write_bytes(work / "a.bin", b"1")
    cache.commit("x", "k", work)
    assert stat.S_IMODE((tmp_path / "c2" / "x" / "k" / "a.bin").stat().st_mode) == 0o640


def test_recordings_cache_follows_file_contents(compose_cfg, tmp_path, lake_site, caplog):
    root = tmp_path / "rec"
    cfg = compose_cfg(["+site=frozen_lake", "features=physics"])
    feature_sets = build_feature_sets(cfg.features)
    cache = StageCache(tmp_path / "cache")
    source = folder(root)
    field_cfg = {"audio_dir": str(root)}
    first = load_or_build_field(lake_site, source, field_cfg, feature_sets, to_plain(cfg.features.groups), cache)
    events = pd.read_csv(root / "events.csv")
    events.loc[0, "end_s"] = 0.9  # edited in place: same path, same config
    events.to_csv(root / "events.csv", index=False)
    caplog.set_level(logging.INFO)
    second = load_or_build_field(lake_site, source, field_cfg, feature_sets, to_plain(cfg.features.groups), cache)
    assert any("cache miss: field_features" in r.message for r in caplog.records)
    assert second.events["end_s"].iloc[0] == 0.9 and first.events["end_s"].iloc[0] == 1.0
    audio = sf.read(root / "ev2.wav", dtype="float32")[0]
    sf.write(root / "ev2.wav", np.zeros_like(audio), RATE, subtype="FLOAT")  # replaced by a dead recording
    third = load_or_build_field(lake_site, source, field_cfg, feature_sets, to_plain(cfg.features.groups), cache)
    assert third.events["quality_flags"].iloc[2] != "" and second.events["quality_flags"].iloc[2] == ""


# ----------------------------------------------------------------------------------------- disk full
@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device"), OSError("1267200 requested and 158688 written")])
def test_a_full_disk_is_one_clear_error_naming_path_and_free_space(tmp_path, monkeypatch, failure):
    def full(*_args, **_kwargs):
        raise failure

    monkeypatch.setattr(np, "save", full)
    target = tmp_path / "sim" / "events_0000000_0000064.npy"
    with pytest.raises(StorageError) as info:
        atomic_save_npy(target, np.zeros(10))
    message = str(info.value)
    assert str(target) in message and "no space left" in message and "MiB free" in message and "\n" not in message
    assert isinstance(info.value, AcoustlabError)
    assert not target.exists() and not list(target.parent.glob("*.tmp"))  # nothing half-written left behind


@pytest.mark.slow
def test_a_plotting_failure_never_loses_the_metrics(compose_cfg, tmp_path, monkeypatch, caplog):
    import acoustlab.reporting.plots as plots

    def broken(*_args, **_kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(plots, "write_run_plots", broken)
    cfg = compose_cfg(
        ["+site=frozen_lake", "+experiment=smoke", "tracking=none", "model.n_estimators=20", f"paths.outputs_dir={tmp_path / 'out'}"]
    )
    caplog.set_level(logging.WARNING)
    metrics = run_experiment(cfg, tmp_path / "run")
    on_disk = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert on_disk["errors"] == metrics["errors"] and (tmp_path / "run" / "predictions.parquet").exists()
    assert any("plots not written" in r.message for r in caplog.records)
    assert not (tmp_path / "run" / "TRACKING_PENDING.json").exists()  # logged (to the null tracker): marker removed


def test_projected_mic_coordinates_that_disagree_with_the_local_ones_are_named(tmp_path):
    mics, _ = lake_folder(tmp_path)
    mics.assign(easting_m=mics["x_m"] + 500000.0, northing_m=mics["y_m"] + [0.0, 0.0, 3.0], crs="EPSG:32617").to_csv(
        tmp_path / "mics.csv", index=False
    )
    with pytest.raises(DataError, match=r"mics.csv, line \d: x_m, y_m and easting_m, northing_m disagree by"):
        folder(tmp_path).projection()
    mics.assign(easting_m=mics["x_m"] + 500000.0, northing_m=mics["y_m"] + 4100000.0).to_csv(tmp_path / "mics.csv", index=False)
    rotation, translation, crs, geographic = folder(tmp_path).projection()
    np.testing.assert_allclose(rotation, np.eye(2), atol=1e-9)
    np.testing.assert_allclose(translation, [500000.0, 4100000.0], atol=1e-6)
    assert crs == "" and not geographic


def test_a_recordings_folder_whose_mics_are_given_in_latitude_longitude_is_placed_in_their_utm_zone(tmp_path):
    pyproj = pytest.importorskip("pyproj")
    mics, _ = lake_folder(tmp_path)
    lon, lat = pyproj.Transformer.from_crs("EPSG:32633", "EPSG:4326", always_xy=True).transform(mics["x_m"] + 500000.0, mics["y_m"] + 5.2e6)
    mics.drop(columns=["x_m", "y_m"]).assign(latitude=lat, longitude=lon).to_csv(tmp_path / "mics.csv", index=False)
    local, _ = folder(tmp_path).tables()
    spans = local[["x_m", "y_m"]].to_numpy(float) - local[["x_m", "y_m"]].to_numpy(float)[0]
    np.testing.assert_allclose(spans, mics[["x_m", "y_m"]].to_numpy(float), atol=1e-6)  # the same array, in its own zone
    rotation, translation, crs, geographic = folder(tmp_path).projection()
    assert crs == "EPSG:32633" and geographic
    np.testing.assert_allclose(rotation, np.eye(2), atol=1e-12)
    # playback spots surveyed with the same GPS: in the same local frame (a spot at mic b, one unknown, one 10 m north of a)
    _, spot_lat = pyproj.Transformer.from_crs("EPSG:32633", "EPSG:4326", always_xy=True).transform(500000.0, 5.2e6 + 10.0)
    events = pd.read_csv(tmp_path / "events.csv").assign(latitude=[lat[1], np.nan, spot_lat], longitude=[lon[1], np.nan, lon[0]])
    events.to_csv(tmp_path / "events.csv", index=False)
    _, read = folder(tmp_path).tables()
    np.testing.assert_allclose(
        read[["x_m", "y_m"]].to_numpy(float)[[0, 2]], [local.loc[1, ["x_m", "y_m"]], local.loc[0, ["x_m", "y_m"]] + [0, 10]], atol=1e-6
    )
    assert read[["x_m", "y_m"]].iloc[1].isna().all()
    events.assign(x_m=0.0).to_csv(tmp_path / "events.csv", index=False)
    with pytest.raises(DataError, match="events.csv: give the spots once"):
        folder(tmp_path).tables()


def test_error_messages_show_numbers_as_numbers():
    """A numpy scalar in a message reads 24000 or nan, never np.int64(24000) or np.float64(nan)."""
    import numpy as np

    from acoustlab.core.errors import show

    assert [show(np.int64(24000)), show(np.float64("nan")), show(np.float32(0.5)), show("x")] == ["24000", "nan", "0.5", "'x'"]


@given(n_mics=st.integers(3, 8), weak=st.sets(st.integers(0, 7), max_size=8), seed=st.integers(0, 10**6))
def test_a_mic_is_weak_exactly_when_none_of_its_pairs_reaches_the_height(n_mics, weak, seed):
    """``weakly_correlated_mics``: pairs of two good mics are high, every pair with a weak mic low; a mic is weak exactly when
    it is one of the weak ones (or when it is the only good one left: no good partner)."""
    from itertools import combinations

    from acoustlab.toolkit.quality import weakly_correlated_mics

    weak = {m for m in weak if m < n_mics}
    pairs = list(combinations(range(n_mics), 2))
    rng = np.random.default_rng(seed)
    heights = np.array([[rng.uniform(0.1, 0.3) if not ({i, j} & weak) else rng.uniform(0.0, 0.02) for i, j in pairs]])
    good = n_mics - len(weak)
    expected = np.array([m in weak or good < 2 for m in range(n_mics)])
    np.testing.assert_array_equal(weakly_correlated_mics(heights, pairs, n_mics, 0.05)[0], expected)
    heights[0, 0] = np.nan  # a missing height counts as no peak
    assert weakly_correlated_mics(heights, pairs, n_mics, 0.05).shape == (1, n_mics)


@given(scale=st.floats(0.05, 1.0), seed=st.integers(0, 10**6))
def test_a_relative_gcc_height_drops_the_same_mics_whatever_the_recordings_scale_of_heights(scale, seed):
    """``features.gcc.min_peak_relative``: a file coding that lowers every GCC height alike (an MP3's lost high band) drops
    no other mic under the relative rule, while a fixed height drops the good mics too once the heights fall below it."""
    from itertools import combinations

    from acoustlab.toolkit.quality import weakly_correlated_mics

    pairs = list(combinations(range(6), 2))
    rng = np.random.default_rng(seed)
    heights = np.array([[rng.uniform(0.15, 0.3) if 5 not in (i, j) else rng.uniform(0.0, 0.02) for i, j in pairs]])  # mic 5: noise
    expected = np.array([[False] * 5 + [True]])
    np.testing.assert_array_equal(weakly_correlated_mics(heights * scale, pairs, 6, None, relative=0.2), expected)
    np.testing.assert_array_equal(weakly_correlated_mics(heights, pairs, 6, 0.03), expected)  # as recorded: the same
    assert weakly_correlated_mics(heights * 0.08, pairs, 6, 0.03).all()  # every height below 0.03: every mic dropped
