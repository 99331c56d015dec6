"""Detections on single recorders grouped into events heard by the array.

One call reaches every recorder within the array's largest travel time. Detections of one label
whose windows lie within that time of each other are one event, each recorder at most once: a
recorder's next detection is its next call, so a detector's consecutive fixed windows (BirdNET's
3-s windows of a bird singing on and on) become one event per window instead of chaining into one
long event. A detection joins the open event (within the travel time of its reach, lacking its
recorder) it overlaps most, else starts one. The event's clip spans the earliest start to the
latest end of its detections, widened on both sides only by what a recorder that did not detect it
needs: a recorder's arrival lies within its travel time from any recorder that heard the call, so
the widening is, over the recorders without a detection, the largest of their shortest travel
times to one with (none where every recorder detected it: each detection holds its own arrival),
plus a stated pad for a detector's box that starts late. A wider clip only adds the noise around
the call to every cross-correlation. Without the travel times (``travel_s``) the clip is widened by
the linkage distance, the array's largest travel time. Events heard by
fewer than ``min_recorders`` recorders are dropped (they cannot be localized); events longer than
``max_event_s`` (a chorus merged into one window) are kept but flagged ``too_long`` and not read.
The detection band (Raven's ``Low/High Freq (Hz)``) of an event is the union of its detections'
bands, NaN where none was given.
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from acoustlab.core import columns as col

log = logging.getLogger(__name__)

#: Columns of the events table, in order.
EVENT_TABLE_COLUMNS = (
    col.EVENT_ID,
    col.START,
    col.END,
    "label",
    "n_recorders",
    "recorders",
    "score",
    col.BAND_LOW,
    col.BAND_HIGH,
    "too_long",
    "not_read",
    "detections",
    "widening_s",
)


def link_per_recorder(start_s: np.ndarray, end_s: np.ndarray, recorder: np.ndarray, margin_s: float) -> np.ndarray:
    """(N,) event number of each detection (sorted by start): linked within ``margin_s``, one detection per recorder per event.

    Open events are those whose reach (latest end) plus ``margin_s`` is not before the detection's
    start; the detection joins the open event without its recorder that it overlaps most (ties:
    the earliest), else starts a new event.
    """
    cluster = np.empty(len(start_s), dtype=np.int64)
    reach: list[float] = []
    first: list[float] = []
    members: list[set] = []
    open_events: list[int] = []
    for k in range(len(start_s)):
        open_events = [c for c in open_events if reach[c] + margin_s >= start_s[k]]
        best, best_overlap = -1, -np.inf
        for c in open_events:
            if recorder[k] in members[c]:
                continue
            overlap = min(end_s[k], reach[c]) - max(start_s[k], first[c])
            if overlap > best_overlap:
                best, best_overlap = c, overlap
        if best < 0:
            best = len(reach)
            reach.append(end_s[k])
            first.append(start_s[k])
            members.append(set())
            open_events.append(best)
        reach[best] = max(reach[best], end_s[k])
        members[best].add(recorder[k])
        cluster[k] = best
    return cluster


def merge_split_calls(start_s: np.ndarray, recorder: np.ndarray, cluster: np.ndarray, margin_s: float) -> tuple[np.ndarray, np.ndarray]:
    """One event per call: events of one call that linking split (a recorder's false positive just before the call took
    its slot, and the call's first arrival joined it) merged again, each recorder's detection nearest the call kept.

    Consecutive events (by their median start) are one call where their median starts lie within
    twice ``margin_s`` (a call's arrivals span at most the array's travel time; jitter and the
    false positive's own offset take the rest) and they share fewer recorders than the smaller
    has: two calls of one bird in quick succession share every recorder and stay two. In the
    merged event a recorder with several detections keeps the one whose start is nearest the
    median start of the recorders with one (of all, where none has one); its others are returned
    as ``apart`` (True): a false positive, or an echo, of a recorder the call already has.

    Returns
    -------
    cluster : numpy.ndarray
        (N,) each detection's event after merging (the ones set apart keep their merged event's).
    apart : numpy.ndarray
        (N,) True for a detection set apart.
    """
    ids, inverse = np.unique(cluster, return_inverse=True)
    by_event = pd.DataFrame({"event": inverse, "start": start_s, "recorder": recorder})
    median = by_event.groupby("event")["start"].median().to_numpy()
    members = by_event.groupby("event")["recorder"].agg(set).to_numpy()
    head_of = np.arange(ids.size)  # each event's merged event, by position in ids
    head, head_recorders, head_median = -1, set(), -np.inf
    for k in np.argsort(median, kind="stable"):
        mine = members[k]
        if head >= 0 and median[k] - head_median <= 2 * margin_s and len(mine & head_recorders) < min(len(mine), len(head_recorders)):
            head_of[k] = head
            head_recorders = head_recorders | mine
        else:
            head, head_recorders, head_median = k, set(mine), median[k]
    merged = ids[head_of[inverse]]
    apart = np.zeros(len(cluster), dtype=bool)
    # only events where a recorder has several detections need a choice: found in one pass, then row by row
    counts = pd.DataFrame({"event": merged, "recorder": recorder}).groupby(["event", "recorder"], sort=False).size()
    crowded = counts.index.get_level_values("event")[counts.to_numpy() > 1].unique()
    rows_of = pd.Series(np.arange(len(cluster))).groupby(merged).indices
    for c in crowded:
        rows = rows_of[c]
        recorders, n = np.unique(recorder[rows], return_counts=True)
        single = np.isin(recorder[rows], recorders[n == 1])
        centre = np.median(start_s[rows[single]] if single.any() else start_s[rows])
        for r in recorders[n > 1]:
            mine = rows[recorder[rows] == r]
            apart[mine[np.argsort(np.abs(start_s[mine] - centre), kind="stable")[1:]]] = True
    return merged, apart


def _without_repeats(detections: pd.DataFrame) -> pd.DataFrame:
    """Detections with each repeat of one recorder's detection (same label, start and end) merged into the first.

    A recorder cannot hear one call twice: a repeat is the same table read twice, or a detector
    writing a window once per view. Kept, each repeat would open an event of its own that no
    other detection closes, and linking would grow with the square of their number. The merged
    row keeps the highest score and every source row.
    """
    key = ["label", "recorder_id", col.START, col.END]
    repeated = detections.duplicated(key, keep=False)
    if not repeated.any():
        return detections
    merged = detections.groupby(key, sort=False, observed=True, dropna=False).agg(
        low_hz=("low_hz", "min"), high_hz=("high_hz", "max"), score=("score", "max"), source=("source", lambda s: ";".join(map(str, s)))
    )
    merged = merged.reset_index().sort_values([col.START, "recorder_id"], kind="stable").reset_index(drop=True)
    log.warning(
        "detections: %d repeat(s) of a detection on the same recorder (same label, start and end) merged into one each",
        len(detections) - len(merged),
    )
    return merged


def clip_widening_s(recorders_heard: np.ndarray, travel_s: pd.DataFrame, pad_s: float) -> np.ndarray:
    """(E,) how far each event's clip reaches beyond its detections on either side, s (see the module docstring).

    Parameters
    ----------
    recorders_heard : numpy.ndarray
        (E,) each event's recorders with a detection, ``;``-joined.
    travel_s : pandas.DataFrame
        Largest travel time between each two recorders read, s (index and columns: recorder ids).
    pad_s : float
        Added to every widening, s.
    """
    names = [str(r) for r in travel_s.index]
    travel = travel_s.to_numpy(float)
    sets, inverse = np.unique(np.asarray(recorders_heard, dtype=str), return_inverse=True)
    per_set = np.empty(sets.size)
    for k, joined in enumerate(sets):  # one value per distinct set of recorders: a season has few
        heard = np.isin(names, joined.split(";"))
        needed = travel[~heard][:, heard].min(axis=1) if heard.any() else travel[~heard].max(axis=1, initial=0.0)
        per_set[k] = float(needed.max(initial=0.0))
    return per_set[inverse] + float(pad_s)


def group_detections(
    detections: pd.DataFrame,
    margin_s: float,
    min_recorders: int = 2,
    max_event_s: float = 10.0,
    travel_s: pd.DataFrame | None = None,
    pad_s: float = 0.0,
) -> pd.DataFrame:
    """Events from detections (see the module docstring), in time order, ``event_id`` 0, 1, ….

    A detection set apart from its call (``merge_split_calls``) is a row of its own, not read, with
    ``not_read`` naming the call's event: never a second position for one call.

    Parameters
    ----------
    detections : pandas.DataFrame
        ``acoustlab.season.detections.DETECTION_COLUMNS``, season seconds.
    margin_s : float
        The array's largest travel time (plus a margin), s: the linkage distance (and the clip's
        widening on each side where ``travel_s`` is None).
    min_recorders : int
        Fewest distinct recorders that must have detected an event.
    max_event_s : float
        Longest clip read, s.
    travel_s : pandas.DataFrame, optional
        Largest travel time between each two recorders read, s (``clip_widening_s``).
    pad_s : float
        Added to the widening on each side where ``travel_s`` is given, s.
    """
    detections = _without_repeats(detections)
    parts = []
    for label, group in detections.groupby("label", sort=True, observed=True):
        g = group.sort_values([col.START, "recorder_id"], kind="stable")
        start, recorder = g[col.START].to_numpy(float), g["recorder_id"].to_numpy()
        cluster, apart = merge_split_calls(
            start, recorder, link_per_recorder(start, g[col.END].to_numpy(float), recorder, margin_s), margin_s
        )
        host = np.where(apart, cluster, -1)  # the event whose call a detection set apart fell in
        cluster = np.where(apart, cluster.max(initial=-1) + 1 + np.arange(len(cluster)), cluster)  # … a row of its own
        agg = (
            g.assign(_cluster=cluster, _host=host)
            .groupby("_cluster", sort=True)
            .agg(
                first=(col.START, "min"),
                last=(col.END, "max"),
                n_recorders=("recorder_id", "nunique"),
                recorders=("recorder_id", lambda r: ";".join(sorted(set(map(str, r))))),
                score=("score", "max"),
                low=("low_hz", "min"),
                high=("high_hz", "max"),
                detections=("source", lambda s: ";".join(map(str, s))),
                host=("_host", "max"),
            )
            .reset_index()
        )
        agg["label"] = label
        parts.append(agg)
    if not parts:
        return pd.DataFrame(columns=list(EVENT_TABLE_COLUMNS))
    events = pd.concat(parts, ignore_index=True)
    heard = events["n_recorders"].to_numpy() >= min_recorders
    hosts_heard = set(zip(events["label"][heard], events["_cluster"][heard], strict=True))
    apart = (events["host"].to_numpy() >= 0) & np.array(
        [(lab, h) in hosts_heard for lab, h in zip(events["label"], events["host"], strict=True)]
    )
    dropped = ~heard & ~apart
    if dropped.any():
        log.info("events: %d of %d heard by fewer than %d recorders; not localized", int(dropped.sum()), len(events), min_recorders)
    if apart.any():
        log.warning(
            "events: %d detection(s) fell within another event's call on a recorder it already has (a false positive or an "
            "echo): kept as rows of their own, flagged in not_read, not localized",
            int(apart.sum()),
        )
    events = events[~dropped].sort_values(["first", "label"], kind="stable").reset_index(drop=True)
    number = {(lab, c): k for k, (lab, c) in enumerate(zip(events["label"], events["_cluster"], strict=True))}
    widening = (
        np.full(len(events), float(margin_s)) if travel_s is None else clip_widening_s(events["recorders"].to_numpy(), travel_s, pad_s)
    )
    out = pd.DataFrame(
        {
            col.EVENT_ID: np.arange(len(events), dtype=np.int64),
            col.START: events["first"].to_numpy(float) - widening,
            col.END: events["last"].to_numpy(float) + widening,
            "label": events["label"].astype(str).to_numpy(),
            "n_recorders": events["n_recorders"].to_numpy(int),
            "recorders": events["recorders"].to_numpy(),
            "score": events["score"].to_numpy(float),
            col.BAND_LOW: events["low"].to_numpy(float),
            col.BAND_HIGH: events["high"].to_numpy(float),
        }
    )
    out["too_long"] = (out[col.END] - out[col.START]).to_numpy() > max_event_s
    out["not_read"] = [
        f"a second detection on recorder {rec} within event {number[(lab, h)]}'s call (a false positive or an echo)" if h >= 0 else ""
        for lab, h, rec in zip(events["label"], events["host"], events["recorders"], strict=True)
    ]
    out["detections"] = events["detections"].to_numpy()
    out["widening_s"] = widening
    if out["too_long"].any():
        log.warning(
            "events: %d longer than max_event_s=%g s (overlapping calls merged); flagged too_long and not localized",
            int(out["too_long"].sum()),
            max_event_s,
        )
    return out
