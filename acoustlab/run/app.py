"""Compose the plugins of a config into a run: data stages, protocol, metrics, tracking."""

from __future__ import annotations

import dataclasses
import json
import logging
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from acoustlab import __version__
from acoustlab.core import columns as col
from acoustlab.core.contracts import declared, hook
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.types import Site
from acoustlab.method.localizer import solve_detections
from acoustlab.method.pipeline import Components, LocalizationPipeline
from acoustlab.method.placement_rules import MapProjection, PlacementRules
from acoustlab.method.trust import TrustSettings
from acoustlab.reporting.experiment_log import PENDING_FILE, log_run_dir
from acoustlab.reporting.metrics import (
    held_out_calibration_summary,
    split_diagnostics_summary,
    summarise,
    summary_text,
)
from acoustlab.reporting.paper import paper_comparison
from acoustlab.reporting.positions import localization_summary
from acoustlab.run.registry import (
    PLUGIN_GROUPS,
    build,
    build_feature_sets,
    build_scorers,
    group_options,
    to_plain,
)
from acoustlab.run.schema import CalibrateOn, ModelTarget, UnsupportedLevels
from acoustlab.stages.cache import StageCache, atomic_write_bytes
from acoustlab.stages.dataset import (
    SimulationPlan,
    load_or_build_field,
    load_or_build_simulated,
)
from acoustlab.stages.field_calibration import (
    FieldCalibration,
    calibrated_site,
    load_calibration,
)
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import add_solver_columns
from acoustlab.toolkit.input_uncertainty import CorrelatedInputErrors, InputUncertainty
from acoustlab.toolkit.quality import QUALITY_REASONS

log = logging.getLogger(__name__)


def code_version() -> str:
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent, timeout=5
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        sha = ""
    return f"{__version__}+{sha}" if sha else __version__


def quality_flag_counts(predictions: pd.DataFrame) -> dict[str, int]:
    """How many detections were flagged, in all and per reason (``dead``, ``truncated``, …), for metrics.json."""
    flags = predictions[col.QUALITY_FLAGS].fillna("").astype(str)
    counts = {"flagged": int((flags != "").sum())}
    for reason in QUALITY_REASONS:
        counts[reason] = int(flags.str.contains(rf"\b{reason}\b").sum())
    return counts


def require_site(cfg: DictConfig) -> None:
    """Stop with a clear message when no site was chosen."""
    if cfg.get("site") is None:
        sites = ", ".join(group_options("site"))
        raise ConfigError(f"no site chosen: pass one with +site=NAME (available: {sites}), e.g. python -m acoustlab +site=frozen_lake")


@dataclass
class BuiltRun:
    """Everything a run needs, built and checked from its config (see ``build_run``)."""

    site: Any
    simulator: Any
    feature_sets: dict
    components: Components
    protocol: Any
    tracker: Any
    cache: StageCache
    plan: SimulationPlan
    field_source: Any = None
    #: ``calibration=PATH``: the field calibration applied to the site and the recordings (``acoustlab.stages.field_calibration``)
    calibration: FieldCalibration | None = None
    #: the site as the config states it, where ``site`` is its calibration (the recordings are read for it)
    stated_site: Any = None


def check_feature_requirements(feature_sets: dict[str, Any], **plugins: Any) -> None:
    """Every feature group a plugin declares in ``required_feature_groups`` must be configured.

    Raises
    ------
    ConfigError
        Naming the plugin, the missing groups and the configured ones.
    """
    configured = set(feature_sets) | {"solver"}  # the solver group is appended by the solver stage
    for what, plugin in plugins.items():
        missing = sorted(set(plugin.required_feature_groups) - configured)
        if missing:
            raise ConfigError(
                f"{what} {type(plugin).__name__} needs the feature groups {missing}, which features= does not compute "
                f"(configured: {', '.join(sorted(configured))}); choose a feature set that has them, e.g. features=physics"
            )


def check_dropped_groups(feature_sets: dict[str, Any], **drops: list[str]) -> None:
    """Every feature group named for ablation must exist (a typo fails now, not after the data stage).

    Raises
    ------
    ConfigError
        Naming the setting (e.g. ``features.drop``), the unknown groups and the available ones.
    """
    available = set(feature_sets) | {"solver"}
    for setting, groups in drops.items():
        unknown = sorted(set(groups) - available)
        if unknown:
            name = setting.replace("_", ".", 1)
            raise ConfigError(
                f"{name} names feature groups {unknown} that the features= option does not have; available: {', '.join(sorted(available))}"
            )


def check_selective(selective: DictConfig, n_events: int) -> None:
    """``pipeline.selective`` settings a run can use, checked before anything is simulated.

    Raises
    ------
    ConfigError
        For ``gross_m`` not a positive number, ``delta`` or ``epsilon`` outside (0, 1), or (when
        enabled) a certificate that needs more calibration events than the run simulates
        (n ≥ log ε / log(1 − δ); see ``acoustlab.toolkit.conformal.selective_threshold``).
    """
    gross_m, delta, epsilon = float(selective.gross_m), float(selective.delta), float(selective.epsilon)
    if not (np.isfinite(gross_m) and gross_m > 0):
        raise ConfigError(f"pipeline.selective.gross_m must be a positive number of metres; got {gross_m}")
    for name, value in (("delta", delta), ("epsilon", epsilon)):
        if not 0 < value < 1:
            raise ConfigError(f"pipeline.selective.{name} must lie in (0, 1); got {value}")
    needed = int(np.ceil(np.log(epsilon) / np.log1p(-delta)))
    if selective.enabled and needed > n_events:
        raise ConfigError(
            f"pipeline.selective: delta={delta:g}, epsilon={epsilon:g} need at least {needed} calibration events "
            f"to certify anything, but data.n_events={n_events}; raise data.n_events or delta"
        )


def build_run(cfg: DictConfig, choices: dict[str, str] | None = None) -> BuiltRun:
    """Build and check every plugin of a config without running anything expensive (the preflight).

    Everything that can be wrong in a config fails here with a ``ConfigError`` or
    ``DataError`` naming the field: site files, simulator settings and call/noise pools,
    plugin options, feature groups a solver or gate needs, conformal levels, TabPFN weights,
    sharding settings. Types of the non-plugin nodes were checked when Hydra composed the config
    (``acoustlab.run.schema``).
    """
    require_site(cfg)
    check_selective(cfg.pipeline.selective, int(cfg.data.n_events))
    site = site_from_config(cfg.site)
    simulator = build(cfg.simulator, "simulator")
    simulator.validate(site)
    feature_sets = build_feature_sets(cfg.features)
    components = Components(
        site=site,
        feature_sets=feature_sets,
        solver=build(cfg.solver, "solver"),
        point_model=build(cfg.model, "model"),
        gate=build(cfg.gate, "gate"),
        error_model=build(cfg.error_model, "error_model"),
        scorers=build_scorers(cfg.conformal),
        levels=list(cfg.conformal.levels),
        dropped_groups=list(cfg.features.drop),
        calibration_folds=cfg.conformal.calibration_folds,
        calibrate_on=CalibrateOn(cfg.conformal.calibrate_on).value,
        unsupported_levels=UnsupportedLevels(cfg.conformal.get("unsupported_levels", "empty")).value,
        ellipse=bool(cfg.conformal.ellipse),
        model_target=ModelTarget(cfg.pipeline.model_target).value,
        dropped_from_model=list(cfg.pipeline.drop_from_model),
        dropped_from_error_model=list(cfg.pipeline.drop_from_error_model),
        error_model_gate_cues=bool(cfg.pipeline.error_model_gate_cues),
        seed=int(cfg.seed),
        selective=dict(cfg.pipeline.selective) if cfg.pipeline.selective.enabled else None,
        extra_gates={name: build(node, "gate") for name, node in cfg.pipeline.extra_gates.items()},
        trust=TrustSettings(**OmegaConf.to_container(cfg.pipeline.trust, resolve=True)),
        input_uncertainty=InputUncertainty(**OmegaConf.to_container(cfg.conformal.input_uncertainty, resolve=True)),
    )
    check_feature_requirements(
        feature_sets,
        solver=components.solver,
        gate=components.gate,
        **{f"pipeline.extra_gates.{name}": g for name, g in components.extra_gates.items()},
    )
    check_dropped_groups(
        feature_sets,
        features_drop=components.dropped_groups,
        pipeline_drop_from_model=components.dropped_from_model,
        pipeline_drop_from_error_model=components.dropped_from_error_model,
    )
    for level in components.levels:
        if not 0 < level < 1:
            raise ConfigError(f"conformal.levels must lie in (0, 1); got {level}")
    for learned in (components.point_model, components.error_model):
        preflight = hook(learned, "preflight")
        if preflight is not None:  # e.g. TabPFN: weights must exist before anything is simulated
            preflight()
    protocol = build(cfg.protocol, "protocol")
    field_source = None
    if declared(protocol, "needs_field"):  # recordings are checked now, not after the training simulation
        field_source = build(cfg.field, "field")
        if field_source is None:
            protocol_name = (choices or {}).get("protocol") or type(protocol).__name__
            raise ConfigError(f"protocol={protocol_name} needs field recordings: choose field=playback_standin or field=recordings")
        validate = hook(field_source, "validate")
        if validate is not None:
            validate(site)
    validate_protocol = hook(protocol, "validate")
    if validate_protocol is not None:  # e.g. a season's recordings and detector tables, before any simulation
        validate_protocol(site)
    tracker = build(cfg.tracking, "tracking")

    cache = StageCache(cfg.cache.dir, enabled=cfg.cache.enabled, file_mode=cfg.cache.file_mode)
    if cfg.data.shard_count > 1 and not cache.enabled:
        raise ConfigError("data.shard_count > 1 fills the cache shard by shard; it needs cache.enabled=true")
    plan = SimulationPlan(seed=cfg.seed, **OmegaConf.to_container(cfg.data, resolve=True))
    calibration, stated_site = None, None
    if cfg.get("calibration"):  # after the recordings were checked against the stated array
        if declared(protocol, "calibrates"):
            raise ConfigError("calibrate starts from the stated array: drop calibration=… (a calibration is not calibrated again)")
        calibration = load_calibration(str(cfg.calibration), site)
        stated_site, site = site, calibrated_site(site, calibration)
        # a season assumes one temperature: protocol.temperature_c where given (its yaml has the key), else the site's middle
        given = not declared(protocol, "assumes_weather") or cfg.protocol.temperature_c is not None
        allowance = calibrated_allowance(calibration, stated_site, components.input_uncertainty, protocol, given)
        components = dataclasses.replace(components, site=site, input_uncertainty=allowance)
    components = dataclasses.replace(components, placement=placement_rules(cfg, field_source, calibration))
    return BuiltRun(site, simulator, feature_sets, components, protocol, tracker, cache, plan, field_source, calibration, stated_site)


def placement_rules(cfg: DictConfig, field_source: Any, calibration: FieldCalibration | None) -> PlacementRules:
    """How the run's field detections are solved and reported: the plausible-region bound, the weak-recorder rule, the
    calibration and the field source's map projection (``acoustlab.method.localizer``)."""
    project = hook(field_source, "projection") if field_source is not None else None
    projection = project() if project is not None else None
    return PlacementRules(
        plausible_margin_fraction=cfg.pipeline.plausible_margin_fraction,
        calibration=calibration,
        min_gcc_peak=OmegaConf.select(cfg, "features.gcc.min_peak", default=None),
        projection=None if projection is None else MapProjection(*projection),
    )


def calibrated_allowance(
    calibration: FieldCalibration, stated_site: Site, stated: InputUncertainty, protocol: Any, temperature_given: bool = True
) -> CorrelatedInputErrors:
    """The radii's input allowance under ``calibration=PATH``: its covariance, with ``stated``'s limits (and thermometer σ where
    ``protocol`` assumes the weather); logs what the calibration changes, and warns where a season's assumed temperature
    was not given (``temperature_given``: the offset then lands on the middle of the site's range)."""
    log.info(
        "calibration %s (%s…): mics moved up to %.2f m, thermometer offset %+.2f °C, clock offsets up to %.3g ms; its "
        "covariance is the radii's input allowance in place of conformal.input_uncertainty's standard deviations",
        calibration.path,
        calibration.sha256[:12],
        float(np.abs(calibration.mic_positions_m - stated_site.mic_positions_m).max()),
        calibration.temperature_offset_c,
        1e3 * float(np.abs(calibration.clock_offset_s).max()),
    )
    # a season reads no thermometer: its one assumed temperature stays off the air by the stated σ
    assumed_sd_c = stated.temperature_c if declared(protocol, "assumes_weather") else 0.0
    if assumed_sd_c:
        log.info("the season assumes one temperature for every detection: the allowance keeps its %.2g °C error", assumed_sd_c)
    if not temperature_given:
        log.warning(
            "protocol.temperature_c is not given: the calibration's thermometer offset (%+.2f °C) is added to the middle of the "
            "site's temperature range; give your thermometer's typical reading as protocol.temperature_c",
            calibration.temperature_offset_c,
        )
    if np.any(calibration.clock_drift) and declared(protocol, "streams"):
        log.warning(
            "%s corrects clock drift at each detection's start_s, seconds from the season's first file: its playbacks' "
            "time_s must count from that same instant (docs/calibrate.md)",
            calibration.path,
        )
    # the stated exact_above_m and max_sigma_m still apply
    return dataclasses.replace(
        calibration.input_uncertainty(assumed_sd_c), exact_above_m=stated.exact_above_m, max_sigma_m=stated.max_sigma_m
    )


@dataclass
class RunData:
    """A run's data, ready for its protocol: the simulated dataset and the field recordings (or None), each
    with the solver's columns under the plausible-region bound (``pipeline.plausible_margin_fraction``)."""

    dataset: Any
    field_data: Any = None


def prepare_data(cfg: DictConfig, built: BuiltRun | None = None) -> RunData | None:
    """The one path from a config to a run's data: simulate (or load from the cache), features, solver columns, bound.

    The app, the protocols' tests and the benchmarks all call this, so a benchmark measures the data
    a real run gets (the same plausible-region bound, the same field preparation).

    Parameters
    ----------
    cfg : omegaconf.DictConfig
        The composed config.
    built : BuiltRun, optional
        The checked plugins (``build_run``); built from ``cfg`` when not given.

    Returns
    -------
    RunData or None
        None for a sharded simulation run (``data.shard_count > 1``) that filled its shard of the cache.
    """
    built = built if built is not None else build_run(cfg)
    dataset = load_or_build_simulated(
        built.site, built.simulator, to_plain(cfg.simulator), built.feature_sets, to_plain(cfg.features.groups), built.plan, built.cache
    )
    if dataset is None:
        return None
    dataset.features = solver_features(cfg, dataset.features, dataset.events, built.site, built.components.solver)
    return RunData(dataset, prepare_field(cfg, built) if built.field_source is not None else None)


def prepare_field(cfg: DictConfig, built: BuiltRun) -> Any:
    """The field recordings' features and events (cached), the calibration applied, with the solver's columns."""
    field_data = load_or_build_field(
        built.site,
        built.field_source,
        to_plain(cfg.field),
        built.feature_sets,
        to_plain(cfg.features.groups),
        built.cache,
        stated_site=built.stated_site,
    )
    field_data.features, field_data.events = solve_detections(built.components, field_data.features, field_data.events)
    return field_data


def solver_features(cfg: DictConfig, features: pd.DataFrame, events: pd.DataFrame, site: Any, solver: Any) -> pd.DataFrame:
    """``features`` with ``solver``'s columns appended under the run's plausible-region bound (to compare solvers on one dataset)."""
    return add_solver_columns(features, events, site, solver, cfg.pipeline.plausible_margin_fraction)


def run_experiment(
    cfg: DictConfig,
    run_dir: Path,
    choices: dict[str, str] | None = None,
    parent_run_id: str | None = None,
    run_name: str | None = None,
    built: BuiltRun | None = None,
) -> dict:
    """Run one job: build plugins, get the (cached) dataset, run the protocol, write and log results.

    Parameters
    ----------
    cfg : omegaconf.DictConfig
        The composed config.
    run_dir : pathlib.Path
        Where ``metrics.json``, ``predictions.parquet`` and the resolved config are written.
    choices : dict, optional
        The chosen option of each config group (Hydra's runtime choices).
    parent_run_id : str, optional
        The sweep's parent run in the tracker (set by ``acoustlab.run.sweep.SweepTrackingCallback``).
    run_name : str, optional
        The run's name in the tracker (the CLI names it by the overrides that vary; default ``<site>-<model>``).
    built : BuiltRun, optional
        The run's plugins, built from ``cfg`` by ``build_run`` (the notebook API keeps them to reuse the fitted method).

    Returns
    -------
    dict
        The metrics written to ``metrics.json``.
    """
    started = time.perf_counter()
    run_dir.mkdir(parents=True, exist_ok=True)
    choices = {g: str(v) for g, v in (choices or {}).items() if g in (*PLUGIN_GROUPS, "site", "experiment") and v is not None}

    built = built if built is not None else build_run(cfg, choices)
    if cfg.get("expected_duration"):
        log.info("this experiment takes %s", cfg.expected_duration)
    site, components, protocol, tracker, plan = built.site, built.components, built.protocol, built.tracker, built.plan
    timings: dict[str, float] = {"preflight_s": time.perf_counter() - started}
    if declared(protocol, "streams"):  # a season: fitted once, then chunk by chunk from the recordings (acoustlab.season)
        return _run_streaming(cfg, run_dir, built, choices, tracker, parent_run_id, run_name)
    if declared(protocol, "calibrates"):  # playbacks at known spots: calibration.json, nothing simulated
        from acoustlab.run.calibrate import run_calibration

        return run_calibration(cfg, run_dir, built, choices)
    stage_start = time.perf_counter()
    data = prepare_data(cfg, built)
    if data is None:
        log.info(
            "sharded simulation run: shard %d of %d is in the cache; run without data.shard_count to finish",
            plan.shard_index + 1,
            plan.shard_count,
        )
        return {"shard": {"index": plan.shard_index, "count": plan.shard_count}}
    dataset, field_data = data.dataset, data.field_data
    timings["data_s"] = time.perf_counter() - stage_start
    stage_start = time.perf_counter()
    result = protocol.run(dataset, LocalizationPipeline(components), field_recordings=field_data)
    predictions = result.predictions
    timings["models_s"] = time.perf_counter() - stage_start

    if not declared(protocol, "evaluates"):
        return _write_localization(
            cfg,
            run_dir,
            predictions,
            result,
            components,
            site,
            dataset,
            field_data,
            choices,
            timings,
            started,
            tracker,
            parent_run_id,
            run_name,
            built.calibration,
        )
    summary_rows = predictions[col.IN_SUMMARY].to_numpy(bool) if col.IN_SUMMARY in predictions else np.ones(len(predictions), bool)
    metrics = _evaluation_metrics(
        run_dir, predictions, summary_rows, result, components, dataset, field_data, choices.get("gate") or type(components.gate).__name__
    )
    metrics.update({"site": site.name, "choices": choices, **({"run_name": run_name} if run_name else {})})
    if built.calibration is not None:
        metrics["field_calibration"] = built.calibration.summary()

    # Results land in the run dir first (metrics before any optional artefact), so neither a tracker
    # nor a plotting failure loses them; the pending marker stays until the tracker has them.
    write_results(run_dir, cfg, predictions, metrics)
    if cfg.get("paper_reference"):
        rows, lines = paper_comparison(
            OmegaConf.to_container(cfg.paper_reference, resolve=True), metrics, OmegaConf.to_container(cfg, resolve=True)
        )
        metrics["paper_comparison"] = rows
        atomic_write_bytes(run_dir / "paper_comparison.md", ("\n".join(lines) + "\n").encode())

    def plot() -> None:
        from acoustlab.reporting.plots import (
            write_run_plots,  # matplotlib only when plotting
        )

        write_run_plots(predictions[summary_rows], metrics, site, run_dir / "plots")

    plot_and_time(cfg, run_dir, metrics, timings, started, "plots", plot)
    log.info("%s test detections; errors (m) and conformal coverage:\n%s", metrics[col.METRICS_ERRORS]["gate"]["n"], summary_text(metrics))
    log.info("timings (s): %s", ", ".join(f"{k.removesuffix('_s')} {v:.1f}" for k, v in metrics["timings_s"].items()))
    log.info("run directory: %s", run_dir)
    log_run_dir(tracker, run_dir, parent_run_id=parent_run_id)
    return metrics


def _run_streaming(
    cfg: DictConfig, run_dir: Path, built: BuiltRun, choices: dict[str, str], tracker: Any, parent_run_id: str | None, run_name: str | None
) -> dict:
    """A streaming protocol (``protocol=season``): its stages write the positions; metrics.json gets its summary."""
    metrics = built.protocol.run_season(cfg, built, run_dir, prepare=lambda: prepare_data(cfg, built))
    metrics.update(
        {"site": built.site.name, "choices": choices, "code_version": code_version(), **({"run_name": run_name} if run_name else {})}
    )
    if built.calibration is not None:
        metrics["field_calibration"] = built.calibration.summary()
    atomic_write_bytes(run_dir / "metrics.json", json.dumps(metrics, indent=2, default=str).encode())
    log.info("run directory: %s", run_dir)
    log_run_dir(tracker, run_dir, parent_run_id=parent_run_id)
    return metrics


def _log_held_out(summary: dict[str, Any]) -> None:
    """One line per scorer: the radii's coverage on the calibration playbacks, each spot held out."""
    for scorer, by_level in summary[col.METRICS_COVERAGE].items():
        cells = ", ".join(f"{level}: {'—' if c is None else format(c['detections'], '.2f')}" for level, c in by_level.items())
        log.info(
            "radii (%s) on the %d calibration playbacks at %d spots, each spot held out: coverage %s",
            scorer,
            summary["n_playbacks"],
            summary["n_spots"],
            cells,
        )


def _evaluation_metrics(
    run_dir: Path,
    predictions: pd.DataFrame,
    summary_rows: np.ndarray,
    result: Any,
    components: Components,
    dataset: Any,
    field_data: Any,
    gate_name: str,
) -> dict[str, Any]:
    """metrics.json of a run with ground truth: error and coverage summaries, quality flags, diagnostics, data hashes.

    Raises
    ------
    DataError
        When every test detection is flagged (after writing predictions.parquet, which says why).
    """
    if not summary_rows.any():  # e.g. every field event flagged: nothing to summarise, but the predictions say why
        atomic_write_bytes(run_dir / "predictions.parquet", predictions.to_parquet(index=False))
        counts = quality_flag_counts(predictions) if col.QUALITY_FLAGS in predictions else {}
        raise DataError(
            f"all {len(predictions)} test detections are flagged or from failed hardware ({counts or col.HARDWARE_FAILURE}), "
            f"so there are no errors to summarise; {run_dir / 'predictions.parquet'} has every detection with its flags"
        )
    metrics = summarise(predictions[summary_rows], components.levels, list(components.scorers))
    if not summary_rows.all():
        metrics["all_detections"] = summarise(predictions, components.levels, list(components.scorers))
        metrics["excluded_from_summary"] = int((~summary_rows).sum())
    if col.QUALITY_FLAGS in predictions:
        metrics[col.QUALITY_FLAGS] = quality_flag_counts(predictions)
    if field_data is not None:
        metrics["field_dataset_hash"] = field_data.dataset_hash
    metrics.update(split_diagnostics_summary(result.split_diagnostics, gate_name))
    metrics.update(
        {
            "dataset_hash": dataset.dataset_hash,
            "features_sha256": dataset.features_sha256,
            "n_features": int(len(dataset.features.columns)),
            "code_version": code_version(),
        }
    )
    return metrics


def write_results(run_dir: Path, cfg: DictConfig, predictions: pd.DataFrame, metrics: dict) -> None:
    """The results a run must never lose, each written atomically: predictions, resolved config, metrics, and the pending marker.

    Raises
    ------
    StorageError
        Naming the file and the free space, when the run directory cannot be written.
    """
    atomic_write_bytes(run_dir / "predictions.parquet", predictions.to_parquet(index=False))
    atomic_write_bytes(run_dir / "config_resolved.yaml", OmegaConf.to_yaml(cfg, resolve=True).encode())
    atomic_write_bytes(run_dir / "metrics.json", json.dumps(metrics, indent=2).encode())
    atomic_write_bytes(run_dir / PENDING_FILE, json.dumps({"destination": None, "error": "not yet sent to the tracker"}).encode())


def optional_artefact(what: str, write: Callable[[], Any]) -> None:
    """Write an artefact the results do not depend on (plots, …); a failure is a warning, never a lost run."""
    try:
        write()
    except Exception as exc:
        log.warning("%s not written (%s: %s); the metrics and predictions are saved", what, type(exc).__name__, exc)


def plot_and_time(
    cfg: DictConfig, run_dir: Path, metrics: dict, timings: dict[str, float], started: float, what: str, plot: Callable[[], None]
) -> None:
    """After the results are safe: the optional plots (``plots=true``), then the run's timings added to metrics.json."""
    stage_start = time.perf_counter()
    if bool(cfg.get("plots", True)):
        optional_artefact(what, plot)
    timings["plots_s"] = time.perf_counter() - stage_start
    timings["total_before_tracking_s"] = time.perf_counter() - started
    metrics["timings_s"] = {k: round(v, 3) for k, v in timings.items()}
    now = time.time()  # wall clock, so a tracker shows the job's own start and duration even when it is uploaded later
    metrics["run_time"] = {"started_epoch_ms": int(1000 * (now - timings["total_before_tracking_s"])), "finished_epoch_ms": int(1000 * now)}
    optional_artefact(
        "timings in metrics.json", lambda: atomic_write_bytes(run_dir / "metrics.json", json.dumps(metrics, indent=2).encode())
    )


def _write_localization(
    cfg: DictConfig,
    run_dir: Path,
    predictions: pd.DataFrame,
    result: Any,
    components: Components,
    site: Any,
    dataset: Any,
    field_data: Any,
    choices: dict[str, str],
    timings: dict[str, float],
    started: float,
    tracker: Any,
    parent_run_id: str | None,
    run_name: str | None = None,
    calibration: FieldCalibration | None = None,
) -> dict:
    """A run without ground truth (protocol=localize): positions.csv / .parquet, a map, and a summary instead of error metrics."""
    table = result.positions
    atomic_write_bytes(run_dir / "positions.csv", table.to_csv(index=False).encode())
    atomic_write_bytes(run_dir / "positions.parquet", table.to_parquet(index=False))
    metrics: dict[str, Any] = {col.METRICS_LOCALIZATION: localization_summary(table, components.levels, list(components.scorers))}
    for split in result.split_diagnostics:
        if "training" in split:  # simulated events and calibration playbacks the method was fitted on
            metrics["training"] = split["training"]
        held_out = split.pop("held_out_calibration", None)
        if held_out is not None:  # the radii tested on the calibration playbacks, each spot held out
            metrics["held_out_calibration"] = held_out_calibration_summary(held_out, components.levels, list(components.scorers))
            _log_held_out(metrics["held_out_calibration"])
    if col.QUALITY_FLAGS in predictions:
        metrics[col.QUALITY_FLAGS] = quality_flag_counts(predictions)
    metrics.update(split_diagnostics_summary(result.split_diagnostics, choices.get("gate") or type(components.gate).__name__))
    metrics.update(
        {
            "dataset_hash": dataset.dataset_hash,
            "field_dataset_hash": field_data.dataset_hash,
            "site": site.name,
            "choices": choices,
            "n_features": int(len(dataset.features.columns)),
            "code_version": code_version(),
        }
    )
    if run_name:
        metrics["run_name"] = run_name
    if calibration is not None:
        metrics["field_calibration"] = calibration.summary()
    write_results(run_dir, cfg, predictions, metrics)

    def plot() -> None:
        from acoustlab.reporting.plots import (
            write_positions_map,  # matplotlib only when plotting
        )

        write_positions_map(table, site, components.levels, list(components.scorers), run_dir / "plots")

    plot_and_time(cfg, run_dir, metrics, timings, started, "the positions map", plot)
    shown = table[[col.TRUE_X, col.TRUE_Y, *([col.TRUE_Z] if col.TRUE_Z in table else []), "source", col.PLACED]].head(20)
    log.info(
        "positions (first %d of %d detections; all in %s):\n%s",
        len(shown),
        len(table),
        run_dir / "positions.csv",
        shown.to_string(float_format=lambda v: f"{v:.2f}"),
    )
    log.info("run directory: %s", run_dir)
    log_run_dir(tracker, run_dir, parent_run_id=parent_run_id)
    return metrics
