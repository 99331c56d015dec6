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
from hypothesis import settings as hypothesis_settings

from acoustlab.run.registry import CONF_DIR, build
from acoustlab.stages.sites import site_from_config

REPO = Path(__file__).resolve().parent.parent

# Hypothesis: ``dev`` (the default) tries few examples per property, ``ci`` (HYPOTHESIS_PROFILE=ci, set by .ci/run) the
# count each test states; no deadline either way (a loaded machine is not a failure).
hypothesis_settings.register_profile("dev", max_examples=10, deadline=None)
hypothesis_settings.register_profile("ci", deadline=None, print_blob=True)
hypothesis_settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "dev"))


def examples(n: int) -> int:
    """A property test's example count: ``n`` under the ``ci`` profile, at most 10 under ``dev``."""
    return n if os.environ.get("HYPOTHESIS_PROFILE") == "ci" else min(n, 10)


#: An unmarked test whose call takes longer than this is reported at the end of the run (the marks stay honest).
UNMARKED_CALL_LIMIT_S = 5.0
_unmarked_slow: list[tuple[str, float]] = []


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.when == "call" and report.duration > UNMARKED_CALL_LIMIT_S and "slow" not in report.keywords:
        _unmarked_slow.append((report.nodeid, report.duration))


def pytest_terminal_summary(terminalreporter) -> None:
    if _unmarked_slow:
        terminalreporter.section("unmarked slow tests")
        for nodeid, duration in sorted(_unmarked_slow, key=lambda x: -x[1]):
            terminalreporter.write_line(
                f"{nodeid} took {duration:.1f} s (> {UNMARKED_CALL_LIMIT_S:g} s): mark it @pytest.mark.slow if it runs a whole job, "
                "a subprocess or a launcher, else make it cheaper"
            )


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
