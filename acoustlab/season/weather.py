"""A weather logger's table: each detection of a season gets the air it was heard in.

The speed of sound grows by about 0.6 m/s per °C; a season assuming one temperature for every
detection places its calls with the error of that assumption (a 5 °C day–night swing is a 0.9 %
error in every range difference). ``protocol.weather_csv`` is a CSV with ``time`` (ISO 8601, read
as every start time is: ``acoustlab.toolkit.table_times.iso_times``, times with a UTC offset
converted to UTC as the files' own zoned start times are) and ``temperature_c``, optionally
``relative_humidity_pct``; each event gets the values interpolated linearly in time at the middle
of its detections, the way ``localize`` takes each event's own temperature from its events table.
An event outside the table's span takes the nearest reading, said in one line with how many.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import DataError, show
from acoustlab.toolkit.table_times import iso_times

log = logging.getLogger(__name__)

TIME, TEMPERATURE, HUMIDITY = "time", col.TEMPERATURE, col.HUMIDITY
#: Plausible ranges of each reading (the site's limits for the air): a value outside is a logger fault or a unit slip.
RANGES = {TEMPERATURE: (-60.0, 60.0, "°C"), HUMIDITY: (0.0, 100.0, "%")}


def read_weather(path: Path) -> pd.DataFrame:
    """The weather table at ``path``: ``time`` (Timestamps, sorted), ``temperature_c`` and, where given, ``relative_humidity_pct``.

    Raises
    ------
    DataError
        Naming the file, line and column of the first value that is not what is expected.
    """
    try:
        table = pd.read_csv(path, dtype=str, keep_default_na=False)
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise DataError(f"protocol.weather_csv: cannot read {path}: {str(exc).splitlines()[0]}") from None
    for needed in (TIME, TEMPERATURE):
        if needed not in table:
            raise DataError(f"protocol.weather_csv: {path} has no '{needed}' column (it needs {TIME}, {TEMPERATURE}[, {HUMIDITY}])")
    if table.empty:
        raise DataError(f"protocol.weather_csv: {path} has no readings")
    out = pd.DataFrame({TIME: iso_times(table[TIME], f"protocol.weather_csv: {path}", TIME)})
    for name in (TEMPERATURE, HUMIDITY):
        if name not in table:
            continue
        low, high, unit = RANGES[name]
        values = pd.to_numeric(table[name], errors="coerce").to_numpy(float)
        bad = ~np.isfinite(values) | (values < low) | (values > high)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DataError(
                f"protocol.weather_csv: {path}, line {i + 2}, column '{name}': {show(table[name].iloc[i])} is not a number in "
                f"[{low:g}, {high:g}] {unit}"
            )
        out[name] = values
    repeated = out[TIME].duplicated()
    if repeated.any():
        i = int(np.flatnonzero(repeated.to_numpy())[0])
        raise DataError(f"protocol.weather_csv: {path}, line {i + 2}: time {show(table[TIME].iloc[i])} is given twice")
    return out.sort_values(TIME, kind="stable").reset_index(drop=True)


def weather_at(weather: pd.DataFrame, seconds: np.ndarray, origin: pd.Timestamp, path: Path) -> pd.DataFrame:
    """(E,) ``temperature_c`` (and ``relative_humidity_pct`` where the table has it) at each of ``seconds`` after ``origin``
    (the recordings' naive start time, UTC where the files gave a zone)."""
    at = np.asarray((weather[TIME] - origin).dt.total_seconds(), dtype=float)
    seconds = np.asarray(seconds, dtype=float)
    outside = (seconds < at[0]) | (seconds > at[-1])
    if outside.any():
        log.warning(
            "protocol.weather_csv: %d of %d events lie outside %s's readings (%s to %s): they take the nearest reading",
            int(outside.sum()),
            seconds.size,
            path.name,
            weather[TIME].iloc[0],
            weather[TIME].iloc[-1],
        )
    return pd.DataFrame(
        {name: np.interp(seconds, at, weather[name].to_numpy(float)) for name in (TEMPERATURE, HUMIDITY) if name in weather}
    )
