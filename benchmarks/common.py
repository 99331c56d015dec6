"""Helpers shared by the benchmark scripts: compose the real config, write JSON + Markdown."""

from __future__ import annotations

import json
import logging
import math
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from acoustlab.run.registry import CONF_DIR

REPO = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
log = logging.getLogger("benchmarks")


def time_cli(args: list[str]) -> float:
    """Seconds one ``python -m acoustlab ARGS`` command takes in a fresh process, imports included.

    Raises
    ------
    SystemExit
        With the command and the end of its stderr when it fails.
    """
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "acoustlab", *args], cwd=REPO, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"command failed: {args}\n{proc.stderr[-3000:]}")
    log.info("%6.1f s  %s", elapsed, " ".join(args))
    return elapsed


def compose_cfg(overrides: list[str]):
    """The composed acoustlab config for ``overrides``."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def machine() -> dict[str, Any]:
    """A short description of the machine the numbers were measured on."""
    import os

    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    # "cpus": the cores this process may run on (a benchmark pinned with taskset reports its share, not the machine's)
    return {"python": platform.python_version(), "machine": platform.machine(), "cpus": usable, "machine_cpus": os.cpu_count()}


def script_sha256(script: Path) -> str:
    """SHA-256 of a benchmark script's source: a result made by another version of the script is stale."""
    from acoustlab.core.digests import file_sha256

    return file_sha256(script)


#: Distributions whose releases can move a result (numerics, learned models, configs); their versions go into every result.
PACKAGES = ("numpy", "scipy", "pandas", "pyarrow", "scikit-learn", "xgboost", "xgboost-cpu", "torch", "tabpfn", "soundfile",
            "hydra-core", "omegaconf")


def package_versions() -> dict[str, str]:
    """Installed versions of :data:`PACKAGES` (those not installed are left out)."""
    from importlib import metadata

    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return versions


def provenance() -> dict[str, Any]:
    """What made a result: the commit (and whether the work tree had changes), the benchmark script and its digest, the package versions.

    Two runs of the same commit can differ where a package release changed (an XGBoost or scikit-learn
    update moves the learned models' figures): ``packages`` says which releases made this one.
    """
    script = Path(sys.argv[0]).resolve()

    def git(*args: str) -> str:
        proc = subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True)
        return proc.stdout.strip() if proc.returncode == 0 else ""

    # results written by earlier benchmarks of the same session are not changes to what made this one
    changes = git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)benchmarks/results")
    return {"commit": git("rev-parse", "HEAD"), "uncommitted_changes": bool(changes),
            "script": script.relative_to(REPO).as_posix() if script.is_relative_to(REPO) else str(script),
            "script_sha256": script_sha256(script) if script.is_file() else "", "packages": package_versions()}


def write_results(name: str, result: dict[str, Any], markdown: list[str]) -> None:
    """Write ``results/<name>.json`` and ``results/<name>.md``, both naming the commit and script version that made them.

    ``python benchmarks/check_results.py`` lists results whose script or imported code changed since.
    """
    RESULTS.mkdir(parents=True, exist_ok=True)
    made_with = provenance()
    (RESULTS / f"{name}.json").write_text(json.dumps({**result, "provenance": made_with}, indent=2, default=float))
    note = (f"Made with commit {made_with['commit'][:10]}{' plus uncommitted changes' if made_with['uncommitted_changes'] else ''} "
            f"by {made_with['script']} (sha256 {made_with['script_sha256'][:12]}).")
    (RESULTS / f"{name}.md").write_text("\n".join([*markdown, "", note]) + "\n")


def run_in_process(overrides: list[str], keep: Path | None = None) -> dict[str, Any]:
    """One acoustlab job in this process (``tracking=none``, no plots): its metrics, with ``bench_seconds``.

    With ``keep`` its predictions.parquet is copied there (e.g. under outputs/, not committed) for a closer look.
    """
    from acoustlab.run.app import run_experiment  # imported when a benchmark runs a job, not by every script importing this module

    cfg = compose_cfg([*overrides, "tracking=none", "plots=false"])
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        metrics = run_experiment(cfg, Path(tmp) / "run", {})
        metrics["bench_seconds"] = time.perf_counter() - start
        if keep is not None:
            keep.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(Path(tmp) / "run" / "predictions.parquet", keep)
        return metrics


def fmt(v: float | None) -> str:
    """A metric for a Markdown table: '—' for a missing value, '∞' for a failure, 2 decimals below 10, none above."""
    if v is None or math.isnan(v):
        return "—"
    if v == float("inf"):
        return "∞"
    return f"{v:.2f}" if v < 10 else f"{v:.0f}"
