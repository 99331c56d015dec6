"""Compose the plugins of a config into a run: data stages, protocol, metrics, tracking."""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from acoustlab.core import columns as col
from acoustlab.core.contracts import EvaluationProtocol, Job, declared, hook
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.files import atomic_write_bytes
from acoustlab.core.types import Site
from acoustlab.method.pipeline import Components, LocalizationPipeline
from acoustlab.method.placement_rules import MapProjection, PlacementRules
from acoustlab.method.run_context import RunContext, RunSettings, field_dataset, simulated_dataset
from acoustlab.method.trust import TrustSettings
from acoustlab.reporting.experiment_log import log_run_dir
from acoustlab.reporting.metrics import (
    split_diagnostics_summary,
    summarise,
    summary_text,
)
from acoustlab.reporting.paper import paper_comparison
from acoustlab.reporting.run_files import code_version, plot_and_time, quality_flag_counts, write_results
from acoustlab.run.registry import (
    PLUGIN_GROUPS,
    build,
    build_feature_sets,
    build_scorers,
    group_options,
    to_plain,
)
from acoustlab.run.schema import CalibrateOn, ModelTarget, UnsupportedLevels
from acoustlab.stages.cache import StageCache
from acoustlab.stages.dataset import (
    SimulationPlan,
)
from acoustlab.stages.field_calibration import (
    FieldCalibration,
    calibrated_site,
    load_calibration,
)
from acoustlab.stages.sites import site_from_config, site_map_projection
from acoustlab.stages.solver_columns import add_solver_columns
from acoustlab.toolkit.input_uncertainty import CorrelatedInputErrors, InputUncertainty

log = logging.getLogger(__name__)


def require_site(cfg: DictConfig) -> None:
    """Stop with a clear message when no site was chosen."""
    if cfg.get("site") is None:
        sites = ", ".join(group_options("site"))
        raise ConfigError(f"no site chosen: pass one with +site=NAME (available: {sites}), e.g. python -m acoustlab +site=frozen_lake")


@dataclass
class BuiltRun:
    """Everything a run needs, built and checked from its config (see ``build_run``): the job's typed context, the
    protocol that runs on it, and the tracker."""

    context: RunContext
    protocol: EvaluationProtocol | Job
    tracker: Any

    def __getattr__(self, name: str) -> Any:
        """The context's fields as the run's own: ``site``, ``components``, ``feature_sets``, ``simulator``, ``cache``,
        ``plan``, ``field_source``, ``calibration``, ``stated_site`` (``acoustlab.method.run_context.RunContext``)."""
        if name == "context":  # not yet set (e.g. while copying): never recurse
            raise AttributeError(name)
        return getattr(self.context, name)


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
    components = build_components(cfg, site)
    protocol = build(cfg.protocol, "protocol")
    field_source = build_field_source(cfg, protocol, site, choices)
    validate_protocol = hook(protocol, "validate")
    if validate_protocol is not None:  # e.g. a season's recordings and detector tables, before any simulation
        validate_protocol(site)
    patch = hook(protocol, "config_patch")
    changes = patch(site, field_source, OmegaConf.to_container(cfg, resolve=True)) if patch is not None else None
    if changes:  # e.g. calibrate: the GCC lag window widened to what the stated array may be off
        cfg = OmegaConf.merge(cfg, changes)  # the caller's config is untouched
        components = dataclasses.replace(components, feature_sets=build_feature_sets(cfg.features))
    tracker = build(cfg.tracking, "tracking")

    cache = StageCache(cfg.cache.dir, enabled=cfg.cache.enabled, file_mode=cfg.cache.file_mode)
    if cfg.data.shard_count > 1 and not cache.enabled:
        raise ConfigError("data.shard_count > 1 fills the cache shard by shard; it needs cache.enabled=true")
    plan = SimulationPlan(seed=cfg.seed, **OmegaConf.to_container(cfg.data, resolve=True))
    calibration, stated_site = None, None
    if cfg.get("calibration"):  # after the recordings were checked against the stated array
        calibration = load_calibration(str(cfg.calibration), site)
        stated_site, site = site, calibrated_site(site, calibration)
        allowance = calibrated_allowance(calibration, stated_site, components.input_uncertainty)
        components = dataclasses.replace(components, site=site, input_uncertainty=allowance)
    components = dataclasses.replace(components, placement=placement_rules(cfg, field_source, calibration))
    settings = run_settings(cfg, site, choices)
    context = RunContext(components, simulator, cache, plan, settings, field_source, stated_site)
    return BuiltRun(context, protocol, tracker)


def build_components(cfg: DictConfig, site: Site) -> Components:
    """The method's configured plugins and settings, checked against each other (feature groups, levels, weights)."""
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
    return components


def build_field_source(cfg: DictConfig, protocol: EvaluationProtocol | Job, site: Site, choices: dict[str, str] | None) -> Any:
    """The field recordings a protocol needs, built and checked against the site now (not after the training simulation);
    None for one that needs none."""
    if not declared(protocol, "needs_field"):
        return None
    field_source = build(cfg.field, "field")
    if field_source is None:
        protocol_name = (choices or {}).get("protocol") or type(protocol).__name__
        raise ConfigError(f"protocol={protocol_name} needs field recordings: choose field=playback_standin or field=recordings")
    validate = hook(field_source, "validate")
    if validate is not None:
        validate(site)
    return field_source


def run_settings(cfg: DictConfig, site: Site, choices: dict[str, str] | None) -> RunSettings:
    """The run's settings as plain values for the job (``acoustlab.method.run_context.RunSettings``)."""
    return RunSettings(
        simulator=to_plain(cfg.simulator),
        feature_groups=to_plain(cfg.features.groups),
        field=to_plain(cfg.field) if cfg.get("field") is not None else {},
        config=OmegaConf.to_container(cfg, resolve=True, enum_to_str=True),
        sample_rate_hz=float(cfg.simulator.sample_rate_hz),
        outputs_dir=Path(str(cfg.paths.outputs_dir)),
        plots=bool(cfg.get("plots", True)),
        record={"site": site.name, "choices": dict(choices or {})},
    )


def placement_rules(cfg: DictConfig, field_source: Any, calibration: FieldCalibration | None) -> PlacementRules:
    """How the run's field detections are solved and reported: the plausible-region bound, the weak-recorder rule, the
    calibration and the field source's map projection (``acoustlab.method.localizer``)."""
    project = hook(field_source, "projection") if field_source is not None else None
    projection = project() if project is not None else None
    if projection is None:  # a season: the site's own mics table may place it on the map
        projection = site_map_projection(cfg.site)
    return PlacementRules(
        plausible_margin_fraction=cfg.pipeline.plausible_margin_fraction,
        calibration=calibration,
        min_gcc_peak=OmegaConf.select(cfg, "features.gcc.min_peak", default=None),
        min_gcc_peak_relative=OmegaConf.select(cfg, "features.gcc.min_peak_relative", default=None),
        projection=None if projection is None else MapProjection(*projection),
    )


def calibrated_allowance(calibration: FieldCalibration, stated_site: Site, stated: InputUncertainty) -> CorrelatedInputErrors:
    """The radii's input allowance under ``calibration=PATH``: its covariance, with ``stated``'s limits; logs what the
    calibration changes. A job that assumes the weather adds its thermometer σ itself (the season)."""
    log.info(
        "calibration %s (%s…): mics moved up to %.2f m, thermometer offset %+.2f °C, clock offsets up to %.3g ms; its "
        "covariance is the radii's input allowance in place of conformal.input_uncertainty's standard deviations",
        calibration.path,
        calibration.sha256[:12],
        float(np.abs(calibration.mic_positions_m - stated_site.mic_positions_m).max()),
        calibration.temperature_offset_c,
        1e3 * float(np.abs(calibration.clock_offset_s).max()),
    )
    # the stated exact_above_m and max_sigma_m still apply
    return dataclasses.replace(calibration.input_uncertainty(0.0), exact_above_m=stated.exact_above_m, max_sigma_m=stated.max_sigma_m)


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
    dataset = simulated_dataset(built.context)
    if dataset is None:
        return None
    return RunData(dataset, field_dataset(built.context) if built.field_source is not None else None)


def prepare_field(cfg: DictConfig, built: BuiltRun) -> Any:
    """The field recordings' features and events (cached), the calibration applied, with the solver's columns."""
    return field_dataset(built.context)


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
    context, protocol = built.context, built.protocol
    record = {"site": context.site.name, "choices": choices, "code_version": code_version(), **({"run_name": run_name} if run_name else {})}
    if context.calibration is not None:
        record["field_calibration"] = context.calibration.summary()
    context = dataclasses.replace(context, settings=dataclasses.replace(context.settings, record=record))
    if isinstance(protocol, Job):  # localize, season, calibrate: the job writes its own results
        metrics = protocol.run_job(context, run_dir)
    else:
        metrics = _evaluate(cfg, run_dir, context, protocol, started)
    if "shard" not in metrics:
        log.info("run directory: %s", run_dir)
        log_run_dir(built.tracker, run_dir, parent_run_id=parent_run_id)
    return metrics


def _evaluate(cfg: DictConfig, run_dir: Path, context: RunContext, protocol: EvaluationProtocol, started: float) -> dict:
    """An evaluation protocol's run: data, the protocol's splits, error and coverage metrics, plots."""
    timings: dict[str, float] = {"preflight_s": time.perf_counter() - started}
    stage_start = time.perf_counter()
    dataset = simulated_dataset(context)
    if dataset is None:
        log.info(
            "sharded simulation run: shard %d of %d is in the cache; run without data.shard_count to finish",
            context.plan.shard_index + 1,
            context.plan.shard_count,
        )
        return {"shard": {"index": context.plan.shard_index, "count": context.plan.shard_count}}
    field_data = field_dataset(context) if context.field_source is not None else None
    timings["data_s"] = time.perf_counter() - stage_start
    stage_start = time.perf_counter()
    components, record = context.components, context.settings.record
    result = protocol.run(dataset, LocalizationPipeline(components), field_recordings=field_data)
    predictions = result.predictions
    timings["models_s"] = time.perf_counter() - stage_start
    summary_rows = predictions[col.IN_SUMMARY].to_numpy(bool) if col.IN_SUMMARY in predictions else np.ones(len(predictions), bool)
    gate_name = record["choices"].get("gate") or type(components.gate).__name__
    metrics = _evaluation_metrics(run_dir, predictions, summary_rows, result, components, dataset, field_data, gate_name)
    metrics.update(record)

    # Results land in the run dir first (metrics before any optional artefact), so neither a tracker
    # nor a plotting failure loses them; the pending marker stays until the tracker has them.
    write_results(run_dir, context.settings.config, predictions, metrics)
    if cfg.get("paper_reference"):
        rows, lines = paper_comparison(OmegaConf.to_container(cfg.paper_reference, resolve=True), metrics, context.settings.config)
        metrics["paper_comparison"] = rows
        atomic_write_bytes(run_dir / "paper_comparison.md", ("\n".join(lines) + "\n").encode())

    def plot() -> None:
        from acoustlab.reporting.plots import (
            write_run_plots,  # matplotlib only when plotting
        )

        write_run_plots(predictions[summary_rows], metrics, context.site, run_dir / "plots")

    plot_and_time(context.settings.plots, run_dir, metrics, timings, started, "plots", plot)
    log.info("%s test detections; errors (m) and conformal coverage:\n%s", metrics[col.METRICS_ERRORS]["gate"]["n"], summary_text(metrics))
    log.info("timings (s): %s", ", ".join(f"{k.removesuffix('_s')} {v:.1f}" for k, v in metrics["timings_s"].items()))
    return metrics


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
