"""Typed schema of the config's non-plugin nodes (Hydra structured configs).

The main config (``conf/config.yaml``) lists ``acoustlab_schema`` first in its defaults, so every
composed config is checked against these dataclasses (types here; the default values, with
comments, stay in ``conf/config.yaml``, their one home): a mistyped key (``data.n_event=5``) or a
value of the wrong type (``data.n_events=abc``) fails when Hydra composes, before anything runs.
Plugin nodes (simulator, solver, model, …) stay free-form: their keys are the plugin's
constructor arguments, checked when the plugin is built.

OmegaConf 2.3 has no ``typing.Literal``; closed choices are ``str`` enums instead.
"""

from __future__ import annotations

from dataclasses import dataclass, make_dataclass
from dataclasses import field as dc_field
from enum import Enum
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf

from acoustlab.core.cores import free_cores
from acoustlab.core.resources import CONF_DIR
from acoustlab.method.trust import TrustSettings
from acoustlab.toolkit.input_uncertainty import InputUncertainty

SCHEMA_NAME = "acoustlab_schema"


class CalibrateOn(str, Enum):
    """Which training rows calibrate conformal: every row, field rows with known positions, or field rows where there are enough."""

    auto = "auto"
    all = "all"
    field = "field"


class UnsupportedLevels(str, Enum):
    """A level the field calibration spots are too few to guarantee: no radius, or the simulation's rescaled and labelled."""

    empty = "empty"
    rescaled = "rescaled"


class SelectiveUnit(str, Enum):
    """What selective localization counts as independent: source positions (clustered errors) or detections."""

    position = "position"
    event = "event"


class ModelTarget(str, Enum):
    """What the point model predicts: the position (as in the paper) or the solver's error."""

    absolute = "absolute"
    correction = "correction"


@dataclass
class DataConfig:
    """How many events to simulate and how to split the work (the work split never changes the data)."""

    n_events: int = MISSING
    events_per_position: int = MISSING
    chunk_size: int = MISSING
    n_jobs: int = MISSING
    shard_index: int = MISSING
    shard_count: int = MISSING


@dataclass
class SelectiveConfig:
    """Selective localization: return no position where the predicted error says it cannot be trusted."""

    enabled: bool = False
    gross_m: float = 5.0
    delta: float = 0.01
    epsilon: float = 0.1
    unit: SelectiveUnit = SelectiveUnit.position


@dataclass
class PipelineConfig:
    """What the point model predicts, the solver's plausible region, and which feature groups each learned model is denied."""

    model_target: ModelTarget = MISSING
    plausible_margin_fraction: float | None = MISSING
    drop_from_model: list[str] = dc_field(default_factory=list)
    drop_from_error_model: list[str] = dc_field(default_factory=list)
    error_model_gate_cues: bool = True
    selective: SelectiveConfig = dc_field(default_factory=lambda: SelectiveConfig())
    extra_gates: dict[str, Any] = dc_field(default_factory=dict)
    trust: TrustSettings = dc_field(default_factory=TrustSettings)


@dataclass
class CacheConfig:
    """The content-addressed cache of simulations and features."""

    enabled: bool = MISSING
    dir: str = MISSING
    file_mode: str = "0644"


@dataclass
class PathsConfig:
    """Where runs, caches and the MLflow store live."""

    outputs_dir: str = MISSING


@dataclass
class FeaturesConfig:
    """The feature groups (plugins), settings shared by several groups, and the ablation knob.

    ``drop`` is the one home of the feature-group ablation: groups withheld from both learned
    models (``pipeline.drop_from_model`` / ``drop_from_error_model`` withhold from one only).
    """

    groups: dict[str, Any] = dc_field(default_factory=dict)
    gcc: dict[str, Any] = dc_field(default_factory=dict)
    drop: list[str] = dc_field(default_factory=list)


@dataclass
class ConformalConfig:
    """Conformal scorers (plugins) compared in one run, and the settings they share."""

    levels: list[float] = MISSING
    calibration_folds: int = MISSING
    calibrate_on: CalibrateOn = CalibrateOn.auto
    unsupported_levels: UnsupportedLevels = UnsupportedLevels.empty
    scorers: dict[str, Any] = dc_field(default_factory=dict)
    ellipse: bool = False
    input_uncertainty: InputUncertainty = dc_field(default_factory=InputUncertainty)


@dataclass
class SiteConfig:
    """A site: mics, trees, weather ranges, ground, noise, species (validated when the site is built)."""

    name: str = "???"
    mics: Any | None = None
    mics_csv: str | None = None
    #: OpenSoundscape's coordinates table (one row per file) and its detections: the recorders detections use
    coords_csv: str | None = None
    detections_csv: str | None = None
    trees_csv: str | None = None
    temperature_c: Any = None
    relative_humidity_pct: Any = None
    ground: dict[str, Any] = dc_field(default_factory=dict)
    noise: dict[str, Any] = dc_field(default_factory=dict)
    species_pool: list[str] = dc_field(default_factory=list)
    source_height_m: Any = None
    hull_expansion: float = 0.0
    foliage_db_per_m: Any | None = None


#: Plugin groups whose nodes are free-form (their keys are the plugin's constructor arguments).
FREE_FORM_GROUPS = ("simulator", "solver", "model", "gate", "error_model", "protocol", "field", "tracking")


@dataclass
class _TypedRoot:
    seed: int = MISSING
    plots: bool = MISSING
    #: a field calibration file (``acoustlab calibrate``) applied in localize and season
    calibration: str | None = None
    data: DataConfig = dc_field(default_factory=DataConfig)
    pipeline: PipelineConfig = dc_field(default_factory=PipelineConfig)
    cache: CacheConfig = dc_field(default_factory=CacheConfig)
    paths: PathsConfig = dc_field(default_factory=PathsConfig)
    features: FeaturesConfig = dc_field(default_factory=FeaturesConfig)
    conformal: ConformalConfig = dc_field(default_factory=ConformalConfig)
    site: SiteConfig | None = None
    #: the paper's published figures for this experiment (``paper_forest``, ``paper_frozen_lake``): written beside ours
    paper_reference: dict[str, Any] | None = None
    #: what a long experiment costs, as measured (said before it starts: a run logs it, a sweep with its job count)
    expected_duration: str | None = None


#: The root: the typed nodes above plus one free-form node per plugin group in ``FREE_FORM_GROUPS``.
AcoustlabConfig = make_dataclass("AcoustlabConfig", [(g, Any, None) for g in FREE_FORM_GROUPS], bases=(_TypedRoot,))


def option_descriptions(width: int = 110) -> str:
    """Every option of every config group with a one-line description: the first comment line of its YAML (for ``--help``)."""
    lines = []
    for group in sorted(p for p in CONF_DIR.iterdir() if p.is_dir() and p.name != "hydra"):
        lines.append(f"{group.name}:")
        for option in sorted(group.glob("*.yaml")):
            # the first line after any "# @package" directive, where it is a comment
            head = next((line for line in option.read_text().splitlines() if line.strip() and not line.startswith("# @package")), "")
            text = head.lstrip("#").strip() if head.startswith("#") else ""
            entry = f"  {option.stem:<28} {text}"
            lines.append(entry if len(entry) <= width else entry[: width - 1] + "…")
    return "\n".join(lines)


def register() -> None:
    """Register the schema with Hydra's ConfigStore and the ``${threads:}`` and ``${options:}`` resolvers (idempotent)."""
    ConfigStore.instance().store(name=SCHEMA_NAME, node=AcoustlabConfig)
    if not OmegaConf.has_resolver("threads"):
        OmegaConf.register_new_resolver("threads", free_cores, use_cache=True)
    if not OmegaConf.has_resolver("options"):  # --help: each option with its description
        OmegaConf.register_new_resolver("options", option_descriptions, use_cache=True)


register()
