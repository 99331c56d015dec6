"""Plugin contracts as :class:`typing.Protocol` s.

Every plugin is a class registered by a YAML file with a ``_target_`` in its Hydra config group
(see ``conf/``). The runner only ever talks to plugins through these contracts; runtime inputs
(the site, the sample rate) are passed as arguments, never written into configs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
import pandas as pd

from acoustlab.data import RecordingBatch, Site


@runtime_checkable
class Simulator(Protocol):
    """Renders labelled multichannel recordings of calls at a site.

    Implementations must derive every random draw of event ``e`` from ``(seed, e)`` only, so that
    an event's audio is identical however events are chunked, sharded or parallelised.
    """

    sample_rate_hz: float

    def validate(self, site: Site) -> None:
        """Raise :class:`acoustlab.errors.ConfigError` if this simulator cannot run at ``site``."""

    def simulate(self, site: Site, event_ids: np.ndarray, position_ids: np.ndarray, seed: int) -> RecordingBatch:
        """Render events ``event_ids`` (int array) at source positions ``position_ids`` with base seed ``seed``.

        Events that share a position id share the source position (drawn from ``(seed, position_id)``).
        """


@runtime_checkable
class FeatureSet(Protocol):
    """One ablatable group of features; columns are named ``<group>__<name>`` with units in the name."""

    group: str

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        """(column name, unit, definition) of every column ``transform`` returns, in order."""

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        """One row per event of ``batch`` (same order), columns ``group__name``, all float."""


@dataclass
class SolverResult:
    """Output of a TDOA solver for a batch of events.

    Attributes
    ----------
    position_m : numpy.ndarray
        (B, 2) estimated source positions in m.
    residual_m : numpy.ndarray
        (B,) RMS range-difference residual in m.
    converged : numpy.ndarray
        (B,) bool, True where the iteration converged.
    diagnostics : dict of str to numpy.ndarray
        Further (B,) diagnostics named with units (e.g. ``n_roots``, ``gdop``).
    """

    position_m: np.ndarray
    residual_m: np.ndarray
    converged: np.ndarray
    diagnostics: dict[str, np.ndarray] = field(default_factory=dict)


@runtime_checkable
class Solver(Protocol):
    """Localises sources from time differences of arrival."""

    def solve(
        self,
        mic_positions_m: np.ndarray,
        tdoa_s: np.ndarray,
        speed_of_sound_m_s: float | np.ndarray,
    ) -> SolverResult:
        """Positions from TDOAs.

        ``mic_positions_m`` is (M, 2) or (M, 3); ``tdoa_s`` is (B, M), the arrival time at each
        mic minus that at mic 0 (column 0 is zero); ``speed_of_sound_m_s`` a float or (B,).
        Solvers that can use received levels accept an optional ``received_level_db`` (B, M)
        keyword; the pipeline passes it when the ``environment`` features exist.
        """


@runtime_checkable
class PointModel(Protocol):
    """A scikit-learn regressor (``fit`` returns self, ``predict``, ``get_params``/``set_params``).

    The runner clones it once per coordinate (x and y).
    """

    def fit(self, X: Any, y: Any) -> Any: ...

    def predict(self, X: Any) -> np.ndarray: ...

    def get_params(self, deep: bool = True) -> dict[str, Any]: ...

    def set_params(self, **params: Any) -> Any: ...


@dataclass
class GateDecision:
    """Where a gate took the model's estimate instead of the solver's.

    Attributes
    ----------
    position_m : numpy.ndarray
        (B, 2) chosen estimate in m.
    substituted : numpy.ndarray
        (B,) bool, True where the model's estimate replaced the solver's.
    """

    position_m: np.ndarray
    substituted: np.ndarray


@runtime_checkable
class Gate(Protocol):
    """Chooses, per event, between the solver's and the point model's estimate."""

    def decide(
        self, solver_position_m: np.ndarray, model_position_m: np.ndarray, features: pd.DataFrame, site: Site
    ) -> GateDecision:
        """Return the hybrid estimate; ``features`` holds the events' feature rows in the same order."""


@runtime_checkable
class ErrorModel(Protocol):
    """Predicts the scale of the hybrid estimate's 2-D error (m) from features (scikit-learn style)."""

    def fit(self, X: pd.DataFrame, error_m: np.ndarray) -> Any: ...

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        """(B,) predicted error scale in m (positive)."""


@runtime_checkable
class ConformalScorer(Protocol):
    """Turns predicted errors into calibrated radii at nominal coverage levels."""

    def fit(self, error_m: np.ndarray, predicted_m: np.ndarray, gdop: np.ndarray, levels: list[float]) -> Any:
        """Calibrate on held-out errors (m), the error model's predictions (m) and GDOP."""

    def radius(self, predicted_m: np.ndarray, gdop: np.ndarray) -> np.ndarray:
        """(B, L) radii in m, one column per calibrated level."""


@runtime_checkable
class FieldSource(Protocol):
    """Supplies field recordings with known or unknown source positions."""

    def load(self, site: Site) -> RecordingBatch:
        """All field events; unknown true positions are NaN, ``position_id`` groups repeated playbacks."""


@runtime_checkable
class Tracker(Protocol):
    """Records a run's parameters, metrics, tables and artifacts (e.g. in MLflow).

    A sweep (Hydra multirun) gets one parent run opened by :meth:`open_sweep` before its jobs and
    closed by :meth:`close_sweep` after them; each job's run names it as ``parent_run_id``.
    """

    #: Where runs go, for messages (e.g. the tracking URI); None when nothing is recorded.
    destination: str | None

    def check_reachable(self) -> None:
        """Raise an exception saying why when the store cannot be reached (before anything is logged)."""
        ...

    def start(self, run_name: str, params: dict[str, Any], tags: dict[str, str], parent_run_id: str | None = None) -> None: ...

    def log_metrics(self, metrics: dict[str, float]) -> None: ...

    def log_table(self, table: pd.DataFrame, artifact_file: str) -> None: ...

    def log_artifact(self, path: str) -> None: ...

    def finish(self, status: str = "FINISHED") -> None: ...

    def open_sweep(self, run_name: str, params: dict[str, Any], tags: dict[str, str]) -> str | None:
        """Create a sweep's parent run (not made active) and return its id; None when not tracked."""
        ...

    def close_sweep(self, run_id: str, status: str, tables: dict[str, pd.DataFrame], artifact_dirs: list[str]) -> None:
        """Log the sweep's summary tables and artifact directories into its parent run and end it."""
        ...
