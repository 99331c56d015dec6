"""protocol=season end to end on a synthetic season: positions near the truth, sharded == unsharded, resumable, verified method."""

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import soundfile as sf
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from acoustlab.core.errors import DataError
from acoustlab.method.saved import METHOD_FILE, load_method
from acoustlab.run.app import run_experiment
from acoustlab.season.stream import localize_chunks, merge_parts, part_bytes, part_path, read_manifest
from acoustlab.season.synthetic import SyntheticSeason, write_season
from acoustlab.stages.sites import site_from_config

N_CALLS = 24


def season_overrides(folder, output_dir, *extra):
    return [
        "+site=frozen_lake",
        "+experiment=smoke",
        "protocol=season",
        "tracking=none",
        "model.n_estimators=20",
        f"protocol.recordings.audio_dir={folder / 'audio'}",
        f"protocol.detections.paths=[{folder / 'raven'}]",
        "protocol.chunk_events=5",
        "protocol.batch_events=3",
        f"protocol.output_dir={output_dir}",
        *extra,
    ]


@pytest.fixture(scope="module")
def season(tmp_path_factory):
    """A 60-s synthetic season of the frozen lake in 20-s files (calls cross file boundaries), fitted and localized once."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from acoustlab.run.registry import CONF_DIR

    root = tmp_path_factory.mktemp("season")
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=season_overrides(root, root / "out", f"paths.outputs_dir={root / 'outputs'}"))
        site = site_from_config(cfg.site)
        truth = write_season(
            SyntheticSeason.for_site(
                site, duration_s=60, file_s=20, n_calls=N_CALLS, min_spacing_s=2.0, sample_rate_hz=float(cfg.simulator.sample_rate_hz)
            ),
            root,
        )
        metrics = run_experiment(cfg, root / "run")
    GlobalHydra.instance().clear()
    return root, truth, metrics, cfg


@pytest.mark.slow
def test_a_season_is_localized_from_raven_tables_near_the_truth(season):
    root, truth, metrics, _ = season
    table = pd.read_parquet(root / "run" / "positions.parquet")
    assert len(table) == N_CALLS and metrics["localization"]["n_detections"] == N_CALLS
    assert {"event_id", "time", "label", "n_recorders", "x_m", "y_m", "placed", "radius_fixed_0.95_m", "band_low_hz"} <= set(table.columns)
    assert table["n_recorders"].eq(3).all() and table["time"].iloc[0].startswith("2026-05-01T05:00:")
    error = np.hypot(table["x_m"] - truth["x_m"], table["y_m"] - truth["y_m"])
    assert np.median(error) < 1.0 and (error < 5).mean() >= 0.9, error.describe()
    assert (root / "run" / "positions.csv").is_file() and json.loads((root / "run" / "metrics.json").read_text())["season"][
        "n_events"
    ] == N_CALLS


@pytest.mark.slow
def test_an_event_s_clips_aligned_by_its_time_differences_line_up_where_its_fix_explains_them(season):
    """``python -m acoustlab.aligned_clips``: one channel per mic shifted by its measured arrival; on the synthetic season's
    well-placed calls the aligned channels' cross-correlation peaks within a sample or two of zero lag, and each mic's
    residual at the fix is centimetres."""
    from acoustlab.aligned_clips import main

    root = season[0]
    table = pd.read_parquet(root / "run" / "positions.parquet")
    ids = table["event_id"].iloc[:3].tolist()
    assert main([str(root / "run"), *map(str, ids), "--out", str(root / "aligned")]) == 0
    for event in ids:
        audio, rate = sf.read(root / "aligned" / f"event_{event}.wav")
        residuals = pd.read_csv(root / "aligned" / f"event_{event}.csv")
        assert audio.shape[1] == 3 and len(audio) > rate * 0.1
        assert residuals["fix_uses_mic"].all() and (residuals["residual_m"].abs() < 0.2).all(), residuals
        for m in (1, 2):
            xc = np.correlate(audio[:, 0], audio[:, m], mode="full")
            assert abs(int(np.argmax(np.abs(xc))) - (len(audio) - 1)) <= 2
    assert main([str(root / "run"), "99999"]) == 2  # an event the run does not have: one line, no traceback


def _placed(season, table: pd.DataFrame, batch_events: int) -> pd.DataFrame:
    """The positions ``localize_events`` gives the events of ``table`` as one chunk, ``batch_events`` at a time."""
    from dataclasses import replace

    from acoustlab.season.recorder_files import RecorderFiles
    from acoustlab.season.stream import FILES, ChunkPlan, localize_events

    directory = season[0] / "out"
    manifest = read_manifest(directory)
    recordings = RecorderFiles.load(directory / FILES)
    try:
        return localize_events(
            load_method(directory, manifest["method_sha256"]),
            recordings,
            table.reset_index(drop=True),
            manifest["recorders"],
            replace(ChunkPlan.from_manifest(manifest), batch_events=batch_events),
            recordings.origin,
        )
    finally:
        recordings.close()


@pytest.fixture(scope="module")
def whole_season(season):
    """Every event of the season placed in one chunk of 64 (the reference for cutting it otherwise)."""
    from acoustlab.season.stream import EVENTS

    events = pd.read_parquet(season[0] / "out" / EVENTS)
    assert len({round(e - s, 6) for s, e in zip(events["start_s"], events["end_s"], strict=True)}) > 1  # clips of several lengths
    return events, _placed(season, events, 64)


@pytest.mark.slow
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(batch=st.integers(1, 30), cuts=st.lists(st.integers(1, N_CALLS - 1), max_size=3, unique=True), repeat=st.integers(0, N_CALLS - 1))
def test_a_season_s_answer_does_not_depend_on_how_it_is_cut(season, whole_season, batch, cuts, repeat):
    """Any batch size and any chunk boundaries leave every column of every row bit for bit as it was (``check_exact``), and
    a call placed three times among other events gets its own answer each time: each clip is padded by its own length
    only, and every later step is per event (the trust check's neighbours included)."""
    events, whole = whole_season
    bounds = [0, *sorted(cuts), len(events)]
    cut = pd.concat([_placed(season, events.iloc[a:b], batch) for a, b in zip(bounds[:-1], bounds[1:], strict=True)], ignore_index=True)
    pd.testing.assert_frame_equal(cut, whole, check_exact=True)
    copies = pd.concat([events.iloc[[repeat] * 3], events.iloc[::-1]], ignore_index=True)
    again = _placed(season, copies, batch)
    for k in range(3):
        pd.testing.assert_series_equal(again.iloc[k], whole.iloc[repeat], check_names=False, check_exact=True)
    pd.testing.assert_frame_equal(again.iloc[3:].iloc[::-1].reset_index(drop=True), whole, check_exact=True)


@pytest.mark.slow
def test_each_event_is_placed_in_its_own_air_where_the_events_carry_it(season, whole_season):
    """Events carrying the plan's own weather give the plan's positions bit for bit; the same events carrying a 20 °C warmer
    air are placed with that air's speed of sound, so they move (the season was rendered at the plan's)."""
    events, whole = whole_season
    plan = read_manifest(season[0] / "out")["plan"]
    same = events.assign(temperature_c=plan["temperature_c"], relative_humidity_pct=plan["relative_humidity_pct"])
    pd.testing.assert_frame_equal(_placed(season, same, 8), whole, check_exact=True)
    warm = _placed(season, same.assign(temperature_c=plan["temperature_c"] + 20.0), 8)
    truth = season[1]
    error = {name: np.hypot(t["solver_x_m"] - truth["x_m"], t["solver_y_m"] - truth["y_m"]) for name, t in (("own", whole), ("warm", warm))}
    assert np.median(error["warm"]) > 2 * np.median(error["own"]), {k: np.median(v) for k, v in error.items()}


@pytest.mark.slow
def test_sharded_runs_give_the_unsharded_positions(season, compose_cfg, tmp_path):
    root, _, _, _ = season
    unsharded = pd.read_parquet(root / "run" / "positions.parquet")
    fitted = tmp_path / "sharded"
    shutil.copytree(root / "out", fitted, ignore=shutil.ignore_patterns("parts"))  # the fitted method and events, no positions
    for shard in range(3):  # as three SLURM array tasks would
        cfg = compose_cfg(
            season_overrides(
                root,
                fitted,
                "protocol.stage=localize",
                f"protocol.shard={shard}",
                "protocol.n_shards=3",
                f"paths.outputs_dir={tmp_path / 'outputs'}",
            )
        )
        run_experiment(cfg, tmp_path / f"shard{shard}")
    cfg = compose_cfg(season_overrides(root, fitted, "protocol.stage=merge", f"paths.outputs_dir={tmp_path / 'outputs'}"))
    run_experiment(cfg, tmp_path / "merged")
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "merged" / "positions.parquet"), unsharded, check_exact=True)
    local = tmp_path / "local"  # two local worker processes (acoustlab.core.workers)
    shutil.copytree(root / "out", local, ignore=shutil.ignore_patterns("parts"))
    cfg = compose_cfg(season_overrides(root, local, "protocol.n_jobs=2", f"paths.outputs_dir={tmp_path / 'outputs'}"))
    run_experiment(cfg, tmp_path / "local_run")
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "local_run" / "positions.parquet"), unsharded, check_exact=True)


@pytest.mark.slow
def test_a_killed_run_resumes_without_redoing_finished_chunks(season, tmp_path):
    root, _, _, _ = season
    folder = tmp_path / "killed"
    shutil.copytree(root / "out", folder, ignore=shutil.ignore_patterns("parts"))
    code = (
        f"from pathlib import Path; from acoustlab.season.stream import localize_chunks; localize_chunks(Path({str(folder)!r}), range(5))"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], env={**os.environ, "PYTHONWARNINGS": "ignore"})
    deadline = time.monotonic() + 120
    while not part_path(folder, 0).is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    finished = {k: part_path(folder, k).stat().st_mtime_ns for k in range(5) if part_path(folder, k).is_file()}
    assert finished, "the run was killed before its first chunk"
    computed = localize_chunks(folder, range(5))
    assert computed == 5 - len(finished)
    assert {k: part_path(folder, k).stat().st_mtime_ns for k in finished} == finished  # finished chunks untouched
    pd.testing.assert_frame_equal(merge_parts(folder), pd.read_parquet(root / "run" / "positions.parquet"))


@pytest.mark.slow
def test_a_local_worker_stops_when_its_parent_is_killed(season, tmp_path):
    """A worker started by a run (as its local workers are) stops before its next chunk once that run is killed."""
    root, _, _, _ = season
    folder = tmp_path / "orphan"
    shutil.copytree(root / "out", folder, ignore=shutil.ignore_patterns("parts"))
    code = (
        "import multiprocessing as mp, os, sys, time\n"
        "from acoustlab.season.stream import localize_shard\n"
        "if __name__ == '__main__':\n"
        "    ctx = mp.get_context('spawn')\n"
        f"    child = ctx.Process(target=localize_shard, args=({str(folder)!r}, 0, 1, 1, os.getpid()))\n"
        "    child.start()\n"
        "    print(child.pid, flush=True)\n"
        "    time.sleep(600)\n"
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONWARNINGS": "ignore"}
    )
    child = int(parent.stdout.readline())
    deadline = time.monotonic() + 120
    while not part_path(folder, 0).is_file() and time.monotonic() < deadline:
        time.sleep(0.02)
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        stat = Path(f"/proc/{child}/stat")
        try:  # gone, or a zombie nobody reaps (a container's init may not)
            if stat.read_text().rsplit(")", 1)[1].split()[0] == "Z":
                break
        except (FileNotFoundError, ProcessLookupError):
            break
        time.sleep(0.1)
    else:
        os.kill(child, signal.SIGKILL)
        pytest.fail("the worker kept running after its parent was killed")
    assert sum(part_path(folder, k).is_file() for k in range(5)) < 5


def _children_of(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(stat.parent.name))
        except (OSError, ValueError, IndexError):
            continue
    return found


def _running(pid: int) -> bool:
    """Whether ``pid`` is alive and not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_killed_two_worker_season_leaves_no_process(season, tmp_path):
    """kill -9 of a season running two local workers: within seconds no process it started is left (the workers die
    with it, mid-chunk; no idle pool or resource tracker stays), and the parts written are whole."""
    root, _, _, _ = season
    folder = tmp_path / "killed_pool"
    shutil.copytree(root / "out", folder, ignore=shutil.ignore_patterns("parts"))
    code = f"from pathlib import Path\nfrom acoustlab.season.stream import localize_in_workers\nif __name__ == '__main__':\n    localize_in_workers(Path({str(folder)!r}), 2, 1)\n"
    parent = subprocess.Popen([sys.executable, "-c", code], env={**os.environ, "PYTHONWARNINGS": "ignore"})
    deadline = time.monotonic() + 120
    while not part_path(folder, 0).is_file() and parent.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    children = _children_of(parent.pid)
    assert len(children) >= 2, "the workers had not started"
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 20
    while any(_running(pid) for pid in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = [pid for pid in children if _running(pid)]
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    assert not left, f"{len(left)} process(es) the killed season started kept running"
    for k in range(5):  # whatever was written is whole: it reads, and a resume computes only the rest
        if part_path(folder, k).is_file():
            pd.read_parquet(part_path(folder, k))
    localize_chunks(folder, range(5))
    pd.testing.assert_frame_equal(merge_parts(folder), pd.read_parquet(root / "run" / "positions.parquet"))


@pytest.mark.slow
def test_a_changed_method_file_is_refused_and_other_inputs_never_mix(season, compose_cfg, tmp_path):
    root, _, _, _ = season
    folder = tmp_path / "tampered"
    shutil.copytree(root / "out", folder)
    with open(folder / METHOD_FILE, "ab") as handle:
        handle.write(b"\0")
    with pytest.raises(DataError, match="SHA-256 .* differs from the recorded"):
        load_method(folder, read_manifest(folder)["method_sha256"])
    other = tmp_path / "other"
    shutil.copytree(root / "out", other)
    before = {p.name: p.read_bytes() for p in other.iterdir() if p.is_file()}
    cfg = compose_cfg(season_overrides(root, other, "protocol.chunk_events=4", f"paths.outputs_dir={tmp_path / 'outputs'}"))
    with pytest.raises(DataError, match="holds 5 parts of a season run made with other .*chunk_events"):
        run_experiment(cfg, tmp_path / "run")
    assert {p.name: p.read_bytes() for p in other.iterdir() if p.is_file()} == before  # refused before anything was rewritten


@pytest.mark.slow
def test_damaged_foreign_or_orphan_parts_are_recomputed_or_refused_in_one_line(season, tmp_path):
    """An empty or damaged part is computed again; a part of other events, or parts without the season's manifest, stop."""
    from acoustlab.season.stream import MANIFEST, check_manifest

    root, _, _, _ = season
    expected = pd.read_parquet(root / "run" / "positions.parquet")
    folder = tmp_path / "damaged"
    shutil.copytree(root / "out", folder)
    part_path(folder, 1).write_bytes(b"")  # a 0-byte part
    part_path(folder, 3).write_bytes(part_path(folder, 3).read_bytes()[:100])  # a cut-off part
    with pytest.raises(DataError, match=r"part-000001.parquet cannot be read; run protocol.stage=localize again"):
        merge_parts(folder)
    assert localize_chunks(folder, range(5)) == 2
    pd.testing.assert_frame_equal(merge_parts(folder), expected)
    shutil.copy(part_path(folder, 0), part_path(folder, 2))  # another chunk's part under this chunk's name
    with pytest.raises(DataError, match="part-000002.parquet holds the metadata of another season's part, not that of chunk 2"):
        localize_chunks(folder, range(5))
    with pytest.raises(DataError, match="not that of chunk 2"):
        merge_parts(folder)
    # another season's chunk 2 (every season numbers its events 0, 1, 2 …: the same event ids), or a part with no season
    own = pd.read_parquet(expected_part := part_path(root / "out", 2))
    for foreign in (part_bytes(own, "f" * 64, 2), own.to_parquet(index=False)):
        part_path(folder, 2).write_bytes(foreign)
        with pytest.raises(DataError, match="part-000002.parquet holds the metadata of another season's part"):
            merge_parts(folder)
    shutil.copy(expected_part, part_path(folder, 2))
    pd.testing.assert_frame_equal(merge_parts(folder), expected)
    (folder / MANIFEST).unlink()
    with pytest.raises(DataError, match="holds 5 parts but no season.json"):
        check_manifest(folder, read_manifest(root / "out"))


@pytest.mark.slow
def test_a_recording_changed_since_the_fit_is_refused(season, tmp_path):
    """A file rewritten between a kill and its resume would mix two recordings into one season: the localize stage and a
    new fit over old parts both stop, naming it."""
    import soundfile as sf

    from acoustlab.season.recorder_files import RecorderFiles
    from acoustlab.season.stream import FILES

    root, _, _, _ = season
    audio = tmp_path / "audio"
    shutil.copytree(root / "audio", audio)
    indexed = RecorderFiles.from_file_names(audio)
    indexed.check_unchanged()
    path = Path(indexed.table["path"].iloc[1])
    samples, rate = sf.read(path, dtype="float32")
    before = path.stat()
    sf.write(path, samples[::-1].copy(), rate)  # same length, other samples
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))  # as cp -p or rsync -t of another copy leaves it
    assert path.stat().st_size == before.st_size and path.stat().st_mtime_ns == before.st_mtime_ns
    with pytest.raises(DataError, match=f"{path.name} changed since the season was fitted \\(content, at the same size and time\\)"):
        indexed.check_unchanged()
    folder = tmp_path / "season"
    shutil.copytree(root / "out", folder)
    indexed.save(folder / FILES)  # as fitted from the original files
    with pytest.raises(DataError, match="changed since the season was fitted"):
        localize_chunks(folder, range(5))
    again = RecorderFiles.from_file_names(audio)  # a new fit indexes the new file: its digest differs from the parts' run
    from acoustlab.season.stream import ChunkPlan, season_manifest

    manifest = read_manifest(folder)
    assert (
        season_manifest(pd.DataFrame(), None, ChunkPlan.from_manifest(manifest), [], {}, again)["recordings"]
        != (season_manifest(pd.DataFrame(), None, ChunkPlan.from_manifest(manifest), [], {}, indexed)["recordings"])
    )


@pytest.mark.slow
def test_shards_as_a_hydra_multirun_then_merge(season, run_cli, tmp_path):
    """The command-line path a SLURM array takes (here Hydra's basic launcher): one job per shard, then the merge stage."""
    root, _, _, _ = season
    folder = tmp_path / "multirun"
    shutil.copytree(root / "out", folder, ignore=shutil.ignore_patterns("parts"))
    common = [a for a in season_overrides(root, folder) if a != "protocol=season"]
    proc = run_cli(
        "season",
        "-m",
        *common,
        "protocol.stage=localize",
        "protocol.n_shards=2",
        "protocol.shard=0,1",
        f"hydra.sweep.dir={tmp_path / 'sweep'}",
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    proc = run_cli("season", *common, "protocol.stage=merge", f"hydra.run.dir={tmp_path / 'merged'}", timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    pd.testing.assert_frame_equal(
        pd.read_parquet(tmp_path / "merged" / "positions.parquet"), pd.read_parquet(root / "run" / "positions.parquet")
    )


@pytest.mark.slow
def test_the_season_defaults_are_the_fast_settings_with_the_full_sets_solver_fixes(season, compose_cfg, tmp_path):
    """The season's defaults (lean features, the coarse GCC search: the fixture's run) place the season as
    the full set with the default search does (``features=physics solver=consistent_set``): near the
    truth, the solver's fixes the same (the same consistent sets from nearly the same lags); each fitted method records
    its settings, so every shard runs what was fitted."""
    root, truth, _, cfg = season
    assert cfg.solver._target_.endswith(".ConsistentSetSolver") and cfg.features.gcc.search == "coarse"
    assert "ir" not in cfg.features.groups and cfg.data.n_events == 120  # the lean set, and smoke's small fit
    default_method = load_method(root / "out").method.pipeline.c
    assert type(default_method.solver).__name__ == "ConsistentSetSolver" and "ir" not in default_method.feature_sets
    assert default_method.feature_sets["tdoa"].search == "coarse"
    full_cfg = compose_cfg(
        [
            *season_overrides(root, tmp_path / "out", "features=physics", "solver=consistent_set"),
            f"paths.outputs_dir={tmp_path / 'outputs'}",
        ]
    )
    assert full_cfg.solver._target_.endswith(".ConsistentSetSolver") and "ir" in full_cfg.features.groups
    run_experiment(full_cfg, tmp_path / "run")
    full, default = pd.read_parquet(tmp_path / "run" / "positions.parquet"), pd.read_parquet(root / "run" / "positions.parquet")
    assert len(full) == len(default) == N_CALLS
    for table in (full, default):
        error = np.hypot(table["x_m"] - truth["x_m"], table["y_m"] - truth["y_m"])
        assert np.median(error) < 1.0 and (error < 5).mean() >= 0.9, error.describe()
    apart = np.hypot(full["solver_x_m"] - default["solver_x_m"], full["solver_y_m"] - default["solver_y_m"])
    assert (apart < 0.05).mean() >= 0.9, apart.describe()
    saved = load_method(tmp_path / "out").method.pipeline.c
    assert type(saved.solver).__name__ == "ConsistentSetSolver" and "ir" in saved.feature_sets
    assert saved.feature_sets["tdoa"].search == "fine"


@pytest.mark.slow
def test_a_season_with_calibration_places_calls_with_the_calibrated_array(tmp_path, caplog):
    """The recorders stand 1.5–2 m off their stated positions; a calibration from 8 spots of exact playbacks moves them back, and
    the season run with ``calibration=PATH`` places the calls several times closer, recording the file's digest on every row."""
    import dataclasses

    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from acoustlab.run.registry import CONF_DIR
    from acoustlab.stages.field_calibration import write_calibration
    from acoustlab.toolkit.array_calibration import Priors, calibrate_array
    from tests.test_field_calibration import playbacks

    def configure(*extra):
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose(
                config_name="config",
                overrides=season_overrides(tmp_path, tmp_path / "out", f"paths.outputs_dir={tmp_path / 'outputs'}", *extra),
            )

    site = site_from_config(configure().site)
    true_mics = site.mic_positions_m + np.array([[0.0, 0.0, 0.0], [1.5, -1.2, 0.0], [-1.0, 1.6, 0.0]])
    settings = SyntheticSeason.for_site(site, duration_s=40, file_s=20, n_calls=16, min_spacing_s=2.0, sample_rate_hz=24000.0)
    truth = write_season(dataclasses.replace(settings, mics_m=true_mics), tmp_path)
    spots = np.column_stack([np.random.default_rng(1).uniform(-40, 40, (8, 2)) + site.mic_positions_m[:, :2].mean(0), np.full(8, 1.5)])
    calibration = calibrate_array(
        playbacks(true_mics, spots, np.zeros(3), 0.0), Priors(site.mic_positions_m, np.full(3, 2.0)), ["0", "1", "2"], timing_sigma_s=1e-5
    )
    np.testing.assert_allclose(calibration.mic_positions_m[:, :2], true_mics[:, :2], atol=0.05)
    path = tmp_path / "calibration.json"
    digest = write_calibration(path, calibration, site, pd.DataFrame({"event_id": [f"pb{k}" for k in range(len(calibration.spot))]}))
    # a season reads no thermometer: the allowance keeps the stated thermometer σ for its one assumed temperature
    from acoustlab.run.app import build_run
    from acoustlab.stages.field_calibration import load_calibration

    built = build_run(configure(f"calibration={path}", "conformal.input_uncertainty.temperature_c=1.5"))
    carried = built.protocol.with_assumed_weather(built.context).components.input_uncertainty
    from_file = load_calibration(str(path), site).input_uncertainty().covariance
    assert carried.covariance[0, 0] == pytest.approx(from_file[0, 0] + 1.5**2)
    np.testing.assert_array_equal(carried.covariance[1:, 1:], from_file[1:, 1:])
    given = build_run(configure(f"calibration={path}", "protocol.temperature_c=11.0")).protocol
    caplog.clear()
    given.warn_about_calibration(load_calibration(str(path), site))
    assert "protocol.temperature_c is not given" not in caplog.text
    errors = {}
    for label, extra in (("stated", ()), ("calibrated", (f"calibration={path}", f"protocol.output_dir={tmp_path / 'out_cal'}"))):
        metrics = run_experiment(configure(*extra), tmp_path / label)
        table = pd.read_parquet(tmp_path / label / "positions.parquet")
        errors[label] = float(np.median(np.hypot(table["x_m"] - truth["x_m"], table["y_m"] - truth["y_m"])))
    GlobalHydra.instance().clear()
    assert "protocol.temperature_c is not given" in caplog.text  # the offset needs a thermometer's reading to correct
    assert errors["calibrated"] < 0.4 * errors["stated"], errors
    assert (table["calibration_sha256"] == digest).all()
    assert metrics["field_calibration"]["sha256"] == digest


@pytest.mark.slow
def test_the_same_season_command_resumes_in_the_same_folder(season, tmp_path):
    """Without protocol.output_dir the season's folder is named by its inputs under paths.outputs_dir: running the command
    again finds it, reuses the fitted method and computes no chunk twice; another chunking gets a folder of its own."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from acoustlab.run.registry import CONF_DIR

    root, _, _, _ = season

    def run(name, *extra):
        overrides = [o for o in season_overrides(root, None) if not o.startswith("protocol.output_dir")]
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=[*overrides, f"paths.outputs_dir={tmp_path / 'outputs'}", *extra])
        metrics = run_experiment(cfg, tmp_path / name)
        GlobalHydra.instance().clear()
        return metrics["season"]

    first, again = run("first"), run("again")
    assert first["output_dir"] == again["output_dir"] and Path(first["output_dir"]).is_relative_to(tmp_path / "outputs" / "seasons")
    assert first["chunks_computed"] > 0 and again["chunks_computed"] == 0
    assert run("other", "protocol.chunk_events=7")["output_dir"] != first["output_dir"]


@pytest.mark.slow
def test_the_detector_tables_are_read_once_and_kept_compact(season, tmp_path, monkeypatch):
    """The preflight's read of the tables is the one the fit uses (not read twice); repeated strings are categories."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from acoustlab.run.registry import CONF_DIR
    from acoustlab.season import protocol

    root, _, _, _ = season
    reads = []
    real = protocol.read_detections

    def counting(*args, **kwargs):
        table = real(*args, **kwargs)
        reads.append(table)
        return table

    monkeypatch.setattr(protocol, "read_detections", counting)
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=season_overrides(root, tmp_path / "out", f"paths.outputs_dir={root / 'outputs'}"))
    run_experiment(cfg, tmp_path / "run")
    GlobalHydra.instance().clear()
    assert len(reads) == 1
    assert all(str(reads[0][c].dtype) == "category" for c in ("recorder_id", "label", "source"))


@pytest.mark.slow
def test_a_season_folder_with_an_attacker_s_method_runs_no_code(season, compose_cfg, tmp_path, caplog):
    """A received or tampered season folder whose method is replaced by a pickle that would create a file, with every digest
    beside it (method.sha256.json, season.json) updated to match: the season stops in one line and the file is never made
    (a saved method is read without running code, whoever wrote it); ``protocol.stage=fit`` fits it again."""
    import hashlib
    import pickle

    from acoustlab.method.saved import DIGEST_FILE
    from acoustlab.season.stream import MANIFEST

    root, _, _, _ = season
    folder = tmp_path / "received"
    shutil.copytree(root / "out", folder, ignore=shutil.ignore_patterns("parts"))
    created = tmp_path / "pwned"

    class Payload:  # what an attacker would ship: code that runs when unpickled
        def __reduce__(self):
            return (open, (str(created), "w"))

    evil = pickle.dumps(Payload())
    (folder / METHOD_FILE).write_bytes(evil)
    digest = hashlib.sha256(evil).hexdigest()
    record = json.loads((folder / DIGEST_FILE).read_text())
    (folder / DIGEST_FILE).write_text(json.dumps({**record, "sha256": digest}))
    manifest = json.loads((folder / MANIFEST).read_text())
    (folder / MANIFEST).write_text(json.dumps({**manifest, "method_sha256": digest}))
    overrides = season_overrides(root, folder, f"paths.outputs_dir={tmp_path / 'outputs'}")
    with pytest.raises(DataError, match="not a saved acoustlab method"):
        run_experiment(compose_cfg([*overrides, "protocol.stage=localize"]), tmp_path / "run")
    assert not created.exists()
    # the fit stage fits a method it cannot load again (one warning), and the season then runs with it
    with caplog.at_level(logging.WARNING, logger="acoustlab.season"):
        run_experiment(compose_cfg(overrides), tmp_path / "refit")
    assert "is not used" in caplog.text and "fitting it again" in caplog.text
    assert load_method(folder, json.loads((folder / MANIFEST).read_text())["method_sha256"]) is not None
    assert not created.exists()


@pytest.mark.slow
def test_a_season_on_mics_given_in_latitude_longitude_is_a_map_layer_in_their_utm_zone(compose_cfg, tmp_path, caplog):
    """Mics as a GPS shows them (latitude/longitude, no local coordinates): the season is placed in their local frame and
    every position is also written in the UTM zone's easting/northing and in latitude/longitude, and the GeoPackage a GIS
    opens is in that zone; their survey error (``position_sigma_m``) is carried by the radii."""
    gpd = pytest.importorskip("geopandas")
    from test_map_frame import gps_table

    from acoustlab.toolkit.map_frame import geographic_of

    gps_table(position_sigma_m=3.0).to_csv(tmp_path / "mics.csv", index=False)
    overrides = season_overrides(tmp_path, tmp_path / "out", f"paths.outputs_dir={tmp_path / 'outputs'}")
    overrides[0:1] = ["+site=from_csv", f"site.mics_csv={tmp_path / 'mics.csv'}"]
    cfg = compose_cfg(overrides)
    site = site_from_config(cfg.site)
    truth = write_season(
        SyntheticSeason.for_site(
            site, duration_s=30, file_s=15, n_calls=8, min_spacing_s=2.0, sample_rate_hz=float(cfg.simulator.sample_rate_hz)
        ),
        tmp_path,
    )
    with caplog.at_level(logging.INFO):
        run_experiment(cfg, tmp_path / "run")
    # a GPS-surveyed array without playbacks: the radii carry the survey's error, as localize's do, and say so
    assert "the radii carry the mics table's survey error, position_sigma_m up to 3.00 m" in caplog.text
    fitted = load_method(tmp_path / "out", read_manifest(tmp_path / "out")["method_sha256"])
    assert fitted.components.input_uncertainty.mic_position_m == 3.0
    table = pd.read_parquet(tmp_path / "run" / "positions.parquet")
    placed = table["placed"].to_numpy(bool)
    assert placed.sum() >= 6 and (table["crs"] == "EPSG:32617").all()
    assert np.median(np.hypot(table["x_m"] - truth["x_m"], table["y_m"] - truth["y_m"])[placed]) < 1.0
    latitude, longitude = geographic_of(table["easting_m"], table["northing_m"], "EPSG:32617")
    np.testing.assert_allclose(table[["latitude", "longitude"]][placed], np.c_[latitude, longitude][placed], atol=1e-12)
    assert table["latitude"][placed].between(41.2995, 41.3009).all()  # in and around the array
    layer = gpd.read_file(tmp_path / "run" / "positions.gpkg", layer="positions")
    assert layer.crs.to_epsg() == 32617
    np.testing.assert_allclose(layer.geometry.x[placed], table["easting_m"][placed], atol=1e-6)
