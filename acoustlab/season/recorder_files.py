"""Which recorder's file covers which absolute time, and clips cut by absolute time across files.

A season is many files per recorder (an AudioMoth writes one file per hour, a Song Meter one per
schedule slot), each starting at its own timestamp. ``RecorderFiles`` indexes them from

- a table ``recorder_id, file, start_time`` (ISO 8601 times, e.g. ``2026-05-01T05:30:00``; a file
  may also have a ``channel``), or
- file names holding the start time (``20260501_053000.WAV``, ``S4A01234_20260501_053000.wav``,
  ``rec_2026-05-01T05-30-00.flac``) in one sub-folder per recorder (the folder name is the
  recorder id).

Times inside a season are seconds since the season's origin (the earliest file start), a float64
that keeps a resolution of nanoseconds over years. Only the audio headers are read to index;
samples are read per clip (``RecorderFiles.read``), from as many files as the clip crosses: a
clip across a file boundary is stitched, a stretch no file covers is zeros and flagged (``gap``
between two files, ``out_of_range`` before the first or after the last).
"""

from __future__ import annotations

import json
import logging
import os
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import soundfile as sf

from acoustlab.core import columns as col
from acoustlab.core.digests import sampled_file_sha256
from acoustlab.core.errors import DataError, show
from acoustlab.core.files import atomic_write_bytes
from acoustlab.toolkit.file_start import start_from_metadata, timestamp_from_name
from acoustlab.toolkit.table_times import iso_times

log = logging.getLogger(__name__)

AUDIO_SUFFIXES = (".wav", ".flac")
#: Files within this many seconds of each other's end count as contiguous (clock rounding in names).
CONTIGUOUS_TOLERANCE_S = 0.5


def _start_of(path: Path) -> pd.Timestamp:
    """When a file starts: the time its recorder wrote into it (GUANO, Broadcast WAV, AudioMoth, OpenSoundscape), else the time in its name."""
    start = start_from_metadata(path)
    return start if start is not None else timestamp_from_name(path.name)


@dataclass
class ClipRead:
    """Samples of one recorder over one time window and what was wrong with them.

    Attributes
    ----------
    samples : numpy.ndarray
        (S,) float32 samples (zeros where no file covers the time).
    flags : list of str
        ``gap`` (between two files), ``out_of_range`` (before the first or after the last file),
        ``unreadable (file: reason)`` (a damaged file; the clip is not placed).
    """

    samples: np.ndarray
    flags: list[str]


class _RecorderArrays:
    """One recorder's files as arrays (a clip read looks them up without pandas)."""

    def __init__(self, table: pd.DataFrame) -> None:
        self.start_s = table[col.START].to_numpy(float)
        self.end_s = table[col.END].to_numpy(float)
        self.n_frames = table["n_frames"].to_numpy(np.int64)
        self.channel = table["channel"].to_numpy(np.int64)
        self.path = table["path"].astype(str).tolist()
        #: the recorder's sample rate, Hz (all its files share it)
        self.rate = float(table["sample_rate_hz"].iloc[0])


class RecorderFiles:
    """Every recorder's files with their absolute start times, in one season clock.

    Parameters
    ----------
    table : pandas.DataFrame
        One row per file: ``recorder_id`` (str), ``path`` (str), ``start`` (pandas Timestamp),
        optionally ``channel`` (int, 0 when absent).

    Raises
    ------
    DataError
        For files that cannot be read, differing sample rates, or overlapping files of one recorder.
    """

    def __init__(self, table: pd.DataFrame) -> None:
        if table.empty:
            raise DataError("recordings: no audio files found")
        table = table.copy()
        table["recorder_id"] = table["recorder_id"].astype(str)
        if "channel" not in table:
            table["channel"] = 0
        frames, rates = [], []
        for path in table["path"]:
            try:
                info = sf.info(path)
            except (RuntimeError, OSError, sf.LibsndfileError) as exc:
                raise DataError(f"recordings: cannot read the header of {path}: {str(exc).splitlines()[0]}") from None
            frames.append(info.frames)
            rates.append(info.samplerate)
        table["n_frames"] = frames
        stats = [os.stat(path) for path in table["path"]]
        table["size_bytes"] = [s.st_size for s in stats]  # what the season was indexed from: a resume checks it
        table["mtime_ns"] = [s.st_mtime_ns for s in stats]
        table["content_sha256"] = [sampled_file_sha256(path) for path in table["path"]]  # a same-size, same-time rewrite
        table["sample_rate_hz"] = np.asarray(rates, dtype=float)
        for recorder, files in table.groupby("recorder_id", sort=False):  # recorders may differ; one recorder's files may not
            if files["sample_rate_hz"].nunique() > 1:
                odd = files["path"].to_numpy()[files["sample_rate_hz"].to_numpy() != files["sample_rate_hz"].iloc[0]][0]
                raise DataError(
                    f"recordings: recorder {recorder}'s files differ in sample rate "
                    f"({sorted({int(r) for r in files['sample_rate_hz']})} Hz), e.g. {odd}; one recorder's files need one rate"
                )
        self._index(table)

    def _index(self, table: pd.DataFrame, max_open_files: int = 64) -> None:
        """Season times of every file, sorted per recorder, checked for overlaps."""
        #: the lowest recorder rate, Hz: a detection's band must lie below every recorder's Nyquist
        self.sample_rate_hz = float(table["sample_rate_hz"].min())
        self.origin = table["start"].min()
        table[col.START] = (table["start"] - self.origin).dt.total_seconds().to_numpy(float)
        table[col.END] = table[col.START] + table["n_frames"] / table["sample_rate_hz"]
        self.table = table.sort_values(["recorder_id", col.START], kind="stable").reset_index(drop=True)
        self._check_overlaps()
        self.recorders = sorted(self.table["recorder_id"].unique())
        self._by_recorder = {r: _RecorderArrays(self.table[self.table["recorder_id"] == r]) for r in self.recorders}
        self._by_name: dict[str, list[int]] = {}
        self._by_path: dict[str, list[int]] = {}
        for k, path in enumerate(self.table["path"]):
            self._by_name.setdefault(Path(path).name, []).append(k)
            self._by_path[str(path)] = [k]
        self._open: OrderedDict[str, sf.SoundFile] = OrderedDict()
        self.max_open_files = int(max_open_files)

    def _check_overlaps(self) -> None:
        t = self.table
        same = t["recorder_id"].to_numpy()[1:] == t["recorder_id"].to_numpy()[:-1]
        overlap = t[col.START].to_numpy()[1:] < t[col.END].to_numpy()[:-1] - CONTIGUOUS_TOLERANCE_S
        bad = np.flatnonzero(same & overlap)
        if bad.size:
            k = bad[0]
            overlap_s = t[col.END].iloc[k] - t[col.START].iloc[k + 1]
            raise DataError(
                f"recordings: recorder {t['recorder_id'].iloc[k]}: {t['path'].iloc[k + 1]} starts at {t['start'].iloc[k + 1]}, "
                f"before {t['path'].iloc[k]} ends ({overlap_s:.3f} s overlap); check the start times"
            )

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_table(cls, csv_path: str | Path, audio_dir: str | Path | None = None, allow_outside_audio_dir: bool = False) -> RecorderFiles:
        """Index from a CSV with ``recorder_id, file, start_time`` (file paths relative to ``audio_dir`` or the CSV's folder).

        With ``audio_dir`` every file must lie inside it once links are followed (absolute paths, ``..``
        and linked folders included), unless ``allow_outside_audio_dir``; without, the table's paths
        are taken as written (relative ones from the CSV's folder).
        """
        path = Path(csv_path)
        if not path.is_file():
            raise DataError(f"recordings.files_csv: file {path} does not exist")
        try:
            table = pd.read_csv(path, skipinitialspace=True, dtype={"recorder_id": str, "file": str})
        except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
            raise DataError(f"recordings.files_csv: cannot read {path} as a CSV table: {str(exc).splitlines()[0]}") from None
        table.columns = [str(c).strip() for c in table.columns]
        missing = [c for c in ("recorder_id", "file", "start_time") if c not in table]
        if missing:
            raise DataError(f"recordings.files_csv: {path} lacks columns {missing}; found {list(table.columns)}")
        start = iso_times(table["start_time"], f"recordings.files_csv: {path}", "start_time")
        base = Path(audio_dir) if audio_dir is not None else path.parent
        files = [str(f if Path(f).is_absolute() else base / f) for f in table["file"].astype(str)]
        root = base.resolve()
        outside = [k for k, f in enumerate(files) if not Path(f).resolve().is_relative_to(root)] if audio_dir is not None else []
        if outside and not allow_outside_audio_dir:  # the rule of field=recordings: a table reads only the folder it is given
            k = outside[0]
            raise DataError(
                f"recordings.files_csv: {path} line {k + 2}, column file: {show(table['file'].iloc[k])} resolves to "
                f"{Path(files[k]).resolve()}, outside recordings.audio_dir {root} (absolute, '..' or a link); set "
                "protocol.recordings.allow_outside_audio_dir=true to read it anyway"
            )
        absent = [f for f in files if not Path(f).is_file()]
        if absent:
            raise DataError(f"recordings.files_csv: {path}: {len(absent)} files do not exist, e.g. {absent[0]}")
        out = pd.DataFrame({"recorder_id": table["recorder_id"].astype(str).str.strip(), "path": files, "start": start})
        if "channel" in table:
            out["channel"] = pd.to_numeric(table["channel"], errors="raise").astype(int)
        return cls(out)

    @classmethod
    def from_file_names(cls, audio_dir: str | Path) -> RecorderFiles:
        """Index ``audio_dir/<recorder_id>/<…YYYYMMDD_HHMMSS…>.wav`` (start times from the names)."""
        root = Path(audio_dir)
        if not root.is_dir():
            raise DataError(f"recordings.audio_dir: {root} is not a folder")
        rows = [
            {"recorder_id": f.parent.name, "path": str(f), "start": _start_of(f)}
            for f in sorted(root.glob("*/*"))
            if f.suffix.lower() in AUDIO_SUFFIXES
        ]
        if not rows:
            raise DataError(f"recordings.audio_dir: no .wav/.flac files in sub-folders of {root} (one sub-folder per recorder)")
        return cls(pd.DataFrame(rows))

    def save(self, path: Path) -> None:
        """Write the index (files, recorders, start times, lengths) as Parquet; ``load`` reads it without opening any audio."""
        table = self.table.assign(start=self.table["start"].astype("datetime64[ns]"))
        atomic_write_bytes(path, table.to_parquet(index=False))
        atomic_write_bytes(path.with_suffix(".json"), json.dumps({"sample_rate_hz": self.sample_rate_hz}).encode())

    @classmethod
    def load(cls, path: Path) -> RecorderFiles:
        """The index written by ``save`` (headers are not read again)."""
        self = cls.__new__(cls)
        table = pd.read_parquet(path)
        if "sample_rate_hz" not in table:  # an index written before recorders could differ in rate
            table["sample_rate_hz"] = float(json.loads(path.with_suffix(".json").read_text())["sample_rate_hz"])
        self._index(table)
        return self

    def check_unchanged(self) -> None:
        """Refuse files rewritten, resized or removed since the season was indexed (at the fit).

        A resumed or sharded season reads its clips from these files; a file changed in between would
        mix positions computed from two recordings into one season, silently.

        Raises
        ------
        DataError
            Naming the first changed or missing file.
        """
        if "mtime_ns" not in self.table:  # indexed by an earlier version: nothing recorded to compare
            return
        content = self.table["content_sha256"] if "content_sha256" in self.table else [None] * len(self.table)
        for path, size, mtime, sampled in zip(self.table["path"], self.table["size_bytes"], self.table["mtime_ns"], content, strict=True):
            try:
                now = os.stat(path)
                changed = (now.st_size != size or now.st_mtime_ns != mtime) and "size or modification time"
                changed = changed or (sampled is not None and sampled_file_sha256(path) != sampled and "content, at the same size and time")
            except OSError:
                raise DataError(f"recordings: {path} is gone since the season was fitted; restore it, or fit a new season") from None
            if changed:
                raise DataError(
                    f"recordings: {path} changed since the season was fitted ({changed}); its positions would "
                    "mix two recordings: restore the file, or fit the season again in a new protocol.output_dir"
                )

    # -- lookups ------------------------------------------------------------------------------
    def seconds(self, time: pd.Timestamp | str) -> float:
        """A wall-clock time as seconds since the season's origin."""
        return float((pd.Timestamp(time) - self.origin).total_seconds())

    def file_row(self, name: str, recorder_id: str | None = None) -> pd.Series:
        """The index row of a file given by its path, or its name (with the recorder where names repeat across recorders).

        Raises
        ------
        DataError
            When no indexed file matches, or the name is shared by several recorders and none is given.
        """
        return self.table.iloc[self.file_index(name, recorder_id)]

    def file_indices(self, names: Sequence[str], recorder_ids: Sequence[str | None]) -> np.ndarray:
        """(N,) ``file_index`` of every (name, recorder) pair, each distinct pair looked up once (a table repeats its files)."""
        pairs = list(zip(map(str, names), recorder_ids, strict=True))
        found = {pair: self.file_index(*pair) for pair in dict.fromkeys(pairs)}
        return np.fromiter((found[pair] for pair in pairs), dtype=np.int64, count=len(pairs))

    def file_index(self, name: str, recorder_id: str | None = None) -> int:
        """The position in ``table`` of a file given by its path, or its name (see ``file_row``)."""
        text = str(name)
        rows = self._by_path.get(text)
        if rows is None:
            rows = self._by_name.get(Path(text).name, [])
            if recorder_id is not None:
                rows = [k for k in rows if self.table["recorder_id"].iloc[k] == str(recorder_id)]
        if not rows:
            within = f" of recorder {recorder_id}" if recorder_id is not None else ""
            raise DataError(f"detections: file {text!r}{within} is not among the season's recordings ({len(self.table)} files indexed)")
        if len(rows) > 1:
            owners = sorted(self.table["recorder_id"].iloc[rows])
            raise DataError(
                f"detections: file name {Path(text).name!r} is used by recorders {', '.join(owners)}: give the recorder "
                "(protocol.detections.recorder_column, one table per recorder named or foldered by its id, or Begin Path)"
            )
        return int(rows[0])

    # -- reading ------------------------------------------------------------------------------
    def _handle(self, path: str) -> sf.SoundFile:
        handle = self._open.pop(path, None)
        if handle is None:
            handle = sf.SoundFile(path)
            while len(self._open) >= self.max_open_files:
                self._open.popitem(last=False)[1].close()
        self._open[path] = handle
        return handle

    def _forget(self, path: str) -> None:
        """Close and drop a file's handle after a failed read (its position is unknown)."""
        handle = self._open.pop(path, None)
        if handle is not None:
            handle.close()

    def close(self) -> None:
        """Close every open file."""
        while self._open:
            self._open.popitem()[1].close()

    def rate_of(self, recorder_id: str) -> float:
        """The sample rate of one recorder's files, Hz."""
        files = self._by_recorder.get(str(recorder_id))
        if files is None:
            raise DataError(f"recordings: no files of recorder {recorder_id!r}; recorders: {', '.join(self.recorders)}")
        return files.rate

    def read(self, recorder_id: str, start_s: float, n_samples: int, context: int = 0, extension: int = 0) -> ClipRead:
        """``n_samples`` of one recorder from ``start_s`` (season seconds), stitched across its files.

        Sample k of the clip is the recording at time ``start_s + k / fs`` (fs the recorder's rate, ``rate_of``); in file f
        that is sample ``round((start_s − start_f) · fs) + k``, so a clip across a boundary equals
        the same clip cut from the files joined end to end. The first and last ``context`` samples are
        context around the detections: where no file covers them they are zeros and flag nothing; so are the last
        ``extension`` samples, beyond the window (its extension to an FFT-friendly length).
        """
        files = self._by_recorder.get(str(recorder_id))
        if files is None:
            raise DataError(f"recordings: no files of recorder {recorder_id!r}; recorders: {', '.join(self.recorders)}")
        fs = files.rate
        out = np.zeros(n_samples, dtype=np.float32)
        covered = np.zeros(n_samples, dtype=bool)
        damaged: list[str] = []
        end_s = start_s + n_samples / fs
        for k in np.flatnonzero((files.start_s < end_s) & (files.end_s > start_s)):
            first = int(round((start_s - files.start_s[k]) * fs))  # file sample of clip sample 0
            lo, hi = max(0, -first), min(n_samples, int(files.n_frames[k]) - first)
            if hi <= lo:
                continue
            try:
                handle = self._handle(files.path[k])
                handle.seek(first + lo)
                n_read = _read_into(handle, hi - lo, int(files.channel[k]), out[lo:hi])
            except (sf.LibsndfileError, RuntimeError, OSError) as exc:  # a damaged stretch costs this clip, not the season
                self._forget(files.path[k])
                out[lo:hi] = 0.0
                damaged.append(f"{Path(files.path[k]).name}: {str(exc).splitlines()[0][:80]}")
                continue
            covered[lo : lo + n_read] = True
        flags = [f"unreadable ({'; '.join(damaged)})"] if damaged else []
        if (
            not covered.all() and not damaged
        ):  # in clip samples, with the same rounding as the reads: where the recorder's first file begins, its last ends
            first_k, last_k = 0, int(files.end_s.argmax())
            lead = -int(round((start_s - files.start_s[first_k]) * fs))
            tail = int(files.n_frames[last_k]) - int(round((start_s - files.start_s[last_k]) * fs))
            missing = np.flatnonzero(~covered)
            missing = missing[(missing >= context) & (missing < n_samples - context - extension)]
            if ((missing >= lead) & (missing < tail)).any():
                flags.append("gap")
            if ((missing < lead) | (missing >= tail)).any():
                flags.append("out_of_range")
        return ClipRead(out, flags)


#: libsndfile's float scale of 16-bit PCM (full scale = 1): ``sf.read(dtype="float32")`` returns the samples times this.
PCM16_SCALE = np.float32(1.0 / 0x8000)


def _read_into(handle: sf.SoundFile, n_frames: int, channel: int, out: np.ndarray) -> int:
    """Read up to ``n_frames`` of one channel from the handle's position into ``out`` (float32, full scale = 1); the frames read.

    16-bit PCM (most recorders' WAV files) is read as integers and scaled here: the same floats
    as libsndfile's own conversion (a product by 2⁻¹⁵), at under half its cost.
    """
    if handle.subtype == "PCM_16":
        data = handle.read(n_frames, dtype="int16", always_2d=True)[:, channel]
        np.multiply(data, PCM16_SCALE, out=out[: len(data)])
    else:
        data = handle.read(n_frames, dtype="float32", always_2d=True)[:, channel]
        out[: len(data)] = data
    return len(data)
