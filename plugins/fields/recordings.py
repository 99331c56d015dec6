"""Real recordings as input: a folder of WAV/FLAC files with a mics table and an events table.

Two layouts are accepted.

acoustlab layout
    ``mics_csv`` with ``mic_id, x_m, y_m, z_m`` and either a ``file`` column (one mono file per
    mic) or none (then ``events_csv`` has a ``file`` column naming one multichannel file per
    event, channels in the mics table's order). ``events_csv`` has ``event_id`` (a whole number, or
    text such as ``call00``, given back as is in the positions), ``start_s, end_s``
    and optionally ``file``, ``position_id``, ``x_m, y_m`` (true position when known),
    ``temperature_c``, ``relative_humidity_pct``, ``hardware_failure``, ``low_hz, high_hz`` (the
    event's own frequency band: its GCC runs there, as a season's detector bands do) and
    ``time_s`` (when it happened, for a field calibration's clock drift).

OpenSoundscape layout (so its users can switch)
    ``coords_csv`` with ``file, x, y[, z]`` (one row per file; files at the same coordinates are
    one recorder's, read by their start times: ``acoustlab.toolkit.peer_tables``) and
    ``detections_csv`` with ``file, start_time, end_time`` and one 0/1 column per class; every
    window detected by at least ``min_receivers`` recorders becomes an event (recorders that did
    not detect it are still used; their clip is cut at the same times). Detection times are each
    file's own; windows of different recorders are linked by overlap (``linked_windows``), one per
    recorder.

Start times. Where the mics have files of their own, each clip is cut at its own file's time: a
file's start comes from a table (mics ``start_time``, coordinates or detections
``start_timestamp``), else its metadata or name (``acoustlab.toolkit.file_start``); with none the
files are taken to start together. ``events_csv`` times are seconds from the earliest file's start.

Unknown true positions are NaN; events without a ``position_id`` each get their own.

Checks. ``RecordingFolder.validate`` (run by the preflight, before any simulation) reads the
tables and the audio files' headers only: numbers where numbers belong, unique event ids, files
that exist inside ``audio_dir``, readable headers, enough channels, events no longer than
``max_event_s``. Problems of the samples themselves are per clip and do not stop a run:
``RecordingFolder.load`` flags each event (``quality_flags``, e.g. ``"mic 2: dead"``) whose
clip on some mic is out of the file, truncated, non-finite, dead or clipped
(``acoustlab.toolkit.quality``); flagged events stay in the predictions and are left out of
summaries, and a mic dead in every event of a position sets that position's ``hardware_failure``.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError, DataError, show
from acoustlab.core.resources import resolve_path
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.toolkit.audio import load_channels, load_mono
from acoustlab.toolkit.dsp import clip_samples
from acoustlab.toolkit.file_start import file_start_time
from acoustlab.toolkit.map_frame import map_projection, spots_in_local_frame, with_map_coordinates
from acoustlab.toolkit.peer_tables import RECORDER, recorders_of, without_heightless
from acoustlab.toolkit.quality import (
    DEAD_MICS,
    QUALITY_REASONS,
    QualityThresholds,
    clip_quality,
    duplicate_channels,
    failed_positions,
    mics_to_drop,
)
from acoustlab.toolkit.table_times import iso_times

log = logging.getLogger(__name__)

#: Events column: the user's event id where it is text (``event_id`` is then the row's number).
EVENT_NAME = "event_name"
#: Mics table column (computed): when the mic's file starts after the earliest file, s.
FILE_OFFSET = "file_offset_s"
#: A recorder that made several files (OpenSoundscape's layout): its files in order of start, and each one's ``FILE_OFFSET``.
RECORDER_FILES = "recorder_files"
RECORDER_OFFSETS = "recorder_offsets_s"

#: Largest audio array (events × mics × samples, float32) a load may allocate, bytes.
MAX_AUDIO_BYTES = 4 * 2**30
#: Peak memory of a localize run per byte of its audio array (the features' spectra and correlations; 7.2 GB measured for a
#: 0.95 GiB array of 60 windows of 59 s), used by the preflight against the memory available.
PEAK_PER_AUDIO_BYTE = 8


def available_memory_bytes() -> int | None:
    """Memory available to a new allocation (Linux ``MemAvailable``), or None where it cannot be read."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _read(path_text: str, field: str, required: tuple[str, ...]) -> pd.DataFrame:
    """A CSV table with its required columns and at least one row (errors name the file)."""
    path = resolve_path(path_text)
    if not path.is_file():
        raise DataError(f"field.{field}: file {path} does not exist")
    try:
        table = pd.read_csv(path, skipinitialspace=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, OSError) as exc:
        raise DataError(f"field.{field}: cannot read {path} as a CSV table: {str(exc).splitlines()[0]}") from None
    table.columns = [str(c).strip() for c in table.columns]
    if field == "mics_csv":  # mics given by latitude/longitude: their local frame and map coordinates
        table = with_map_coordinates(table, f"field.{field}: {path}")
    if "file" in required and "file" not in table.columns and table.columns[0].startswith("Unnamed: 0"):
        table = table.rename(columns={table.columns[0]: "file"})  # the index pandas wrote (OpenSoundscape's aru_coords.csv)
    missing = [c for c in required if c not in table.columns]
    if missing:
        raise DataError(f"field.{field}: {path} lacks columns {missing}; found {list(table.columns)}")
    if table.empty:
        raise DataError(f"field.{field}: {path} has a header but no rows")
    table.attrs["path"] = str(path)
    return table


def _number_text_spots(events: pd.DataFrame) -> None:
    """Text spot ids (``spot_01``, as ``plan_playbacks`` names them) numbered in order of first appearance, in place; a
    row without one (a detection of unknown position) gets a number of its own after them. A column of numbers is left
    as it is."""
    if col.POSITION_ID not in events:
        return
    raw = events[col.POSITION_ID]
    given = raw.notna() & (raw.astype(str).str.strip() != "")
    if pd.to_numeric(raw[given], errors="coerce").notna().all():
        return
    codes, _ = pd.factorize(raw[given].astype(str).str.strip())
    numbered = np.empty(len(events), dtype=np.int64)
    numbered[given.to_numpy()] = codes
    numbered[~given.to_numpy()] = codes.max(initial=-1) + 1 + np.arange(int((~given).sum()))
    events[col.POSITION_ID] = numbered


def _numeric(
    table: pd.DataFrame, field: str, columns: tuple[str, ...], finite: bool = True, lower: float | None = None, upper: float | None = None
) -> None:
    """Convert ``columns`` to float in place; a cell that is not a number (or not finite, or out of range) names its line."""
    for name in columns:
        if name not in table:
            continue
        raw = table[name]
        values = pd.to_numeric(raw, errors="coerce").astype(float)
        bad = (raw.notna() & values.isna()) | (~np.isfinite(values) if finite else np.isinf(values))
        if lower is not None:
            bad |= values < lower
        if upper is not None:
            bad |= values > upper
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            expected = "a finite number" if finite else "a number or empty"
            if lower is not None or upper is not None:
                expected += f" in [{lower}, {upper}]"
            raise DataError(
                f"field.{field}: {table.attrs.get('path', field)}, line {i + 2}, column {name!r}: {show(raw.iloc[i])} is not {expected}"
            )
        table[name] = values


def _unique(table: pd.DataFrame, field: str, column: str) -> None:
    duplicated = table[column][table[column].duplicated()]
    if not duplicated.empty:
        raise DataError(
            f"field.{field}: {table.attrs.get('path', field)}, column {column!r}: "
            f"{show(duplicated.iloc[0])} appears more than once; every row needs its own {column}"
        )


class RecordingFolder:
    """Field recordings from files (see the module docstring).

    Parameters
    ----------
    audio_dir : str
        Folder of the audio files (paths in the tables are relative to it).
    mics_csv, events_csv : str, optional
        acoustlab layout tables.
    coords_csv, detections_csv : str, optional
        OpenSoundscape layout tables (used when given instead of the above).
    sample_rate_hz : float
        Rate the audio is resampled to, Hz.
    temperature_c, relative_humidity_pct : float
        Weather assumed where the events table has none.
    min_receivers : int
        OpenSoundscape layout: minimum receivers that detected a window.
    pad_s : float
        Extra audio kept before the start and after the end of each event, s.
    max_event_s : float
        Longest event accepted, s (a typo such as ``end_s=3600`` stops in the preflight instead
        of allocating gigabytes).
    allow_outside_audio_dir : bool
        Accept file names that resolve outside ``audio_dir`` (``../``, absolute paths, links).
    quality : dict, optional
        ``acoustlab.toolkit.quality.QualityThresholds`` fields (``dead_peak_to_peak``,
        ``clip_level``, ``clip_share``).
    recorder_sample_rate_hz : float, optional
        The rate the recorders were set to; every audio file's header must declare it (a file whose
        samples were written under another rate would place sources metres off). None: not checked.
    compare_durations : bool
        With one file per mic, refuse a file whose duration is a standard-rate ratio of the
        others' median (half as long: 24 kHz samples under a 48 kHz header), naming it.
    chunk_events : int
        Events read and turned into features at a time (``load_chunks``): peak memory is one
        chunk's audio and its transforms, whatever the number of events. The answer does not
        depend on it (each event's features are its own).

    Notes
    -----
    A mics table may name one multichannel file for several mics; it then needs a ``channel``
    column (0-based) saying which channel each mic is (never the average of all channels). Two
    mics whose clips of an event are identical sample for sample are flagged ``duplicate``.
    """

    def __init__(
        self,
        audio_dir: str,
        mics_csv: str | None = None,
        events_csv: str | None = None,
        coords_csv: str | None = None,
        detections_csv: str | None = None,
        sample_rate_hz: float = 24000.0,
        temperature_c: float = 15.0,
        relative_humidity_pct: float = 60.0,
        min_receivers: int = 3,
        pad_s: float = 0.05,
        max_event_s: float = 60.0,
        allow_outside_audio_dir: bool = False,
        quality: dict | None = None,
        recorder_sample_rate_hz: float | None = None,
        compare_durations: bool = True,
        chunk_events: int = 256,
    ) -> None:
        if not ((mics_csv and events_csv) or (coords_csv and detections_csv)):
            raise ConfigError("field: give mics_csv and events_csv, or coords_csv and detections_csv (OpenSoundscape layout)")
        for name, value, low in (("sample_rate_hz", sample_rate_hz, 1.0), ("max_event_s", max_event_s, 1e-3), ("pad_s", pad_s, 0.0)):
            if not isinstance(value, (int, float)) or not np.isfinite(value) or value < low:
                raise ConfigError(f"field.{name} must be a number >= {low}; got {value!r}")
        if not -60.0 <= float(temperature_c) <= 60.0:
            raise ConfigError(f"field.temperature_c must lie in [-60, 60] °C; got {temperature_c}")
        if not 0.0 <= float(relative_humidity_pct) <= 100.0:
            raise ConfigError(f"field.relative_humidity_pct must lie in [0, 100] %; got {relative_humidity_pct}")
        if not isinstance(chunk_events, int) or chunk_events < 1:
            raise ConfigError(f"field.chunk_events must be a whole number >= 1; got {chunk_events!r}")
        self.chunk_events = chunk_events
        if int(min_receivers) < 2:
            raise ConfigError(f"field.min_receivers must be >= 2; got {min_receivers}")
        self.audio_dir = audio_dir
        self.mics_csv, self.events_csv = mics_csv, events_csv
        self.coords_csv, self.detections_csv = coords_csv, detections_csv
        self.sample_rate_hz = float(sample_rate_hz)
        self.temperature_c = float(temperature_c)
        self.relative_humidity_pct = float(relative_humidity_pct)
        self.min_receivers = int(min_receivers)
        self.pad_s = float(pad_s)
        self.max_event_s = float(max_event_s)
        self.allow_outside_audio_dir = bool(allow_outside_audio_dir)
        if recorder_sample_rate_hz is not None and not (isinstance(recorder_sample_rate_hz, (int, float)) and recorder_sample_rate_hz > 0):
            raise ConfigError(f"field.recorder_sample_rate_hz must be a positive number (Hz) or null; got {recorder_sample_rate_hz!r}")
        self.recorder_sample_rate_hz = None if recorder_sample_rate_hz is None else float(recorder_sample_rate_hz)
        self.compare_durations = bool(compare_durations)
        try:
            self.thresholds = QualityThresholds(**(quality or {}))
        except TypeError as exc:
            raise ConfigError(f"field.quality: {exc}; known keys: dead_peak_to_peak, clip_level, clip_share") from None

    # ----------------------------------------------------------------------------------- tables
    def tables(self) -> tuple[pd.DataFrame, pd.DataFrame]:
        """(mics, events) in the acoustlab layout, checked, converting the OpenSoundscape layout if needed.

        Read once per state of the table files (path, size, modification time): a run asks for them
        several times, and the files' start times may come from every audio file's metadata.
        """
        state = tuple(
            (str(path), path.stat().st_size, path.stat().st_mtime_ns) if path.is_file() else (str(path),)
            for path in (resolve_path(t) for t in (self.mics_csv, self.events_csv, self.coords_csv, self.detections_csv) if t)
        )
        if getattr(self, "_tables_read", (None,))[0] != state:
            self._tables_read = (state, self._read_tables())
        mics, events = self._tables_read[1]
        return mics.copy(), events.copy()

    def _read_tables(self) -> tuple[pd.DataFrame, pd.DataFrame]:
        if self.mics_csv and self.events_csv:
            mics = _read(self.mics_csv, "mics_csv", col.MIC_XYZ)
            events = _read(self.events_csv, "events_csv", (col.EVENT_ID, col.START, col.END))
        else:
            mics, events = self._opensoundscape_tables()
        _numeric(mics, "mics_csv", col.MIC_XYZ)
        if "mic_id" in mics:
            _unique(mics, "mics_csv", "mic_id")
        if "file" in mics:
            mics["file"] = mics["file"].astype(str).str.strip()
        if (
            col.EVENT_ID in events
            and events[col.EVENT_ID].notna().all()
            and pd.to_numeric(events[col.EVENT_ID], errors="coerce").isna().all()
        ):
            # text ids (call00, …): kept as the user's name of the event, numbered in table order inside; a mix of numbers
            # and text, or an empty id, is refused below as a cell that is not a number
            events[col.EVENT_ID] = events[col.EVENT_ID].astype(str).str.strip()
            _unique(events, "events_csv", col.EVENT_ID)
            events[EVENT_NAME] = events[col.EVENT_ID]
            events[col.EVENT_ID] = np.arange(len(events))
        _number_text_spots(events)
        events = spots_in_local_frame(events, mics, f"field.events_csv: {events.attrs.get('path')}")
        _numeric(events, "events_csv", (col.EVENT_ID, col.START, col.END, col.POSITION_ID))
        _numeric(events, "events_csv", (col.TRUE_X, col.TRUE_Y, col.TRUE_Z), finite=False)
        _numeric(events, "events_csv", (col.POSITION_SIGMA,), finite=False, lower=0.0)  # a spot's survey error per axis, m
        _numeric(events, "events_csv", (col.TEMPERATURE,), lower=-60.0, upper=60.0)
        _numeric(events, "events_csv", ("time_s",), finite=False)
        self._check_bands(events)
        _numeric(events, "events_csv", (col.HUMIDITY,), lower=0.0, upper=100.0)
        for name in (col.EVENT_ID, col.POSITION_ID):
            if name in events and (events[name] != np.round(events[name])).any():
                i = int(np.flatnonzero((events[name] != np.round(events[name])).to_numpy())[0])
                raise DataError(
                    f"field.events_csv: {events.attrs.get('path')}, line {i + 2}, column {name!r}: "
                    f"{show(events[name].iloc[i])} is not a whole number"
                )
        events[col.EVENT_ID] = events[col.EVENT_ID].astype(np.int64)
        _unique(events, "events_csv", col.EVENT_ID)
        too_short = events[col.END] <= events[col.START]
        if too_short.any():
            i = int(np.flatnonzero(too_short.to_numpy())[0])
            raise DataError(
                f"field.events_csv: {events.attrs.get('path')}, line {i + 2}: end_s {events[col.END].iloc[i]} "
                f"is not after start_s {events[col.START].iloc[i]}"
            )
        too_long = (events[col.END] - events[col.START]) > self.max_event_s
        if too_long.any():
            i = int(np.flatnonzero(too_long.to_numpy())[0])
            raise DataError(
                f"field.events_csv: {events.attrs.get('path')}, line {i + 2}: the event lasts "
                f"{events[col.END].iloc[i] - events[col.START].iloc[i]:g} s, more than field.max_event_s={self.max_event_s:g} s "
                f"(raise it if the event really is that long)"
            )
        if "file" not in mics and "file" not in events:
            raise DataError("field: the mics table has no 'file' column, so events_csv needs one (multichannel files)")
        if "file" in mics and FILE_OFFSET not in mics:
            where = f"field.mics_csv: {mics.attrs.get('path')}"
            starts = self._file_starts(mics["file"].astype(str).str.strip().tolist(), mics.get("start_time"), where, "start_time")
            mics[FILE_OFFSET] = _offsets(starts, mics["file"].astype(str).str.strip())
        if "file" in events:
            events["file"] = events["file"].astype(str).str.strip()
        return mics, events

    def _opensoundscape_tables(self) -> tuple[pd.DataFrame, pd.DataFrame]:
        coords = _read(self.coords_csv, "coords_csv", ("file", "x", "y"))
        det = _read(self.detections_csv, "detections_csv", ("file", "start_time", "end_time"))
        coords["file"] = coords["file"].astype(str).str.strip()
        det["file"] = det["file"].astype(str).str.strip()
        unused = ~coords["file"].isin(set(det["file"]))
        if unused.any() and not unused.all():  # a file no detection names needs no coordinates (its row may lack them)
            log.info(
                "field.coords_csv: %d files have no detections and are left out (first: %r)",
                int(unused.sum()),
                coords["file"][unused].iloc[0],
            )
            path = coords.attrs["path"]
            coords = coords[~unused].reset_index(drop=True)
            coords.attrs["path"] = path
        coords = without_heightless(coords, f"field.coords_csv: {coords.attrs.get('path')}")
        _numeric(coords, "coords_csv", ("x", "y", "z"))
        _numeric(det, "detections_csv", ("start_time", "end_time"))
        classes = [c for c in det.columns if c not in ("file", "start_time", "end_time", "start_timestamp")]
        _numeric(det, "detections_csv", tuple(classes))
        files = recorders_of(coords, None)  # files at one position are one recorder's
        known = det["file"].isin(set(files["file"]))
        if not known.any():
            raise DataError(
                f"field.detections_csv: none of its files ({show(det['file'].iloc[0])}, …) is in the coords table "
                f"{coords.attrs['path']} ({show(files['file'].iloc[0])}, …); the file names must match"
            )
        if not known.all():
            log.warning(
                "field.detections_csv: %d detections name files not in the coords table and are ignored (first: %r)",
                int((~known).sum()),
                det.loc[~known, "file"].iloc[0],
            )
        hit = det[classes].max(axis=1) > 0 if classes else pd.Series(True, index=det.index)
        stated = coords.set_index("file")["start_timestamp"] if "start_timestamp" in coords else None
        if stated is None and "start_timestamp" in det:  # the peer's absolute window starts: each file's start follows
            absolute = iso_times(det["start_timestamp"], f"field.detections_csv: {det.attrs.get('path')}", "start_timestamp")
            stated = (absolute - pd.to_timedelta(det["start_time"].to_numpy(float), unit="s")).groupby(det["file"]).min()
        where = f"field.coords_csv: {coords.attrs.get('path')}"
        starts = self._file_starts(files["file"].tolist(), None if stated is None else files["file"].map(stated), where, "start_timestamp")
        files[FILE_OFFSET] = _offsets(starts, files["file"])
        mics = _recorder_mics(files)
        mics.attrs["path"] = coords.attrs["path"]
        det = det[hit & known]
        offset = det["file"].map(dict(zip(files["file"], files[FILE_OFFSET], strict=True))).to_numpy(float)
        recorder = det["file"].map(dict(zip(files["file"], files[RECORDER], strict=True))).to_numpy()
        windows = linked_windows(recorder, det["start_time"].to_numpy(float) + offset, det["end_time"].to_numpy(float) + offset)
        windows = windows[windows["n_files"] >= self.min_receivers]
        if windows.empty:
            raise DataError(
                f"field.detections_csv: no time window was detected by at least field.min_receivers={self.min_receivers} "
                f"receivers, so there is nothing to localize"
            )
        events = pd.DataFrame(
            {
                col.EVENT_ID: np.arange(len(windows)),
                col.START: windows[col.START].to_numpy(float),
                col.END: windows[col.END].to_numpy(float),
            }
        )
        events.attrs["path"] = det.attrs.get("path", self.detections_csv)
        return mics, events

    def _file_starts(self, files: list[str], stated: pd.Series | None, where: str, column: str) -> pd.Series | None:
        """Each per-mic file's start time: stated in a table column, else read from the file (metadata, else its name).

        None where no file says when it starts (the files are taken to start together); one line
        naming a file where some do and some do not.
        """
        if stated is not None:
            return iso_times(stated, where, column)
        starts = pd.Series([file_start_time(self.audio_path(f)) for f in files], index=files, dtype=object)
        known = starts.notna().to_numpy()
        if not known.any():
            return None
        if not known.all():
            missing, given = files[int(np.flatnonzero(~known)[0])], files[int(np.flatnonzero(known)[0])]
            raise DataError(
                f"field: {missing!r} says nothing of when it starts (no GUANO, Broadcast WAV, AudioMoth or OpenSoundscape time, no time in its "
                f"name) while {given!r} does; give every file's start ({where}, column {column}) or none"
            )
        return pd.to_datetime(starts)

    # ------------------------------------------------------------------------------------ audio
    def audio_path(self, file: str) -> Path:
        """Where a file named in a table lies; outside ``audio_dir`` only with ``allow_outside_audio_dir``."""
        root = resolve_path(self.audio_dir)
        path = (root / str(file)).resolve()
        if not self.allow_outside_audio_dir and not path.is_relative_to(root.resolve()):
            raise DataError(
                f"field: the file {file!r} resolves to {path}, outside field.audio_dir={root}; "
                "set field.allow_outside_audio_dir=true to read it anyway"
            )
        if not path.is_file():
            raise DataError(f"field: audio file {path} does not exist")
        return path

    @staticmethod
    def _audio_files(mics: pd.DataFrame, events: pd.DataFrame) -> list[str]:
        """The audio files the tables name, each once: one per mic (or several: a recorder's files), or one multichannel file per event."""
        if RECORDER_FILES in mics:
            return list(dict.fromkeys(f for files in mics[RECORDER_FILES] for f in files))
        return list(dict.fromkeys(mics["file"] if "file" in mics else events["file"]))

    def _header(self, path: Path) -> object:
        """soundfile's header of a file; a clear error where it cannot be read."""
        import soundfile as sf

        try:
            info = sf.info(str(path))
        except Exception as exc:  # noqa: BLE001 - soundfile raises RuntimeError/LibsndfileError/OSError
            raise DataError(f"field: cannot read the audio header of {path}: {exc}") from None
        if info.samplerate <= 0 or info.channels < 1:
            raise DataError(f"field: {path} declares {info.samplerate} Hz and {info.channels} channels")
        if info.frames == 0:
            log.warning("field: %s holds no samples; every event on it is flagged out_of_range", path)
        return info

    def validate(self, site: Site | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
        """Check the tables and the audio headers without reading samples (the preflight); return the tables.

        Raises
        ------
        DataError
            Naming the file, line, column or value and what was expected.
        """
        mics, events = self.tables()
        if site is not None:
            positions = mics[list(col.MIC_XYZ)].to_numpy(float)
            if positions.shape != site.mic_positions_m.shape or not np.allclose(positions, site.mic_positions_m, atol=1e-3):
                raise DataError(
                    f"field: the recordings' {len(positions)} mic positions do not match site {site.name!r} "
                    f"({site.n_mics} mics); build the site from the same mics table"
                )
        durations: dict[str, tuple[float, float]] = {}
        for file in self._audio_files(mics, events):
            path = self.audio_path(file)
            info = self._header(path)
            durations[str(path)] = (info.frames / info.samplerate, float(info.samplerate))
            if "file" not in mics and info.channels < len(mics):
                raise DataError(f"field: {path} has {info.channels} channels but the mics table lists {len(mics)} mics")
            if self.recorder_sample_rate_hz is not None and info.samplerate != self.recorder_sample_rate_hz:
                raise DataError(
                    f"field: {path} declares {info.samplerate} Hz but field.recorder_sample_rate_hz is "
                    f"{self.recorder_sample_rate_hz:g} Hz; fix the file's header (or the setting)"
                )
            if "file" in mics:
                self._check_channels(mics, file, path, info.channels)
        # a recorder's several files cover different stretches (only those with detections are read): nothing to compare
        if "file" in mics and RECORDER_FILES not in mics and self.compare_durations:
            _check_rate_labels(durations)
        self._check_memory(len(mics), events)
        return mics, events

    def _check_memory(self, n_mics: int, events: pd.DataFrame) -> None:
        """One chunk of events (``chunk_events``, at the longest event) must fit in memory while its features are computed."""
        n = int(((events[col.END] - events[col.START]).max() + 2 * self.pad_s) * self.sample_rate_hz) + 1
        at_once = min(len(events), self.chunk_events)
        size = at_once * n_mics * n * 4
        if size > MAX_AUDIO_BYTES:
            raise DataError(
                f"field: {at_once} events × {n_mics} mics × {n} samples need {size / 2**30:.1f} GiB at once; "
                f"lower field.chunk_events (now {self.chunk_events}; at most {MAX_AUDIO_BYTES / 2**30:.0f} GiB at once)"
            )
        available = available_memory_bytes()
        if available is not None and PEAK_PER_AUDIO_BYTE * size > available:
            raise DataError(
                f"field: {at_once} events × {n_mics} mics × {n} samples ({size / 2**30:.2f} GiB of audio) at once need about "
                f"{PEAK_PER_AUDIO_BYTE * size / 2**30:.1f} GiB while their features are computed, and {available / 2**30:.1f} GiB "
                f"is available; lower field.chunk_events (now {self.chunk_events})"
            )

    def _check_bands(self, events: pd.DataFrame) -> None:
        """Per-event frequency bands (``low_hz``, ``high_hz``, as a detector table gives them): 0 ≤ low < high ≤ Nyquist, or both empty."""
        names = [c for c in ("low_hz", "high_hz") if c in events]
        if not names:
            return
        if len(names) == 1:
            raise DataError(f"field.events_csv: {events.attrs.get('path')} has {names[0]} without its pair; give both low_hz and high_hz")
        nyquist = self.sample_rate_hz / 2
        _numeric(events, "events_csv", ("low_hz", "high_hz"), finite=False, lower=0.0, upper=nyquist)
        low, high = events["low_hz"].to_numpy(float), events["high_hz"].to_numpy(float)
        bad = (np.isfinite(low) != np.isfinite(high)) | (np.isfinite(low) & np.isfinite(high) & (low >= high))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DataError(
                f"field.events_csv: {events.attrs.get('path')}, line {i + 2}: low_hz {show(low[i])} and high_hz {show(high[i])} "
                "must both be given with low_hz < high_hz (or both empty: the default band)"
            )

    @staticmethod
    def _check_channels(mics: pd.DataFrame, file: str, path: Path, n_channels: int) -> None:
        """Mics sharing a file need a ``channel`` column, within the file's channels, one channel per mic."""
        users = mics.index[mics["file"] == file]
        names = mics["mic_id"].astype(str) if "mic_id" in mics else pd.Series([str(k) for k in range(len(mics))], index=mics.index)
        if "channel" not in mics:
            if len(users) > 1:
                raise DataError(
                    f"field.mics_csv: mics {', '.join(names[users])} all name {path} ({n_channels} channel(s)); add a "
                    f"'channel' column (0-based) saying which channel each mic is, or give each mic its own file"
                )
            return
        channel = pd.to_numeric(mics.loc[users, "channel"], errors="coerce")
        bad = ~channel.between(0, n_channels - 1) | (channel != np.round(channel))
        if bad.any():
            k = bad.idxmax()
            raise DataError(
                f"field.mics_csv: mic {names[k]} reads channel {mics.loc[k, 'channel']!r} of {path}, which has channels 0–{n_channels - 1}"
            )
        if channel.duplicated().any():
            raise DataError(
                f"field.mics_csv: mics {', '.join(names[users[channel.duplicated(keep=False).to_numpy()]])} read the same "
                f"channel of {path}; each mic is its own channel"
            )

    def projection(self) -> tuple[np.ndarray, np.ndarray, str, bool] | None:
        """The rigid map from the site's local frame to the mics table's map coordinates, or None without them.

        A mics table may carry ``easting_m, northing_m`` (and a ``crs`` such as ``EPSG:32617``) or
        ``latitude, longitude`` beside (or instead of) the local ``x_m, y_m``; positions are then
        also written in map coordinates (``acoustlab.toolkit.map_frame.map_projection``).
        """
        mics, _ = self.tables()
        return map_projection(mics, f"field.mics_csv: {mics.attrs.get('path')}")

    def input_files(self) -> list[Path]:
        """Every table and audio file these recordings are read from (the cache key hashes their contents)."""
        mics, events = self.tables()
        tables = [resolve_path(t) for t in (self.mics_csv, self.events_csv, self.coords_csv, self.detections_csv) if t]
        return tables + [self.audio_path(f) for f in self._audio_files(mics, events)]

    def load(self, site: Site) -> RecordingBatch:
        """Cut every event from the recordings, flagging bad clips; see ``acoustlab.core.contracts.FieldSource``.

        All events at once (``load_chunks`` streams them ``chunk_events`` at a time, as ``localize`` does).
        """
        mics, events = self.validate(site)
        batch = self._batch(mics, events)
        batch.events[col.HARDWARE_FAILURE] = failed_positions(batch.events)
        return batch

    def load_chunks(self, site: Site) -> Iterator[RecordingBatch]:
        """The events ``chunk_events`` at a time, each chunk's batch as ``load`` would cut its events (memory: one chunk's audio).

        A position's ``hardware_failure`` from a mic dead in all its events needs every chunk: the
        caller applies ``acoustlab.toolkit.quality.failed_positions`` to the joined events.
        """
        mics, events = self.validate(site)
        for first in range(0, len(events), self.chunk_events):
            yield self._batch(mics, events.iloc[first : first + self.chunk_events])

    def load_events(self, site: Site, event_ids: list[str]) -> RecordingBatch:
        """The clips of the events named ``event_ids`` (as the positions table gives them: the user's text ids, else
        the numbers), in that order, cut as ``load`` cuts them.

        Raises
        ------
        DataError
            Naming the ids the events table does not have.
        """
        mics, events = self.validate(site)
        names = (events[EVENT_NAME] if EVENT_NAME in events else events[col.EVENT_ID]).astype(str).to_numpy()
        wanted = [str(e) for e in event_ids]
        missing = [e for e in wanted if e not in set(names)]
        if missing:
            raise DataError(
                f"field.events_csv: no event {', '.join(missing[:5])} (events: {', '.join(names[:5])}{', …' if len(names) > 5 else ''})"
            )
        rows = [int(np.flatnonzero(names == e)[0]) for e in wanted]
        return self._batch(mics, events.iloc[rows])

    def _batch(self, mics: pd.DataFrame, events: pd.DataFrame) -> RecordingBatch:
        """The clips of ``events`` on every mic, each flagged; ``dead_mics`` and the stated ``hardware_failure`` per event."""
        fs = self.sample_rate_hz
        pad = int(round(self.pad_s * fs))
        # each clip's window (the event widened by pad_s on both sides) cut as a season cuts its clips
        lengths = np.array(
            [clip_samples(0.0, end - start + 2 * self.pad_s, fs)[1] for start, end in zip(events[col.START], events[col.END], strict=True)],
            dtype=np.int64,
        )
        windows = np.round(((events[col.END] - events[col.START]).to_numpy(float) + 2 * self.pad_s) * fs).astype(np.int64)
        audio = np.zeros((len(events), len(mics), int(lengths.max())), dtype=np.float32)
        per_mic = "file" in mics.columns
        paths = {f: str(self.audio_path(f)) for f in self._audio_files(mics, events)}  # resolved once, not per event and mic
        reasons = np.empty((len(events), len(mics)), dtype=object)
        for k, ev in enumerate(events.itertuples()):
            for m in range(len(mics)):
                file, offset = _file_at(mics, m, ev.start_s) if per_mic else (ev.file, 0.0)
                start = clip_samples(ev.start_s - offset - self.pad_s, 0.0, fs)[0]  # each file's own time: it may start later
                if per_mic and "channel" in mics:
                    signal = load_channels(paths[file], fs)[int(mics["channel"].iloc[m])]
                elif per_mic:
                    signal = load_mono(paths[file], fs)
                else:
                    signal = load_channels(paths[ev.file], fs)[m]
                audio[k, m, : lengths[k]], reasons[k, m] = clip_quality(
                    signal, start, int(lengths[k]), self.thresholds, margin=pad, extension=int(lengths[k] - windows[k])
                )
            for m in duplicate_channels(audio[k, :, : lengths[k]]):  # the same samples on two mics: a wiring or table error
                reasons[k, m] = [*reasons[k, m], "duplicate"]
        flags = [_describe(row, mics) for row in reasons]
        dropped, usable = zip(*(mics_to_drop(list(row)) for row in reasons), strict=True) if len(reasons) else ((), ())
        position = events[col.POSITION_ID].to_numpy(int) if col.POSITION_ID in events else events[col.EVENT_ID].to_numpy(int)
        stated_failure = (
            events[col.HARDWARE_FAILURE].astype(str).str.strip().str.lower().isin(["1", "1.0", "true", "yes"]).to_numpy()
            if col.HARDWARE_FAILURE in events
            else np.zeros(len(events), bool)
        )
        n_flagged = sum(bool(f) for f in flags)
        if n_flagged:
            log.warning(
                "field: %d of %d events flagged (%s); they are kept in the predictions and left out of summaries",
                n_flagged,
                len(events),
                "; ".join(f"event {e}: {f}" for e, f in zip(events[col.EVENT_ID], flags, strict=True) if f)[:300],
            )
        rows = pd.DataFrame(
            {
                col.EVENT_ID: events[col.EVENT_ID].to_numpy(int),
                col.POSITION_ID: position,
                col.TRUE_X: events[col.TRUE_X].to_numpy(float) if col.TRUE_X in events else np.nan,
                col.TRUE_Y: events[col.TRUE_Y].to_numpy(float) if col.TRUE_Y in events else np.nan,
                col.TRUE_Z: events[col.TRUE_Z].to_numpy(float) if col.TRUE_Z in events else np.nan,
                col.TEMPERATURE: events[col.TEMPERATURE].fillna(self.temperature_c).to_numpy(float)
                if col.TEMPERATURE in events
                else self.temperature_c,
                col.HUMIDITY: events[col.HUMIDITY].fillna(self.relative_humidity_pct).to_numpy(float)
                if col.HUMIDITY in events
                else self.relative_humidity_pct,
                col.START: events[col.START].to_numpy(float),
                col.END: events[col.END].to_numpy(float),
                col.QUALITY_FLAGS: flags,
                # a flagged clip costs its mic, not the event, while enough good mics remain (solved from those)
                "quality_ok": list(usable),
                col.MICS_DROPPED: list(dropped),
                DEAD_MICS: [";".join(str(m) for m, r in enumerate(row) if "dead" in r) for row in reasons],
                col.HARDWARE_FAILURE: stated_failure,
                col.CLIP_SAMPLES: lengths,
            }
        )
        if "low_hz" in events:  # the GCC of each event runs in its own band (as a season's detector tables give it)
            rows[col.BAND_LOW] = events["low_hz"].to_numpy(float)
            rows[col.BAND_HIGH] = events["high_hz"].to_numpy(float)
        if EVENT_NAME in events:  # the user's own (text) event ids, reported as event_id in the positions
            rows[EVENT_NAME] = events[EVENT_NAME].to_numpy(object)
        if "time_s" in events:  # when the event happened (clock drift of a field calibration is per second of it)
            rows["time_s"] = events["time_s"].to_numpy(float)
        if col.POSITION_SIGMA in events:  # a playback spot's survey error: calibrate estimates the spot with the array
            rows[col.POSITION_SIGMA] = events[col.POSITION_SIGMA].to_numpy(float)
        return RecordingBatch(audio=audio, sample_rate_hz=fs, events=rows)


#: Sample rates recorders are set to, Hz: a file whose duration says it holds one of these under another header is mislabelled.
STANDARD_RATES_HZ = (8000, 11025, 16000, 22050, 24000, 32000, 44100, 48000, 88200, 96000, 192000, 250000, 256000, 384000)


def _check_rate_labels(durations: dict[str, tuple[float, float]], tolerance: float = 0.005) -> None:
    """One array's files record the same stretch of time: a file lasting a standard-rate ratio of the others' median
    (e.g. half: 24 kHz samples under a 48 kHz header) has a wrong sample rate in its header (one line naming it)."""
    if len(durations) < 3:
        return
    median = float(np.median([d for d, _ in durations.values()]))
    if median <= 0:
        return
    for path, (duration, rate) in durations.items():
        implied = rate * duration / median  # the rate at which the file would last as long as the others
        for standard in STANDARD_RATES_HZ:
            if standard != rate and abs(implied - standard) <= tolerance * standard:
                raise DataError(
                    f"field: {path} lasts {duration:.3f} s where the array's files last {median:.3f} s (median): its header's "
                    f"{rate:g} Hz is likely wrong ({standard:g} Hz would make it {median:.3f} s); fix the header, or set "
                    "field.compare_durations=false if this recorder really recorded that much less"
                )


def _offsets(starts: pd.Series | None, files: pd.Series) -> np.ndarray:
    """(M,) each mic's file start after the earliest one, s (0 where the files are taken to start together)."""
    if starts is None:
        return np.zeros(len(files))
    values = pd.to_datetime(pd.Series(np.asarray(starts)))
    if values.nunique() > 1:
        log.info(
            "field: the mics' files start up to %.3f s apart; each clip is cut at its own file's time",
            (values.max() - values.min()).total_seconds(),
        )
    return (values - values.min()).dt.total_seconds().to_numpy(float)


def linked_windows(recorders: np.ndarray, start_s: np.ndarray, end_s: np.ndarray) -> pd.DataFrame:
    """One event per call heard by several recorders: each recorder's detection window linked to the others' overlapping it most.

    Windows are taken in order of their start (absolute, s); an unlinked window anchors an event
    and, from every other recorder, the unlinked window overlapping it by at least half of the
    shorter window joins it. A recorder contributes at most one window to an event, so a
    detector's consecutive fixed windows (a long song cut in 3-s windows) stay separate events
    instead of chaining into one long one.

    Parameters
    ----------
    recorders : numpy.ndarray
        (N,) which recorder made each window (a file name, or a recorder index where one recorder made several files).
    start_s, end_s : numpy.ndarray
        (N,) each window's start and end on the common clock, s.

    Returns
    -------
    pandas.DataFrame
        ``start_s, end_s`` (the anchor's window) and ``n_files`` (recorders linked) per event, in order of start.
    """
    order = np.lexsort((end_s, start_s))
    sorted_start = start_s[order]
    linked = np.zeros(len(recorders), dtype=bool)
    rows = []
    for position, anchor in enumerate(order):
        if linked[anchor]:
            continue
        linked[anchor] = True
        members = {recorders[anchor]}
        lo, hi = start_s[anchor], end_s[anchor]
        # every window before the anchor in start order is linked already, and a later one overlaps it only if it
        # starts before its end: a sweep, not all N windows per anchor (a season's table has 10⁵)
        near = np.sort(order[position + 1 : np.searchsorted(sorted_start, hi, side="left")])  # ties broken by table order
        overlap = np.minimum(end_s[near], hi) - np.maximum(start_s[near], lo)
        enough = ~linked[near] & (overlap >= 0.5 * np.minimum(end_s[near] - start_s[near], hi - lo)) & (overlap > 0)
        for k in near[enough][np.argsort(-overlap[enough], kind="stable")]:
            if recorders[k] not in members:
                members.add(recorders[k])
                linked[k] = True
        rows.append((lo, hi, len(members)))
    return pd.DataFrame(rows, columns=[col.START, col.END, "n_files"])


def _recorder_mics(files: pd.DataFrame) -> pd.DataFrame:
    """One mic per recorder from ``recorders_of``'s files (with ``FILE_OFFSET``): its first file, and all of them in order of start."""
    files = files.sort_values([RECORDER, FILE_OFFSET], kind="stable")
    first = files.drop_duplicates(RECORDER)
    mics = pd.DataFrame(
        {
            "file": first["file"].to_numpy(),
            col.MIC_X: first["x"].to_numpy(float),
            col.MIC_Y: first["y"].to_numpy(float),
            col.MIC_Z: first["z"].to_numpy(float),
            FILE_OFFSET: first[FILE_OFFSET].to_numpy(float),
        }
    )
    if len(files) > len(first):  # several files per recorder: read by time
        grouped = files.groupby(RECORDER, sort=True)
        mics[RECORDER_FILES] = [tuple(g["file"]) for _, g in grouped]
        mics[RECORDER_OFFSETS] = [tuple(g[FILE_OFFSET].astype(float)) for _, g in grouped]
        log.info("field.coords_csv: %d files from %d recorders (files at one position are one recorder's)", len(files), len(first))
    return mics


def _file_at(mics: pd.DataFrame, m: int, time_s: float) -> tuple[str, float]:
    """The file of mic ``m`` a clip starting at ``time_s`` (common clock, s) lies in, and that file's offset, s: the last file
    started by then (the first where none has; a clip in a gap is then flagged out of range or truncated)."""
    if RECORDER_FILES not in mics:
        return str(mics["file"].iloc[m]), float(mics[FILE_OFFSET].iloc[m]) if FILE_OFFSET in mics else 0.0
    offsets = np.asarray(mics[RECORDER_OFFSETS].iloc[m], float)
    k = max(int(np.searchsorted(offsets, time_s, side="right")) - 1, 0)
    return str(mics[RECORDER_FILES].iloc[m][k]), float(offsets[k])


def _describe(reasons_per_mic: np.ndarray, mics: pd.DataFrame) -> str:
    """One event's flags as text, e.g. ``"mic 2: dead; mic 4: truncated, clipped"`` (empty when every clip is fine)."""
    names = mics["mic_id"].astype(str).tolist() if "mic_id" in mics else [str(m) for m in range(len(mics))]
    parts = [
        f"mic {names[m]}: {', '.join(r for r in QUALITY_REASONS if r in reasons)}" for m, reasons in enumerate(reasons_per_mic) if reasons
    ]
    return "; ".join(parts)
