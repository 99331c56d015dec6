"""Shared fixtures: compose the real conf/ and shrink runs to tiny data."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from acoustlab.run.registry import CONF_DIR, build
from acoustlab.stages.sites import site_from_config

REPO = Path(__file__).resolve().parent.parent


def _compose(overrides: list[str]):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


@pytest.fixture
def compose_cfg():
    """Compose the real config with overrides, as the CLI would (without running Hydra's job)."""
    yield _compose
    GlobalHydra.instance().clear()


@pytest.fixture(scope="session")
def simulate_site():
    """``simulate_site(site_name, n_events, seed)``: the site and a batch of the default simulator (noise, trunks, ground), one
    event per source position."""

    def _simulate(site_name: str, n_events: int, seed: int):
        cfg = _compose([f"+site={site_name}"])
        site = site_from_config(cfg.site)
        ids = np.arange(n_events)
        return site, build(cfg.simulator, "simulator").simulate(site, ids, ids, seed)

    yield _simulate
    GlobalHydra.instance().clear()


@pytest.fixture
def run_cli(tmp_path):
    """Run ``python -m acoustlab`` in a subprocess with outputs under a temp folder."""

    def _run(*args: str, outputs: Path | None = None, timeout: float | None = None) -> subprocess.CompletedProcess:
        out = outputs or tmp_path / "outputs"
        env = {**os.environ, "PYTHONWARNINGS": "ignore"}
        return subprocess.run(
            [sys.executable, "-m", "acoustlab", *args, f"paths.outputs_dir={out}"],
            capture_output=True,
            text=True,
            cwd=REPO,
            env=env,
            timeout=timeout,
        )

    return _run
