"""What a job receives: the run's checked plugins and settings, typed, and the one path from them to the run's data.

``acoustlab.run.app.build_run`` builds a ``RunContext`` from a config (every plugin built and
checked, nothing expensive run); the evaluation protocols, ``localize``, ``season`` and
``calibrate`` all get their data from it through ``simulated_dataset`` and ``field_dataset``, so a
job, a benchmark and a test see the same data (the same cache keys, plausible-region bound and
field preparation). Nothing here reads a config: the settings that key the cache arrive as plain
values.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from acoustlab.core.contracts import FeatureSet, FieldSource, Simulator
from acoustlab.core.types import Site
from acoustlab.method.localizer import solve_detections
from acoustlab.method.pipeline import Components
from acoustlab.stages.cache import StageCache
from acoustlab.stages.dataset import Dataset, SimulationPlan, load_or_build_field, load_or_build_simulated
from acoustlab.stages.field_calibration import FieldCalibration
from acoustlab.stages.solver_columns import add_solver_columns


@dataclass
class RunSettings:
    """The settings a job needs as plain values (the config itself stays in ``acoustlab.run``).

    Attributes
    ----------
    simulator, feature_groups, field : dict
        The resolved ``simulator``, ``features.groups`` and ``field`` nodes: they key the cache.
    config : dict
        The whole resolved config, for what a job keys its saved results by (a season's fitted method) and writes beside them.
    sample_rate_hz : float
        The simulator's sample rate, Hz: what the method's features are computed at.
    outputs_dir : pathlib.Path
        ``paths.outputs_dir``: where jobs keep what outlives one run folder (a season's parts).
    plots : bool
        ``plots``: write the optional figures.
    record : dict
        What every job's ``metrics.json`` records of the run (site, config choices, run name, code version).
    """

    simulator: dict[str, Any] = dataclasses.field(default_factory=dict)
    feature_groups: dict[str, Any] = dataclasses.field(default_factory=dict)
    field: dict[str, Any] = dataclasses.field(default_factory=dict)
    config: dict[str, Any] = dataclasses.field(default_factory=dict)
    sample_rate_hz: float = 48000.0
    outputs_dir: Path = Path("outputs")
    plots: bool = True
    record: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclass
class RunContext:
    """Everything a job needs, built and checked from its config (``acoustlab.run.app.build_run``).

    Attributes
    ----------
    components : Components
        The configured, never-fitted plugins and the method's settings (placement rules included); ``site`` and
        ``calibration`` are theirs.
    simulator : Simulator
        The site's simulator.
    cache : StageCache
        The content-addressed stage cache.
    plan : SimulationPlan
        Which events to simulate.
    settings : RunSettings
        Plain settings (cache keys, sample rate, output folder, plots).
    field_source : FieldSource, optional
        The field recordings (jobs that need them).
    stated_site : Site, optional
        The site as the config states it, where ``site`` is its calibration (the recordings are read for it).
    """

    components: Components
    simulator: Simulator
    cache: StageCache
    plan: SimulationPlan
    settings: RunSettings
    field_source: FieldSource | None = None
    stated_site: Site | None = None

    @property
    def site(self) -> Site:
        """The array the method is trained for: the calibrated array under ``calibration=PATH``."""
        return self.components.site

    @property
    def calibration(self) -> FieldCalibration | None:
        """``calibration=PATH``: the field calibration applied to the site and the recordings, or None."""
        return self.components.placement.calibration

    @property
    def feature_sets(self) -> dict[str, FeatureSet]:
        """The configured feature groups, in config order."""
        return self.components.feature_sets


def simulated_dataset(context: RunContext) -> Dataset | None:
    """The site's simulated dataset (from the cache when possible) with the solver's columns under the plausible-region bound.

    Returns None for a sharded simulation run (``data.shard_count > 1``) that filled its shard of the cache.
    """
    s = context.settings
    dataset = load_or_build_simulated(
        context.site, context.simulator, s.simulator, context.feature_sets, s.feature_groups, context.plan, context.cache
    )
    if dataset is None:
        return None
    c = context.components
    dataset.features = add_solver_columns(dataset.features, dataset.events, c.site, c.solver, c.placement.plausible_margin_fraction)
    return dataset


def field_dataset(context: RunContext, solved: bool = True) -> Dataset:
    """The field recordings' features and events (cached), read for the stated array; with ``solved``, the calibration
    applied and the solver's columns added (``acoustlab.method.localizer.solve_detections``)."""
    if context.field_source is None:
        raise ValueError("this run has no field source")
    s = context.settings
    data = load_or_build_field(
        context.site, context.field_source, s.field, context.feature_sets, s.feature_groups, context.cache, stated_site=context.stated_site
    )
    if solved:
        data.features, data.events = solve_detections(context.components, data.features, data.events)
    return data
