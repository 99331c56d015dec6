"""OpenSoundscape's coordinates table as the recorders of an array: one mic per position, however many files it made.

OpenSoundscape's ``aru_coords.csv`` lists one row per audio *file* (the file path, then ``x``,
``y`` and optionally ``z`` in m). A recorder that made several files over a morning appears once
per file, each row with the same coordinates. acoustlab's mics are recorders, so rows at one
position are one mic whose files are read by time; rows of files no detection names are left out
(a table often lists every file of a deployment). A file whose row gives no height where the
others do (the peer's example lists a too-short file so) cannot place its recorder in 3-D: it is
left out with one warning, and with it its mic, as a bad clip costs its mic (``without_heightless``).
One rule, used by the field's tables and by ``+site=recordings``, so the simulation's mics and the
recordings' mics are the same list.
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

log = logging.getLogger(__name__)

#: Column of the recorders table: the 0-based recorder (mic) each file belongs to.
RECORDER = "recorder"


def without_heightless(coords: pd.DataFrame, where: str) -> pd.DataFrame:
    """``coords`` without the rows whose ``z`` is empty where other rows give one, said in one warning naming them.

    A ``z`` that is text rather than empty is left for the caller's number check (an error, not a
    missing value); a table without heights at all keeps every row (the array is flat).
    """
    if "z" not in coords:
        return coords
    raw = coords["z"]
    empty = raw.isna() | (raw.astype(str).str.strip() == "")
    if not empty.any() or empty.all():
        return coords
    names = coords.loc[empty, "file"].astype(str).tolist()
    log.warning(
        "%s: %d file(s) give no height (z) where the others do and are left out with their recorder, as the peer drops them (first: %r)",
        where,
        len(names),
        names[0],
    )
    kept = coords[~empty].reset_index(drop=True)
    kept.attrs = dict(coords.attrs)
    return kept


def recorders_of(coords: pd.DataFrame, detected_files: set[str] | None) -> pd.DataFrame:
    """The files of ``coords`` that detections use, each with the recorder it belongs to.

    Parameters
    ----------
    coords : pandas.DataFrame
        ``file, x, y`` and optionally ``z`` (m), one row per file, numbers already checked.
    detected_files : set of str, optional
        Files some detection names; None keeps every row.

    Returns
    -------
    pandas.DataFrame
        ``file, x, y, z`` and ``recorder`` (0-based, numbered in order of first appearance),
        one row per kept file, in the table's order. Files at exactly the same coordinates share a
        recorder.
    """
    kept = coords if detected_files is None else coords[coords["file"].isin(detected_files)]
    kept = kept.reset_index(drop=True)
    xyz = np.column_stack(
        [kept["x"].to_numpy(float), kept["y"].to_numpy(float), kept["z"].to_numpy(float) if "z" in kept else np.zeros(len(kept))]
    )
    _, first, inverse = np.unique(xyz, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # recorders numbered by their first row
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return pd.DataFrame({"file": kept["file"].to_numpy(), "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], RECORDER: rank[inverse.ravel()]})


def recorder_positions_m(recorders: pd.DataFrame) -> np.ndarray:
    """(R, 3) each recorder's position, m, in recorder order (from ``recorders_of``)."""
    first = recorders.drop_duplicates(RECORDER).sort_values(RECORDER)
    return first[["x", "y", "z"]].to_numpy(float)
