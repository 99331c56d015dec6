"""acoustlab from Python: localize recordings or a season, or solve time differences, and get a table back.

The functions take the command line's settings as keyword arguments (nested dicts for config
groups) and return pandas tables, so a notebook needs one import::

    from acoustlab.api import localize

    positions = localize(
        "loca2021",
        field={"mics_csv": "mics.csv", "events_csv": "events.csv", "audio_dir": "audio"},
        features={"gcc": {"band_hz": [6000, 10500]}},
        solver={"dimensions": 3},
    )

They run exactly what ``python -m acoustlab localize +site=loca2021 field=recordings ...`` runs (the
same config, checks and cache), writing the run folder too; ``run_dir`` says where (default: a new
folder under ``outputs/api/``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import logging
import sys
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.playback_signal import write_playback_sweep as write_playback_sweep  # what to play back (docs/calibrate.md)

if TYPE_CHECKING:
    from acoustlab.method.localizer import FittedLocalizer


def overrides_from(settings: Mapping[str, Any], prefix: str = "") -> list[str]:
    """Hydra overrides (``key.sub=value``) for nested settings; strings are quoted, lists written as lists.

    Examples
    --------
    >>> overrides_from({"field": {"audio_dir": "my audio"}, "solver": {"dimensions": 3}})
    ["field.audio_dir='my audio'", 'solver.dimensions=3']
    """
    out = []
    for key, value in settings.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out += overrides_from(value, f"{name}.")
        else:
            out.append(f"{name}={_value(value)}")
    return out


def _value(value: Any) -> str:
    """One value in Hydra's override grammar."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float, np.integer, np.floating)):
        return repr(float(value)) if isinstance(value, (float, np.floating)) else str(int(value))
    if isinstance(value, (str, Path)):
        return "'" + str(value).replace("\\", "\\\\").replace("'", "\\'") + "'"
    if isinstance(value, Sequence):
        return "[" + ",".join(_value(v) for v in value) + "]"
    raise ConfigError(f"a setting must be a number, string, path, bool, None or list; got {type(value).__name__} {value!r}")


#: The loggers a call's progress is shown from (acoustlab's stages and the plugins').
_PROGRESS_LOGGERS = ("acoustlab", "plugins")


@contextlib.contextmanager
def progress_shown(verbose: bool = True) -> Iterator[None]:
    """Show acoustlab's progress lines (INFO) on stderr for the duration of a call, as the command line does.

    Where the caller configured logging (a handler on the root or acoustlab logger), that is left
    alone. ``verbose=False`` keeps only warnings and errors.
    """
    loggers = [logging.getLogger(name) for name in _PROGRESS_LOGGERS]
    levels = [lg.level for lg in loggers]
    handler = None
    if not verbose:
        for lg in loggers:
            lg.setLevel(logging.WARNING)
    elif not logging.getLogger().handlers and not any(lg.handlers for lg in loggers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S"))
        for lg in loggers:
            lg.addHandler(handler)
            lg.setLevel(logging.INFO)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)
            if handler is not None:
                lg.removeHandler(handler)


def _run(
    protocol: str, site: str, overrides: Sequence[str], run_dir: str | Path | None, settings: Mapping[str, Any], verbose: bool = True
) -> tuple[Path, Any, list[str]]:
    """Compose the config as the command line would, run the job; its run folder, its built plugins and the overrides."""
    from acoustlab.run.app import build_run, run_experiment
    from acoustlab.run.plugin_checks import compose_config
    from acoustlab.run.preflight import check_argv

    given = [f"+site={site}", f"protocol={protocol}", *overrides_from(settings), *overrides]
    check_argv(given)
    cfg = compose_config(given)
    folder = Path(run_dir) if run_dir is not None else Path("outputs") / "api" / datetime.datetime.now().strftime("%Y-%m-%d_%H-%M-%S-%f")
    with progress_shown(verbose):
        built = build_run(cfg)
        run_experiment(cfg, folder, built=built)
    return folder, built, given


def place(method: FittedLocalizer, *, overrides: Sequence[str] = (), verbose: bool = True, **settings: Any) -> pd.DataFrame:
    """Place other recordings of the same array with a method ``localize(..., return_method=True)`` fitted; no fit again.

    Everything but the recordings stays as fitted: site, calibration, features, solver, models, gate
    and radii. Only ``field`` settings may change (the rest of ``field`` as first given), e.g.
    ``place(method, field={"events_csv": "night2.csv"})``; the answer is the positions table
    ``localize`` would write for those detections, row for row (the same ``FittedLocalizer.place``).
    Rows with a known ``x_m, y_m`` are playbacks and are skipped. Nothing is written to disk.

    Parameters
    ----------
    method : FittedLocalizer
        What ``localize(..., return_method=True)`` returned.
    overrides : sequence of str, optional
        ``field.*`` overrides as on the command line.
    verbose : bool
        Show progress lines (default); ``False`` shows only warnings.
    **settings
        Only ``field={...}``.

    Raises
    ------
    ConfigError
        For a setting outside ``field``, or recordings with nothing to place.
    """
    from acoustlab.method.localizer import unknown_position_rows
    from acoustlab.run.app import build_run, prepare_field
    from acoustlab.run.plugin_checks import compose_config

    changed = [*overrides_from(settings), *overrides]
    outside = [o for o in changed if not o.startswith("field.")]
    if outside:
        raise ConfigError(f"a fitted method places other recordings: only field.* settings may change; got {outside[0]!r}")
    cfg = compose_config([*method.recipe, *changed])
    with progress_shown(verbose):
        built = build_run(cfg)
        data = prepare_field(cfg, built)
        rows = unknown_position_rows(data.events)
        if rows.size == 0:
            raise ConfigError("every detection of these recordings has a known position (x_m, y_m): there is nothing to place")
        return method.place_solved(data.features.iloc[rows], data.events.iloc[rows]).positions


def localize(
    site: str,
    *,
    overrides: Sequence[str] = (),
    run_dir: str | Path | None = None,
    return_method: bool = False,
    verbose: bool = True,
    **settings: Any,
) -> pd.DataFrame | tuple[pd.DataFrame, FittedLocalizer]:
    """Place every detection of your recordings, as ``python -m acoustlab localize``; the positions table.

    Parameters
    ----------
    site : str
        A site of ``conf/site`` (``"recordings"`` for your own array: its mics from ``field={"mics_csv": ...}``).
    overrides : sequence of str, optional
        Command-line overrides as they are written there (``"+experiment=smoke"``).
    run_dir : str or Path, optional
        The run folder (default: a new one under ``outputs/api/``).
    return_method : bool
        Also return the fitted method (``acoustlab.method.localizer.FittedLocalizer``):
        ``place(method, field={...})`` places more recordings of the same array without fitting again.
    verbose : bool
        Show the run's progress lines on stderr, as the command line does (default; where you configured
        logging yourself it is left alone); ``False`` shows only warnings and errors.
    **settings
        Config groups as nested dicts: ``field={"mics_csv": ..., "events_csv": ..., "audio_dir": ...}``,
        ``solver={"dimensions": 3}``; ``field`` defaults to ``recordings``; ``calibration="…/calibration.json"``
        applies a field calibration (``calibrate``).

    Returns
    -------
    pandas.DataFrame
        One row per detection, the columns of ``positions.csv`` (docs/localize.md): ``x_m, y_m,
        z_m`` in m, ``source``, the radii ``radius_<scorer>_<level>_m`` in m, the solver's diagnostics;
        with ``return_method``, ``(positions, method)``.
    """
    overrides = ["field=recordings", *overrides] if not any(o.startswith("field=") for o in overrides) else list(overrides)
    folder, built, given = _run("localize", site, overrides, run_dir, settings, verbose)
    positions = pd.read_parquet(folder / "positions.parquet")
    return (positions, dataclasses.replace(built.protocol.fitted, recipe=tuple(given))) if return_method else positions


def calibrate(
    site: str, *, overrides: Sequence[str] = (), run_dir: str | Path | None = None, verbose: bool = True, **settings: Any
) -> dict[str, Any]:
    """Calibrate the array from playbacks at known spots, as ``python -m acoustlab calibrate``; the calibration.

    The recordings' events with ``x_m, y_m`` are the playbacks (docs/calibrate.md); the other
    parameters are ``localize``'s. The calibration file is ``<run_dir>/calibration.json``: pass its
    path as ``calibration=`` to ``localize`` or ``season``.

    Returns
    -------
    dict
        The content of calibration.json (mic positions in m, thermometer offset in °C, clock offsets in s, …)
        with ``path``, the file.
    """
    overrides = ["field=recordings", *overrides] if not any(o.startswith("field=") for o in overrides) else list(overrides)
    folder, _, _ = _run("calibrate", site, overrides, run_dir, settings, verbose)
    return {**json.loads((folder / "calibration.json").read_text()), "path": str(folder / "calibration.json")}


def _solve_arguments(mic_positions_m: Any, tdoa_s: Any, speed_of_sound_m_s: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | float]:
    """``solve``'s arguments as arrays, each checked by name (shapes, finite mics, a speed of sound in air's range)."""

    def numbers(name: str, value: Any) -> np.ndarray:
        try:
            return np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise ConfigError(f"solve: {name} must be numbers; got {type(value).__name__}") from None

    mics = numbers("mic_positions_m", mic_positions_m)
    if mics.ndim != 2 or mics.shape[1] not in (2, 3) or mics.shape[0] < 3 or not np.isfinite(mics).all():
        raise ConfigError(f"solve: mic_positions_m must be (M, 2) or (M, 3) finite positions in m with M >= 3; got shape {mics.shape}")
    tdoa = np.atleast_2d(numbers("tdoa_s", tdoa_s))
    if tdoa.ndim != 2 or tdoa.shape[1] != mics.shape[0]:
        raise ConfigError(f"solve: tdoa_s must be (E, {mics.shape[0]}) or ({mics.shape[0]},), one per mic; got shape {tdoa.shape}")
    speed = numbers(col.SPEED_OF_SOUND, speed_of_sound_m_s)  # the argument is named after the events table's column
    if speed.ndim > 1 or (speed.ndim == 1 and speed.shape[0] != tdoa.shape[0]):
        raise ConfigError(f"solve: speed_of_sound_m_s must be one value or {tdoa.shape[0]} (one per event); got shape {speed.shape}")
    if not np.isfinite(speed).all() or (speed < 200).any() or (speed > 450).any():
        raise ConfigError(f"solve: speed_of_sound_m_s must lie in 200–450 m/s (air from −70 to +230 °C); got {speed_of_sound_m_s}")
    return mics, tdoa, float(speed) if speed.ndim == 0 else speed


def plan_playbacks(
    site: str,
    n_spots: int,
    *,
    position_sigma_m: float | Sequence[float] = 2.0,
    candidates_xy_m: np.ndarray | None = None,
    source_height_m: float | None = None,
    min_mic_distance_m: float | None = None,
    overrides: Sequence[str] = (),
    **settings: Any,
) -> pd.DataFrame:
    """Where to play back for ``calibrate``: ``n_spots`` spots chosen for the stated array (docs/calibrate.md).

    What to play there: the sweep ``write_playback_sweep`` writes (a song's cross-correlation has
    near-equal peaks one period apart, and from few spots the calibration can take wrong ones).

    Parameters
    ----------
    site : str
        The site (its mics as stated, e.g. ``field={"mics_csv": "mics.csv"}`` in ``settings``).
    n_spots : int
        Spots to play back from (≥ 3).
    position_sigma_m : float or sequence of float
        The mics' stated horizontal error per axis, m (one value, or one per mic; 0 for a surveyed mic).
    candidates_xy_m : numpy.ndarray, optional
        (C, 2) the spots a field team can reach, m; default a grid over the array grown by 0.3 × its extent.
    source_height_m : float, optional
        The speaker's height, m (default the site's assumed source height).
    min_mic_distance_m : float, optional
        No spot nearer a stated mic than this, m (default 5 × the largest ``position_sigma_m``, at least 3 m).

    Returns
    -------
    pandas.DataFrame
        One row per spot in the order chosen: ``position_id`` (``spot_01`` …), ``x_m``, ``y_m``,
        ``z_m`` and ``predicted_mic_sd_m``, the root-mean-square standard deviation of the mics'
        coordinates a calibration from the spots so far would leave (timing noise only: a lower bound).
        Add a playback's time and clip to each row and it is ``calibrate``'s events table.
    """
    from acoustlab.method.protocols.calibrate import CalibrateProtocol
    from acoustlab.toolkit.event_physics import assumed_source_height_m
    from acoustlab.toolkit.playback_plan import plan_playbacks as plan

    if isinstance(n_spots, bool) or not isinstance(n_spots, (int, np.integer)) or n_spots < 3:
        raise ConfigError(f"plan_playbacks: n_spots must be a whole number >= 3; got {n_spots!r}")
    if source_height_m is not None and not (isinstance(source_height_m, (int, float)) and np.isfinite(source_height_m)):
        raise ConfigError(f"plan_playbacks: source_height_m must be a finite number of metres; got {source_height_m!r}")
    if min_mic_distance_m is not None and not (isinstance(min_mic_distance_m, (int, float)) and min_mic_distance_m >= 0):
        raise ConfigError(f"plan_playbacks: min_mic_distance_m must be a number of metres >= 0; got {min_mic_distance_m!r}")
    if candidates_xy_m is not None:
        candidates = np.asarray(candidates_xy_m)
        if (
            candidates.ndim != 2
            or candidates.shape[1] != 2
            or not np.issubdtype(candidates.dtype, np.number)
            or not np.isfinite(candidates).all()
        ):
            raise ConfigError(f"plan_playbacks: candidates_xy_m must be a (C, 2) array of finite x, y in m; got shape {candidates.shape}")
    built = load_site(site, overrides=overrides, **settings)
    sigma = (
        np.broadcast_to(np.asarray(position_sigma_m, dtype=float), (built.n_mics,))
        if np.ndim(position_sigma_m) == 0
        else np.asarray(position_sigma_m, dtype=float)
    )
    if sigma.shape != (built.n_mics,) or not np.isfinite(sigma).all() or (sigma < 0).any():
        raise ConfigError(f"plan_playbacks: position_sigma_m must be one number >= 0 or {built.n_mics} of them (m); got {position_sigma_m}")
    priors = dataclasses.replace(CalibrateProtocol().priors(built, None), position_sigma_m=sigma.copy())
    height = assumed_source_height_m(built) if source_height_m is None else float(source_height_m)
    result = plan(priors, n_spots, candidates_xy_m=candidates_xy_m, source_height_m=height, min_mic_distance_m=min_mic_distance_m)
    return pd.DataFrame(
        {
            col.POSITION_ID: [f"spot_{k + 1:02d}" for k in range(n_spots)],
            col.TRUE_X: result.spots_m[:, 0],
            col.TRUE_Y: result.spots_m[:, 1],
            col.TRUE_Z: result.spots_m[:, 2],
            "predicted_mic_sd_m": result.predicted_sd_m,
        }
    )


def season(
    site: str, *, overrides: Sequence[str] = (), run_dir: str | Path | None = None, verbose: bool = True, **settings: Any
) -> pd.DataFrame:
    """Localize a season of long recordings from detector tables, as ``python -m acoustlab season``; the positions table.

    ``protocol={"recordings": {"audio_dir": ...}, "detections": {"paths": [...], "format": "raven"}}`` names
    the inputs (docs/season.md); the other parameters are ``localize``'s.
    """
    folder, _, _ = _run("season", site, list(overrides), run_dir, settings, verbose)
    return pd.read_parquet(folder / "positions.parquet")


def aligned_clips(run_dir: str | Path, events: Sequence[object], out_dir: str | Path | None = None) -> list[Path]:
    """Each event's clips aligned by its time differences, with each mic's residual at the fix, as
    ``python -m acoustlab.aligned_clips`` writes them (``RUN_DIR/aligned/event_<id>.wav`` and ``.csv``); the WAV paths.

    ``events``: event ids as ``positions.csv`` gives them; ``run_dir``: a ``localize`` or ``season`` run's folder.
    """
    from acoustlab.aligned_clips import write_aligned_clips

    return write_aligned_clips(run_dir, events, out_dir)


def solve(
    mic_positions_m: np.ndarray,
    tdoa_s: np.ndarray,
    speed_of_sound_m_s: float | np.ndarray = 343.0,
    *,
    solver: str = "hyperbolic",
    source_height_m: float = 0.0,
    **params: Any,
) -> pd.DataFrame:
    """Positions from time differences you already have, with the solver's diagnostics as columns.

    Parameters
    ----------
    mic_positions_m : array (M, 2) or (M, 3)
        Mic positions in m (local frame, x east, y north, z up).
    tdoa_s : array (E, M) or (M,)
        Arrival time at each mic minus that at mic 0, s, one row per event.
    speed_of_sound_m_s : float or array (E,)
        m/s.
    solver : {"hyperbolic", "least_squares"}
        ``hyperbolic`` (closed form + polish; ``dimensions=3`` for x, y and height with ≥ 4 mics) or
        ``least_squares``. The consistent-set solver needs GCC candidates, not time differences.
    source_height_m : float
        The height a 2-D fix assumes, m.
    **params
        The solver's options (``conf/solver/<solver>.yaml``), e.g. ``dimensions=3``.

    Returns
    -------
    pandas.DataFrame
        ``x_m, y_m, z_m`` (m; NaN where there is no fix), ``residual_m``, ``converged`` and every
        diagnostic (``gdop``, ``n_roots``, ``height_gdop``, ...).
    """
    from acoustlab.core.contracts import SolverInputs
    from acoustlab.run.plugin_checks import compose_config
    from acoustlab.run.registry import build

    if solver not in ("hyperbolic", "least_squares"):
        raise ConfigError(f"solve: solver must be hyperbolic or least_squares; got {solver!r}")
    mics, tdoa, speed = _solve_arguments(mic_positions_m, tdoa_s, speed_of_sound_m_s)
    cfg = compose_config([f"solver={solver}", *overrides_from({"solver": {"source_height_m": source_height_m, **params}})])
    result = build(cfg.solver, "solver").solve(SolverInputs(mic_positions_m=mics, tdoa_s=tdoa, speed_of_sound_m_s=speed))
    table = pd.DataFrame({col.TRUE_X: result.position_m[:, 0], col.TRUE_Y: result.position_m[:, 1]})  # positions.csv's names
    table[col.TRUE_Z] = result.diagnostics.get("source_height_m", np.full(len(table), source_height_m))
    table.loc[table[col.TRUE_X].isna(), col.TRUE_Z] = np.nan
    table["residual_m"] = result.residual_m
    table["converged"] = result.converged
    for name, values in result.diagnostics.items():
        if name != "source_height_m":
            table[name] = values
    return table


def load_site(site: str, *, overrides: Sequence[str] = (), **settings: Any) -> Any:
    """A site as every run builds it (``conf/site/<site>.yaml`` with ``settings``, e.g. ``field={"mics_csv": ...}``).

    Returns
    -------
    acoustlab.core.types.Site
        ``mic_positions_m`` (M, 3), ``mic_pairs``, trees, weather and source-height ranges, …
    """
    from acoustlab.run.plugin_checks import compose_config
    from acoustlab.run.preflight import check_argv
    from acoustlab.stages.sites import site_from_config

    field = ["field=recordings"] if "field" in settings and not any(o.startswith("field=") for o in overrides) else []
    given = [f"+site={site}", *field, *overrides_from(settings), *overrides]
    check_argv(given)
    return site_from_config(compose_config(given).site)


def metrics(run_dir: str | Path) -> dict[str, Any]:
    """The ``metrics.json`` of a run folder (what ``localize`` and ``season`` wrote)."""
    return json.loads((Path(run_dir) / "metrics.json").read_text())
