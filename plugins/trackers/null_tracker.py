"""A tracker that records nothing beyond the run directory (``tracking=none``)."""

from __future__ import annotations

from typing import Any

import pandas as pd


class NullTracker:
    """Keeps results only in the run directory; every call is a no-op."""

    destination = None

    def check_reachable(self) -> None:
        """Nothing to reach."""

    def start(
        self,
        run_name: str,
        params: dict[str, Any],
        tags: dict[str, str],
        parent_run_id: str | None = None,
        start_time_ms: int | None = None,
    ) -> None:
        """Do nothing."""

    def log_metrics(self, metrics: dict[str, float]) -> None:
        """Do nothing."""

    def log_table(self, table: pd.DataFrame, artifact_file: str) -> None:
        """Do nothing."""

    def log_artifact(self, path: str, artifact_path: str | None = None) -> None:
        """Do nothing."""

    def finish(self, status: str = "FINISHED", end_time_ms: int | None = None) -> None:
        """Do nothing."""

    def open_sweep(self, run_name: str, params: dict[str, Any], tags: dict[str, str]) -> None:
        """No parent run."""
        return None

    def close_sweep(self, run_id: str, status: str, tables: dict[str, pd.DataFrame], artifact_dirs: list[str]) -> None:
        """Do nothing."""
