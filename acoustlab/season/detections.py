"""Detector tables in: Raven selection tables, BirdNET result tables, OpenSoundscape score tables.

Every reader returns the same table, one row per detection on one recorder, in season seconds
(``acoustlab.season.recorder_files.RecorderFiles``):

``recorder_id, start_s, end_s, low_hz, high_hz, label, score, source``

(``low_hz``/``high_hz`` NaN where the table gives no band; ``score`` NaN where it has none;
``source`` is ``<table file>:<line>``). Times in a detector table are offsets into an audio file;
the file's start time in the season places them.

Raven selection tables (tab-separated ``.txt``)
    ``Begin Time (s)``, ``End Time (s)``, ``Low Freq (Hz)``, ``High Freq (Hz)`` and the file:
    ``Begin File`` or ``Begin Path``; with ``File Offset (s)`` (Raven's offset into the begin file)
    the detection starts at that offset, else ``Begin Time (s)`` is taken as the offset (a table
    made per file). Rows repeated per view (Spectrogram and Waveform) count once per ``Selection``.
    The label is ``label_column`` (e.g. ``Species``, ``Annotation``; BirdNET's Raven output has
    ``Common Name`` and ``Confidence``).
BirdNET-Analyzer CSV
    ``Start (s), End (s), Scientific name, Common name, Confidence`` and ``File`` (the combined
    table); a per-file table ``<audio name>.BirdNET.results.csv`` without a ``File`` column names
    its audio file in its own name.
OpenSoundscape score tables (CSV)
    ``file, start_time, end_time`` and one score column per class; a detection is a row whose
    score for a chosen class is at least ``min_score``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import DataError, show
from acoustlab.season.recorder_files import RecorderFiles

log = logging.getLogger(__name__)

DETECTION_COLUMNS = ("recorder_id", col.START, col.END, "low_hz", "high_hz", "label", "score", "source")
FORMATS = ("raven", "birdnet", "opensoundscape")
RAVEN_TIMES = ("Begin Time (s)", "End Time (s)")
#: How far a detection's begin may lie outside its file, s (rounding of the tables' times).
OFFSET_TOLERANCE_S = 0.01
BIRDNET_TIMES = ("Start (s)", "End (s)")


def _read_table(path: Path, sep: str, what: str) -> pd.DataFrame:
    if not path.is_file():
        raise DataError(f"detections: {what} {path} does not exist")
    try:
        table = pd.read_csv(path, sep=sep, skipinitialspace=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise DataError(f"detections: cannot read {path} as a {what}: {str(exc).splitlines()[0]}") from None
    table.columns = [str(c).strip() for c in table.columns]
    table.attrs["path"] = str(path)
    return table


def _require(table: pd.DataFrame, columns: Sequence[str], what: str) -> None:
    missing = [c for c in columns if c not in table]
    if missing:
        raise DataError(f"detections: {table.attrs['path']} ({what}) lacks columns {missing}; found {list(table.columns)}")


def _numbers(table: pd.DataFrame, column: str) -> np.ndarray:
    """A column as floats; a cell that is not a finite number names its line."""
    values = pd.to_numeric(table[column], errors="coerce").to_numpy(float)
    bad = ~np.isfinite(values) & table[column].notna().to_numpy()
    if column in (*RAVEN_TIMES, *BIRDNET_TIMES, "start_time", "end_time", "File Offset (s)"):
        bad |= ~np.isfinite(values)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        line = table.attrs["lines"][k] if "lines" in table.attrs else k + 2
        raise DataError(f"detections: {table.attrs['path']} line {line}, column {column!r}: {show(table[column].iloc[k])} is not a number")
    return values


def table_recorder(table: pd.DataFrame, recordings: RecorderFiles, recorder_column: str | None) -> list[str | None]:
    """Each row's recorder: its ``recorder_column``, else the recorder whose id the table's name or folder starts with, else None."""
    if recorder_column:
        _require(table, [recorder_column], f"recorder_column={recorder_column}")
        return table[recorder_column].astype(str).str.strip().tolist()
    path = Path(table.attrs["path"])
    ids = set(recordings.recorders)
    named = next((r for r in (path.name.split(".")[0], path.parent.name) if r in ids), None)
    return [named] * len(table)


def _place(
    table: pd.DataFrame,
    files: Sequence[str],
    offset_s: np.ndarray,
    duration_s: np.ndarray,
    recordings: RecorderFiles,
    low: np.ndarray,
    high: np.ndarray,
    label: np.ndarray,
    score: np.ndarray,
    recorders: Sequence[str | None],
) -> pd.DataFrame:
    """Detections in season seconds from per-file offsets (a row's line in its file: ``table.attrs["lines"]``, else its
    position + 2)."""
    line = np.asarray(table.attrs.get("lines", np.arange(len(table)) + 2))
    if (duration_s <= 0).any():
        k = int(np.flatnonzero(duration_s <= 0)[0])
        raise DataError(f"detections: {table.attrs['path']} line {line[k]}: the detection ends before it begins ({duration_s[k]:.3f} s)")
    _check_band(table, low, high, recordings.sample_rate_hz)
    rows = recordings.file_indices(files, recorders)
    start = recordings.table[col.START].to_numpy(float)[rows] + offset_s
    length_s = (recordings.table["n_frames"].to_numpy(float) / recordings.table["sample_rate_hz"].to_numpy(float))[rows]
    outside = ~((offset_s >= -OFFSET_TOLERANCE_S) & (offset_s <= length_s + OFFSET_TOLERANCE_S))
    if outside.any():  # a begin time outside its own file: a wrong file or a wrong time, never a call in it
        k = int(np.flatnonzero(outside)[0])
        log.warning(
            "detections: %d row(s) of %s begin outside their file and are left out, e.g. line %d: %.3f s into %s, which is %.3f s "
            "long (a Raven table over a sequence of files needs its File Offset (s) column)",
            int(outside.sum()),
            table.attrs["path"],
            line[k],
            offset_s[k],
            files[k],
            length_s[k],
        )
    detections = pd.DataFrame(
        {
            "recorder_id": recordings.table["recorder_id"].to_numpy()[rows],
            col.START: start,
            col.END: start + duration_s,
            "low_hz": low,
            "high_hz": high,
            "label": label.astype(str),
            "score": score,
            "source": [f"{Path(table.attrs['path']).name}:{k}" for k in line],
        }
    )
    return detections[~outside].reset_index(drop=True) if outside.any() else detections


def _check_band(table: pd.DataFrame, low: np.ndarray, high: np.ndarray, sample_rate_hz: float) -> None:
    """A detection's band must be a band of the recordings: 0 ≤ low < high ≤ the Nyquist frequency.

    The band sets the event's GCC band; one outside the recordings' spectrum would leave the GCC
    nothing but noise and place the call anywhere, with no warning.
    """
    nyquist = sample_rate_hz / 2
    known_low, known_high = np.isfinite(low), np.isfinite(high)
    problems = (
        (known_low & (low < 0), "Low Freq (Hz) is negative"),
        (known_high & (high > nyquist), f"High Freq (Hz) is above the recordings' Nyquist frequency, {nyquist:g} Hz"),
        (known_low & known_high & (low >= high), "Low Freq (Hz) is not below High Freq (Hz)"),
    )
    for bad, what in problems:
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise DataError(f"detections: {table.attrs['path']} line {k + 2}: {what} (low {low[k]:g} Hz, high {high[k]:g} Hz)")


def read_raven(path: Path, recordings: RecorderFiles, label_column: str | None = None, recorder_column: str | None = None) -> pd.DataFrame:
    """Detections of a Raven selection table (see the module docstring)."""
    table = _read_table(path, "\t", "Raven selection table")
    _require(table, RAVEN_TIMES, "Raven selection table")
    if "Selection" in table:
        lines = np.flatnonzero(~table.duplicated("Selection", keep="first").to_numpy()) + 2  # the file's lines, header line 1
        table = table.drop_duplicates("Selection", keep="first").reset_index(drop=True)
        table.attrs["lines"] = lines
        table.attrs["path"] = str(path)
    file_column = next((c for c in ("Begin File", "Begin Path") if c in table), None)
    if file_column is None:
        raise DataError(
            f"detections: {path} (Raven selection table) names no audio file: add the Begin File or Begin Path column "
            "(Raven: View > Selection Table > Choose Columns)"
        )
    begin, end = _numbers(table, RAVEN_TIMES[0]), _numbers(table, RAVEN_TIMES[1])
    offset = _numbers(table, "File Offset (s)") if "File Offset (s)" in table else begin
    low = _numbers(table, "Low Freq (Hz)") if "Low Freq (Hz)" in table else np.full(len(table), np.nan)
    high = _numbers(table, "High Freq (Hz)") if "High Freq (Hz)" in table else np.full(len(table), np.nan)
    label = _label(table, label_column, ("Species", "Common Name", "Annotation", "Label"))
    score = _numbers(table, "Confidence") if "Confidence" in table else np.full(len(table), np.nan)
    return _place(
        table,
        table[file_column].astype(str).tolist(),
        offset,
        end - begin,
        recordings,
        low,
        high,
        label,
        score,
        table_recorder(table, recordings, recorder_column),
    )


def read_birdnet(
    path: Path, recordings: RecorderFiles, label_column: str | None = None, recorder_column: str | None = None
) -> pd.DataFrame:
    """Detections of a BirdNET-Analyzer CSV table (see the module docstring)."""
    table = _read_table(path, ",", "BirdNET table")
    _require(table, (*BIRDNET_TIMES, "Confidence"), "BirdNET table")
    if "File" in table:
        files = table["File"].astype(str).tolist()
    else:
        stem = path.name.split(".BirdNET")[0]
        matches = [Path(p).name for p in recordings.table["path"] if Path(p).stem == stem]
        if len(matches) != 1:
            raise DataError(
                f"detections: {path} has no File column and its name does not name one audio file "
                f"(expected <audio name>.BirdNET.results.csv; {len(matches)} files named {stem!r})"
            )
        files = matches * len(table)
    start, end = _numbers(table, BIRDNET_TIMES[0]), _numbers(table, BIRDNET_TIMES[1])
    confidence = _numbers(table, "Confidence")
    outside = ~((confidence >= 0) & (confidence <= 1))
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        raise DataError(f"detections: {path} line {k + 2}, column 'Confidence': {confidence[k]:g} is not a score in [0, 1]")
    label = _label(table, label_column, ("Common name", "Scientific name"))
    nan = np.full(len(table), np.nan)
    return _place(
        table,
        files,
        start,
        end - start,
        recordings,
        nan,
        nan,
        label,
        confidence,
        table_recorder(table, recordings, recorder_column),
    )


def read_opensoundscape(
    path: Path, recordings: RecorderFiles, classes: Sequence[str] | None, min_score: float, recorder_column: str | None = None
) -> pd.DataFrame:
    """One detection per row and class whose score reaches ``min_score`` (see the module docstring)."""
    table = _read_table(path, ",", "OpenSoundscape score table")
    _require(table, ("file", "start_time", "end_time"), "OpenSoundscape score table")
    score_columns = [c for c in table.columns if c not in ("file", "start_time", "end_time", recorder_column)]
    chosen = list(classes) if classes else score_columns
    _require(table, chosen, "OpenSoundscape score table: the chosen classes")
    start, end = _numbers(table, "start_time"), _numbers(table, "end_time")
    recorders = np.array(table_recorder(table, recordings, recorder_column), dtype=object)
    parts = []
    for name in chosen:
        score = _numbers(table, name)
        keep = score >= min_score
        if keep.any():
            sub = table[keep].reset_index(drop=True)
            sub.attrs["path"] = str(path)
            nan = np.full(int(keep.sum()), np.nan)
            part = _place(
                sub,
                sub["file"].astype(str).tolist(),
                start[keep],
                (end - start)[keep],
                recordings,
                nan,
                nan,
                np.full(int(keep.sum()), name, dtype=object),
                score[keep],
                list(recorders[keep]),
            )
            part["source"] = [f"{path.name}:{k + 2}" for k in np.flatnonzero(keep)]
            parts.append(part)
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=list(DETECTION_COLUMNS))


def _label(table: pd.DataFrame, label_column: str | None, candidates: Sequence[str]) -> np.ndarray:
    if label_column is not None:
        _require(table, [label_column], f"label_column={label_column}")
        return table[label_column].astype(str).to_numpy()
    found = next((c for c in candidates if c in table), None)
    return table[found].astype(str).to_numpy() if found else np.full(len(table), "", dtype=object)


def read_detections(
    paths: Sequence[str | Path],
    fmt: str,
    recordings: RecorderFiles,
    classes: Sequence[str] | None = None,
    min_score: float = 0.0,
    label_column: str | None = None,
    recorder_column: str | None = None,
) -> pd.DataFrame:
    """Every detection of the given tables, of the chosen classes and at least ``min_score``, sorted by time.

    Parameters
    ----------
    paths : list of path
        Detector tables (files, or folders whose ``*.txt`` (Raven) / ``*.csv`` files are read).
    fmt : {"raven", "birdnet", "opensoundscape"}
        The tables' format.
    recordings : RecorderFiles
        The season's files (places file offsets in season time).
    classes : list of str, optional
        Labels (Raven, BirdNET) or score columns (OpenSoundscape) kept; None keeps all.
    min_score : float
        Smallest score kept (BirdNET ``Confidence``, OpenSoundscape score; Raven rows without a
        ``Confidence`` column are all kept).
    label_column : str, optional
        The column holding the label (Raven, BirdNET); default: the format's usual one.
    recorder_column : str, optional
        The column naming each row's recorder. Without it, a table named or foldered by a
        recorder id (``R3.Table.1.selections.txt``, ``R3/…``) is that recorder's, and file names
        must be unique across recorders (or given as full paths).
    """
    if fmt not in FORMATS:
        raise DataError(f"detections.format must be one of {', '.join(FORMATS)}; got {fmt!r}")
    files: list[Path] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            files += sorted(p.rglob("*.txt" if fmt == "raven" else "*.csv"))
        else:
            files.append(p)
    if not files:
        raise DataError(f"detections: no {fmt} tables in {[str(p) for p in paths]}")
    parts = []
    for path in files:
        if fmt == "opensoundscape":
            parts.append(read_opensoundscape(path, recordings, classes, min_score, recorder_column))
            continue
        part = (read_raven if fmt == "raven" else read_birdnet)(path, recordings, label_column, recorder_column)
        keep = np.ones(len(part), bool)
        if classes:
            keep &= part["label"].isin([str(c) for c in classes]).to_numpy()
        keep &= ~(part["score"].to_numpy(float) < min_score)  # NaN scores (no Confidence column) are kept
        parts.append(part[keep])
    out = pd.concat(parts, ignore_index=True).sort_values([col.START, "recorder_id"], kind="stable").reset_index(drop=True)
    for name in ("recorder_id", "label", "source"):  # a few distinct strings repeated on every row: categories, not objects
        if name in out:
            out[name] = out[name].astype("category")
    log.info("detections: %d from %d %s tables (classes %s, score >= %g)", len(out), len(files), fmt, classes or "all", min_score)
    return out
