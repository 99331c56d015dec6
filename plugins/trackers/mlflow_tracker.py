"""MLflow tracker: one MLflow run per job, in an embedded SQLite store by default."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import pandas as pd

log = logging.getLogger(__name__)

#: MLflow refuses parameter values longer than this many characters.
_MAX_PARAM_CHARS = 6000


class MlflowTracker:
    """Logs params, metrics, tables and artifacts of a run to MLflow.

    Parameters
    ----------
    experiment_name : str
        MLflow experiment to log into (created if missing).
    tracking_uri : str, optional
        Tracking URI (``http://host:5000`` for a server); None means the SQLite store
        ``<store_dir>/mlflow.db``.
    store_dir : str
        Directory of the default SQLite store (usually ``outputs/``).
    """

    def __init__(self, experiment_name: str = "acoustlab", tracking_uri: str | None = None, store_dir: str = "outputs") -> None:
        self.experiment_name = experiment_name
        self.store_dir = store_dir
        self.tracking_uri = tracking_uri or f"sqlite:///{Path(store_dir).resolve() / 'mlflow.db'}"
        self._run = None

    def start(self, run_name: str, params: dict[str, Any], tags: dict[str, str]) -> None:
        """Open the run and log params (values longer than MLflow allows are truncated) and tags."""
        import mlflow

        if self.tracking_uri.startswith("sqlite:///"):
            Path(self.tracking_uri[len("sqlite:///") :]).parent.mkdir(parents=True, exist_ok=True)
        mlflow.set_tracking_uri(self.tracking_uri)
        mlflow.set_experiment(self.experiment_name)
        parent = os.environ.get("ACOUSTLAB_PARENT_RUN_ID")
        self._run = mlflow.start_run(run_name=run_name, tags=tags, parent_run_id=parent or None)
        clean = {k[:250]: str(v)[:_MAX_PARAM_CHARS] for k, v in params.items()}
        mlflow.log_params(clean)
        log.info("MLflow run %s in %s (experiment %r)", self._run.info.run_id, self.tracking_uri, self.experiment_name)

    @property
    def run_id(self) -> str | None:
        """The active run's id, once started."""
        return None if self._run is None else self._run.info.run_id

    def log_metrics(self, metrics: dict[str, float]) -> None:
        """Log scalar metrics (names may contain '/', '.', '_')."""
        import mlflow

        mlflow.log_metrics({k: float(v) for k, v in metrics.items()})

    def log_table(self, table: pd.DataFrame, artifact_file: str) -> None:
        """Log a table with :func:`mlflow.log_table` (shown in the MLflow UI's evaluation view)."""
        import mlflow

        mlflow.log_table(data=table, artifact_file=artifact_file)

    def log_artifact(self, path: str) -> None:
        """Upload a file or directory as an artifact."""
        import mlflow

        if Path(path).is_dir():
            mlflow.log_artifacts(path, artifact_path=Path(path).name)
        else:
            mlflow.log_artifact(path)

    def finish(self, status: str = "FINISHED") -> None:
        """Close the run with ``status`` (FINISHED or FAILED)."""
        import mlflow

        if self._run is not None:
            mlflow.end_run(status=status)
            self._run = None
