"""The one module that instantiates plugins from Hydra configs, and lists what is registered.

A plugin is registered by a YAML file with a ``_target_`` in its config group under ``conf/``;
runtime inputs (the site, its geometry) are passed as keyword arguments here, never written into
the config.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import inspect
import re
from pathlib import Path
from typing import Any

import hydra.utils
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from acoustlab.core.errors import AcoustlabError, ConfigError
from acoustlab.core.resources import CONF_DIR
from acoustlab.run import schema  # noqa: F401 - registers the typed config schema before any compose

#: Config groups that hold plugins, with the contract each option must satisfy.
PLUGIN_GROUPS = (
    "simulator",
    "features",
    "solver",
    "model",
    "gate",
    "error_model",
    "conformal",
    "protocol",
    "field",
    "tracking",
)
#: Every user-facing config group (``site`` and ``experiment`` are not plugins).
ALL_GROUPS = ("site", *PLUGIN_GROUPS, "experiment")


def group_options(group: str, conf_dir: Path = CONF_DIR) -> list[str]:
    """Names of the options registered in a config group (YAML files in ``conf/<group>/``)."""
    return sorted(p.stem for p in (conf_dir / group).glob("*.yaml"))


@functools.cache
def check_plugins_package() -> None:
    """Make sure the importable top-level ``plugins`` package is acoustlab's, not another project's.

    Raises
    ------
    ConfigError
        Naming where the foreign ``plugins`` package was found.
    """
    try:
        package = importlib.import_module("plugins")
    except ImportError as exc:
        raise ConfigError(f"acoustlab's 'plugins' package cannot be imported ({exc}); reinstall acoustlab (pip install -e .)") from None
    if getattr(package, "ACOUSTLAB_PLUGINS", False) is not True:
        where = getattr(package, "__file__", None) or list(getattr(package, "__path__", []))
        raise ConfigError(
            f"the top-level package 'plugins' imported from {where} is not acoustlab's (another installed project "
            "ships a package of that name); uninstall that project or install acoustlab in its own environment"
        )


def build(node: Any, what: str, **runtime: Any) -> Any:
    """Instantiate one plugin config (a mapping with ``_target_``), adding runtime keyword arguments.

    Raises
    ------
    ConfigError
        With the config path and the reason when the class cannot be imported or built.
    """
    if node is None or (isinstance(node, DictConfig) and "_target_" not in node):
        return None
    if str(node.get("_target_", "")).startswith("plugins."):
        check_plugins_package()
    try:
        return instantiate(node, _convert_="all", **runtime)
    except InstantiationException as exc:
        cause = exc.__cause__
        if isinstance(cause, AcoustlabError):
            raise cause from None
        unknown = _unknown_setting(node, cause)
        if unknown is not None:
            raise ConfigError(f"{what}.{unknown}") from None
        raise ConfigError(f"cannot instantiate {what}: {exc}".replace("\n", " ")) from None


def _unknown_setting(node: Any, cause: BaseException | None) -> str | None:
    """``"NAME is not a setting of Class; did you mean …?"`` where building failed on an unknown keyword, else None."""
    match = re.search(r"unexpected keyword argument '(\w+)'", str(cause)) if isinstance(cause, TypeError) else None
    if match is None:
        return None
    try:
        target = hydra.utils.get_class(str(node.get("_target_")))
        params = [p for p in inspect.signature(target.__init__).parameters if p != "self"]
    except Exception:  # noqa: BLE001 - a target that is a function, or cannot be inspected: no suggestion
        return None
    near = difflib.get_close_matches(match.group(1), params, n=1)
    hint = f"did you mean {near[0]}?" if near else f"its settings: {', '.join(params)}"
    return f"{match.group(1)} is not a setting of {target.__name__}; {hint}"


def to_plain(node: Any) -> Any:
    """A resolved plain-Python copy of a config node (for cache keys and params)."""
    if isinstance(node, DictConfig) or OmegaConf.is_config(node):
        return OmegaConf.to_container(node, resolve=True)
    return node


def build_feature_sets(features_cfg: DictConfig) -> dict[str, Any]:
    """The feature groups in config order: ``{name: FeatureSet}``."""
    groups = features_cfg.get("groups") or {}
    if not groups:
        raise ConfigError("features.groups is empty; configure at least the 'tdoa' group")
    return {name: build(node, f"features.groups.{name}") for name, node in groups.items()}


def build_scorers(conformal_cfg: DictConfig) -> dict[str, Any]:
    """The conformal scorers to compare: ``{name: ConformalScorer}``."""
    scorers = conformal_cfg.get("scorers") or {}
    if not scorers:
        raise ConfigError("conformal.scorers is empty; configure at least one scorer")
    return {name: build(node, f"conformal.scorers.{name}") for name, node in scorers.items()}
