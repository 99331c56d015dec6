"""The solver stage: run the configured TDOA solver on a feature table and append the ``solver`` group."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.contracts import MICS_USED_MASK, Solver, SolverInputs, SolverResult
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.types import Site
from acoustlab.toolkit.event_physics import assumed_source_height_m, event_speed_of_sound_m_s
from acoustlab.toolkit.geometry import bounding_box
from acoustlab.toolkit.quality import MIN_GOOD_MICS, dropped_mask, weakly_correlated_mics


def tdoa_matrix(features: pd.DataFrame, n_mics: int) -> np.ndarray:
    """(E, M) arrival-time differences to mic 0 from the ``tdoa__lag_0_j_s`` columns (column 0 is 0)."""
    cols = [col.tdoa_lag(0, j) for j in range(1, n_mics)]
    missing = [c for c in cols if c not in features.columns]
    if missing:
        raise DataError(f"the feature table lacks {missing}; the solver needs the 'tdoa' feature group")
    return np.column_stack([np.zeros(len(features)), features[cols].to_numpy(dtype=float)])


def _ranked_per_pair(features: pd.DataFrame, site: Site, name: Callable[[int, int, int], str], k: int) -> np.ndarray | None:
    """(E, P, K) values of the rank-1…k columns ``name(i, j, rank)`` of every pair; None when one is absent."""
    ranked = [[name(i, j, r) for r in range(1, k + 1)] for i, j in site.mic_pairs]
    if not all(c in features.columns for names in ranked for c in names):
        return None
    return np.stack([features[names].to_numpy(dtype=float) for names in ranked], axis=1)


def pair_candidate_lags(features: pd.DataFrame, site: Site) -> np.ndarray | None:
    """(E, P, K) candidate lags of every pair from the ``tdoa`` columns (None without candidates)."""
    k = 1
    while all(col.tdoa_lag(i, j, k + 1) in features.columns for i, j in site.mic_pairs):
        k += 1
    return _ranked_per_pair(features, site, col.tdoa_lag, k)


def pair_candidate_weights(features: pd.DataFrame, site: Site, n_candidates: int) -> np.ndarray | None:
    """(E, P, K) GCC heights of the candidates from the ``xcorr`` group; None when absent."""
    return _ranked_per_pair(features, site, col.xcorr_peak, n_candidates)


def received_levels_db(features: pd.DataFrame, site: Site) -> np.ndarray | None:
    """(E, M) received levels from the ``environment`` group; None when those columns are absent."""
    cols = [col.level_db(m) for m in range(site.n_mics)]
    if not all(c in features.columns for c in cols):
        return None
    return features[cols].to_numpy(dtype=float)


def solver_inputs_for(features: pd.DataFrame, events: pd.DataFrame, site: Site) -> SolverInputs:
    """Everything a solver may read for these events: TDOAs, speed of sound, levels, candidates, height.

    The speed of sound is the events' ``speed_of_sound_m_s`` where known, else computed from their
    temperature and humidity; the source height is the middle of the site's source-height range;
    the SRP-PHAT estimate (when the ``srp`` group exists) is the prior position.
    """
    speed = event_speed_of_sound_m_s(events)
    candidates = pair_candidate_lags(features, site)
    return SolverInputs(
        mic_positions_m=site.mic_positions_m,
        tdoa_s=tdoa_matrix(features, site.n_mics),
        speed_of_sound_m_s=speed,
        received_level_db=received_levels_db(features, site),
        pair_lag_candidates_s=candidates,
        source_height_m=assumed_source_height_m(site),
        pair_lag_weights=None if candidates is None else pair_candidate_weights(features, site, candidates.shape[-1]),
        prior_position_m=features[[col.SRP_X, col.SRP_Y]].to_numpy(float) if {col.SRP_X, col.SRP_Y} <= set(features.columns) else None,
    )


def subset_inputs(inputs: SolverInputs, rows: np.ndarray, keep: np.ndarray, site: Site) -> SolverInputs:
    """The solver inputs of events ``rows`` restricted to the mics ``keep`` (sorted indices into the site's mics).

    The time differences are re-referenced to the first kept mic from the pair candidates (rank 1
    is the strongest GCC peak, what ``tdoa_s`` holds), so a dropped mic 0 takes nothing with it.
    """
    pairs = list(site.mic_pairs)
    kept_pairs = [pairs.index((int(keep[i]), int(keep[j]))) for i in range(len(keep)) for j in range(i + 1, len(keep))]
    cands = None if inputs.pair_lag_candidates_s is None else np.asarray(inputs.pair_lag_candidates_s, float)[np.ix_(rows, kept_pairs)]
    if cands is not None:
        tdoa = np.column_stack([np.zeros(rows.size)] + [cands[:, j - 1, 0] for j in range(1, len(keep))])
    else:  # t_m − t_0 of the kept mics, re-referenced to the first kept one
        full = np.asarray(inputs.tdoa_s, float)[rows][:, keep]
        tdoa = full - full[:, :1]
    speed = np.broadcast_to(np.asarray(inputs.speed_of_sound_m_s, float), (len(inputs.tdoa_s),))[rows]
    return SolverInputs(
        mic_positions_m=np.asarray(inputs.mic_positions_m)[keep],
        tdoa_s=tdoa,
        speed_of_sound_m_s=speed,
        received_level_db=None if inputs.received_level_db is None else np.asarray(inputs.received_level_db, float)[np.ix_(rows, keep)],
        pair_lag_candidates_s=cands,
        source_height_m=inputs.source_height_m,
        pair_lag_weights=None if inputs.pair_lag_weights is None else np.asarray(inputs.pair_lag_weights, float)[np.ix_(rows, kept_pairs)],
        prior_position_m=None if inputs.prior_position_m is None else np.asarray(inputs.prior_position_m, float)[rows],
    )


def drop_weakly_correlated_mics(
    features: pd.DataFrame, events: pd.DataFrame, site: Site, min_peak: float | None, relative: float | None = None
) -> pd.DataFrame:
    """``events`` with every mic whose strongest GCC peak is below ``min_peak`` (``features.gcc.min_peak``) or below
    ``relative`` × its event's strongest (``features.gcc.min_peak_relative``) left out.

    Such a mic joins ``mics_dropped`` and its event's ``quality_flags`` say ``mic <m>: weak_gcc``
    (``acoustlab.toolkit.quality.weakly_correlated_mics``); the event is solved from the others while
    ``MIN_GOOD_MICS`` remain, and is not placed (``quality_ok`` false) when fewer do. Events already
    not usable are left as they are.

    Raises
    ------
    ConfigError
        When the features have no GCC heights (the ``xcorr`` group).
    """
    pairs = list(site.mic_pairs)
    names = [col.xcorr_peak(i, j, 1) for i, j in pairs]
    missing = [n for n in names if n not in features]
    if missing:
        raise ConfigError(
            f"features.gcc.min_peak needs the GCC heights of the xcorr feature group ({missing[0]}, …); "
            "use features=physics or physics_lean, or set features.gcc.min_peak=null and features.gcc.min_peak_relative=null"
        )
    weak = weakly_correlated_mics(
        features[names].to_numpy(float), pairs, site.n_mics, None if min_peak is None else float(min_peak), relative
    )
    events = events.copy()
    usable = events["quality_ok"].fillna(True).to_numpy(bool, copy=True) if "quality_ok" in events else np.ones(len(events), bool)
    already = dropped_mask(events[col.MICS_DROPPED] if col.MICS_DROPPED in events else None, len(events), site.n_mics)
    new = weak & ~already & usable[:, None]
    flags = (
        events[col.QUALITY_FLAGS].fillna("").astype(str).to_numpy(object)
        if col.QUALITY_FLAGS in events
        else np.full(len(events), "", object)
    )
    dropped = (
        events[col.MICS_DROPPED].fillna("").astype(str).to_numpy(object) if col.MICS_DROPPED in events else np.full(len(events), "", object)
    )
    for e in np.flatnonzero(new.any(axis=1)):
        flags[e] = "; ".join([f for f in (flags[e], *(f"mic {m}: weak_gcc" for m in np.flatnonzero(new[e]))) if f])
        bad = already[e] | new[e]
        if site.n_mics - int(bad.sum()) >= MIN_GOOD_MICS:
            dropped[e] = ";".join(str(m) for m in np.flatnonzero(bad))
        else:  # too few good mics: not placed, the flags say why
            usable[e], dropped[e] = False, ""
    events[col.QUALITY_FLAGS], events[col.MICS_DROPPED], events["quality_ok"] = flags, dropped, usable
    return events


def solve_without_dropped_mics(solver: Solver, inputs: SolverInputs, dropped: np.ndarray, site: Site) -> SolverResult:
    """Solve every event, each from its mics that are not ``dropped`` ((E, M) bool; events with none dropped in one batch).

    An event whose flagged clips leave fewer than ``MIN_GOOD_MICS`` mics keeps them all (it is not
    placed anyway: its ``quality_ok`` is false).
    """
    droppable = dropped.any(axis=1) & ((~dropped).sum(axis=1) >= MIN_GOOD_MICS)
    whole = np.flatnonzero(~droppable)
    if whole.size == len(dropped):
        return solver.solve(inputs)
    n = len(dropped)
    position, residual, converged = np.full((n, 2), np.nan), np.full(n, np.nan), np.zeros(n, dtype=bool)
    diagnostics: dict[str, np.ndarray] = {}
    masks, group = np.unique(np.where(droppable[:, None], dropped, False), axis=0, return_inverse=True)
    for g, mask in enumerate(masks):
        rows = np.flatnonzero(group.ravel() == g)
        keep = np.flatnonzero(~mask)
        part = solver.solve(subset_inputs(inputs, rows, keep, site) if mask.any() else _rows(inputs, rows))
        position[rows], residual[rows], converged[rows] = part.position_m, part.residual_m, part.converged
        if MICS_USED_MASK in part.diagnostics:  # the subset's mic k is the site's mic keep[k]
            part.diagnostics[MICS_USED_MASK] = _remapped_mask(part.diagnostics[MICS_USED_MASK], keep)
        for name, values in part.diagnostics.items():
            diagnostics.setdefault(name, np.full(n, np.nan))[rows] = values
    return SolverResult(position_m=position, residual_m=residual, converged=converged, diagnostics=diagnostics)


def _remapped_mask(mask: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Bits of a subset's mics (bit k: mic ``keep[k]``) as bits of the site's mics."""
    bits = np.nan_to_num(np.asarray(mask, float)).astype(np.int64)
    out = sum((((bits >> k) & 1) << int(m)) for k, m in enumerate(keep))
    return np.where(np.isfinite(mask), np.asarray(out, float), np.nan)


def mics_used(result: SolverResult, dropped: np.ndarray) -> list[str]:
    """Each event's mics the fix rests on (``;``-joined indices): the solver's own choice where it reports one
    (``MICS_USED_MASK``), else every mic not ``dropped`` ((E, M) bool); empty without a fix."""
    n, m = dropped.shape
    mask = result.diagnostics.get(MICS_USED_MASK)
    fixed = np.isfinite(np.asarray(result.position_m, float)).all(axis=1)
    out = []
    for e in range(n):
        if not fixed[e]:
            out.append("")
        elif mask is not None and np.isfinite(mask[e]):
            bits = int(mask[e])
            out.append(";".join(str(k) for k in range(m) if bits >> k & 1))
        else:
            out.append(";".join(str(k) for k in np.flatnonzero(~dropped[e])))
    return out


def _rows(inputs: SolverInputs, rows: np.ndarray) -> SolverInputs:
    """The solver inputs of events ``rows``, every mic kept (a solver's answer for an event does not depend on its batch)."""

    def pick(values: np.ndarray | None) -> np.ndarray | None:
        return None if values is None else np.asarray(values, float)[rows]

    return SolverInputs(
        mic_positions_m=np.asarray(inputs.mic_positions_m),
        tdoa_s=np.asarray(inputs.tdoa_s, float)[rows],
        speed_of_sound_m_s=np.broadcast_to(np.asarray(inputs.speed_of_sound_m_s, float), (len(inputs.tdoa_s),))[rows],
        received_level_db=pick(inputs.received_level_db),
        pair_lag_candidates_s=pick(inputs.pair_lag_candidates_s),
        source_height_m=inputs.source_height_m,
        pair_lag_weights=pick(inputs.pair_lag_weights),
        prior_position_m=pick(inputs.prior_position_m),
    )


#: ``solver__failure`` codes: why an event has no solver fix.
FAILURE_NONE, FAILURE_NO_FIX, FAILURE_IMPLAUSIBLE = 0, 1, 2


def bound_fixes(position_m: np.ndarray, site: Site, plausible_margin_fraction: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Replace fixes far outside the site by NaN and say why.

    Parameters
    ----------
    position_m : numpy.ndarray
        (E, 2) solver fixes in m.
    site : Site
        The site (its mics define the plausible region).
    plausible_margin_fraction : float or None
        The plausible region is the mics' bounding box grown on every side by this fraction of the
        largest mic-to-mic distance; None keeps every finite fix (no bound).

    Returns
    -------
    position_m : numpy.ndarray
        (E, 2) fixes, NaN where there is none or it was implausible.
    failure : numpy.ndarray
        (E,) int codes: 0 a fix, 1 no fix (non-finite), 2 a fix outside the plausible region.
    """
    position_m = np.array(position_m, dtype=float)
    finite = np.isfinite(position_m).all(axis=1)
    failure = np.where(finite, FAILURE_NONE, FAILURE_NO_FIX)
    if plausible_margin_fraction is not None:
        low, high = bounding_box(site.mic_positions_m, float(plausible_margin_fraction))
        outside = finite & ((position_m < low) | (position_m > high)).any(axis=1)
        failure = np.where(outside, FAILURE_IMPLAUSIBLE, failure)
    position_m[failure != FAILURE_NONE] = np.nan
    return position_m, failure


def solve_events(features: pd.DataFrame, events: pd.DataFrame, site: Site, solver: Solver) -> SolverResult:
    """The solver's result for every event, each from its mics not in ``mics_dropped``."""
    inputs = solver_inputs_for(features, events, site)
    return solve_without_dropped_mics(solver, inputs, events_dropped_mask(events, site), site)


def events_dropped_mask(events: pd.DataFrame, site: Site) -> np.ndarray:
    """(E, M) True where an event's mic is in its ``mics_dropped``."""
    return dropped_mask(events[col.MICS_DROPPED] if col.MICS_DROPPED in events else None, len(events), site.n_mics)


def add_solver_columns(
    features: pd.DataFrame,
    events: pd.DataFrame,
    site: Site,
    solver: Solver,
    plausible_margin_fraction: float | None = None,
    result: SolverResult | None = None,
) -> pd.DataFrame:
    """Run the solver on every event (or take its ``result``) and append its estimate and diagnostics as group ``solver``.

    With ``plausible_margin_fraction`` a fix outside the plausible region (see ``bound_fixes``)
    is never emitted as a number: its position is NaN and ``solver__failure`` says why.
    """
    result = solve_events(features, events, site, solver) if result is None else result
    position, failure = bound_fixes(result.position_m, site, plausible_margin_fraction)
    out = features.copy()
    out[col.SOLVER_X] = position[:, 0]
    out[col.SOLVER_Y] = position[:, 1]
    out[col.solver_column("residual_m")] = result.residual_m
    out[col.solver_column("converged")] = result.converged.astype(float)
    for name, values in result.diagnostics.items():
        if name != MICS_USED_MASK:  # which mics is no feature (reported as mics_used in the positions)
            out[col.solver_column(name)] = np.asarray(values, dtype=float)
    out[col.SOLVER_FAILURE] = failure.astype(float)
    if {col.SRP_X, col.SRP_Y} <= set(features.columns):  # score-based agreement: how far the SRP-PHAT map's peak lies
        srp = features[[col.SRP_X, col.SRP_Y]].to_numpy(float)
        out[col.solver_column("srp_disagreement_m")] = np.sqrt(((position - srp) ** 2).sum(axis=1))
    for name, _, _ in col.SOLVER_CATALOG:  # every solver fills the same columns (NaN where it has no such diagnostic)
        if name not in out.columns:
            out[name] = np.nan
    # Learned models take NaN as "missing"; an infinite GDOP (degenerate geometry) becomes missing too.
    solver_cols = [c for c in out.columns if col.group_of(c) == "solver"]
    out[solver_cols] = out[solver_cols].replace([np.inf, -np.inf], np.nan)
    return out
