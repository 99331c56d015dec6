"""Localize a season chunk by chunk: bounded memory, Parquet parts, resumable, sharded.

A season's output folder holds

``files.parquet``
    the recorders' files and their start times (``RecorderFiles``);
``events.parquet``
    the events to place (``group_detections``);
``method.joblib`` + ``method.sha256.json``
    the method fitted once on the site's simulation (``acoustlab.method.saved``);
``season.json``
    what the parts were made from (digests of the events and the method, chunk sizes);
``parts/part-NNNNNN.parquet``
    the positions of chunk N (``chunk_events`` events), written atomically when the chunk is done.

Chunk k is always events ``[k · chunk_events, (k + 1) · chunk_events)`` and is computed in batches
of ``batch_events`` events, so the same chunk gives the same rows whichever shard or resumed run
computes it. Shard s of n computes the chunks k with k mod n = s; a finished part is never
recomputed; ``merge_parts`` joins the parts in chunk order. Peak memory is one batch's audio
(``batch_events`` × mics × clip samples × 4 bytes) and its transforms, the rows of one chunk, and
the fitted method: it does not grow with the season.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import scipy.signal as ss

from acoustlab.core import columns as col
from acoustlab.core.digests import frame_sha256
from acoustlab.core.errors import DataError
from acoustlab.core.files import atomic_write_bytes
from acoustlab.core.heap import keep_freed_memory
from acoustlab.core.types import RecordingBatch
from acoustlab.core.workers import run_in_workers
from acoustlab.method.localizer import FittedLocalizer
from acoustlab.method.saved import load_method
from acoustlab.season.recorder_files import RecorderFiles
from acoustlab.stages.dataset import extract_features
from acoustlab.toolkit.dsp import clip_samples
from acoustlab.toolkit.quality import QualityThresholds, clip_quality, mics_to_drop

log = logging.getLogger(__name__)

FILES, EVENTS, MANIFEST, PARTS = "files.parquet", "events.parquet", "season.json", "parts"
#: Event fields carried into the positions table beside the positions.
SEASON_FIELDS = ("time", "label", "n_recorders", "recorders", "score", col.BAND_LOW, col.BAND_HIGH, "detections")
#: Length of the stand-in clip of an event too long to read, s (it is flagged and not placed).
TOO_LONG_STAND_IN_S = 0.1


@dataclass
class ChunkPlan:
    """How a season's events are cut: ``chunk_events`` per part, ``batch_events`` per computation."""

    chunk_events: int = 256
    batch_events: int = 16
    temperature_c: float = 15.0
    relative_humidity_pct: float = 60.0
    use_detection_band: bool = True
    quality: QualityThresholds = field(default_factory=QualityThresholds)
    #: each event's clip reaches this far beyond its detections on either side, s (``protocol.events.margin_s``): context,
    #: so where it lies outside the recordings (a detection at a file's very start) the clip is not flagged
    margin_s: float = 0.0

    def __post_init__(self) -> None:
        if self.chunk_events < 1 or self.batch_events < 1:
            raise DataError(f"protocol.chunk_events and protocol.batch_events must be >= 1; got {self.chunk_events}, {self.batch_events}")

    @classmethod
    def from_manifest(cls, manifest: dict[str, Any]) -> ChunkPlan:
        """The plan a season's ``season.json`` recorded (``season_manifest``'s ``plan``)."""
        settings = manifest["plan"]
        return cls(**{k: v for k, v in settings.items() if k != "quality"}, quality=QualityThresholds(**settings["quality"]))


def part_path(directory: Path, k: int) -> Path:
    """Where chunk ``k``'s positions are written."""
    return directory / PARTS / f"part-{k:06d}.parquet"


def n_chunks(n_events: int, chunk_events: int) -> int:
    """How many chunks ``n_events`` make."""
    return -(-n_events // chunk_events)


def shard_chunks(n_events: int, chunk_events: int, shard: int, n_shards: int) -> list[int]:
    """Chunks of shard ``shard`` of ``n_shards`` (every n-th chunk, so shards cover the season evenly in time)."""
    if not 0 <= shard < n_shards:
        raise DataError(f"protocol.shard must be in [0, {n_shards}) with protocol.n_shards={n_shards}; got {shard}")
    return list(range(shard, n_chunks(n_events, chunk_events), n_shards))


def season_manifest(
    events: pd.DataFrame,
    method_sha256: str | None,
    plan: ChunkPlan,
    recorders: list[str],
    radii: dict[str, list[Any]],
    recordings: RecorderFiles | None = None,
) -> dict[str, Any]:
    """What a season's parts are made from: the events' and the audio files' digests, the method's, the chunking, the recorders,
    the radii. The files' digest covers each file's path, length, size and modification time, so a file rewritten between a
    kill and its resume is not mixed in."""
    files = (
        None
        if recordings is None
        else frame_sha256(
            recordings.table[[c for c in ("path", "n_frames", "size_bytes", "mtime_ns", "content_sha256") if c in recordings.table]]
        )
    )
    return {
        "events_sha256": frame_sha256(events),
        "recordings": files,
        "n_events": len(events),
        "method_sha256": method_sha256,
        "chunk_events": plan.chunk_events,
        "batch_events": plan.batch_events,
        "recorders": recorders,
        "radii": radii,
        "plan": {k: v for k, v in plan.__dict__.items() if k != "quality"} | {"quality": plan.quality.__dict__},
    }


def check_manifest(directory: Path, manifest: dict[str, Any], unknown: tuple[str, ...] = ()) -> None:
    """Refuse to add to a folder whose parts were made from other inputs (keys in ``unknown`` are not compared yet).

    Raises
    ------
    DataError
        When the folder already holds parts made from different inputs.
    """
    path = directory / MANIFEST
    parts = sorted((directory / PARTS).glob("part-*.parquet"))
    if not path.is_file():
        if parts:
            raise DataError(
                f"{directory} holds {len(parts)} parts but no {MANIFEST}: they are not this run's; "
                "choose another protocol.output_dir, or delete the folder to start again"
            )
        return
    old = json.loads(path.read_text())
    differs = [k for k in manifest if k not in unknown and old.get(k) != manifest[k]]
    if differs and parts:
        raise DataError(
            f"{directory} holds {len(parts)} parts of a season run made with other {', '.join(differs)}; "
            "choose another protocol.output_dir, or delete the folder to start again"
        )


def write_manifest(directory: Path, manifest: dict[str, Any]) -> None:
    """Write ``season.json`` after ``check_manifest`` (parts of other inputs are never mixed)."""
    check_manifest(directory, manifest)
    atomic_write_bytes(directory / MANIFEST, json.dumps(manifest, indent=2).encode())


def read_manifest(directory: Path) -> dict[str, Any]:
    """The season run's manifest (what its parts are made from)."""
    path = directory / MANIFEST
    if not path.is_file():
        raise DataError(f"{directory} holds no season run ({MANIFEST} missing): run the fit stage first (protocol.stage=fit)")
    return json.loads(path.read_text())


def _clip(
    recordings: RecorderFiles,
    recorder: str,
    start_s: float,
    length_s: float,
    sample_rate_hz: float,
    thresholds: QualityThresholds,
    margin_s: float = 0.0,
) -> tuple[np.ndarray, list[str]]:
    """One recorder's clip at the method's sample rate, and its quality flags (none for what is missing in the ``margin_s`` context)."""
    rate = recordings.rate_of(recorder)  # recorders may run at different rates: each clip is resampled from its own
    n_clip = clip_samples(0.0, length_s, sample_rate_hz)[1]  # the window's samples at the method's rate (the one clip rule)
    n_file = int(np.ceil(n_clip * rate / sample_rate_hz))
    extension = max(n_file - int(round(length_s * rate)), 0)  # beyond the window: read where the recording goes on
    read = recordings.read(recorder, start_s, n_file, context=min(int(round(margin_s * rate)), n_file // 2), extension=extension)
    samples = read.samples
    if rate != sample_rate_hz:  # the method was fitted at the simulator's rate
        up, down = int(sample_rate_hz), int(rate)
        g = np.gcd(up, down)
        samples = ss.resample_poly(samples, up // g, down // g).astype(np.float32)
    samples = samples[:n_clip]
    clip, reasons = clip_quality(samples, 0, samples.size, thresholds)
    return clip, [*read.flags, *reasons]


def not_read_reasons(events: pd.DataFrame) -> np.ndarray:
    """(E,) why an event's clips are not read ('' where they are): ``too_long``, or its ``not_read`` note."""
    noted = events["not_read"].fillna("").astype(str).to_numpy() if "not_read" in events else np.full(len(events), "")
    return np.where(events["too_long"].to_numpy(bool), "too_long", noted)


def clip_lengths_s(events: pd.DataFrame) -> np.ndarray:
    """Each event's clip length, s (an event not read gets a stand-in: it is flagged, not read)."""
    return np.where(not_read_reasons(events) != "", TOO_LONG_STAND_IN_S, (events[col.END] - events[col.START]).to_numpy(float))


def padded_samples(lengths_s: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    """Each clip's length in samples, the length its features are computed at (``clip_samples``: its own length only)."""
    return np.array([clip_samples(0.0, length, sample_rate_hz)[1] for length in lengths_s], dtype=np.int64)


def read_batch(
    recordings: RecorderFiles, events: pd.DataFrame, recorders: list[str], sample_rate_hz: float, plan: ChunkPlan
) -> RecordingBatch:
    """The clips of ``events`` on every recorder (in the site's mic order) as a batch, flagged per clip."""
    lengths_s = clip_lengths_s(events)
    padded = padded_samples(lengths_s, sample_rate_hz)
    n_max = int(padded.max())
    audio = np.zeros((len(events), len(recorders), n_max), dtype=np.float32)
    flags, dropped, usable = [], [], []
    # what lies beyond an event's detections is context: missing there (before the first file, in a gap) it flags nothing
    context_s = events["widening_s"].to_numpy(float) if "widening_s" in events else np.full(len(events), plan.margin_s)
    starts = events[col.START].to_numpy(float)
    for e, (start, length, why_not) in enumerate(zip(starts, lengths_s, not_read_reasons(events), strict=True)):
        if why_not:
            flags.append(why_not)
            dropped.append("")
            usable.append(False)
            continue
        parts, per_mic = [], []
        for m, recorder in enumerate(recorders):
            clip, reasons = _clip(recordings, recorder, start, length, sample_rate_hz, plan.quality, float(context_s[e]))
            audio[e, m, : clip.size] = clip[:n_max]
            per_mic.append(reasons)
            if reasons:
                parts.append(f"mic {recorder}: {', '.join(reasons)}")
        flags.append("; ".join(parts))
        drop, ok = mics_to_drop(per_mic)  # a flagged clip costs its recorder, not the event, while enough remain
        dropped.append(drop)
        usable.append(ok)
    rows = pd.DataFrame(
        {
            col.EVENT_ID: events[col.EVENT_ID].to_numpy(np.int64),
            col.POSITION_ID: events[col.EVENT_ID].to_numpy(np.int64),
            col.TRUE_X: np.nan,
            col.TRUE_Y: np.nan,
            col.TRUE_Z: np.nan,
            # a weather table gives each event its own air (``acoustlab.season.weather``); else the plan's one assumption
            col.TEMPERATURE: events[col.TEMPERATURE].to_numpy(float) if col.TEMPERATURE in events else plan.temperature_c,
            col.HUMIDITY: events[col.HUMIDITY].to_numpy(float) if col.HUMIDITY in events else plan.relative_humidity_pct,
            col.START: events[col.START].to_numpy(float),
            col.END: events[col.END].to_numpy(float),
            col.QUALITY_FLAGS: flags,
            "quality_ok": usable,
            col.MICS_DROPPED: dropped,
            col.HARDWARE_FAILURE: False,
            # each clip is computed at its own padded length (extract_features), never its batch-mates': an event's answer
            # depends on the event alone, whatever the batch and chunk sizes
            col.CLIP_SAMPLES: padded,
        }
    )
    if plan.use_detection_band:
        rows[col.BAND_LOW] = events[col.BAND_LOW].to_numpy(float)
        rows[col.BAND_HIGH] = events[col.BAND_HIGH].to_numpy(float)
    return RecordingBatch(audio=audio, sample_rate_hz=sample_rate_hz, events=rows)


def localize_events(
    fitted: FittedLocalizer,
    recordings: RecorderFiles,
    events: pd.DataFrame,
    recorders: list[str],
    plan: ChunkPlan,
    origin: pd.Timestamp,
    on_batch: Callable[[int], None] | None = None,
) -> pd.DataFrame:
    """Positions of ``events`` (one chunk): audio and features batch by batch, the method on the chunk's features at once.

    ``on_batch(n)`` is called after each batch with the number of its events (progress).
    """
    features, rows = [], []
    for first in range(0, len(events), plan.batch_events):  # peak memory: one batch's audio and its transforms
        batch = read_batch(recordings, events.iloc[first : first + plan.batch_events], recorders, float(fitted.sample_rate_hz), plan)
        features.append(extract_features(batch, fitted.site, fitted.feature_sets))
        rows.append(batch.events)
        if on_batch is not None:
            on_batch(batch.n_events)
    detections = pd.concat(rows, ignore_index=True).assign(label=events["label"].to_numpy())
    times = (origin + pd.to_timedelta(events[col.START].to_numpy(float), unit="s")).strftime("%Y-%m-%dT%H:%M:%S.%f")
    season_fields = pd.DataFrame({"time": times, **{name: events[name].to_numpy() for name in SEASON_FIELDS[2:]}})
    return fitted.place(pd.concat(features, ignore_index=True), detections, season_fields).positions


def chunk_event_ids(directory: Path, chunk_events: int) -> list[np.ndarray]:
    """The event ids of every chunk, in order (what each part must hold)."""
    ids = pd.read_parquet(directory / EVENTS, columns=[col.EVENT_ID])[col.EVENT_ID].to_numpy(np.int64)
    return [ids[i : i + chunk_events] for i in range(0, ids.size, chunk_events)]


#: Keys of each part's Parquet metadata: the season it belongs to (``season_identity``) and the chunk it holds.
PART_SEASON_KEY, PART_CHUNK_KEY = b"acoustlab.season", b"acoustlab.chunk"


def season_identity(manifest: dict[str, Any]) -> str:
    """The SHA-256 of a season's manifest (its events, files, method, chunking and radii): what each of its parts carries.

    Every season numbers its events 0, 1, 2 …, so event ids alone cannot tell this season's part
    from another's; two seasons with one identity were made from the same inputs and give the same parts.
    """
    return hashlib.sha256(json.dumps(manifest, sort_keys=True, default=str).encode()).hexdigest()


def part_bytes(table: pd.DataFrame, identity: str, k: int) -> bytes:
    """Chunk ``k``'s positions as a Parquet file that names its season and chunk in its metadata."""
    arrow = pa.Table.from_pandas(table, preserve_index=False)
    arrow = arrow.replace_schema_metadata(
        {**(arrow.schema.metadata or {}), PART_SEASON_KEY: identity.encode(), PART_CHUNK_KEY: str(k).encode()}
    )
    sink = pa.BufferOutputStream()
    pq.write_table(arrow, sink)
    return sink.getvalue().to_pybytes()


def read_part(directory: Path, k: int, event_ids: np.ndarray, identity: str, columns: list[str] | None = None) -> pd.DataFrame | None:
    """Chunk ``k``'s part (``columns`` of it), or None where it cannot be read (an empty or damaged file: the chunk is computed again).

    Raises
    ------
    DataError
        When the part reads but is not this season's chunk ``k`` (its metadata names another season
        or chunk, or none, or it holds other events): it was copied in from elsewhere.
    """
    path = part_path(directory, k)
    try:
        metadata = pq.read_schema(path).metadata or {}
        table = pd.read_parquet(path, columns=columns)
    except (OSError, ValueError) as exc:
        log.warning("%s cannot be read (%s); chunk %d is computed again", path, str(exc).splitlines()[0][:120], k)
        return None
    held = table[col.EVENT_ID].to_numpy(np.int64) if col.EVENT_ID in table else np.array([], dtype=np.int64)
    ours = metadata.get(PART_SEASON_KEY) == identity.encode() and metadata.get(PART_CHUNK_KEY) == str(k).encode()
    if not ours or not np.array_equal(held, event_ids):
        what = "other events than" if ours else "the metadata of another season's part, not that of"
        raise DataError(
            f"{path} holds {what} chunk {k} of this season (it is not this run's part); delete it and run protocol.stage=localize again"
        )
    return table


def localize_chunks(
    directory: Path,
    chunks: Iterable[int],
    fitted: FittedLocalizer | None = None,
    progress_every_s: float = 5.0,
    label: str = "season",
    parent_pid: int | None = None,
) -> int:
    """Compute the listed chunks whose part is not yet written; return how many were computed.

    Everything is read from ``directory`` (the method verified by its digest), so a shard on
    another machine computes exactly what the unsharded run would. A local worker passes its
    parent's ``parent_pid``: when the parent is gone (killed), the worker stops before its next
    chunk instead of running on unseen (every part is written atomically, so a resume redoes
    nothing that was finished).
    """
    keep_freed_memory()  # every batch allocates the same large arrays again
    manifest = read_manifest(directory)
    fitted = fitted if fitted is not None else load_method(directory, manifest["method_sha256"])
    recordings = RecorderFiles.load(directory / FILES)
    plan = ChunkPlan.from_manifest(manifest)
    recordings.check_unchanged()
    chunk_ids = chunk_event_ids(directory, plan.chunk_events)
    identity = season_identity(manifest)
    todo = [
        k
        for k in chunks
        if not part_path(directory, k).is_file() or read_part(directory, k, chunk_ids[k], identity, [col.EVENT_ID]) is None
    ]
    total = sum(min(plan.chunk_events, manifest["n_events"] - k * plan.chunk_events) for k in todo)
    progress = _RateLog(total, progress_every_s, label)
    computed = 0
    for k in todo:
        if parent_pid is not None and os.getppid() != parent_pid:
            log.warning("%s: the run that started this worker is gone; stopping before chunk %d", label, k)
            break
        computed += 1
        chunk = read_chunk(directory, k, plan.chunk_events)
        table = localize_events(fitted, recordings, chunk, manifest["recorders"], plan, recordings.origin, on_batch=progress.add)
        part_path(directory, k).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(part_path(directory, k), part_bytes(table, identity, k))
    recordings.close()
    return computed


class _RateLog:
    """A progress line (done, rate, time left) at most every ``every_s`` seconds, and one at the end."""

    def __init__(self, total: int, every_s: float, label: str) -> None:
        self.total, self.every_s, self.label = total, every_s, label
        self.done = 0
        self.started = self.last = time.monotonic()

    def add(self, n: int) -> None:
        self.done += n
        now = time.monotonic()
        if now - self.last >= self.every_s or self.done >= self.total:
            self.last = now
            rate = self.done / max(now - self.started, 1e-9)
            log.info(
                "%s: %d/%d detections, %.1f detections/s, about %.0f s left",
                self.label,
                self.done,
                self.total,
                rate,
                (self.total - self.done) / max(rate, 1e-9),
            )


def write_events(directory: Path, events: pd.DataFrame, chunk_events: int) -> None:
    """``events.parquet`` with one row group per chunk, so a process reads only its chunks' events (not the season's)."""
    atomic_write_bytes(directory / EVENTS, events.to_parquet(index=False, row_group_size=chunk_events))


def read_chunk(directory: Path, k: int, chunk_events: int) -> pd.DataFrame:
    """The events of chunk ``k`` (its row group; the whole table is read only for a file written otherwise)."""
    events = pq.ParquetFile(directory / EVENTS)
    sizes = [events.metadata.row_group(g).num_rows for g in range(events.metadata.num_row_groups)]
    if all(n == chunk_events for n in sizes[:-1]) and k < len(sizes):
        return events.read_row_group(k).to_pandas()
    return pd.read_parquet(directory / EVENTS).iloc[k * chunk_events : (k + 1) * chunk_events].reset_index(drop=True)


def localize_shard(directory: str, shard: int, n_shards: int, threads: int = 1, parent_pid: int | None = None) -> int:
    """One local worker's shard: the chunks k ≡ shard (mod n_shards), with ``threads`` threads for numerics.

    ``parent_pid``: the run that started the worker; the worker stops when that process is gone.
    """
    from threadpoolctl import threadpool_limits

    directory_path = Path(directory)
    manifest = read_manifest(directory_path)
    with threadpool_limits(limits=threads):
        return localize_chunks(
            directory_path,
            shard_chunks(manifest["n_events"], manifest["chunk_events"], shard, n_shards),
            label=f"season shard {shard + 1}/{n_shards}",
            parent_pid=parent_pid,
        )


def localize_in_workers(directory: Path, n_workers: int, threads: int) -> int:
    """Every chunk of the season in ``directory`` over ``n_workers`` local processes of ``threads`` threads each, each a shard;
    the workers die with this process (``acoustlab.core.workers``). Returns how many chunks were computed."""
    shards = [(str(directory), s, n_workers, threads, os.getpid()) for s in range(n_workers)]
    return int(sum(run_in_workers(localize_shard, shards, n_workers)))


def missing_chunks(directory: Path) -> list[int]:
    """Chunks whose part is not written yet."""
    manifest = read_manifest(directory)
    return [k for k in range(n_chunks(manifest["n_events"], manifest["chunk_events"])) if not part_path(directory, k).is_file()]


def merge_parts(directory: Path) -> pd.DataFrame:
    """Every part in chunk order, as one positions table.

    Raises
    ------
    DataError
        Naming the chunks not computed yet.
    """
    missing = missing_chunks(directory)
    if missing:
        raise DataError(
            f"{directory}: {len(missing)} chunks not computed yet (e.g. {missing[:5]}); run the localize stage "
            "for every shard first (protocol.stage=localize), then merge"
        )
    manifest = read_manifest(directory)
    identity = season_identity(manifest)
    parts = []
    for k, event_ids in enumerate(chunk_event_ids(directory, manifest["chunk_events"])):
        part = read_part(directory, k, event_ids, identity)
        if part is None:
            raise DataError(
                f"{part_path(directory, k)} cannot be read; run protocol.stage=localize again (it computes that chunk anew), then merge"
            )
        parts.append(part)
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
