"""The files every job writes into its run folder, each atomically: predictions, resolved config, metrics, figures.

One place for how a run folder is written, whichever job writes it (``acoustlab.run.app`` for the
evaluation protocols, ``localize`` and ``calibrate`` from the method layer), so a folder's layout
and its pending-upload marker are the same for every kind of run.
"""

from __future__ import annotations

import json
import logging
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from acoustlab import __version__
from acoustlab.core import columns as col
from acoustlab.core.files import atomic_write_bytes
from acoustlab.reporting.experiment_log import PENDING_FILE
from acoustlab.toolkit.quality import QUALITY_REASONS

log = logging.getLogger(__name__)


def code_version() -> str:
    """acoustlab's version, with the commit of a git checkout (``0.2.0+abc1234``)."""
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent, timeout=5
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        sha = ""
    return f"{__version__}+{sha}" if sha else __version__


def quality_flag_counts(predictions: pd.DataFrame) -> dict[str, int]:
    """How many detections were flagged, in all and per reason (``dead``, ``truncated``, …), for metrics.json."""
    flags = predictions[col.QUALITY_FLAGS].fillna("").astype(str)
    counts = {"flagged": int((flags != "").sum())}
    for reason in QUALITY_REASONS:
        counts[reason] = int(flags.str.contains(rf"\b{reason}\b").sum())
    return counts


def write_metrics(run_dir: Path, metrics: dict[str, Any]) -> None:
    """``metrics.json`` (values JSON cannot hold written as text)."""
    atomic_write_bytes(run_dir / "metrics.json", json.dumps(metrics, indent=2, default=str).encode())


def write_config(run_dir: Path, config: dict[str, Any]) -> None:
    """``config_resolved.yaml``: the run's whole resolved config (what ``python -m acoustlab.aligned_clips`` and the report read)."""
    atomic_write_bytes(run_dir / "config_resolved.yaml", yaml.safe_dump(config, sort_keys=False, allow_unicode=True).encode())


def write_results(run_dir: Path, config: dict[str, Any], predictions: pd.DataFrame, metrics: dict) -> None:
    """The results a run must never lose, each written atomically: predictions, resolved config, metrics, and the pending marker.

    Raises
    ------
    StorageError
        Naming the file and the free space, when the run directory cannot be written.
    """
    atomic_write_bytes(run_dir / "predictions.parquet", predictions.to_parquet(index=False))
    write_config(run_dir, config)
    write_metrics(run_dir, metrics)
    atomic_write_bytes(run_dir / PENDING_FILE, json.dumps({"destination": None, "error": "not yet sent to the tracker"}).encode())


def write_positions(run_dir: Path, table: pd.DataFrame, csv: bool = True) -> None:
    """A positions table as every job writes it: ``positions.parquet``, ``positions.csv`` (with ``csv``), and the map layer
    ``positions.gpkg`` (``acoustlab.reporting.geo``; optional: a failure there is a warning, never a lost run)."""
    from acoustlab.reporting.geo import GEOPACKAGE, write_geopackage

    atomic_write_bytes(run_dir / "positions.parquet", table.to_parquet(index=False))
    if csv:
        atomic_write_bytes(run_dir / "positions.csv", table.to_csv(index=False).encode())
    optional_artefact(GEOPACKAGE, lambda: write_geopackage(table, run_dir / GEOPACKAGE))


def optional_artefact(what: str, write: Callable[[], Any]) -> None:
    """Write an artefact the results do not depend on (plots, …); a failure is a warning, never a lost run."""
    try:
        write()
    except Exception as exc:
        log.warning("%s not written (%s: %s); the metrics and predictions are saved", what, type(exc).__name__, exc)


def plot_and_time(
    plots: bool, run_dir: Path, metrics: dict, timings: dict[str, float], started: float, what: str, plot: Callable[[], None]
) -> None:
    """After the results are safe: the optional plots (``plots=true``), then the run's timings added to metrics.json."""
    stage_start = time.perf_counter()
    if plots:
        optional_artefact(what, plot)
    timings["plots_s"] = time.perf_counter() - stage_start
    timings["total_before_tracking_s"] = time.perf_counter() - started
    metrics["timings_s"] = {k: round(v, 3) for k, v in timings.items()}
    now = time.time()  # wall clock, so a tracker shows the job's own start and duration even when it is uploaded later
    metrics["run_time"] = {"started_epoch_ms": int(1000 * (now - timings["total_before_tracking_s"])), "finished_epoch_ms": int(1000 * now)}
    optional_artefact("timings in metrics.json", lambda: write_metrics(run_dir, metrics))
