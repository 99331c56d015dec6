"""The one place that builds and parses column names and result keys shared between modules.

Feature columns are ``<group>__<name>`` with the unit at the end of the name. Prediction tables
(``predictions.parquet``) hold ``<method>_x_m`` / ``<method>_y_m`` / ``error_<method>_m`` per
method and ``radius__<scorer>__<level>`` per conformal scorer and nominal level. Metrics key
levels by ``level_key``. A module that needs one of these names calls a function here instead
of repeating an f-string, so a rename happens in one place.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

from acoustlab.core.errors import DataError

#: Separator between a feature group and the column's name.
GROUP_SEPARATOR = "__"
#: The estimates every prediction table carries, in report order.
ESTIMATORS = ("solver", "model", "gate")
#: …and the oracle: per event the better of solver and model (it needs the truth; a bound on what a gate can reach).
METHODS = (*ESTIMATORS, "oracle")
#: Event tables (written by simulators and field sources, read by the pipeline, protocols and
#: reports): the key, the true source position (NaN where unknown) and the event's weather.
EVENT_ID = "event_id"
POSITION_ID = "position_id"
TRUE_X, TRUE_Y, TRUE_Z = "x_m", "y_m", "z_m"
TRUE_XY = (TRUE_X, TRUE_Y)
TRUE_XYZ = (TRUE_X, TRUE_Y, TRUE_Z)
TEMPERATURE = "temperature_c"
HUMIDITY = "relative_humidity_pct"
#: Speed of sound the simulator used for the event (m/s); field tables may lack it (then derived from the weather).
SPEED_OF_SOUND = "speed_of_sound_m_s"
#: Event SNR (dB) a simulator drew; read by the Cramér–Rao bound.
SNR = "snr_db"
CALL_DURATION = "call_duration_s"
EMISSION_TIME = "emission_time_s"
#: Cramér–Rao bound on the 2-D position error at a test event (m), in prediction tables.
CRB = "crb_m"
#: A detection's window in its recording (s from the file's start; events tables of recordings, positions.csv).
START, END = "start_s", "end_s"
#: A detection's own frequency band (Hz; Raven's Low/High Freq): every GCC of that event uses it where given.
BAND_LOW, BAND_HIGH = "band_low_hz", "band_high_hz"
#: Mic tables (a site's ``mics_csv``, a recordings folder's mics.csv): one row per mic.
MIC_X, MIC_Y, MIC_Z = "x_m", "y_m", "z_m"
MIC_XYZ = (MIC_X, MIC_Y, MIC_Z)
#: A site's ``trees_csv``: one row per trunk.
TREE_X, TREE_Y, TREE_DIAMETER = "x_m", "y_m", "diameter_m"
#: The ``environment`` feature group's weather columns.
ENV_TEMPERATURE = "environment__temperature_c"
ENV_HUMIDITY = "environment__relative_humidity_pct"
ENV_SPEED_OF_SOUND = "environment__speed_of_sound_m_s"
#: The SRP-PHAT feature group's estimate (features=physics_srp).
SRP_X, SRP_Y, SRP_POWER = "srp__x_m", "srp__y_m", "srp__power"
#: positions.csv (protocol=localize) beside x_m, y_m, z_m of the reported estimate.
POSITION_SOLVER_Z = "solver_z_m"
#: Distance between the solver's and the model's estimates (m); also a cue of the learned gate.
SOLVER_MODEL_DISTANCE = "solver_model_distance_m"
POSITION_SOURCE = "source"
#: Prediction tables, beside the estimates: the gate's choice, selective localization, quality.
SUBSTITUTED = "substituted"
PLACED = "placed"
ABSTAIN_REASON = "abstain_reason"
PREDICTED_ERROR = "predicted_error_m"
FOLD = "fold"
WITHHELD_POSITION = "withheld_position"
IN_SUMMARY = "in_summary"
QUALITY_FLAGS = "quality_flags"
HARDWARE_FAILURE = "hardware_failure"
#: events: the mics (indices in the site's order, ";"-separated) whose clip was unusable and are left out of the solve
MICS_DROPPED = "mics_dropped"
#: The mics a field fix rests on, by index in the mics table's order (``;``-separated): neither dropped nor left out by the solver.
MICS_USED = "mics_used"
#: A mics table's column: a mic's survey error per axis, m (0: surveyed); an events table's: its playback spot's (empty or 0: exact).
POSITION_SIGMA = "position_sigma_m"
#: A field fix on a subset of the usable mics with a residual above good fixes' (``acoustlab.method.localizer.with_support_flags``).
WEAK_SUPPORT = "weak_support"
#: Samples of an event's own clip in a batch padded to its longest (the features see only these).
CLIP_SAMPLES = "clip_samples"
#: The solver's point estimate (withheld from the error model).
SOLVER_X, SOLVER_Y = "solver__x_m", "solver__y_m"
SOLVER_ESTIMATE_COLUMNS = (SOLVER_X, SOLVER_Y)
SOLVER_GDOP = "solver__gdop"
SOLVER_SOURCE_HEIGHT = "solver__source_height_m"
SOLVER_FAILURE = "solver__failure"
SOLVER_RESIDUAL = "solver__residual_m"
SOLVER_HEIGHT_GDOP = "solver__height_gdop"
SOLVER_HEIGHT_AMBIGUOUS = "solver__height_ambiguous"
SOLVER_CONSISTENCY = "solver__consistency"
SOLVER_N_MICS_USED = "solver__n_mics_used"
#: The gate's context, an input of the error model beside the features (pipeline.error_model_gate_cues).
GATE_SOLVER_MODEL_DISTANCE = "gate__solver_model_distance_m"
GATE_SUBSTITUTED = "gate__substituted"
GATE_ESTIMATE_GDOP = "gate__estimate_gdop"
GATE_ESTIMATE_RANGE = "gate__estimate_range_m"
#: Why the trust check overrode a gate's choice ('' where it did not; ``acoustlab.method.trust``).
TRUST_REASON = "trust_reason"
#: The extra-gate name under which the configured gate's choice before the trust check is reported (method ``gate_without_trust``).
GATE_WITHOUT_TRUST = "without_trust"
#: Per-axis position error (m) the stated input errors cause at a field detection (carried into its radii).
INPUT_SIGMA = "input_sigma_m"
#: the true source's distance outside the mics' convex hull ÷ the array extent (0 inside)
HULL_DISTANCE = "hull_distance_extent"
#: why a detection's radius at some level is empty (too few calibration positions for that level's guarantee)
RADIUS_NOTE = "radius_note"
#: The trust check's per-row cues (``trust__novelty``, ``trust__solver_outside_support``, …).
TRUST_PREFIX = "trust"


def trust_flag(name: str) -> str:
    """``trust__<name>``: one of the trust check's per-row cues in a prediction table."""
    return f"{TRUST_PREFIX}__{name}"


#: The ``solver`` feature group appended to every feature table (name, unit, definition).
SOLVER_CATALOG = (
    (SOLVER_X, "m", "solver's estimate, x (east)"),
    (SOLVER_Y, "m", "solver's estimate, y (north)"),
    (SOLVER_RESIDUAL, "m", "RMS range-difference residual at the estimate"),
    ("solver__converged", "1", "1 where the iteration converged"),
    (SOLVER_GDOP, "1", "TDOA geometric dilution of precision at the estimate"),
    ("solver__n_roots", "1", "number of distinct positions that fit the TDOAs equally well"),
    (SOLVER_SOURCE_HEIGHT, "m", "source height: assumed by a 2-D solver, estimated by a 3-D one (solver.dimensions=3)"),
    (SOLVER_HEIGHT_GDOP, "1", "factor from range-difference error (m) to height error (m) of a 3-D fix; large near the mics' plane"),
    (SOLVER_HEIGHT_AMBIGUOUS, "1", "1 where a 3-D fix's mirror image about the mics' plane is above ground and fits as well"),
    ("solver__dimensions_used", "1", "3 where the 3-D fix was kept, 2 where it failed or was implausible and the 2-D fix replaced it"),
    ("solver__residual_s", "s", "RMS residual expressed as time"),
    ("solver__conditioning", "1", "condition number of the TDOA Jacobian at the estimate"),
    (SOLVER_FAILURE, "1", "why there is no fix: 0 a fix, 1 no solution, 2 a fix outside the plausible region (then x, y are NaN)"),
    ("solver__consistent_pairs", "1", "mic pairs with a GCC peak consistent with the chosen arrival times (consistent-set solver)"),
    (SOLVER_CONSISTENCY, "1", "share of the pairs among trusted mics that are consistent (consistent-set solver)"),
    ("solver__score_margin", "1", "GCC-height score of the chosen candidate set minus the runner-up's (consistent-set solver)"),
    (SOLVER_N_MICS_USED, "1", "mics trusted for the fix (consistent-set solver)"),
    ("solver__closure_rms_s", "s", "RMS misfit of the chosen pair lags to the fitted arrival times (consistent-set solver)"),
    ("solver__srp_disagreement_m", "m", "distance from the solver's fix to the SRP-PHAT estimate (features=physics_srp)"),
)
RADIUS_PREFIX = "radius"

#: metrics.json blocks (written by reporting.metrics and the app, read by reports, the tracker and benchmarks).
METRICS_ERRORS = "errors"  # per method: n, mean, p50 … p99, share_gt_5m, n_failed
METRICS_COVERAGE = "coverage"  # per scorer and level key: empirical coverage
METRICS_WIDTH = "interval_width"  # per scorer and level key: median_m, mean_m, max_m
METRICS_CI95 = "ci95"  # position-bootstrap 95 % intervals of errors and coverage
METRICS_COVERAGE_BY_POSITION = "coverage_by_position"
METRICS_COVERAGE_BY_CONDITION = "coverage_by_condition"  # per condition (gdop, hull, snr): bins with n and coverage
METRICS_SPEARMAN = "spearman_rho"
METRICS_GROSS_AUC = "gross_error_auc"
METRICS_SUBSTITUTION = "substitution_rate"
METRICS_RISK_COVERAGE = "risk_coverage"
METRICS_GATE_GAP = "gate_gap"
METRICS_LOCALIZATION = "localization"  # protocol=localize: the positions' summary instead of errors
METRICS_GATE = "gate"  # the configured gate: {name, diagnostics, by_split}


def feature(group: str, name: str) -> str:
    """The column ``<group>__<name>``."""
    return f"{group}{GROUP_SEPARATOR}{name}"


def group_of(column: str) -> str:
    """The feature group of a ``group__name`` column.

    Raises
    ------
    DataError
        When the column is not named ``group__name``.
    """
    if GROUP_SEPARATOR not in column:
        raise DataError(f"feature column {column!r} is not named 'group__name'")
    return column.split(GROUP_SEPARATOR, 1)[0]


def groups_in(columns: Iterable[str]) -> set[str]:
    """The feature groups present among ``columns``."""
    return {group_of(c) for c in columns}


# --- feature columns read by more than one module -------------------------------------------


def tdoa_lag(i: int, j: int, rank: int = 1) -> str:
    """``tdoa__lag_i_j_s`` (rank 1, the highest GCC peak) or ``tdoa__lag_i_j_c<rank>_s``: t_j − t_i in s."""
    suffix = "" if rank == 1 else f"_c{rank}"
    return f"tdoa__lag_{i}_{j}{suffix}_s"


def xcorr_peak(i: int, j: int, rank: int) -> str:
    """``xcorr__peak_i_j_c<rank>``: GCC height of pair (i, j)'s candidate of that rank."""
    return f"xcorr__peak_{i}_{j}_c{rank}"


def solver_column(name: str) -> str:
    """A column of the ``solver`` group, e.g. ``solver_column("gdop")`` → ``solver__gdop``."""
    return feature("solver", name)


def level_db(mic: int) -> str:
    """``environment__level_<mic>_db``: received level in the call band, dB."""
    return f"environment__level_{mic}_db"


def noise_db(mic: int) -> str:
    """``environment__noise_<mic>_db``: noise level in the call band, dB."""
    return f"environment__noise_{mic}_db"


def snr_db(mic: int) -> str:
    """``environment__snr_<mic>_db``: received level minus noise level, dB."""
    return f"environment__snr_{mic}_db"


def spectral_centroid_hz(mic: int) -> str:
    """``spectral__centroid_<mic>_hz``."""
    return f"spectral__centroid_{mic}_hz"


def spectral_bandwidth_hz(mic: int) -> str:
    """``spectral__bandwidth_<mic>_hz``."""
    return f"spectral__bandwidth_{mic}_hz"


def ir_spread_s(mic: int) -> str:
    """``ir__spread_<mic>_s``: time the envelope stays within 10 dB of its peak."""
    return f"ir__spread_{mic}_s"


# --- prediction tables and metrics ----------------------------------------------------------


def estimate_xy(method: str) -> tuple[str, str]:
    """``(<method>_x_m, <method>_y_m)``: a method's estimate (or ``"true"``: the truth) in a prediction table."""
    return f"{method}_x_m", f"{method}_y_m"


def error_m(method: str) -> str:
    """``error_<method>_m``: a method's 2-D error in a prediction table."""
    return f"error_{method}_m"


def ellipse(level: float, part: str) -> str:
    """``ellipse__<level>__<part>``: an error ellipse's ``a_m`` (semi-major), ``b_m`` (semi-minor) or ``angle_deg`` (major axis from east)."""
    return f"ellipse__{level_key(level)}__{part}"


#: Prefix of the methods of gates compared beside the configured one (``pipeline.extra_gates``).
EXTRA_GATE_PREFIX = "gate_"


def extra_gate_method(name: str) -> str:
    """``gate_<name>``: the method name of an extra gate (its columns are ``gate_<name>_x_m``, ``error_gate_<name>_m``)."""
    return f"{EXTRA_GATE_PREFIX}{name}"


def methods_in(columns: Iterable[str]) -> list[str]:
    """Every method with an error column: ``METHODS`` present, then the extra gates in column order."""
    present = set(columns)
    extras = [m.group(1) for c in columns if (m := re.fullmatch(rf"error_({EXTRA_GATE_PREFIX}\w+)_m", c))]
    return [m for m in METHODS if error_m(m) in present] + extras


def level_key(level: float) -> str:
    """A nominal coverage level as used in column names and metrics keys (``0.95`` → ``"0.95"``)."""
    return f"{float(level):g}"


def radius(scorer: str, level: float) -> str:
    """``radius__<scorer>__<level>``: a conformal radius in m."""
    return f"{RADIUS_PREFIX}{GROUP_SEPARATOR}{scorer}{GROUP_SEPARATOR}{level_key(level)}"


def one_set_coverage(level: str | float) -> str:
    """``radius_covers_at_least__<level>``: with probability 0.9 over the calibration spots, the share of calls at a new spot
    the radii at that level cover at least (a field calibration only; ``acoustlab.toolkit.conformal.one_set_coverage``)."""
    return f"radius_covers_at_least{GROUP_SEPARATOR}{level_key(float(level))}"


def parse_radius(column: str) -> tuple[str, str] | None:
    """``(scorer, level key)`` of a ``radius__<scorer>__<level>`` column; None for any other column."""
    parts = column.split(GROUP_SEPARATOR)
    if len(parts) != 3 or parts[0] != RADIUS_PREFIX:
        return None
    return parts[1], parts[2]
