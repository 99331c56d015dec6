"""Plugin contracts as ``typing.Protocol`` s.

Every plugin is a class registered by a YAML file with a ``_target_`` in its Hydra config group
(see ``conf/``). The runner only ever talks to plugins through these contracts; runtime inputs
(the site, the sample rate) are passed as arguments, never written into configs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import pandas as pd

from acoustlab.core.types import RecordingBatch, Site

#: Optional properties a plugin may declare (as a class or instance attribute), and the value every
#: plugin that declares none is taken to have, as scikit-learn's estimator tags. Read them with
#: ``declared``; a name not listed here is a programming error (a test scans for others).
OPTIONAL_PROPERTIES: dict[str, Any] = {
    # learned plugins (point and error models, CQR): fit on whole source positions up to this many rows (None: every row)
    "max_train_rows": None,
    # conformal scorers: needs per-level quantile predictions from its own fit_predict_quantiles (CQR); with
    # fit_quantiles / predict_quantiles as well, its final quantile model is fitted once and kept with the method
    "needs_quantiles": False,
    # conformal scorers: "event" or "position" where the scorer can calibrate over source positions (set to "position"
    # when calibrating on field spots); None: it cannot
    "calibration_unit": None,
    # conformal scorers: fit and radius take ``hull_distance`` (the estimate's distance outside the mics' hull, array extents)
    "needs_hull_distance": False,
    # conformal scorers: how a position-level quantile is taken ("pooled", "subsample" or "pac": the rank that covers at least
    # level − pac_epsilon with probability 1 − pac_delta over calibration sets), for the one-set statement and the spots needed
    "position_method": "pooled",
    "pac_delta": 0.1,
    "pac_epsilon": 0.05,
    # protocols and jobs: needs field recordings (checked in the preflight)
    "needs_field": False,
    # simulators and feature sets: bumped by hand to invalidate cached results of an unchanged module
    "cache_version": "0",
    # trackers: the id of the last run sent and where it went (for the upload marker)
    "last_run_id": None,
    "tracking_uri": None,
}
#: Optional hooks a plugin may define; a plugin without one is taken to need nothing there. Get them with ``hook``.
#: ``preflight()`` (models: check what must exist before anything is simulated, e.g. weights), ``validate(site)``
#: (field sources and protocol=season: check tables and headers), ``input_files()`` (field sources: the files whose contents key the
#: cache), ``projection()`` (field sources: the rigid map to map coordinates as ``acoustlab.toolkit.map_frame.map_projection`` returns it, or None), ``fit_quantiles(x, error, levels)``
#: (conformal scorers with ``needs_quantiles``: fit the final quantile model once, applied by their ``predict_quantiles``),
#: ``config_patch(site, field_source, config)`` (protocols and jobs: config changes the job needs, given the resolved config
#: as a plain dict, returned as a plain nested dict merged into it before the context is built, e.g. calibrate's wider GCC
#: lag window; None for none), ``radius_notes(predicted_m, gdop, **region)`` (conformal scorers: (B,) why a row's radii
#: are infinite, '' where they are not, e.g. a Mondrian region without calibration events), ``load_events(site, event_ids)``
#: (field sources: the clips of those events only, as ``load`` cuts them: ``python -m acoustlab.aligned_clips``).
OPTIONAL_HOOKS = (
    "preflight",
    "validate",
    "input_files",
    "projection",
    "fit_quantiles",
    "tables",
    "load_chunks",
    "load_events",
    "config_patch",
    "radius_notes",
)


def declared(plugin: Any, name: str) -> Any:
    """The optional property ``name`` of ``plugin``: its own value, or the default of ``OPTIONAL_PROPERTIES``.

    Raises
    ------
    KeyError
        For a name no contract declares.
    """
    if name not in OPTIONAL_PROPERTIES:
        raise KeyError(f"{name!r} is not an optional plugin property; declared: {sorted(OPTIONAL_PROPERTIES)}")
    return getattr(plugin, name, OPTIONAL_PROPERTIES[name])


def hook(plugin: Any, name: str) -> Callable[..., Any] | None:
    """The optional hook ``name`` of ``plugin`` (a bound method), or None where it defines none.

    Raises
    ------
    KeyError
        For a name no contract declares.
    """
    if name not in OPTIONAL_HOOKS:
        raise KeyError(f"{name!r} is not an optional plugin hook; declared: {list(OPTIONAL_HOOKS)}")
    return getattr(plugin, name, None)


@runtime_checkable
class Simulator(Protocol):
    """Renders labelled multichannel recordings of calls at a site.

    Implementations must derive every random draw of event ``e`` from ``(seed, e)`` only, so that
    an event's audio is identical however events are chunked, sharded or parallelised.
    """

    sample_rate_hz: float

    def validate(self, site: Site) -> None:
        """Raise ``acoustlab.core.errors.ConfigError`` if this simulator cannot run at ``site``."""

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


#: A solver diagnostic that is not a feature: the mics a fix rests on, as bits (mic m adds 2^m). A solver that leaves some of
#: its mics out (the consistent set) reports it; without it every mic given was used.
MICS_USED_MASK = "mics_used_mask"


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


@dataclass(frozen=True)
class SolverInputs:
    """Everything a TDOA solver may read for a batch of events; solvers read nothing else.

    Attributes
    ----------
    mic_positions_m : numpy.ndarray
        (M, 2) or (M, 3) mic positions in m (a missing z is 0).
    tdoa_s : numpy.ndarray
        (B, M) arrival time at each mic minus that at mic 0, s (column 0 is zero).
    speed_of_sound_m_s : float or numpy.ndarray
        Speed of sound, m/s: one value or (B,).
    received_level_db : numpy.ndarray, optional
        (B, M) received level per mic in the call band, dB (the ``environment`` feature group);
        None when those features were not computed.
    pair_lag_candidates_s : numpy.ndarray, optional
        (B, P, K) the K highest GCC peak lags of every mic pair i < j (the ``tdoa`` group with
        candidates), s; None when only one lag per pair exists.
    pair_lag_weights : numpy.ndarray, optional
        (B, P, K) the GCC heights of those candidates (the ``xcorr`` group), finite (NaN counts as 0);
        None when absent.
    source_height_m : float, optional
        The source height to assume, m (the middle of the site's source-height range); a solver's
        own ``source_height_m`` setting takes precedence; None: the mean mic height.
    prior_position_m : numpy.ndarray, optional
        (B, 2) an independent estimate per event (SRP-PHAT's peak, with ``features=physics_srp``)
        a solver may use to break ties between candidate sets; None when absent.
    """

    mic_positions_m: np.ndarray
    tdoa_s: np.ndarray
    speed_of_sound_m_s: float | np.ndarray
    received_level_db: np.ndarray | None = None
    pair_lag_candidates_s: np.ndarray | None = None
    source_height_m: float | None = None
    pair_lag_weights: np.ndarray | None = None
    prior_position_m: np.ndarray | None = None


@runtime_checkable
class Solver(Protocol):
    """Localises sources from time differences of arrival.

    ``required_feature_groups`` names the feature groups whose columns the solver needs (checked
    before anything runs); optional inputs (levels, candidates) are filled when their groups exist.
    """

    required_feature_groups: tuple[str, ...]

    def solve(self, inputs: SolverInputs) -> SolverResult:
        """Positions and diagnostics for every event of ``inputs``."""


@runtime_checkable
class PointModel(Protocol):
    """A scikit-learn regressor (``fit`` returns self, ``predict``, ``get_params``/``set_params``).

    The runner clones it once per coordinate (x and y). A model that must not see more than some
    number of rows (TabPFN: 1,000) may set an attribute ``max_train_rows``; the pipeline then fits
    it on whole source positions up to that many rows, whatever the protocol's budget.
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
    """Chooses, per event, between the solver's and the point model's estimate.

    The pipeline works on a fresh copy of the configured gate for every split: it calls
    ``fit`` on the split's out-of-fold training predictions (a no-op for gates with nothing to
    learn), then ``decide``, and reports ``diagnostics`` per split.
    ``required_feature_groups`` names the feature groups ``decide`` reads (checked before
    anything runs).
    """

    required_feature_groups: tuple[str, ...]

    def fit(
        self,
        solver_position_m: np.ndarray,
        model_position_m: np.ndarray,
        features: pd.DataFrame,
        site: Site,
        truth_m: np.ndarray,
        groups: np.ndarray | None = None,
    ) -> Any:
        """Learn what the gate needs from simulated training events with known positions; return self.

        ``model_position_m`` are out-of-fold predictions; ``groups`` are the events' source
        positions (a gate that cross-validates itself keeps them apart).
        """

    def decide(self, solver_position_m: np.ndarray, model_position_m: np.ndarray, features: pd.DataFrame, site: Site) -> GateDecision:
        """Return the hybrid estimate; ``features`` holds the events' feature rows in the same order."""

    def diagnostics(self) -> dict[str, Any]:
        """JSON-serialisable facts about the fitted gate (e.g. the chosen threshold); {} when none."""


class StatelessGate:
    """Mixin for gates that learn nothing: ``fit`` returns self, ``diagnostics`` is empty."""

    required_feature_groups: tuple[str, ...] = ()

    def fit(
        self,
        solver_position_m: np.ndarray,
        model_position_m: np.ndarray,
        features: pd.DataFrame,
        site: Site,
        truth_m: np.ndarray,
        groups: np.ndarray | None = None,
    ) -> Any:
        """Nothing to learn."""
        return self

    def diagnostics(self) -> dict[str, Any]:
        """No diagnostics."""
        return {}


@runtime_checkable
class ErrorModel(Protocol):
    """Predicts the scale of the hybrid estimate's 2-D error (m) from features (scikit-learn style).

    May set ``max_train_rows`` as a ``PointModel`` may.
    """

    def fit(self, X: pd.DataFrame, error_m: np.ndarray) -> Any: ...

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        """(B,) predicted error scale in m (positive)."""


@runtime_checkable
class ConformalScorer(Protocol):
    """Turns predicted errors into calibrated radii at nominal coverage levels."""

    def fit(
        self, error_m: np.ndarray, predicted_m: np.ndarray, gdop: np.ndarray, levels: list[float], groups: np.ndarray | None = None
    ) -> Any:
        """Calibrate on held-out errors (m), the error model's predictions (m), GDOP and the events' positions (``groups``)."""

    def radius(self, predicted_m: np.ndarray, gdop: np.ndarray) -> np.ndarray:
        """(B, L) radii in m, one column per calibrated level."""


@runtime_checkable
class EvaluationProtocol(Protocol):
    """Decides which events train, calibrate and test, and runs the localization pipeline on them (sim_only, cross_fit,
    field_eval, lopo): the run has ground truth, and the app writes error and coverage metrics.

    May declare ``needs_field`` (``OPTIONAL_PROPERTIES``). ``dataset`` and ``field_recordings`` are
    ``acoustlab.stages.dataset.Dataset`` s, ``pipeline`` a ``acoustlab.method.pipeline.LocalizationPipeline``
    (typed loosely: this layer is below both).
    """

    def run(self, dataset: Any, pipeline: Any, field_recordings: Any = None) -> Any:
        """Fit and predict; returns a ``acoustlab.method.pipeline.MethodResult``."""


@runtime_checkable
class Job(Protocol):
    """A kind of run that is not an evaluation (localize, season, calibrate): it gets its data from the run's context and
    writes its own results into the run folder.

    ``context`` is an ``acoustlab.method.run_context.RunContext`` (typed loosely: this layer is below it): the site,
    the configured plugins, the cache, the field source, the calibration and plain settings. May declare
    ``needs_field`` and define the hooks ``validate(site)`` and ``config_patch(site, field_source, config)``.
    """

    def run_job(self, context: Any, run_dir: Path) -> dict[str, Any]:
        """Run the job; returns what ``metrics.json`` in ``run_dir`` holds (the job writes it)."""


@runtime_checkable
class FieldSource(Protocol):
    """Supplies field recordings with known or unknown source positions."""

    def load(self, site: Site) -> RecordingBatch:
        """All field events; unknown true positions are NaN, ``position_id`` groups repeated playbacks.

        A source may also offer ``load_chunks(site)`` (an optional hook): the same events as batches
        of a bounded size, which the field stage then reads one at a time.
        """


@runtime_checkable
class Tracker(Protocol):
    """Records a run's parameters, metrics, tables and artifacts (e.g. in MLflow).

    A sweep (Hydra multirun) gets one parent run opened by ``open_sweep`` before its jobs and
    closed by ``close_sweep`` after them; each job's run names it as ``parent_run_id``.
    """

    #: Where runs go, for messages (e.g. the tracking URI); None when nothing is recorded.
    destination: str | None

    def check_reachable(self) -> None:
        """Raise an exception saying why when the store cannot be reached (before anything is logged)."""
        ...

    def start(
        self,
        run_name: str,
        params: dict[str, Any],
        tags: dict[str, str],
        parent_run_id: str | None = None,
        start_time_ms: int | None = None,
    ) -> None:
        """Open a run; ``start_time_ms`` (Unix epoch, ms) is when the job really started (a run logged after it finished)."""
        ...

    def log_metrics(self, metrics: dict[str, float]) -> None: ...

    def log_table(self, table: pd.DataFrame, artifact_file: str) -> None: ...

    def log_artifact(self, path: str, artifact_path: str | None = None) -> None:
        """Upload one file, under the folder ``artifact_path`` of the run's artifacts (None: at their root)."""
        ...

    def finish(self, status: str = "FINISHED", end_time_ms: int | None = None) -> None:
        """Close the run with FINISHED, FAILED or KILLED; ``end_time_ms`` (Unix epoch, ms) when the job really ended."""
        ...

    def open_sweep(self, run_name: str, params: dict[str, Any], tags: dict[str, str]) -> str | None:
        """Create a sweep's parent run (not made active) and return its id; None when not tracked."""
        ...

    def close_sweep(self, run_id: str, status: str, tables: dict[str, pd.DataFrame], artifact_dirs: list[str]) -> None:
        """Log the sweep's summary tables and artifact directories into its parent run and end it."""
        ...
