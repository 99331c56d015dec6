"""Helpers shared by the benchmark scripts: compose the real config, write JSON + Markdown."""

from __future__ import annotations

import json
import platform
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from acoustlab.registry import CONF_DIR

RESULTS = Path(__file__).resolve().parent / "results"


def compose_cfg(overrides: list[str]):
    """The composed acoustlab config for ``overrides``."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def machine() -> dict[str, Any]:
    """A short description of the machine the numbers were measured on."""
    import os

    return {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count()}


def write_results(name: str, result: dict[str, Any], markdown: list[str]) -> None:
    """Write ``results/<name>.json`` and ``results/<name>.md``."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=2, default=float))
    (RESULTS / f"{name}.md").write_text("\n".join(markdown) + "\n")
