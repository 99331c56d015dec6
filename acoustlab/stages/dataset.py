"""The cached data stages: simulate recordings, then extract features, in chunks.

Simulation streams chunk by chunk to ``<cache>/simulation/<key>/`` (audio as .npy, events as
parquet) so memory stays bounded by one chunk; features are computed chunk by chunk from there
and stored as one parquet table in ``<cache>/features/<key>/``. Keys hash exactly the config that
determines a stage plus the plugin code version (``acoustlab.stages.cache.plugin_version``).
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

from acoustlab.core import columns as col
from acoustlab.core.contracts import FeatureSet, Simulator, hook
from acoustlab.core.digests import file_sha256
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.files import atomic_save_npy, atomic_write_bytes
from acoustlab.core.progress import progress
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.stages.cache import (
    MANIFEST,
    StageCache,
    code_digest,
    plugin_version,
    write_manifest,
)
from acoustlab.toolkit.quality import DEAD_MICS, failed_positions

log = logging.getLogger(__name__)


@dataclass
class Dataset:
    """Feature table and event table of a dataset, row-aligned.

    Attributes
    ----------
    events : pandas.DataFrame
        One row per event (see ``acoustlab.core.types.EVENT_COLUMNS``).
    features : pandas.DataFrame
        One row per event, columns ``group__name``.
    dataset_hash : str
        SHA-256 of the recordings and the event table (identical data ⇔ identical hash).
    features_sha256 : str
        SHA-256 of the feature table's file as read (verified against the cache manifest).
    """

    events: pd.DataFrame
    features: pd.DataFrame
    dataset_hash: str
    features_sha256: str = ""


@dataclass(frozen=True)
class SimulationPlan:
    """Which events to simulate.

    Attributes
    ----------
    n_events : int
        Number of events.
    events_per_position : int
        Consecutive events sharing one source position (the exchangeable group).
    seed : int
        Base seed of every random draw.
    chunk_size : int
        Events per stored chunk (does not change the data).
    n_jobs : int
        Worker processes rendering chunks in parallel (does not change the data).
    shard_index, shard_count : int
        Render only chunks ``k`` with ``k % shard_count == shard_index`` (a cluster job array
        filling a shared cache); ``shard_count=1`` renders everything.
    """

    n_events: int
    events_per_position: int
    seed: int
    chunk_size: int = 64
    n_jobs: int = 1
    shard_index: int = 0
    shard_count: int = 1

    def __post_init__(self) -> None:
        if self.n_events < 1:
            raise ConfigError(f"data.n_events must be >= 1; got {self.n_events}")
        if self.events_per_position < 1:
            raise ConfigError(f"data.events_per_position must be >= 1; got {self.events_per_position}")
        if self.n_jobs < 1:
            raise ConfigError(f"data.n_jobs must be >= 1 worker process; got {self.n_jobs}")
        if self.seed < 0:
            raise ConfigError(f"seed must be a non-negative integer; got {self.seed}")
        if self.chunk_size < 1:
            raise ConfigError(f"data.chunk_size must be >= 1; got {self.chunk_size}")
        if self.shard_count < 1 or not 0 <= self.shard_index < self.shard_count:
            raise ConfigError(f"data.shard_index must be in [0, data.shard_count); got {self.shard_index} of {self.shard_count}")

    def chunks(self) -> list[tuple[int, int]]:
        """[start, stop) event ranges of the chunks."""
        return [(s, min(s + self.chunk_size, self.n_events)) for s in range(0, self.n_events, self.chunk_size)]


def _chunk_name(start: int, stop: int) -> str:
    return f"events_{start:07d}_{stop:07d}"


class _DataHasher:
    """SHA-256 over all audio then all event rows, independent of how events are chunked."""

    def __init__(self) -> None:
        self.audio = hashlib.sha256()
        self.events = hashlib.sha256()

    def update(self, batch_audio: np.ndarray, events: pd.DataFrame) -> None:
        self.audio.update(np.ascontiguousarray(batch_audio).tobytes())
        self.events.update(pd.util.hash_pandas_object(events, index=False).to_numpy().tobytes())

    def hexdigest(self) -> str:
        return hashlib.sha256((self.audio.hexdigest() + self.events.hexdigest()).encode()).hexdigest()


def simulation_key(site: Site, simulator: Simulator, simulator_cfg: dict[str, Any], plan: SimulationPlan) -> str:
    """Content address of a simulation: site, simulator config and code, events, seed."""
    return StageCache.key(
        {
            "stage": "simulation",
            "stage_code": code_digest(__name__, follow_imports=False),
            "site": site.fingerprint(),
            "simulator": simulator_cfg,
            "plugin": plugin_version(simulator),
            "n_events": plan.n_events,
            "events_per_position": plan.events_per_position,
            "seed": plan.seed,
        }
    )


def _render_chunk(site: Site, simulator: Simulator, plan: SimulationPlan, start: int, stop: int, work: Path) -> None:
    """Render events [start, stop) and store them atomically (a worker's unit of work)."""
    audio_path = work / f"{_chunk_name(start, stop)}.npy"
    events_path = work / f"{_chunk_name(start, stop)}.parquet"
    if audio_path.exists() and events_path.exists():  # finished before an interruption, or by another shard
        return
    ids = np.arange(start, stop)
    batch = simulator.simulate(site, ids, ids // plan.events_per_position, plan.seed)
    atomic_save_npy(audio_path, batch.audio)
    atomic_write_bytes(events_path, batch.events.to_parquet(index=False))


def simulate_to_cache(
    site: Site, simulator: Simulator, simulator_cfg: dict[str, Any], plan: SimulationPlan, cache: StageCache
) -> Path | None:
    """Simulate (or find in the cache) every event; return the directory of the stored chunks.

    Chunks are rendered by ``plan.n_jobs`` worker processes and written as they finish, so memory
    holds one chunk per worker. With ``plan.shard_count > 1`` only this shard's chunks are rendered
    into the shared work directory and None is returned; a later unsharded run finds them there.
    """
    key = simulation_key(site, simulator, simulator_cfg, plan)
    render = partial(_render_simulation, site, simulator, plan, cache, key)
    if plan.shard_count > 1:  # shards of a job array write disjoint chunks of one work directory: no lock
        return cache.lookup("simulation", key, repair=True) or render()
    return cache.get_or_build("simulation", key, render)


def _render_simulation(site: Site, simulator: Simulator, plan: SimulationPlan, cache: StageCache, key: str) -> Path | None:
    """Render this job's (missing) chunks into the work directory; commit the entry unless sharded."""
    simulator.validate(site)
    work = cache.partial_dir("simulation", key)
    chunks = plan.chunks()
    mine = [c for k, c in enumerate(chunks) if k % plan.shard_count == plan.shard_index]
    todo = [c for c in mine if not (work / f"{_chunk_name(*c)}.npy").exists() or not (work / f"{_chunk_name(*c)}.parquet").exists()]
    if len(todo) < len(mine):
        log.info("resuming simulation: %d of %d chunks already rendered", len(mine) - len(todo), len(mine))
    desc = f"simulate {site.name}" + (f" shard {plan.shard_index + 1}/{plan.shard_count}" if plan.shard_count > 1 else "")
    if plan.n_jobs == 1 or len(todo) <= 1:
        for start, stop in progress(todo, desc=desc, unit="chunk"):
            _render_chunk(site, simulator, plan, start, stop, work)
    else:
        jobs = Parallel(n_jobs=plan.n_jobs, return_as="generator_unordered")(
            delayed(_render_chunk)(site, simulator, plan, start, stop, work) for start, stop in todo
        )
        for _ in progress(jobs, total=len(todo), desc=desc, unit="chunk"):
            pass
    if plan.shard_count > 1:
        log.info("shard %d of %d rendered into %s", plan.shard_index + 1, plan.shard_count, work)
        return None
    digest = _DataHasher()
    for start, stop in chunks:
        digest.update(*_read_chunk_or_render(site, simulator, plan, start, stop, work))
    manifest = {
        "chunks": [_chunk_name(s, e) for s, e in chunks],
        "sample_rate_hz": simulator.sample_rate_hz,
        "dataset_hash": digest.hexdigest(),
        "site": site.name,
        "n_events": plan.n_events,
    }
    write_manifest(work, manifest)
    return cache.commit("simulation", key, work)


def _read_chunk_or_render(
    site: Site, simulator: Simulator, plan: SimulationPlan, start: int, stop: int, work: Path
) -> tuple[np.ndarray, pd.DataFrame]:
    """A rendered chunk of the work directory; one that cannot be read (damaged after an interruption) is rendered again."""
    name = _chunk_name(start, stop)
    try:
        return _load_chunk(work, name)
    except Exception as exc:
        log.warning("simulation chunk %s in %s is unreadable (%s: %s); rendering it again", name, work, type(exc).__name__, exc)
        for suffix in (".npy", ".parquet"):
            (work / f"{name}{suffix}").unlink(missing_ok=True)
        _render_chunk(site, simulator, plan, start, stop, work)
        return _load_chunk(work, name)


def _load_chunk(directory: Path, name: str) -> tuple[np.ndarray, pd.DataFrame]:
    """A stored chunk: (E, M, S) audio and its event rows."""
    return np.load(directory / f"{name}.npy"), pd.read_parquet(directory / f"{name}.parquet")


def _chunk_features(sim_dir: Path, name: str, sample_rate_hz: float, site: Site, feature_sets: dict[str, FeatureSet]):
    """Features and events of one stored chunk (a worker's unit of work)."""
    audio, events = _load_chunk(sim_dir, name)
    batch = RecordingBatch(audio=audio, sample_rate_hz=sample_rate_hz, events=events)
    return extract_features(batch, site, feature_sets), batch.events


def extract_features(batch: RecordingBatch, site: Site, feature_sets: dict[str, FeatureSet]) -> pd.DataFrame:
    """Every feature group on one batch, concatenated column-wise in the configured group order.

    Where the events give their own clip lengths (``clip_samples``: recordings of events of different
    lengths, zero-padded to the longest), each length is computed as a batch of its own, cut to that
    length: the padding would change an event's spectra (a PHAT weighting, a noise floor over frames),
    so its features would depend on the other events in the table.
    """
    if col.CLIP_SAMPLES in batch.events:
        return _features_by_clip_length(batch, site, feature_sets)
    return _features_of(batch, site, feature_sets)


def _features_by_clip_length(batch: RecordingBatch, site: Site, feature_sets: dict[str, FeatureSet]) -> pd.DataFrame:
    """``extract_features`` per clip length, cut to that length, in the batch's row order."""
    lengths = batch.events[col.CLIP_SAMPLES].to_numpy(np.int64)
    groups = [np.flatnonzero(lengths == n) for n in np.unique(lengths)]
    tables = []
    for rows in groups:
        events = batch.events.iloc[rows].drop(columns=[col.CLIP_SAMPLES]).reset_index(drop=True)
        audio = batch.audio[rows, :, : int(lengths[rows[0]])]
        tables.append(_features_of(RecordingBatch(audio, batch.sample_rate_hz, events), site, feature_sets))
    order = np.argsort(np.concatenate(groups), kind="stable")
    return pd.concat(tables, ignore_index=True).iloc[order].reset_index(drop=True)


def _features_of(batch: RecordingBatch, site: Site, feature_sets: dict[str, FeatureSet]) -> pd.DataFrame:
    """Every feature group on one batch whose clips all fill its samples."""
    tables = []
    for name, fs in feature_sets.items():
        table = fs.transform(batch, site)
        if len(table) != batch.n_events:
            raise DataError(f"feature group {name!r} returned {len(table)} rows for {batch.n_events} events")
        wrong = [c for c in table.columns if not c.startswith(f"{fs.group}__")]
        if wrong:
            raise DataError(f"feature group {name!r} produced columns outside its group {fs.group!r}: {wrong[:3]}")
        tables.append(table.reset_index(drop=True).astype(float))
    return pd.concat(tables, axis=1)


def _store_tables(cache: StageCache, stage: str, key: str, features: pd.DataFrame, events: pd.DataFrame, dataset_hash: str) -> Path:
    """Write a feature-stage entry (features, events, data hash) and commit it to the cache."""
    work = cache.partial_dir(stage, key)
    atomic_write_bytes(work / "features.parquet", features.to_parquet(index=False))
    atomic_write_bytes(work / "events.parquet", events.to_parquet(index=False))
    write_manifest(work, {"dataset_hash": dataset_hash})
    return cache.commit(stage, key, work)


def _read_tables(entry: Path) -> Dataset:
    """The Dataset stored in a feature-stage entry (its files were verified against the manifest by the lookup)."""
    manifest = json.loads((entry / MANIFEST).read_text())
    return Dataset(
        events=pd.read_parquet(entry / "events.parquet"),
        features=pd.read_parquet(entry / "features.parquet"),
        dataset_hash=manifest["dataset_hash"],
        features_sha256=manifest["files"]["features.parquet"],
    )


def _get_verified_tables(cache: StageCache, stage: str, key: str, build: Callable[[], Path | None]) -> Dataset | None:
    """A feature-stage entry read back, rebuilding it once where it is unreadable despite matching its checksums."""
    found = cache.get_or_build(stage, key, build)
    if found is None:
        return None
    try:
        return _read_tables(found)
    except Exception as exc:
        if not cache.enabled:
            raise
        with cache.building(stage, key):
            cache.discard(stage, key, f"{type(exc).__name__}: {exc}")
        found = cache.get_or_build(stage, key, build)
        return None if found is None else _read_tables(found)


def _features_to_cache(sim_dir: Path, site: Site, feature_sets: dict[str, FeatureSet], n_jobs: int, cache: StageCache, key: str) -> Path:
    """Extract features from every stored simulation chunk (in ``n_jobs`` processes) and commit them."""
    manifest = json.loads((sim_dir / MANIFEST).read_text())
    names = manifest["chunks"]
    jobs = Parallel(n_jobs=n_jobs, return_as="generator")(
        delayed(_chunk_features)(sim_dir, name, float(manifest["sample_rate_hz"]), site, feature_sets) for name in names
    )
    results = list(progress(jobs, total=len(names), desc="features", unit="chunk"))
    return _store_tables(
        cache,
        "features",
        key,
        pd.concat([r[0] for r in results], ignore_index=True),
        pd.concat([r[1] for r in results], ignore_index=True),
        manifest["dataset_hash"],
    )


def load_or_build_simulated(
    site: Site,
    simulator: Simulator,
    simulator_cfg: dict[str, Any],
    feature_sets: dict[str, FeatureSet],
    features_cfg: dict[str, Any],
    plan: SimulationPlan,
    cache: StageCache,
) -> Dataset | None:
    """The feature and event tables of a simulated dataset, from the cache when possible.

    Returns None for a sharded run (``plan.shard_count > 1``), which only renders its shard.
    """
    sim_key = simulation_key(site, simulator, simulator_cfg, plan)
    feat_key = StageCache.key(
        {
            "stage": "features",
            "stage_code": code_digest(__name__, follow_imports=False),
            "simulation": sim_key,
            "features": features_cfg,
            "plugins": {name: plugin_version(fs) for name, fs in feature_sets.items()},
        }
    )

    def build() -> Path | None:
        sim_dir = simulate_to_cache(site, simulator, simulator_cfg, plan, cache)
        return None if sim_dir is None else _features_to_cache(sim_dir, site, feature_sets, plan.n_jobs, cache, feat_key)

    dataset = _get_verified_tables(cache, "features", feat_key, build)
    cache.cleanup()
    return dataset


def load_or_build_field(
    site: Site,
    field_source: Any,
    field_cfg: dict[str, Any],
    feature_sets: dict[str, FeatureSet],
    features_cfg: dict[str, Any],
    cache: StageCache,
    stated_site: Site | None = None,
) -> Dataset:
    """Feature and event tables of a field source's recordings, cached like the simulated ones.

    ``stated_site``: the site as stated by the user, where ``site`` is a field calibration of it:
    the recordings are read (or rendered) for the stated array, their features computed for the
    calibrated one (the geometry the method is trained on).
    """
    input_files = hook(field_source, "input_files")
    inputs = input_files() if input_files is not None else []
    key = StageCache.key(
        {
            "stage": "field_features",
            "stage_code": code_digest(__name__, follow_imports=False),
            "site": site.fingerprint(),
            **({"stated_site": stated_site.fingerprint()} if stated_site is not None else {}),
            "field": field_cfg,
            "inputs": {str(path): file_sha256(path) for path in inputs},  # an edited table or replaced WAV is a new entry
            "field_plugin": plugin_version(field_source),
            "features": features_cfg,
            "plugins": {name: plugin_version(fs) for name, fs in feature_sets.items()},
        }
    )

    def build() -> Path:
        read_site = stated_site if stated_site is not None else site
        chunks = hook(field_source, "load_chunks")
        batches = chunks(read_site) if chunks is not None else iter([field_source.load(read_site)])
        digest, features, events = _DataHasher(), [], []
        for batch in batches:  # a chunk's audio at a time (peak memory), each event's features its own
            digest.update(batch.audio, batch.events)
            features.append(extract_features(batch, site, feature_sets))
            events.append(batch.events)
        joined = pd.concat(events, ignore_index=True)
        if DEAD_MICS in joined:  # a mic dead at every event of a position failed there (needs all chunks)
            joined[col.HARDWARE_FAILURE] = failed_positions(joined)
        return _store_tables(cache, "field_features", key, pd.concat(features, ignore_index=True), joined, digest.hexdigest())

    dataset = _get_verified_tables(cache, "field_features", key, build)
    cache.cleanup()
    return dataset
