"""ISO 8601 times in a table's column, read one way wherever start times are read (files tables, the peer's tables).

Times with a UTC offset are converted to UTC; times without one are kept as written (an array's
recorders share a setting). A column mixing the two is refused: read either way, the other half
would be off by the offset (2 h in central European summer), silently.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from acoustlab.core.errors import DataError, show

#: A UTC offset at the end of an ISO 8601 time: ``Z``, ``+02:00``, ``-0500``.
OFFSET_PATTERN = r"(?:Z|[+-]\d{2}:?\d{2})$"


def iso_times(values: pd.Series, where: str, column: str) -> pd.Series:
    """The column's times as naive timestamps (UTC where they carry an offset), or one line naming the first bad value.

    Parameters
    ----------
    values : pandas.Series
        The column, as read.
    where : str
        The table, as the message names it (e.g. ``recordings.files_csv: /data/files.csv``).
    column : str
        The column's name.

    Raises
    ------
    DataError
        Naming the line (counting the header as line 1) and the value: one that is not an ISO 8601
        time, or one with a UTC offset in a column whose first time has none (or the reverse).
    """
    text = values.astype(str).str.strip()
    has_offset = text.str.contains(OFFSET_PATTERN, regex=True).to_numpy()
    if has_offset.any() and not has_offset.all():
        line = int(np.flatnonzero(has_offset != has_offset[0])[0])
        raise DataError(
            f"{where}, line {line + 2}, column {column}: {show(text.iloc[line])} {'has' if has_offset[line] else 'lacks'} a UTC "
            f"offset and line 2 {'does not' if has_offset[line] else 'does'}; give every time with an offset or none"
        )
    parsed = pd.to_datetime(text, errors="coerce", format="ISO8601", utc=bool(has_offset.all()))
    if parsed.isna().any():
        line = int(np.flatnonzero(parsed.isna().to_numpy())[0])
        raise DataError(
            f"{where}, line {line + 2}, column {column}: {show(values.iloc[line])} is not an ISO 8601 time (e.g. 2026-05-01T05:30:00)"
        )
    return parsed.dt.tz_localize(None) if parsed.dt.tz is not None else parsed
