"""``protocol=season``: localize a season of long recordings from detector tables, streaming and sharded.

``python -m acoustlab season +site=NAME protocol.recordings.audio_dir=… protocol.detections.paths=[…]``
runs four stages (``protocol.stage``):

``fit``
    index the recordings (headers only), read the detector tables, group detections into events,
    fit the method once on the site's simulation and save it with its SHA-256
    (``acoustlab.method.saved``);
``localize``
    place the events chunk by chunk (``acoustlab.season.stream``): every chunk with
    ``protocol.shard``/``protocol.n_shards`` given (a SLURM array task through Hydra's submitit
    launcher: ``-m protocol.shard=0,1,2,3``), or all of them over ``protocol.n_jobs`` local
    worker processes; finished chunks are never recomputed (a killed run resumes);
``merge``
    join the parts into ``positions.parquet`` (and ``positions.csv``) in the run folder;
``all`` (default)
    fit (unless the output folder holds a method fitted from the same config), localize, merge.

Every stage of one season shares ``protocol.output_dir`` (default: ``<paths.outputs_dir>/seasons/<site>-<key>``,
named by the season's inputs, so the same command resumes it).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.cores import free_cores
from acoustlab.core.digests import file_sha256
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.resources import resolve_path
from acoustlab.core.types import Site
from acoustlab.method.localizer import FittedLocalizer
from acoustlab.method.pipeline import LocalizationPipeline
from acoustlab.method.run_context import RunContext, simulated_dataset
from acoustlab.method.saved import load_method, save_method, saved_info
from acoustlab.method.splits import cap_rows
from acoustlab.reporting.positions import localization_summary
from acoustlab.reporting.run_files import write_config, write_metrics, write_positions
from acoustlab.season.detections import FORMATS, read_detections
from acoustlab.season.events import group_detections
from acoustlab.season.recorder_files import RecorderFiles
from acoustlab.season.stream import (
    FILES,
    ChunkPlan,
    check_manifest,
    localize_chunks,
    localize_in_workers,
    merge_parts,
    missing_chunks,
    n_chunks,
    read_manifest,
    season_manifest,
    shard_chunks,
    write_events,
    write_manifest,
)
from acoustlab.season.weather import read_weather, weather_at
from acoustlab.stages.field_calibration import FieldCalibration
from acoustlab.stages.mic_survey import mics_table_of, survey_allowance
from acoustlab.toolkit.input_uncertainty import InputUncertainty
from acoustlab.toolkit.physics import speed_of_sound_m_s
from acoustlab.toolkit.quality import QualityThresholds

log = logging.getLogger(__name__)

STAGES = ("all", "fit", "localize", "merge")
#: What a saved method is (part of its key): a folder holding a method saved as something else is fitted again
SAVED_METHOD_FORMAT = "skops:acoustlab.method.localizer.FittedLocalizer"


#: Config keys that size thread pools and worker processes (``${threads:}``): they never change a result.
THREAD_KEYS = ("n_jobs", "n_threads", "nthread")


def without_thread_counts(node: Any) -> Any:
    """A plain config without its thread and worker counts, at any depth."""
    if isinstance(node, dict):
        return {k: without_thread_counts(v) for k, v in node.items() if k not in THREAD_KEYS}
    if isinstance(node, list):
        return [without_thread_counts(v) for v in node]
    return node


class SeasonLocalize:
    """Localize a season (see the module docstring); settings as in ``conf/protocol/season.yaml``."""

    def __init__(
        self,
        recordings: dict[str, Any],
        detections: dict[str, Any],
        events: dict[str, Any],
        max_train_rows: int = 1000,
        seed: int = 0,
        chunk_events: int = 256,
        batch_events: int = 16,
        temperature_c: float | None = None,
        relative_humidity_pct: float | None = None,
        weather_csv: str | None = None,
        output_dir: str | None = None,
        stage: str = "all",
        shard: int | None = None,
        n_shards: int = 1,
        n_jobs: int = 1,
        progress_every_s: float = 5.0,
        write_csv: bool = True,
        quality: dict[str, float] | None = None,
    ) -> None:
        if stage not in STAGES:
            raise ConfigError(f"protocol.stage must be one of {', '.join(STAGES)}; got {stage!r}")
        if n_shards < 1 or n_jobs < 1:
            raise ConfigError(f"protocol.n_shards and protocol.n_jobs must be >= 1; got {n_shards}, {n_jobs}")
        if shard is not None and not 0 <= int(shard) < n_shards:
            raise ConfigError(f"protocol.shard must be in [0, {n_shards}) (protocol.n_shards={n_shards}); got {shard}")
        if (detections or {}).get("format") not in FORMATS:
            raise ConfigError(f"protocol.detections.format must be one of {', '.join(FORMATS)}; got {(detections or {}).get('format')!r}")
        self.recordings_cfg = dict(recordings or {})
        self.detections_cfg = dict(detections)
        self.events_cfg = dict(events or {})
        self.max_train_rows, self.seed = int(max_train_rows), int(seed)
        self.chunk_events, self.batch_events = int(chunk_events), int(batch_events)
        self.temperature_c, self.relative_humidity_pct = temperature_c, relative_humidity_pct
        self.weather_csv = str(weather_csv) if weather_csv else None
        self.output_dir, self.stage = output_dir, stage
        self.shard, self.n_shards, self.n_jobs = (None if shard is None else int(shard)), int(n_shards), int(n_jobs)
        self.progress_every_s, self.write_csv = float(progress_every_s), bool(write_csv)
        self.quality = QualityThresholds(**(quality or {}))
        ChunkPlan(self.chunk_events, self.batch_events)  # checks the sizes now
        #: (site name, recordings, events) the preflight read, handed to ``fit`` so the tables are read once
        self._read: tuple[str, RecorderFiles, pd.DataFrame] | None = None

    # -- inputs -----------------------------------------------------------------------------------
    def recordings(self) -> RecorderFiles:
        """The season's files (from ``files_csv`` or from file names under ``audio_dir``)."""
        files_csv, audio_dir = self.recordings_cfg.get("files_csv"), self.recordings_cfg.get("audio_dir")
        if files_csv:
            return RecorderFiles.from_table(files_csv, audio_dir, bool(self.recordings_cfg.get("allow_outside_audio_dir", False)))
        if audio_dir:
            return RecorderFiles.from_file_names(audio_dir)
        raise ConfigError(
            "protocol=season needs protocol.recordings.files_csv (recorder_id, file, start_time) or "
            "protocol.recordings.audio_dir (one sub-folder per recorder, start times in the file names)"
        )

    def recorder_order(self, recordings: RecorderFiles, site: Site) -> list[str]:
        """Recorder ids in the site's mic order (``protocol.recordings.recorders``, or the sorted ids)."""
        order = [str(r) for r in (self.recordings_cfg.get("recorders") or recordings.recorders)]
        unknown = sorted(set(order) - set(recordings.recorders))
        if unknown:
            raise DataError(f"protocol.recordings.recorders names {unknown}, which have no files; recorders found: {recordings.recorders}")
        if len(order) != site.n_mics:
            raise DataError(
                f"the season has {len(order)} recorders ({', '.join(order)}) but site {site.name} has {site.n_mics} mics; "
                "list the recorders in the site's mic order in protocol.recordings.recorders"
            )
        return order

    def margin_s(self, site: Site) -> float:
        """Linkage distance, s: the array's largest travel time at the slowest sound speed, plus 10 ms."""
        if self.events_cfg.get("margin_s") is not None:
            return float(self.events_cfg["margin_s"])
        return float(self._travel_times_s(site).max()) + 0.01

    @staticmethod
    def _travel_times_s(site: Site) -> np.ndarray:
        """(M, M) travel time between each two mics at the slowest sound speed of the site, s."""
        mics = site.mic_positions_m
        distance = np.linalg.norm(mics[:, None, :] - mics[None, :, :], axis=-1)
        return distance / speed_of_sound_m_s(site.temperature_range_c[0], site.relative_humidity_range_pct[0])

    @classmethod
    def travel_s(cls, site: Site, recorders: list[str]) -> pd.DataFrame:
        """``_travel_times_s`` by recorder id (the recorders in the site's mic order), s."""
        return pd.DataFrame(cls._travel_times_s(site), index=recorders, columns=recorders)

    def pad_s(self) -> float:
        """How far past its detections an event's clip reaches even where every recorder detected it, s (a late-starting box)."""
        given = self.events_cfg.get("pad_s")
        try:
            pad = 0.05 if given is None else float(given)
        except (TypeError, ValueError):
            pad = np.nan
        if not np.isfinite(pad) or pad < 0:
            raise ConfigError(f"protocol.events.pad_s must be a number >= 0 (s); got {self.events_cfg.get('pad_s')!r}")
        return pad

    def events(self, recordings: RecorderFiles, site: Site) -> pd.DataFrame:
        """The season's events from its detector tables."""
        d = self.detections_cfg
        paths = d.get("paths") or []
        if isinstance(paths, str):
            paths = [paths]
        if not paths:
            raise ConfigError("protocol=season needs detector tables: protocol.detections.paths=[table or folder, ...]")
        detections = read_detections(
            paths,
            d["format"],
            recordings,
            d.get("classes"),
            float(d.get("min_score") or 0.0),
            d.get("label_column"),
            d.get("recorder_column"),
        )
        unknown = sorted(set(detections["recorder_id"]) - set(self.recorder_order(recordings, site)))
        if unknown:
            log.warning("detections on recorders %s, which are not in the array, are ignored", unknown)
            detections = detections[~detections["recorder_id"].isin(unknown)]
        min_recorders = int(self.events_cfg.get("min_recorders", 2))
        events = group_detections(
            detections,
            self.margin_s(site),
            min_recorders,
            float(self.events_cfg.get("max_event_s", 10.0)),
            travel_s=self.travel_s(site, self.recorder_order(recordings, site)),
            pad_s=self.pad_s(),
        )
        if events.empty:
            raise DataError(
                f"protocol=season: {len(detections)} detections, but no event was detected on {min_recorders} or more recorders "
                "(protocol.events.min_recorders); nothing to localize"
            )
        return self.with_weather(events, recordings)

    def with_weather(self, events: pd.DataFrame, recordings: RecorderFiles) -> pd.DataFrame:
        """The events with each one's own temperature and humidity from ``protocol.weather_csv`` (as they are without one)."""
        if not self.weather_csv:
            return events
        path = resolve_path(self.weather_csv)
        middle_s = (events[col.START].to_numpy(float) + events[col.END].to_numpy(float)) / 2  # the widening is symmetric
        air = weather_at(read_weather(path), middle_s, recordings.origin, path)
        log.info(
            "season: each event's air from %s (%.1f to %.1f °C over the events)",
            path,
            float(air[col.TEMPERATURE].min()),
            float(air[col.TEMPERATURE].max()),
        )
        return events.assign(**{name: air[name].to_numpy(float) for name in air})

    def validate(self, site: Site) -> None:
        """Preflight: index the recordings and read the detector tables (headers and tables only, no audio); kept for ``fit``."""
        if self.stage in ("fit", "all"):
            recordings = self.recordings()
            self._read = (site.name, recordings, self.events(recordings, site))

    def _inputs(self, site: Site) -> tuple[RecorderFiles, pd.DataFrame]:
        """The recordings' index and the events, read once: by the preflight where it ran, else now."""
        read = self._read
        if read is not None and read[0] == site.name:
            self._read = None
            return read[1], read[2]
        recordings = self.recordings()
        return recordings, self.events(recordings, site)

    # -- stages -----------------------------------------------------------------------------------
    def folder(self, run_dir: Path, context: RunContext | None = None) -> Path:
        """The season's output folder, shared by every stage and shard: ``protocol.output_dir``, else one named by its inputs.

        The default, ``<paths.outputs_dir>/seasons/<site>-<key>``, is the same for the same command
        (site, recordings, detector tables, chunking, weather, quality and the method's config), so
        running the command again resumes it; any change of those gets a folder of its own.
        """
        if self.output_dir:
            return Path(self.output_dir)
        if context is None:
            return run_dir / "season"
        inputs = {
            "recordings": self.recordings_cfg,
            "detections": self.detections_cfg,
            "events": self.events_cfg,
            "chunk": [self.chunk_events, self.batch_events],
            "weather": [self.temperature_c, self.relative_humidity_pct, self.weather_csv],
            "quality": dataclasses.asdict(self.quality),
            "method": self.method_key(context.settings.config),
        }
        key = hashlib.sha256(json.dumps(inputs, sort_keys=True, default=str).encode()).hexdigest()[:12]
        return context.settings.outputs_dir / "seasons" / f"{context.settings.config['site']['name']}-{key}"

    def plan(self, site: Site) -> ChunkPlan:
        """Chunking and the weather assumed for every detection (the middle of the site's ranges unless given)."""
        temperature = self.temperature_c if self.temperature_c is not None else float(np.mean(site.temperature_range_c))
        humidity = (
            self.relative_humidity_pct if self.relative_humidity_pct is not None else float(np.mean(site.relative_humidity_range_pct))
        )
        return ChunkPlan(
            self.chunk_events,
            self.batch_events,
            float(temperature),
            float(humidity),
            bool(self.events_cfg.get("use_detection_band", True)),
            self.quality,
            self.margin_s(site),
        )

    def method_key(self, config: dict[str, Any]) -> str:
        """What the fitted method depends on: the whole (resolved) config except the season's inputs and how it is run."""
        plain = without_thread_counts(copy.deepcopy(config))  # threads change how fast, never what: not part of the key
        plain.pop("hydra", None)
        for name in ("paths", "tracking", "plots", "cache"):
            plain.pop(name, None)
        protocol = plain.get("protocol", {})  # of the season's own settings, only these shape the fitted method
        plain["protocol"] = {name: protocol.get(name) for name in ("_target_", "max_train_rows", "seed")}
        plain["saved_as"] = SAVED_METHOD_FORMAT
        site = config.get("site", {})
        for name in ("mics_csv", "trees_csv"):  # the site's tables: a file edited in place is another array, another method
            if site.get(name) and resolve_path(str(site[name])).is_file():
                plain[f"{name}_sha256"] = file_sha256(resolve_path(str(site[name])))
        return hashlib.sha256(json.dumps(plain, sort_keys=True, default=str).encode()).hexdigest()

    def fit(self, context: RunContext, folder: Path) -> None:
        """Index, events, and the method fitted once (reused when the folder holds one fitted from the same config)."""
        site, components = context.site, context.components
        recordings, events = self._inputs(site)
        order = self.recorder_order(recordings, site)
        radii = {"levels": list(components.levels), "scorers": list(components.scorers)}
        check_manifest(
            folder, season_manifest(events, None, self.plan(site), order, radii, recordings), unknown=("method_sha256",)
        )  # before writing
        folder.mkdir(parents=True, exist_ok=True)
        recordings.save(folder / FILES)
        write_events(folder, events, self.chunk_events)
        key = self.method_key(context.settings.config)
        if context.calibration is not None:  # a calibration file rewritten at the same path is another method
            key = hashlib.sha256(f"{key}:{context.calibration.sha256}".encode()).hexdigest()
        saved = saved_info(folder)
        digest = saved["sha256"] if saved is not None and saved["key"] == key and self._loads(folder, saved["sha256"]) else None
        if digest is not None:
            log.info("season: reusing the method fitted earlier in %s", folder)
        else:
            dataset = simulated_dataset(context)
            if dataset is None:
                raise ConfigError("protocol=season does not shard its simulation: run it without data.shard_count")
            groups = dataset.events[col.POSITION_ID].to_numpy()
            train = np.sort(cap_rows(np.arange(len(dataset.events)), groups, self.max_train_rows, np.random.default_rng([self.seed, 1])))
            log.info("season: fitting the method on %d simulated events (once; every chunk and shard reuses it)", train.size)
            method = LocalizationPipeline(components).fit(dataset.features, dataset.events, train)
            fitted = FittedLocalizer(method, context.settings.sample_rate_hz)
            digest = save_method(fitted, folder, key)
        write_manifest(folder, season_manifest(events, digest, self.plan(site), order, radii, recordings))
        log.info(
            "season: %d events from %d recorders' files (%d files, %s to %s) in %d chunks",
            len(events),
            len(order),
            len(recordings.table),
            recordings.origin,
            recordings.origin + pd.Timedelta(seconds=float(recordings.table[col.END].max())),
            n_chunks(len(events), self.chunk_events),
        )

    @staticmethod
    def _loads(folder: Path, sha256: str) -> bool:
        """Whether the method saved in ``folder`` loads (a changed, forged or older file is fitted again, said in one line)."""
        try:
            load_method(folder, sha256)
        except DataError as exc:
            log.warning("season: the method saved in %s is not used (%s); fitting it again", folder, exc)
            return False
        return True

    def localize(self, folder: Path) -> int:
        """This process's chunks: one shard, or every chunk over ``n_jobs`` local workers."""
        manifest = read_manifest(folder)
        if self.shard is not None:
            chunks = shard_chunks(manifest["n_events"], manifest["chunk_events"], self.shard, self.n_shards)
            return localize_chunks(
                folder, chunks, progress_every_s=self.progress_every_s, label=f"season shard {self.shard + 1}/{self.n_shards}"
            )
        if self.n_jobs == 1:
            return localize_chunks(
                folder, range(n_chunks(manifest["n_events"], manifest["chunk_events"])), progress_every_s=self.progress_every_s
            )
        threads = max(1, free_cores() // self.n_jobs)  # workers × threads ≤ cores: oversubscribed OpenMP spin-waits
        log.info("season: %d local workers, %d thread(s) each", self.n_jobs, threads)
        return localize_in_workers(folder, self.n_jobs, threads)

    def run_job(self, context: RunContext, run_dir: Path) -> dict[str, Any]:
        """Run the configured stage(s); writes and returns the run's metrics (positions summary after a merge)."""
        folder = self.folder(run_dir, context)
        log.info("season folder: %s (the same command resumes it; protocol.output_dir=… chooses another)", folder)
        if context.calibration is not None:
            self.warn_about_calibration(context.calibration)
            if not self.weather_csv:  # with a logger's readings each event has its own air, as in localize
                context = self.with_assumed_weather(context)
        else:  # the radii carry the site's mics table's survey error, as localize's do (a calibration's replaces it)
            stated = survey_allowance(
                context.components.input_uncertainty, mics_table_of(None, context.settings.config["site"]), context.site.n_mics
            )
            context = dataclasses.replace(context, components=dataclasses.replace(context.components, input_uncertainty=stated))
        started = time.perf_counter()
        metrics: dict[str, Any] = {"season": {"output_dir": str(folder), "stage": self.stage}}
        if self.stage in ("fit", "all"):
            self.fit(context, folder)
        if self.stage in ("localize", "all"):
            computed = self.localize(folder)
            metrics["season"]["chunks_computed"] = computed
            missing = missing_chunks(folder)
            metrics["season"]["chunks_missing"] = len(missing)
            log.info("season: %d chunks computed now, %d still missing", computed, len(missing))
        if self.stage in ("merge", "all"):
            table = merge_parts(folder)
            write_positions(run_dir, table, csv=self.write_csv)
            radii = read_manifest(folder)["radii"]
            metrics[col.METRICS_LOCALIZATION] = localization_summary(table, radii["levels"], radii["scorers"])
            summary = metrics[col.METRICS_LOCALIZATION]
            log.info(
                "season: %d detections, %d placed (%d on weak support: weak_support in positions.csv); positions in %s",
                len(table),
                summary["n_placed"],
                summary["n_weak_support"],
                run_dir / "positions.parquet",
            )
        if (folder / "season.json").is_file():
            manifest = read_manifest(folder)
            metrics["dataset_hash"] = manifest["events_sha256"]  # what the positions were computed from: the events and the method
            metrics["season"].update({"n_events": manifest["n_events"], "method_sha256": manifest["method_sha256"]})
        metrics["season"]["seconds"] = time.perf_counter() - started
        metrics.update(context.settings.record)
        run_dir.mkdir(parents=True, exist_ok=True)
        write_config(run_dir, context.settings.config)
        write_metrics(run_dir, metrics)
        return metrics

    def with_assumed_weather(self, context: RunContext) -> RunContext:
        """The context with the radii's calibrated allowance keeping the thermometer σ (``conformal.input_uncertainty.
        temperature_c``): a season reads no thermometer, so its one assumed temperature stays off the air by that much."""
        stated_sd_c = InputUncertainty(**context.settings.config["conformal"]["input_uncertainty"]).temperature_c
        calibrated = context.components.input_uncertainty
        allowance = dataclasses.replace(
            context.calibration.input_uncertainty(stated_sd_c), exact_above_m=calibrated.exact_above_m, max_sigma_m=calibrated.max_sigma_m
        )
        if stated_sd_c:
            log.info("the season assumes one temperature for every detection: the allowance keeps its %.2g °C error", stated_sd_c)
        return dataclasses.replace(context, components=dataclasses.replace(context.components, input_uncertainty=allowance))

    def warn_about_calibration(self, calibration: FieldCalibration) -> None:
        """What a season must know of a field calibration: its offset lands on one assumed temperature, and drift is counted
        from the season's first file."""
        if self.temperature_c is None and not self.weather_csv:
            log.warning(
                "protocol.temperature_c is not given: the calibration's thermometer offset (%+.2f °C) is added to the middle of the "
                "site's temperature range; give your thermometer's typical reading as protocol.temperature_c",
                calibration.temperature_offset_c,
            )
        if np.any(calibration.clock_drift):
            log.warning(
                "%s corrects clock drift at each detection's start_s, seconds from the season's first file: its playbacks' "
                "time_s must count from that same instant (docs/calibrate.md)",
                calibration.path,
            )
