"""Log a finished run directory to the experiment tracker (MLflow); mark it when the tracker failed.

A run writes everything to its run directory first (``metrics.json``, ``predictions.parquet``,
``config_resolved.yaml``, ``plots/``); ``log_run_dir`` then sends that directory to the tracker.
When the tracker fails, the directory keeps a ``TRACKING_PENDING.json`` marker and the warning names
the command that uploads it later::

    python -m acoustlab.upload outputs/runs/2026-11-22/10-00-00-000000 [--tracking-uri URI]
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from acoustlab.core import columns as col
from acoustlab.core.errors import DataError
from acoustlab.reporting.metrics import coverage_table, error_table, flat_metrics

log = logging.getLogger(__name__)

#: Marker left in a run directory whose results did not reach the tracker.
PENDING_FILE = "TRACKING_PENDING.json"
#: Files of a run directory uploaded as artifacts (when present), plus the ``plots`` directory.
RUN_ARTIFACTS = ("metrics.json", "predictions.parquet", "config_resolved.yaml")


#: Limits on what a received run folder may hold (an upload reads folders from anyone): YAML/JSON size (bytes), YAML
#: nodes and nesting depth, and the size of one artifact (bytes).
MAX_TEXT_BYTES = 16 * 2**20
MAX_YAML_NODES = 200_000
MAX_DEPTH = 64
MAX_ARTIFACT_BYTES = 1 * 2**30

#: metrics.json keys a run always writes and the tracker tags a run with.
REQUIRED_METRICS_KEYS = ("site", "dataset_hash", "code_version")


def read_metrics(run_dir: Path, required: tuple[str, ...] = ()) -> dict[str, Any]:
    """A run directory's ``metrics.json``, checked: a JSON object with ``required`` keys as strings.

    Raises
    ------
    DataError
        One line naming the file and what is wrong (unreadable, not JSON, not an object, a key missing),
        for a folder received from someone else as much as for a damaged one.
    """
    path = Path(run_dir) / "metrics.json"
    try:
        if path.stat().st_size > MAX_TEXT_BYTES:
            raise DataError(f"{path} is {path.stat().st_size} bytes, more than a metrics.json can be ({MAX_TEXT_BYTES})")
        metrics = json.loads(path.read_text())
        _check_depth(metrics, path)
    except OSError as exc:
        raise DataError(f"{path} cannot be read ({exc.strerror or exc})") from None
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise DataError(f"{path} is not valid JSON ({str(exc)[:200]}); expected the metrics.json an acoustlab run writes") from None
    if not isinstance(metrics, dict):
        raise DataError(f"{path} holds a JSON {type(metrics).__name__}; expected an object of metrics")
    missing = [k for k in required if not isinstance(metrics.get(k), str)]
    if missing:
        raise DataError(f"{path} lacks {', '.join(missing)} (or they are not strings); expected the metrics.json an acoustlab run writes")
    return metrics


def _check_depth(value: Any, path: Path, depth: int = 0) -> None:
    """Refuse data nested deeper than ``MAX_DEPTH`` (one line naming the file)."""
    if depth > MAX_DEPTH:
        raise DataError(f"{path} is nested deeper than {MAX_DEPTH} levels; not an acoustlab run's file")
    children = value.values() if isinstance(value, dict) else value if isinstance(value, list) else ()
    for child in children:
        _check_depth(child, path, depth + 1)


def load_received_yaml(path: Path) -> dict[str, Any]:
    """A received ``config_resolved.yaml`` as a mapping, read within limits (one line naming the file otherwise).

    The file is parsed as events first: anchors and aliases are refused (acoustlab writes none,
    and a few nested aliases expand to billions of values), as are more than ``MAX_YAML_NODES``
    nodes, nesting deeper than ``MAX_DEPTH`` and files over ``MAX_TEXT_BYTES``.
    """
    if path.stat().st_size > MAX_TEXT_BYTES:
        raise DataError(f"{path} is {path.stat().st_size} bytes, more than a run's config can be ({MAX_TEXT_BYTES})")
    text = path.read_text(errors="replace")
    depth = nodes = 0
    try:
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, yaml.AliasEvent) or (isinstance(event, yaml.NodeEvent) and event.anchor):
                raise DataError(f"{path} uses YAML anchors or aliases, which an acoustlab run's config never has; not read")
            if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > MAX_DEPTH:
                    raise DataError(f"{path} is nested deeper than {MAX_DEPTH} levels; not an acoustlab run's config")
            elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1
            nodes += 1
            if nodes > MAX_YAML_NODES:
                raise DataError(f"{path} has more than {MAX_YAML_NODES} YAML nodes; not an acoustlab run's config")
        received = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise DataError(f"{path} is not readable YAML: {str(exc).splitlines()[0]}") from None
    if received is None:
        return {}
    if not isinstance(received, dict):
        raise DataError(f"{path} holds a YAML {type(received).__name__}; expected the mapping of settings an acoustlab run writes")
    return received


def _parquet_ok(path: Path) -> bool:
    """True for a Parquet file pyarrow can read the footer of (a received file named .parquet may be anything)."""
    import pyarrow.parquet as pq

    try:
        pq.ParquetFile(path).metadata  # noqa: B018 - reading the footer is the check
    except Exception:  # noqa: BLE001 - pyarrow raises ArrowInvalid/OSError and others for a damaged file
        return False
    return True


def artifact_paths(run_dir: Path) -> list[Path]:
    """The run's artifacts to upload: regular files inside ``run_dir`` only.

    A symbolic link (in a folder received from someone else it could point at any file of the
    uploading machine), anything that resolves outside the folder, a file over
    ``MAX_ARTIFACT_BYTES`` and a ``.parquet`` that is not Parquet are left out with a warning; a
    directory (``plots``) is listed file by file.
    """
    root = Path(run_dir).resolve()
    out: list[Path] = []
    for name in (*RUN_ARTIFACTS, "positions.csv", "plots"):
        path = Path(run_dir) / name
        candidates = sorted(path.rglob("*")) if path.is_dir() and not path.is_symlink() else [path]
        for item in candidates:
            if not (item.exists() or item.is_symlink()) or (item.is_dir() and not item.is_symlink()):
                continue
            if item.is_symlink() or not item.is_file() or not item.resolve().is_relative_to(root):
                log.warning("%s is not a regular file inside %s; not uploaded", item, run_dir)
                continue
            if item.stat().st_size > MAX_ARTIFACT_BYTES:
                log.warning("%s is %d bytes, over the %d-byte artifact limit; not uploaded", item, item.stat().st_size, MAX_ARTIFACT_BYTES)
                continue
            if item.suffix == ".parquet" and not _parquet_ok(item):
                log.warning("%s is not a readable Parquet file; not uploaded", item)
                continue
            out.append(item)
    return out


def flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    """Flatten nested dicts/lists into dotted keys."""
    out: dict[str, Any] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}{k}."))
    elif isinstance(d, list) and d and any(isinstance(v, (dict, list)) for v in d):
        for i, v in enumerate(d):
            out.update(flatten(v, f"{prefix}{i}."))
    else:
        out[prefix[:-1]] = d
    return out


def run_params(run_dir: Path, metrics: dict) -> dict[str, Any]:
    """Params of a run: ``choice.<group>`` for every chosen option plus the flattened resolved config."""
    params: dict[str, Any] = {f"choice.{g}": v for g, v in metrics.get("choices", {}).items()}
    config_file = run_dir / "config_resolved.yaml"
    if config_file.exists():
        params.update(flatten(load_received_yaml(config_file)))
    return params


def log_run_dir(tracker: Any, run_dir: Path, parent_run_id: str | None = None) -> bool:
    """Send a finished run directory to ``tracker``; never raises.

    Parameters
    ----------
    tracker : Tracker
        The tracker plugin (see ``acoustlab.core.contracts.Tracker``).
    run_dir : pathlib.Path
        A run directory holding at least ``metrics.json``.
    parent_run_id : str, optional
        The sweep's parent run, making this run its child.

    Returns
    -------
    bool
        True when everything was logged; False when the tracker failed (a warning says how to
        upload the directory later and ``TRACKING_PENDING.json`` marks it).
    """
    run_dir = Path(run_dir)
    try:
        metrics = read_metrics(run_dir, REQUIRED_METRICS_KEYS)
    except DataError as exc:
        log.warning("not sent to the tracker: %s", exc)
        return False
    choices = metrics.get("choices", {})
    run_name = metrics.get("run_name") or f"{metrics['site']}-{choices.get('model', 'model')}"
    tags = {
        "dataset_hash": metrics["dataset_hash"],
        "code_version": metrics["code_version"],
        "site": metrics["site"],
        "run_dir": str(run_dir.resolve()),
    }
    if "field_dataset_hash" in metrics:
        tags["field_dataset_hash"] = metrics["field_dataset_hash"]
    pending = run_dir / PENDING_FILE
    clock: dict[str, Any] = {}
    try:
        tracker.check_reachable()
        clock = metrics.get("run_time") if isinstance(metrics.get("run_time"), dict) else {}
        tracker.start(
            run_name, run_params(run_dir, metrics), tags, parent_run_id=parent_run_id, start_time_ms=clock.get("started_epoch_ms")
        )
        if col.METRICS_ERRORS in metrics:  # an evaluation; a localization run (no truth) has positions instead
            tracker.log_metrics(flat_metrics(metrics))
            tracker.log_table(error_table(metrics), "tables/errors.json")
            tracker.log_table(coverage_table(metrics), "tables/coverage.json")
        else:
            summary = metrics.get(col.METRICS_LOCALIZATION, {})
            tracker.log_metrics({f"localization.{k}": float(v) for k, v in summary.items() if isinstance(v, (int, float))})
        tau_grid = metrics.get("gate", {}).get("diagnostics", {}).get("tau_grid")
        if tau_grid:  # the hybrid gate's τ* search
            tracker.log_table(pd.DataFrame(tau_grid), "tables/tau_grid.json")
        if col.METRICS_RISK_COVERAGE in metrics:
            tracker.log_table(pd.DataFrame(metrics[col.METRICS_RISK_COVERAGE]), "tables/risk_coverage.json")
        for path in artifact_paths(run_dir):
            tracker.log_artifact(str(path), str(path.parent.relative_to(run_dir)) if path.parent != run_dir else None)
        tracker.finish("FINISHED", end_time_ms=clock.get("finished_epoch_ms"))
    except Exception as exc:  # noqa: BLE001 - never lose a finished run to a tracking problem
        destination = getattr(tracker, "destination", None)
        pending.write_text(json.dumps({"destination": destination, "error": f"{type(exc).__name__}: {exc}"}, indent=2))
        uri = f" --tracking-uri {destination}" if destination else ""
        log.warning(
            "tracking failed (%s: %s); nothing is lost: all results are in %s. Upload them later with: python -m acoustlab.upload %s%s",
            type(exc).__name__,
            exc,
            run_dir,
            run_dir,
            uri,
        )
        try:
            tracker.finish("FAILED")
        except Exception:  # noqa: BLE001 - best effort
            pass
        return False
    pending.unlink(missing_ok=True)
    return True
