"""Real recordings as input: a folder of WAV/FLAC files with a mics table and an events table.

Two layouts are accepted.

acoustlab layout
    ``mics_csv`` with ``mic_id, x_m, y_m, z_m`` and either a ``file`` column (one mono file per
    mic) or none (then ``events_csv`` has a ``file`` column naming one multichannel file per
    event, channels in the mics table's order). ``events_csv`` has ``event_id, start_s, end_s``
    and optionally ``file``, ``position_id``, ``x_m, y_m`` (true position when known),
    ``temperature_c``, ``relative_humidity_pct``.

OpenSoundscape layout (so its users can switch)
    ``coords_csv`` with ``file, x, y[, z]`` (one receiver per file) and ``detections_csv`` with
    ``file, start_time, end_time`` and one 0/1 column per class; every distinct
    (start_time, end_time) window detected by at least ``min_receivers`` receivers becomes an
    event (receivers that did not detect it are still used; their clip is cut at the same times).

Unknown true positions are NaN; events without a ``position_id`` each get their own.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.resources import resolve_path
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.toolkit.audio import load_mono


def _read(path_text: str, field: str, required: tuple[str, ...]) -> pd.DataFrame:
    path = resolve_path(path_text)
    if not path.is_file():
        raise DataError(f"field.{field}: file {path} does not exist")
    table = pd.read_csv(path, skipinitialspace=True)
    table.columns = [c.strip() for c in table.columns]
    missing = [c for c in required if c not in table.columns]
    if missing:
        raise DataError(f"field.{field}: {path} lacks columns {missing}; found {list(table.columns)}")
    return table


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
    ) -> None:
        if not ((mics_csv and events_csv) or (coords_csv and detections_csv)):
            raise ConfigError("field: give mics_csv and events_csv, or coords_csv and detections_csv (OpenSoundscape layout)")
        self.audio_dir = audio_dir
        self.mics_csv, self.events_csv = mics_csv, events_csv
        self.coords_csv, self.detections_csv = coords_csv, detections_csv
        self.sample_rate_hz = float(sample_rate_hz)
        self.temperature_c = float(temperature_c)
        self.relative_humidity_pct = float(relative_humidity_pct)
        self.min_receivers = int(min_receivers)
        self.pad_s = float(pad_s)

    def _audio(self, file: str) -> np.ndarray:
        path = resolve_path(self.audio_dir) / str(file).strip()
        if not path.is_file():
            raise DataError(f"field: audio file {path} does not exist")
        return load_mono(str(path), self.sample_rate_hz)

    def tables(self) -> tuple[pd.DataFrame, pd.DataFrame]:
        """(mics, events) in the acoustlab layout, converting the OpenSoundscape layout if needed."""
        if self.mics_csv and self.events_csv:
            mics = _read(self.mics_csv, "mics_csv", ("x_m", "y_m", "z_m"))
            events = _read(self.events_csv, "events_csv", ("event_id", "start_s", "end_s"))
            return mics, events
        coords = _read(self.coords_csv, "coords_csv", ("file", "x", "y"))
        det = _read(self.detections_csv, "detections_csv", ("file", "start_time", "end_time"))
        mics = pd.DataFrame({"file": coords["file"].str.strip(), "x_m": coords["x"], "y_m": coords["y"],
                             "z_m": coords["z"] if "z" in coords else 0.0})
        classes = [c for c in det.columns if c not in ("file", "start_time", "end_time")]
        hit = det[classes].astype(float).max(axis=1) > 0 if classes else pd.Series(True, index=det.index)
        det = det[hit & det["file"].str.strip().isin(set(mics["file"]))]
        windows = det.groupby(["start_time", "end_time"])["file"].nunique().reset_index()
        windows = windows[windows["file"] >= self.min_receivers]
        events = pd.DataFrame({"event_id": np.arange(len(windows)), "start_s": windows["start_time"].to_numpy(float),
                               "end_s": windows["end_time"].to_numpy(float)})
        return mics, events

    def site_mics_m(self) -> np.ndarray:
        """(M, 3) mic positions from the tables (to build or check a site)."""
        return self.tables()[0][["x_m", "y_m", "z_m"]].to_numpy(float)

    def load(self, site: Site) -> RecordingBatch:
        """Cut every event from the recordings; see :class:`acoustlab.core.contracts.FieldSource`."""
        mics, events = self.tables()
        positions = mics[["x_m", "y_m", "z_m"]].to_numpy(float)
        if positions.shape != site.mic_positions_m.shape or not np.allclose(positions, site.mic_positions_m, atol=1e-3):
            raise DataError(
                f"field: the recordings' {len(positions)} mic positions do not match site {site.name!r} "
                f"({site.n_mics} mics); build the site from the same mics table"
            )
        fs = self.sample_rate_hz
        pad = int(self.pad_s * fs)
        lengths = ((events["end_s"] - events["start_s"]).to_numpy(float) * fs).astype(int) + 2 * pad
        if (lengths <= 2 * pad).any():
            bad = events.loc[lengths <= 2 * pad, "event_id"].tolist()
            raise DataError(f"field.events: events {bad[:5]} have end_s <= start_s")
        n = int(lengths.max())
        audio = np.zeros((len(events), len(mics), n), dtype=np.float32)
        per_mic = "file" in mics.columns
        for k, ev in enumerate(events.itertuples()):
            start = int(round(ev.start_s * fs)) - pad
            for m in range(len(mics)):
                if per_mic:
                    signal = self._audio(mics["file"].iloc[m])
                else:
                    if "file" not in events.columns:
                        raise DataError("field: the mics table has no 'file' column, so events_csv needs one (multichannel files)")
                    signal = self._multichannel(ev.file, m)
                seg = signal[max(start, 0) : max(start, 0) + lengths[k]]
                audio[k, m, : seg.size] = seg
        rows = pd.DataFrame(
            {
                "event_id": events["event_id"].to_numpy(int),
                "position_id": events["position_id"].to_numpy(int) if "position_id" in events else events["event_id"].to_numpy(int),
                "x_m": events["x_m"].to_numpy(float) if "x_m" in events else np.nan,
                "y_m": events["y_m"].to_numpy(float) if "y_m" in events else np.nan,
                "z_m": events["z_m"].to_numpy(float) if "z_m" in events else np.nan,
                "temperature_c": events["temperature_c"].to_numpy(float) if "temperature_c" in events else self.temperature_c,
                "relative_humidity_pct": events["relative_humidity_pct"].to_numpy(float) if "relative_humidity_pct" in events else self.relative_humidity_pct,
                "start_s": events["start_s"].to_numpy(float),
                "end_s": events["end_s"].to_numpy(float),
            }
        )
        return RecordingBatch(audio=audio, sample_rate_hz=fs, events=rows)

    def _multichannel(self, file: str, channel: int) -> np.ndarray:
        from fractions import Fraction

        import soundfile as sf
        from scipy.signal import resample_poly

        path = resolve_path(self.audio_dir) / str(file)
        try:
            data, rate = sf.read(str(path), dtype="float32", always_2d=True)
        except Exception as exc:  # soundfile raises several types
            raise DataError(f"field: cannot read audio file {path}: {exc}") from None
        if channel >= data.shape[1]:
            raise DataError(f"field: {path} has {data.shape[1]} channels but the mics table lists more mics")
        x = data[:, channel]
        if rate != self.sample_rate_hz:
            ratio = Fraction(self.sample_rate_hz / rate).limit_denominator(1000)
            x = resample_poly(x, ratio.numerator, ratio.denominator)
        return x.astype(np.float32)
