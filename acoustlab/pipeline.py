"""The localization method as one object: solver features → point model → gate → error model → conformal.

Protocols decide which events train, calibrate and test; this module does the fitting and
predicting for one such split, keeping positions (groups) apart everywhere.
"""

from __future__ import annotations

import inspect
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from sklearn.base import clone
from sklearn.model_selection import GroupKFold
from tqdm.auto import tqdm

from acoustlab.data import Site, group_of
from acoustlab.errors import ConfigError, DataError
from acoustlab.geometry import gdop, position_crb_m
from acoustlab.interfaces import ConformalScorer, ErrorModel, FeatureSet, Gate, PointModel, Solver

log = logging.getLogger(__name__)

#: Solver columns that are the solver's point estimate (withheld from the error model).
SOLVER_ESTIMATE_COLUMNS = ("solver__x_m", "solver__y_m")
#: The ``solver`` feature group appended by :func:`add_solver_columns` (name, unit, definition).
SOLVER_CATALOG = (
    ("solver__x_m", "m", "solver's estimate, x (east)"),
    ("solver__y_m", "m", "solver's estimate, y (north)"),
    ("solver__residual_m", "m", "RMS range-difference residual at the estimate"),
    ("solver__converged", "1", "1 where the iteration converged"),
    ("solver__gdop", "1", "TDOA geometric dilution of precision at the estimate"),
    ("solver__n_roots", "1", "number of distinct positions that fit the TDOAs equally well"),
    ("solver__source_height_m", "m", "source height assumed by the solver"),
    ("solver__residual_s", "s", "RMS residual expressed as time"),
    ("solver__conditioning", "1", "condition number of the TDOA Jacobian at the estimate"),
)


@dataclass
class Components:
    """Everything a protocol needs, already instantiated."""

    site: Site
    feature_sets: dict[str, FeatureSet]
    solver: Solver
    point_model: PointModel
    gate: Gate
    error_model: ErrorModel
    scorers: dict[str, ConformalScorer]
    levels: list[float]
    dropped_groups: list[str] = field(default_factory=list)
    calibration_folds: int = 5
    model_target: str = "absolute"
    dropped_from_model: list[str] = field(default_factory=list)
    dropped_from_error_model: list[str] = field(default_factory=list)


def tdoa_matrix(features: pd.DataFrame, n_mics: int) -> np.ndarray:
    """(E, M) arrival-time differences to mic 0 from the ``tdoa__lag_0_j_s`` columns (column 0 is 0)."""
    cols = [f"tdoa__lag_0_{j}_s" for j in range(1, n_mics)]
    missing = [c for c in cols if c not in features.columns]
    if missing:
        raise DataError(f"the feature table lacks {missing}; the solver needs the 'tdoa' feature group")
    return np.column_stack([np.zeros(len(features)), features[cols].to_numpy(dtype=float)])


def pair_candidate_lags(features: pd.DataFrame, site: Site) -> np.ndarray | None:
    """(E, P, K) candidate lags of every pair from the ``tdoa`` columns (None without candidates)."""
    first = [f"tdoa__lag_{i}_{j}_s" for i, j in site.mic_pairs]
    if not all(c in features.columns for c in first):
        return None
    k = 1
    while all(f"tdoa__lag_{i}_{j}_c{k + 1}_s" in features.columns for i, j in site.mic_pairs):
        k += 1
    cols = [[f"tdoa__lag_{i}_{j}_s"] + [f"tdoa__lag_{i}_{j}_c{r + 1}_s" for r in range(1, k)] for i, j in site.mic_pairs]
    return np.stack([features[c].to_numpy(dtype=float) for c in cols], axis=1)


def add_solver_columns(features: pd.DataFrame, events: pd.DataFrame, site: Site, solver: Solver) -> pd.DataFrame:
    """Run the solver on every event and append its estimate and diagnostics as group ``solver``."""
    speed = events["speed_of_sound_m_s"].to_numpy(dtype=float) if "speed_of_sound_m_s" in events else None
    if speed is None:
        from acoustlab.physics import speed_of_sound_m_s

        speed = speed_of_sound_m_s(events["temperature_c"].to_numpy(float), events["relative_humidity_pct"].to_numpy(float))
    level_cols = [f"environment__level_{m}_db" for m in range(site.n_mics)]
    kwargs = {}
    if all(col in features.columns for col in level_cols) and "received_level_db" in inspect.signature(solver.solve).parameters:
        kwargs["received_level_db"] = features[level_cols].to_numpy(dtype=float)
    params = inspect.signature(solver.solve).parameters
    candidates = pair_candidate_lags(features, site)
    if candidates is not None and "pair_lag_candidates_s" in params:
        kwargs["pair_lag_candidates_s"] = candidates
    result = solver.solve(site.mic_positions_m, tdoa_matrix(features, site.n_mics), speed, **kwargs)
    out = features.copy()
    out["solver__x_m"] = result.position_m[:, 0]
    out["solver__y_m"] = result.position_m[:, 1]
    out["solver__residual_m"] = result.residual_m
    out["solver__converged"] = result.converged.astype(float)
    for name, values in result.diagnostics.items():
        out[f"solver__{name}"] = np.asarray(values, dtype=float)
    for name, _, _ in SOLVER_CATALOG:  # every solver fills the same columns (NaN where it has no such diagnostic)
        if name not in out.columns:
            out[name] = np.nan
    # Learned models take NaN as "missing"; an infinite GDOP (degenerate geometry) becomes missing too.
    solver_cols = [c for c in out.columns if c.startswith("solver__")]
    out[solver_cols] = out[solver_cols].replace([np.inf, -np.inf], np.nan)
    return out


def crb_from_features(features: pd.DataFrame, events: pd.DataFrame, site: Site) -> np.ndarray | None:
    """Per-event Cramér–Rao bound on position (m) at the true position, from measured signal features.

    Uses the median over mics of the per-mic SNR, RMS bandwidth √(centroid² + bandwidth²), band
    2 × bandwidth and the envelope spread as observation time; None when those features are absent.
    """
    m = site.n_mics
    need = [f"environment__snr_{k}_db" for k in range(m)] + [f"spectral__centroid_{k}_hz" for k in range(m)]
    need += [f"spectral__bandwidth_{k}_hz" for k in range(m)] + [f"ir__spread_{k}_s" for k in range(m)]
    if not all(c in features.columns for c in need) or events[["x_m", "y_m"]].isna().any().any():
        return None

    def med(prefix: str, unit: str) -> np.ndarray:
        return np.median(features[[f"{prefix}_{k}_{unit}" for k in range(m)]].to_numpy(float), axis=1)

    centroid, bandwidth = med("spectral__centroid", "hz"), med("spectral__bandwidth", "hz")
    c = events["speed_of_sound_m_s"].to_numpy(float) if "speed_of_sound_m_s" in events else 343.0
    return position_crb_m(
        site.mic_positions_m, events[["x_m", "y_m", "z_m"]].to_numpy(float), med("environment__snr", "db"),
        np.sqrt(centroid**2 + bandwidth**2), med("ir__spread", "s"), 2 * bandwidth, c,
    )


def error_2d_m(estimate_m: np.ndarray, truth_m: np.ndarray) -> np.ndarray:
    """Euclidean 2-D error in m (inf where the estimate is not finite)."""
    err = np.sqrt(((np.asarray(estimate_m) - np.asarray(truth_m)[:, :2]) ** 2).sum(axis=1))
    return np.where(np.isfinite(err), err, np.inf)


class LocalizationPipeline:
    """Fits the learned parts of the method on training events and predicts for test events.

    Parameters
    ----------
    components : Components
        The instantiated plugins.
    """

    def __init__(self, components: Components) -> None:
        self.c = components

    def _columns(self, features: pd.DataFrame, dropped: list[str], who: str) -> list[str]:
        drop = set(self.c.dropped_groups) | set(dropped)
        known = {group_of(col) for col in features.columns}
        unknown = sorted(drop - known)
        if unknown:
            raise ConfigError(f"cannot drop feature groups {unknown} from the {who}: no such group; available: {', '.join(sorted(known))}")
        cols = [col for col in features.columns if group_of(col) not in drop]
        if not cols:
            raise ConfigError(f"dropping feature groups {sorted(drop)} leaves the {who} no features")
        return cols

    def model_columns(self, features: pd.DataFrame) -> list[str]:
        """Columns the point model sees: every group not dropped, the solver's estimate included."""
        return self._columns(features, self.c.dropped_from_model, "point model")

    def error_columns(self, features: pd.DataFrame) -> list[str]:
        """Columns the error model sees: groups not dropped for it, never the solver's point estimate."""
        cols = self._columns(features, self.c.dropped_from_error_model, "error model")
        return [c for c in cols if c not in SOLVER_ESTIMATE_COLUMNS]

    def _offset(self, solver_xy: np.ndarray) -> np.ndarray:
        """What the point model's target is relative to: 0 (absolute) or the solver's estimate (correction)."""
        if self.c.model_target == "absolute":
            return np.zeros_like(solver_xy)
        centre = self.c.site.mic_positions_m[:, :2].mean(axis=0)
        return np.where(np.isfinite(solver_xy), solver_xy, centre)

    def _fit_point(self, x: pd.DataFrame, truth: np.ndarray, solver_xy: np.ndarray) -> tuple[Any, Any]:
        target = truth[:, :2] - self._offset(solver_xy)
        mx = clone(self.c.point_model).fit(x, target[:, 0])
        my = clone(self.c.point_model).fit(x, target[:, 1])
        return mx, my

    def _predict_point(self, models: tuple[Any, Any], x: pd.DataFrame, solver_xy: np.ndarray) -> np.ndarray:
        return np.column_stack([models[0].predict(x), models[1].predict(x)]) + self._offset(solver_xy)

    def _gdop_at(self, position_m: np.ndarray, features: pd.DataFrame) -> np.ndarray:
        """GDOP at estimated positions (finite, ≥ 1e-6; a large value where the geometry is singular)."""
        height = features["solver__source_height_m"].to_numpy(float) if "solver__source_height_m" in features else np.full(len(position_m), np.mean(self.c.site.source_height_range_m))
        pos = np.column_stack([np.nan_to_num(position_m), np.nan_to_num(height)])
        g = gdop(self.c.site.mic_positions_m, pos)
        return np.clip(np.where(np.isfinite(g), g, 1e6), 1e-6, 1e6)

    def _folds(self, groups: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        n_groups = np.unique(groups).size
        # calibration_folds = -1: leave one position out (one fold per training position)
        k = n_groups if self.c.calibration_folds == -1 else min(self.c.calibration_folds, n_groups)
        if k < 2:
            raise DataError(f"calibration needs at least 2 source positions in training; got {n_groups}")
        return list(GroupKFold(n_splits=k).split(np.zeros(groups.size), groups=groups))

    def fit_predict(self, features: pd.DataFrame, events: pd.DataFrame, train: np.ndarray, test: np.ndarray) -> pd.DataFrame:
        """Fit on rows ``train`` and predict rows ``test`` (integer positions into the tables).

        Conformal calibration uses out-of-fold errors over training *positions* (group K-fold):
        every calibration error comes from point and error models that never saw that position.

        Returns
        -------
        pandas.DataFrame
            One row per test event: truth, solver/model/gate estimates and errors (m), GDOP,
            predicted error (m), substitution flag and ``radius__<scorer>__<level>`` (m).
        """
        site = self.c.site
        truth = events[["x_m", "y_m"]].to_numpy(dtype=float)
        groups = events["position_id"].to_numpy()
        if np.intersect1d(groups[train], groups[test]).size:
            raise DataError("a source position appears in both training and test rows")
        mcols, ecols = self.model_columns(features), self.error_columns(features)
        solver_xy = features[list(SOLVER_ESTIMATE_COLUMNS)].to_numpy(dtype=float)
        solver_gdop = features["solver__gdop"].to_numpy(dtype=float) if "solver__gdop" in features else np.full(len(features), np.nan)

        # Out-of-fold hybrid errors on the training positions, for the error model and calibration.
        folds = self._folds(groups[train])
        oof_model = np.empty((train.size, 2))
        for fit_idx, held_idx in tqdm(folds, desc="point model, out-of-fold", unit="fold", disable=None, leave=False):
            models = self._fit_point(features.iloc[train[fit_idx]][mcols], truth[train[fit_idx]], solver_xy[train[fit_idx]])
            oof_model[held_idx] = self._predict_point(models, features.iloc[train[held_idx]][mcols], solver_xy[train[held_idx]])
        # gates with a threshold learnt on simulation (τ*) choose it on the out-of-fold predictions
        if hasattr(self.c.gate, "select_threshold") and getattr(self.c.gate, "tau_db", None) is None:
            self.c.gate.select_threshold(solver_xy[train], oof_model, features.iloc[train], site, truth[train])
        oof_gate = self.c.gate.decide(solver_xy[train], oof_model, features.iloc[train], site)
        oof_err = error_2d_m(oof_gate.position_m, truth[train])
        gdop_train = self._gdop_at(oof_gate.position_m, features.iloc[train])
        finite = np.isfinite(oof_err)
        if not finite.all():
            log.warning("%d training events have no finite hybrid estimate; left out of calibration", (~finite).sum())
        oof_pred = np.empty(train.size)
        for fit_idx, held_idx in tqdm(folds, desc="error model, out-of-fold", unit="fold", disable=None, leave=False):
            fit_idx = fit_idx[finite[fit_idx]]
            em = clone(self.c.error_model).fit(features.iloc[train[fit_idx]][ecols], oof_err[fit_idx])
            oof_pred[held_idx] = em.predict(features.iloc[train[held_idx]][ecols])
        scorers = {
            name: s.fit(oof_err[finite], oof_pred[finite], gdop_train[finite], self.c.levels)
            for name, s in self.c.scorers.items()
        }

        # Final models on all training rows.
        models = self._fit_point(features.iloc[train][mcols], truth[train], solver_xy[train])
        model_xy = self._predict_point(models, features.iloc[test][mcols], solver_xy[test])
        decision = self.c.gate.decide(solver_xy[test], model_xy, features.iloc[test], site)
        gdop_test = self._gdop_at(decision.position_m, features.iloc[test])
        error_model = clone(self.c.error_model).fit(features.iloc[train[finite]][ecols], oof_err[finite])
        predicted = np.maximum(error_model.predict(features.iloc[test][ecols]), 1e-9)

        out = pd.DataFrame(
            {
                "event_id": events["event_id"].to_numpy()[test],
                "position_id": groups[test],
                "true_x_m": truth[test, 0],
                "true_y_m": truth[test, 1],
                "solver_x_m": solver_xy[test, 0],
                "solver_y_m": solver_xy[test, 1],
                "model_x_m": model_xy[:, 0],
                "model_y_m": model_xy[:, 1],
                "gate_x_m": decision.position_m[:, 0],
                "gate_y_m": decision.position_m[:, 1],
                "substituted": decision.substituted,
                "gdop": gdop_test,
                "solver_gdop": solver_gdop[test],
                "predicted_error_m": predicted,
            }
        )
        crb = crb_from_features(features.iloc[test], events.iloc[test], site)
        if crb is not None:
            out["crb_m"] = crb
        for method in ("solver", "model", "gate"):
            out[f"error_{method}_m"] = error_2d_m(out[[f"{method}_x_m", f"{method}_y_m"]].to_numpy(), truth[test])
        for name, scorer in scorers.items():
            radii = scorer.radius(predicted, gdop_test)
            for k, level in enumerate(self.c.levels):
                out[f"radius__{name}__{level:g}"] = radii[:, k]
        return out
