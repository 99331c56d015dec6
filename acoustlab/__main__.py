"""Hydra entry point: ``python -m acoustlab +site=NAME [group=option ...]`` (also the ``acoustlab`` script)."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from acoustlab.errors import AcoustlabError
from acoustlab.preflight import check_argv

log = logging.getLogger("acoustlab")


def _fail(exc: AcoustlabError) -> None:
    print(f"acoustlab: error: {exc}", file=sys.stderr)
    sys.exit(2)


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def _hydra_main(cfg: DictConfig) -> None:
    from acoustlab.app import run_experiment

    hc = HydraConfig.get()
    try:
        run_experiment(cfg, Path(hc.runtime.output_dir), dict(hc.runtime.choices))
    except AcoustlabError as exc:
        _fail(exc)


def main() -> None:
    """Console-script entry point: preflight the command line, then hand over to Hydra."""
    try:
        check_argv(sys.argv[1:])
    except AcoustlabError as exc:
        _fail(exc)
    _hydra_main()


if __name__ == "__main__":
    main()
