"""Shared fixtures: compose the real conf/ and shrink runs to tiny data."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from acoustlab.run.registry import CONF_DIR

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def compose_cfg():
    """Compose the real config with overrides, as the CLI would (without running Hydra's job)."""

    def _compose(overrides: list[str]):
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose(config_name="config", overrides=overrides)

    yield _compose
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
