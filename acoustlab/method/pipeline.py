"""The localization method as one object: solver features → point model → gate → error model → conformal.

Protocols decide which events train, calibrate and test; this module does the fitting and
predicting for one such split, keeping positions (groups) apart everywhere.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from scipy.stats import beta
from sklearn.base import clone
from sklearn.model_selection import GroupKFold

from acoustlab.core import columns as col
from acoustlab.core.contracts import (
    ConformalScorer,
    ErrorModel,
    FeatureSet,
    Gate,
    GateDecision,
    PointModel,
    Solver,
    declared,
    hook,
)
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.progress import progress
from acoustlab.core.types import Site
from acoustlab.method.estimates import error_2d_m, hull_distance_extent
from acoustlab.method.fitted import FittedMethod
from acoustlab.method.placement_rules import PlacementRules
from acoustlab.method.splits import cap_rows
from acoustlab.method.trust import (
    SupportCues,
    TrainingSupport,
    TrustedDecision,
    TrustSettings,
    apply_trust,
    support_cues,
)
from acoustlab.stages.field_calibration import event_time_s
from acoustlab.stages.solver_columns import pair_candidate_lags
from acoustlab.toolkit.conformal import (
    ONE_SET_PROBABILITY,
    one_set_coverage,
    pac_positions_needed,
    positions_needed,
    selective_threshold,
    selective_threshold_by_position,
)
from acoustlab.toolkit.event_physics import source_height_m
from acoustlab.toolkit.geometry import gdop
from acoustlab.toolkit.input_uncertainty import Allowance, CorrelatedInputErrors, InputErrors, InputUncertainty, allowance_m
from acoustlab.toolkit.tdoa import candidate_misfit_m

log = logging.getLogger(__name__)
#: How a radius is made for a level the field positions cannot guarantee (``conformal.unsupported_levels=rescaled``).
NOT_GUARANTEED_METHOD = (
    "not guaranteed: the simulation's radius at this level times the ratio of the field's radius to the simulation's at the "
    "highest level the field positions support (the field sets the scale, the simulation the shape of the tail)"
)
#: ``calibrate_on="auto"`` calibrates on field rows only where they span at least this many positions
MIN_FIELD_CALIBRATION_POSITIONS = 3
#: What a radius guarantees, in one sentence each (metrics.json ``calibration.guarantee``; docs/method.md).
GUARANTEE_SIMULATION = (
    "A radius at level l covers the error of a new detection at a new source position like the simulated ones with "
    "probability about l, marginally over positions: each calibration error comes from models fitted without its position "
    "and the radii use the models refitted on all (cross-conformal with a refit, which has no exact finite-sample "
    "guarantee), so coverage is measured per position and per detection (coverage_by_position, coverage)."
)
GUARANTEE_FIELD = (
    "A radius at level l covers the error of a random call at a new spot with probability about l, marginally over spots, if "
    "the calibration spots are exchangeable with the spots of the calls and the calls of one spot with each other (each spot "
    "weighing the same: Dunn, Wasserman and Ramdas 2022); each spot's errors come from models fitted without that spot and "
    "its playbacks are solved with the array calibrated without it, while the radii use the models refitted on all spots "
    "(cross-conformal with a refit: the rank is split conformal's, the exact bound at least l is not), and a level needing "
    "more spots than given has no radius; calibration_by_split gives what one set of spots may cover."
)
#: … added for a scorer with ``position_method: pac``.
GUARANTEE_PAC = (
    " A PAC scorer's radius ({names}) instead covers at least l − {epsilon:g} with probability {confidence:g} over the set "
    "of spots (one call per spot at the rank of Beta(k, n + 1 − k)'s {delta:g} quantile)."
)


@dataclass
class Components:
    """Everything a protocol needs, already instantiated (the configured, never-fitted plugins)."""

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
    #: ``{"gross_m", "delta", "epsilon"}`` for selective localization (None: every event is placed)
    selective: dict[str, Any] | None = None
    #: gates evaluated beside ``gate`` on the same predictions (reported as methods ``gate_<name>``)
    extra_gates: dict[str, Gate] = field(default_factory=dict)
    #: also calibrate a 2-D error ellipse per detection and level (``acoustlab.toolkit.regions``)
    ellipse: bool = False
    #: which training rows calibrate conformal and selective localization: "auto", "all" or "field"
    calibrate_on: str = "auto"
    #: a level the field calibration positions cannot guarantee: "empty" (no radius) or "rescaled" (labelled "not guaranteed")
    unsupported_levels: str = "empty"
    #: the error model also sees the gate's context (solver–model distance, substitution, GDOP and range at the estimate)
    error_model_gate_cues: bool = True
    #: the run's seed (which whole positions a model with its own row limit fits on)
    seed: int = 0
    #: where the point model counts as outside its training support (``acoustlab.method.trust``)
    trust: TrustSettings = field(default_factory=TrustSettings)
    #: the stated errors of the inputs a user measures (or a field calibration's), carried into the radii of field detections
    input_uncertainty: InputErrors = field(default_factory=InputUncertainty)
    #: how field detections are solved and reported (``acoustlab.method.localizer``)
    placement: PlacementRules = field(default_factory=PlacementRules)


@dataclass
class MethodResult:
    """Predictions of one or more splits and what each split's fitted plugins report.

    Attributes
    ----------
    predictions : pandas.DataFrame
        One row per test event (see ``LocalizationPipeline.fit_predict``).
    split_diagnostics : list of dict
        One entry per split, in order: ``{"gate": gate.diagnostics()}`` (plus ``split``, the
        withheld position, where a protocol has several splits).
    """

    predictions: pd.DataFrame
    split_diagnostics: list[dict[str, Any]]
    #: a localization's positions table (``acoustlab.method.localizer.FittedLocalizer.place``); None where there is truth
    positions: pd.DataFrame | None = None

    @staticmethod
    def concat(parts: list[MethodResult]) -> MethodResult:
        """Pool the splits of a protocol (rows and diagnostics in split order)."""
        return MethodResult(pd.concat([p.predictions for p in parts], ignore_index=True), [d for p in parts for d in p.split_diagnostics])


def clone_for_rows(estimator: Any, n_rows: int) -> Any:
    """A fresh clone of a scikit-learn estimator that can be fitted on ``n_rows`` rows.

    A neighbours model asks for more neighbours than there are rows (``n_neighbors=10`` on a
    small run or a calibration fold) and scikit-learn stops with a traceback at prediction; the
    clone's ``n_neighbors`` (found through ``get_params``, the estimator contract, also inside a
    ``Pipeline``) is clipped to the rows, with a warning.
    """
    fresh = clone(estimator)
    too_many = {
        k: v for k, v in fresh.get_params(deep=True).items() if k.split("__")[-1] == "n_neighbors" and isinstance(v, int) and v > n_rows
    }
    if too_many and n_rows >= 1:
        log.warning(
            "%s: %s > %d training rows; clipped to %d",
            type(estimator).__name__,
            ", ".join(f"{k}={v}" for k, v in too_many.items()),
            n_rows,
            n_rows,
        )
        fresh.set_params(**{k: n_rows for k in too_many})
    return fresh


@dataclass
class SplitData:
    """A training split's tables and the arrays every fitting step reads (rows ``train`` index the tables)."""

    features: pd.DataFrame
    events: pd.DataFrame
    train: np.ndarray
    #: (N, 2) true horizontal positions, m
    truth: np.ndarray
    #: (N,) source positions (the exchangeable unit)
    groups: np.ndarray
    #: the point model's and the error model's input columns
    mcols: list[str]
    ecols: list[str]
    #: (N, 2) the solver's fixes, m
    solver_xy: np.ndarray
    #: (train,) True for the simulated training rows (the ones a gate learns from)
    sim: np.ndarray
    #: calibration folds over the training positions (indices into ``train``)
    folds: list[tuple[np.ndarray, np.ndarray]]


@dataclass
class CalibrationErrors:
    """Out-of-fold results on the training events (indexed like ``train``), and the rows that calibrate."""

    #: (train, 2) point-model estimates, m
    model_xy: np.ndarray
    #: the out-of-fold gates' decisions (after the trust check)
    gate: GateDecision
    #: (train,) gated 2-D errors, m (inf without an estimate); (train,) GDOP at the gated estimate
    error: np.ndarray
    gdop: np.ndarray
    #: (train,) finite error
    finite: np.ndarray
    #: the error model's floor, m (5th percentile of the finite errors)
    floor: float
    #: (train,) rows of the calibration domain (all, or the field rows); ``rows`` = domain & finite
    domain: np.ndarray
    rows: np.ndarray
    #: the error model's inputs on the training events
    x_error: pd.DataFrame


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
        known = col.groups_in(features.columns)
        unknown = sorted(drop - known)
        if unknown:
            raise ConfigError(f"cannot drop feature groups {unknown} from the {who}: no such group; available: {', '.join(sorted(known))}")
        cols = [c for c in features.columns if col.group_of(c) not in drop]
        if not cols:
            raise ConfigError(f"dropping feature groups {sorted(drop)} leaves the {who} no features")
        return cols

    def model_columns(self, features: pd.DataFrame) -> list[str]:
        """Columns the point model sees: every group not dropped, the solver's estimate included."""
        return self._columns(features, self.c.dropped_from_model, "point model")

    def error_columns(self, features: pd.DataFrame) -> list[str]:
        """Columns the error model sees: groups not dropped for it, never the solver's point estimate."""
        cols = self._columns(features, self.c.dropped_from_error_model, "error model")
        return [c for c in cols if c not in col.SOLVER_ESTIMATE_COLUMNS]

    def _offset(self, solver_xy: np.ndarray) -> np.ndarray:
        """What the point model's target is relative to: 0 (absolute) or the solver's estimate (correction)."""
        if self.c.model_target == "absolute":
            return np.zeros_like(solver_xy)
        centre = self.c.site.mic_positions_m[:, :2].mean(axis=0)
        return np.where(np.isfinite(solver_xy), solver_xy, centre)

    def _within_limit(self, groups: np.ndarray, plugin: Any) -> np.ndarray:
        """Indices of the rows (of ``groups``, one per row) that ``plugin`` fits on: all, or whole positions up to its own limit.

        A learned plugin may declare ``max_train_rows`` (TabPFN: 1,000, its pretraining limit), so
        one protocol budget serves every model: ``protocol.max_train_rows=10000`` gives XGBoost
        10,000 rows and TabPFN 1,000 of them, chosen by whole positions from the run's seed.
        """
        rows = np.arange(groups.size)
        limit = declared(plugin, "max_train_rows")
        if limit is None or rows.size <= limit:
            return rows
        kept = cap_rows(rows, groups, int(limit), np.random.default_rng([self.c.seed, 3, rows.size]))
        log.info(
            "%s fits on %d of %d training rows (its max_train_rows=%d, whole positions)", type(plugin).__name__, kept.size, rows.size, limit
        )
        return kept

    def _fit_point(self, x: pd.DataFrame, truth: np.ndarray, solver_xy: np.ndarray, groups: np.ndarray) -> tuple[Any, Any]:
        keep = self._within_limit(groups, self.c.point_model)
        target = truth[keep, :2] - self._offset(solver_xy[keep])
        mx = clone_for_rows(self.c.point_model, keep.size).fit(x.iloc[keep], target[:, 0])
        my = clone_for_rows(self.c.point_model, keep.size).fit(x.iloc[keep], target[:, 1])
        return mx, my

    def _predict_point(self, models: tuple[Any, Any], x: pd.DataFrame, solver_xy: np.ndarray) -> np.ndarray:
        return np.column_stack([models[0].predict(x), models[1].predict(x)]) + self._offset(solver_xy)

    def _gdop_at(self, position_m: np.ndarray, features: pd.DataFrame) -> np.ndarray:
        """GDOP at estimated positions (finite, ≥ 1e-6; a large value where the geometry is singular)."""
        pos = np.column_stack([np.nan_to_num(position_m), source_height_m(features, self.c.site)])
        g = gdop(self.c.site.mic_positions_m, pos)
        return np.clip(np.where(np.isfinite(g), g, 1e6), 1e-6, 1e6)

    def _fit_gate(
        self,
        configured: Gate,
        rows: np.ndarray,
        sim: np.ndarray,
        solver_xy: np.ndarray,
        model_xy: np.ndarray,
        features: pd.DataFrame,
        truth: np.ndarray,
        groups: np.ndarray,
    ) -> Gate:
        """A fresh clone of ``configured`` fitted on the simulated ones of ``rows`` (``model_xy`` indexed like ``rows``).

        The paper chooses τ* on simulation; field rows never teach a gate.
        """
        fit = rows[sim]
        return clone(configured, safe=False).fit(
            solver_xy[fit], model_xy[sim], features.iloc[fit], self.c.site, truth[fit], groups=groups[fit]
        )

    def _support(
        self,
        rows: np.ndarray,
        features: pd.DataFrame,
        mcols: list[str],
        events: pd.DataFrame,
        solver_xy: np.ndarray,
        groups: np.ndarray,
        model_xy: np.ndarray,
        sim: np.ndarray,
    ) -> TrainingSupport | None:
        """The point model's training support learned from the simulated ones of ``rows`` (None with ``trust.enabled=false``).

        ``model_xy`` (indexed like ``rows``) are out-of-fold model estimates: how well the accurate
        ones explain the measured time differences sets the hand-over tolerance. Field playbacks
        among ``rows`` (``sim`` False) teach the point model and calibrate the radii, but neither
        widen the training region nor set the tolerance: the docs promise both from simulation,
        and a few playbacks near the hull's edge would otherwise hand calls beyond it to the model.
        """
        if not self.c.trust.enabled:
            return None
        if sim.any() and not sim.all():
            rows, model_xy = rows[sim], model_xy[sim]
        truth = (
            events[[col.TRUE_X, col.TRUE_Y, col.TRUE_Z]].to_numpy(float)[rows]
            if col.TRUE_Z in events
            else np.column_stack([events[[col.TRUE_X, col.TRUE_Y]].to_numpy(float)[rows], np.full(rows.size, np.nan)])
        )
        model_misfit = self._misfit_m(features.iloc[rows], model_xy)
        model_misfit = None if model_misfit is None else model_misfit[0] * self._gdop_at(model_xy, features.iloc[rows])
        return TrainingSupport(self.c.trust).fit(
            features.iloc[rows][mcols],
            truth,
            error_2d_m(solver_xy[rows], truth),
            groups[rows],
            model_misfit_m=model_misfit,
            model_error_m=None if model_misfit is None else error_2d_m(model_xy, truth),
        )

    def _misfit_m(self, features: pd.DataFrame, *positions_m: np.ndarray) -> list[np.ndarray] | None:
        """(B,) per set of 2-D positions: how well they explain the rows' GCC candidates (``candidate_misfit_m``), m.

        The candidates, heights and speeds are read from ``features`` once for every set; None without candidates.
        """
        candidates = pair_candidate_lags(features, self.c.site)
        if candidates is None or col.ENV_SPEED_OF_SOUND not in features:
            return None
        height, speed = source_height_m(features, self.c.site), features[col.ENV_SPEED_OF_SOUND].to_numpy(float)
        pairs = np.asarray(self.c.site.mic_pairs)
        return [candidate_misfit_m(p, height, self.c.site.mic_positions_m, pairs, candidates, speed) for p in positions_m]

    def _cues(
        self,
        rows: np.ndarray,
        solver_xy: np.ndarray,
        model_xy: np.ndarray,
        features: pd.DataFrame,
        mcols: list[str],
        support: TrainingSupport | None,
    ) -> SupportCues:
        """``rows`` (``model_xy`` indexed like them) checked against the model's training support, once for every gate."""
        at = features.iloc[rows]
        misfit, model_gdop = None, None
        if support is not None and support.handover_tolerance_m_ is not None:
            both = self._misfit_m(at, solver_xy[rows], model_xy)
            misfit = None if both is None else tuple(both)
            model_gdop = self._gdop_at(model_xy, at)
        return support_cues(solver_xy[rows], model_xy, at, at[mcols], support, misfit, model_gdop)

    def _decide(
        self, gate: Gate, rows: np.ndarray, solver_xy: np.ndarray, model_xy: np.ndarray, features: pd.DataFrame, cues: SupportCues
    ) -> TrustedDecision:
        """The gate's decision on ``rows`` (``model_xy`` indexed like them) with hand-overs to a distrusted model undone."""
        decision = gate.decide(solver_xy[rows], model_xy, features.iloc[rows], self.c.site)
        return apply_trust(decision, solver_xy[rows], cues)

    def _folds(self, groups: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        n_groups = np.unique(groups).size
        # calibration_folds = -1: leave one position out (one fold per training position)
        k = n_groups if self.c.calibration_folds == -1 else min(self.c.calibration_folds, n_groups)
        if k < 2:
            raise DataError(f"calibration needs at least 2 source positions in training; got {n_groups}")
        return list(GroupKFold(n_splits=k).split(np.zeros(groups.size), groups=groups))

    def fit_predict(self, features: pd.DataFrame, events: pd.DataFrame, train: np.ndarray, test: np.ndarray) -> MethodResult:
        """Fit on rows ``train`` and predict rows ``test`` (integer positions into the tables).

        The same as ``fit`` on the training rows followed by ``FittedMethod.predict`` on
        the test rows (a test row's prediction depends on the fitted method and its own row only,
        so predicting in chunks gives the same rows). No position may be on both sides.

        Returns
        -------
        MethodResult
            ``predictions``: one row per test event: truth, solver/model/gate estimates and errors
            (m), GDOP, predicted error (m), substitution flag and ``radius__<scorer>__<level>`` (m);
            ``split_diagnostics``: ``[{"gate": ..., "trust": ..., "calibration": ...}]``.
        """
        groups = events[col.POSITION_ID].to_numpy()
        if np.intersect1d(groups[train], groups[test]).size:
            raise DataError("a source position appears in both training and test rows")
        fitted = self.fit(features, events, train)
        out, trust = fitted.predict(features.iloc[test], events.iloc[test])
        info = fitted.split_info(trust)
        if fitted.held_out_calibration is not None:  # a table, summarised by the protocol that reports it (localize)
            info["held_out_calibration"] = fitted.held_out_calibration
        return MethodResult(out, [info])

    def fit(self, features: pd.DataFrame, events: pd.DataFrame, train: np.ndarray) -> FittedMethod:
        """Fit every learned part of the method on rows ``train`` of the tables.

        Every fitted plugin (point and error models, gate, conformal scorers) is a fresh clone of the
        configured one, so splits never share fitted state. Conformal calibration uses out-of-fold
        errors over training *positions* (group K-fold): every calibration error comes from point
        and error models that never saw that position. The steps, in order: the split's arrays;
        out-of-fold point-model estimates; the gate; out-of-fold (calibration) errors; the final
        point model and its training support; the error model and conformal scorers; gates
        compared beside the configured one; the selective threshold.

        Returns
        -------
        FittedMethod
            What predicting needs, and nothing of the training tables beyond the calibration
            events' errors (it can be saved and loaded: ``acoustlab.method.saved``).
        """
        split = self._split(features, events, train)
        oof_model = self._out_of_fold_point(split)
        # the gate learns what it needs (e.g. τ* on simulation) from the out-of-fold predictions, on simulated rows only
        gate = self._fit_gate(self.c.gate, train, split.sim, split.solver_xy, oof_model, features, split.truth, split.groups)
        cal = self._calibration_errors(split, oof_model)
        log.info("final point and error models on %d training rows", train.size)
        models = self._fit_point(features.iloc[train][split.mcols], split.truth[train], split.solver_xy[train], split.groups[train])
        support = self._support(train, features, split.mcols, events, split.solver_xy, split.groups, oof_model, split.sim)
        fitted = FittedMethod(
            pipeline=self,
            mcols=split.mcols,
            ecols=split.ecols,
            point_models=models,
            support=support,
            gate=gate,
            floor=cal.floor,
            calibrated_on_field=bool(cal.domain.sum() < cal.domain.size),
            calibration=self._calibration_summary(cal.domain, cal.rows, split.groups[train]),
            calibration_times_s=_time_span_s(event_time_s(events.iloc[train[cal.rows]])) if cal.domain.sum() < cal.domain.size else None,
        )
        self._fit_error_models(split, cal, fitted)
        if self.c.ellipse:
            rows = cal.rows
            fitted.ellipse_calibration = (
                (cal.gate.position_m - split.truth[train])[rows],
                cal.gate.position_m[rows],
                fitted.oof_predicted[rows],
                source_height_m(features.iloc[train[rows]], self.c.site),
                # calibrated on field spots, an ellipse's guarantee is over spots, as the radii's (their events cluster)
                split.groups[train][rows] if fitted.calibrated_on_field else None,
            )
        for name, configured in self.c.extra_gates.items():  # compared on the same out-of-fold and test predictions
            fitted.extra_gates[name] = self._fit_gate(
                configured, train, split.sim, split.solver_xy, oof_model, features, split.truth, split.groups
            )
        if self.c.selective is not None:
            fitted.selective = self._selective_threshold(
                cal.error[cal.domain], fitted.oof_predicted[cal.domain], split.groups[train][cal.domain]
            )
        return fitted

    def _split(self, features: pd.DataFrame, events: pd.DataFrame, train: np.ndarray) -> SplitData:
        """The training split's arrays (rows ``train`` index the tables)."""
        groups = events[col.POSITION_ID].to_numpy()
        return SplitData(
            features=features,
            events=events,
            train=train,
            truth=events[[col.TRUE_X, col.TRUE_Y]].to_numpy(dtype=float),
            groups=groups,
            mcols=self.model_columns(features),
            ecols=self.error_columns(features),
            solver_xy=features[list(col.SOLVER_ESTIMATE_COLUMNS)].to_numpy(dtype=float),
            # the paper chooses τ* on simulation: field rows never teach a gate
            sim=~events["is_field"].to_numpy(bool)[train] if "is_field" in events else np.ones(train.size, dtype=bool),
            folds=self._folds(groups[train]),
        )

    def _out_of_fold_point(self, s: SplitData) -> np.ndarray:
        """(train, 2) point-model estimates of the training events, each from a fit without its position."""
        oof_model = np.empty((s.train.size, 2))
        for k, (fit_idx, held_idx) in enumerate(progress(s.folds, desc="point model, out-of-fold", unit=col.FOLD, leave=False)):
            log.info("point model, out-of-fold %d/%d (%d rows)", k + 1, len(s.folds), fit_idx.size)  # progress also in logs and batch jobs
            fit, held = s.train[fit_idx], s.train[held_idx]
            models = self._fit_point(s.features.iloc[fit][s.mcols], s.truth[fit], s.solver_xy[fit], s.groups[fit])
            oof_model[held_idx] = self._predict_point(models, s.features.iloc[held][s.mcols], s.solver_xy[held])
        return oof_model

    def _calibration_errors(self, s: SplitData, oof_model: np.ndarray) -> CalibrationErrors:
        """Out-of-fold gated errors of the training events and what calibrates on them."""
        train = s.train
        # calibration errors come from gates that never saw the event's position, as the test errors do
        oof_gate = self._out_of_fold_gate(s.folds, train, s.sim, s.solver_xy, oof_model, s.features, s.truth, s.groups, s.events, s.mcols)
        error = error_2d_m(oof_gate.position_m, s.truth[train])
        gdop_train = self._gdop_at(oof_gate.position_m, s.features.iloc[train])
        finite = np.isfinite(error)
        if not finite.all():
            log.warning("%d training events have no finite hybrid estimate; left out of calibration", (~finite).sum())
        # the error model's predictions are floored at the 5th percentile of the calibration errors, so
        # a fix it wrongly trusts still gets a meaningful radius (never 10⁻⁹ m times a quantile)
        floor = max(float(np.percentile(error[finite], 5)) if finite.any() else 0.0, 1e-9)
        domain = self._calibration_domain(s.events, train, finite)  # the rows that calibrate (all, or the field rows)
        x_error = self._error_inputs(s.features.iloc[train][s.ecols], s.solver_xy[train], oof_model, oof_gate, gdop_train)
        return CalibrationErrors(oof_model, oof_gate, error, gdop_train, finite, floor, domain, domain & finite, x_error)

    def _error_fit_rows(self, s: SplitData, cal: CalibrationErrors, rows: np.ndarray, plugin: Any) -> np.ndarray:
        """The training ``rows`` with a finite error, within ``plugin``'s own row limit."""
        rows = rows[cal.finite[rows]]
        return rows[self._within_limit(s.groups[s.train[rows]], plugin)]

    def _out_of_fold_errors(
        self, s: SplitData, cal: CalibrationErrors, fit_predict: Any, plugin: Any, shape: tuple[int, ...] = (), desc: str | None = None
    ) -> np.ndarray:
        """(train, *shape) predictions of ``fit_predict(x_fit, error_fit, x_held)`` over the calibration folds (finite errors only)."""
        out = np.empty((s.train.size, *shape))
        for fit_idx, held_idx in progress(s.folds, desc=desc, unit=col.FOLD, leave=False) if desc else s.folds:
            fit_idx = self._error_fit_rows(s, cal, fit_idx, plugin)
            out[held_idx] = fit_predict(cal.x_error.iloc[fit_idx], cal.error[fit_idx], cal.x_error.iloc[held_idx])
        return out

    def _fit_error_models(self, s: SplitData, cal: CalibrationErrors, fitted: FittedMethod) -> None:
        """The error model (out-of-fold for calibration, then on every training row) and the conformal scorers, into ``fitted``."""
        log.info("error model, out-of-fold (%d folds)", len(s.folds))
        oof_pred = np.maximum(
            self._out_of_fold_errors(
                s,
                cal,
                lambda x, y, held: clone_for_rows(self.c.error_model, len(x)).fit(x, y).predict(held),
                self.c.error_model,
                desc="error model, out-of-fold",
            ),
            cal.floor,
        )
        rows, levels = cal.rows, self.c.levels
        positions = s.groups[s.train][rows]  # a scorer may calibrate over positions rather than events
        for name, configured in self.c.scorers.items():
            scorer = clone(configured, safe=False)
            if fitted.calibrated_on_field and declared(scorer, "calibration_unit") == "event":
                scorer.calibration_unit = "position"  # field spots are few and their events cluster: a guarantee over spots
            if declared(scorer, "needs_quantiles"):  # CQR: its own quantile model, out-of-fold like the error model
                oof_q = self._out_of_fold_errors(
                    s, cal, lambda x, y, held, scorer=scorer: scorer.fit_predict_quantiles(x, y, held, levels), scorer, shape=(len(levels),)
                )
                fitted.scorers[name] = scorer.fit(
                    cal.error[rows], oof_pred[rows], cal.gdop[rows], levels, quantiles=np.maximum(oof_q[rows], cal.floor), groups=positions
                )
                x_fit, error_fit = cal.x_error.iloc[cal.finite], cal.error[cal.finite]
                fit_quantiles = hook(scorer, "fit_quantiles")
                if fit_quantiles is not None:  # fitted once here, applied to every chunk a season predicts
                    fitted.quantile_models[name] = fit_quantiles(x_fit, error_fit, levels)
                else:  # a scorer with fit_predict_quantiles only: refitted (deterministically) at every predict
                    fitted.quantile_training = (x_fit, error_fit)
            else:
                fitted.scorers[name] = self._fit_scorer(scorer, cal, oof_pred, rows, s.groups[s.train])
        if fitted.calibration.get("not_guaranteed_levels"):
            self._fit_simulation_scorers(s, cal, oof_pred, fitted)
        if fitted.calibrated_on_field:
            fitted.held_out_calibration = self._held_out_calibration(s, cal, oof_pred, fitted)
        fit_rows = self._error_fit_rows(s, cal, np.arange(s.train.size), self.c.error_model)
        fitted.error_model = clone_for_rows(self.c.error_model, fit_rows.size).fit(cal.x_error.iloc[fit_rows], cal.error[fit_rows])
        fitted.oof_predicted = oof_pred

    def _fit_simulation_scorers(self, s: SplitData, cal: CalibrationErrors, oof_pred: np.ndarray, fitted: FittedMethod) -> None:
        """The scorers calibrated on the simulated training rows, for ``unsupported_levels=rescaled`` (``FittedMethod._add_radii``).

        The field spots set the scale (the ratio of the field's radius to the simulation's at the
        highest level they support), the simulation the shape of the tail beyond it: a radius for a
        level the spots are too few to guarantee, labelled "not guaranteed".
        """
        rows = cal.finite & ~cal.domain
        positions = s.groups[s.train][rows]
        if np.unique(positions).size < max(positions_needed(level) for level in self.c.levels):
            log.warning("conformal.unsupported_levels=rescaled: too few simulated positions to rescale; those radii stay empty")
            return
        for name, configured in self.c.scorers.items():
            if declared(configured, "needs_quantiles"):
                continue  # a quantile scorer's tail is its own model's; not rescaled
            fitted.simulation_scorers[name] = self._fit_scorer(clone(configured, safe=False), cal, oof_pred, rows, s.groups[s.train])

    def _held_out_calibration(self, s: SplitData, cal: CalibrationErrors, oof_pred: np.ndarray, fitted: FittedMethod) -> pd.DataFrame:
        """The field calibration rows with radii from scorers calibrated without their own position: coverage held out by spot.

        Their errors and predicted errors are already out-of-fold (models that never saw the
        spot); each spot's radii come from the scorers fitted on the other spots, so whether they
        cover is a fair test of the radii at this site. A failure (no estimate) is never covered.
        Levels the remaining spots cannot guarantee, and quantile scorers (own models), are NaN.
        """
        positions = s.groups[s.train]
        domain = np.flatnonzero(cal.domain)
        truth = s.truth[s.train][domain]
        table = pd.DataFrame(
            {
                col.POSITION_ID: positions[domain],
                col.error_m("gate"): cal.error[domain],
                "gdop": cal.gdop[domain],
                col.HULL_DISTANCE: hull_distance_extent(self.c.site, truth),
            }
        )
        if col.SNR in s.events:
            table[col.SNR] = s.events[col.SNR].to_numpy(float)[s.train][domain]
        unsupported = set(fitted.calibration.get("unsupported_levels", []))
        for name, configured in self.c.scorers.items():
            radii = np.full((domain.size, len(self.c.levels)), np.nan)
            if not declared(configured, "needs_quantiles"):
                for spot in np.unique(positions[domain]):
                    scorer = self._fit_scorer(
                        clone(fitted.scorers[name], safe=False), cal, oof_pred, cal.rows & (positions != spot), positions
                    )
                    held = cal.domain & (positions == spot)
                    at = positions[domain] == spot  # the held rows, among the table's
                    radii[at] = scorer.radius(oof_pred[held], cal.gdop[held], **self._region(scorer, cal.gate.position_m[held]))
            for k, level in enumerate(self.c.levels):
                keep = col.level_key(level) not in unsupported and np.isfinite(radii[:, k]).all()
                table[col.radius(name, level)] = radii[:, k] if keep else np.nan
        return table

    def _fit_scorer(self, scorer: Any, cal: CalibrationErrors, oof_pred: np.ndarray, rows: np.ndarray, positions: np.ndarray) -> Any:
        """``scorer`` (not a quantile scorer) calibrated on the training rows ``rows`` (mask over train; ``positions`` per train row)."""
        region = self._region(scorer, cal.gate.position_m[rows])
        return scorer.fit(cal.error[rows], oof_pred[rows], cal.gdop[rows], self.c.levels, groups=positions[rows], **region)

    def _region(self, scorer: Any, position_m: np.ndarray) -> dict[str, np.ndarray]:
        """``{"hull_distance": (B,)}`` for a scorer that bins by region: each estimate's distance outside the mics' hull, array extents."""
        if not declared(scorer, "needs_hull_distance"):
            return {}
        return {"hull_distance": hull_distance_extent(self.c.site, position_m)}

    def _input_allowance(
        self,
        position_m: np.ndarray,
        features: pd.DataFrame,
        events: pd.DataFrame,
        calibrated_on_field: bool,
        calibration_times_s: tuple[float, float] | None = None,
    ) -> Allowance:
        """What the stated input errors add to each field detection's radii at the configured levels; 0 where none applies.

        Simulated events know their inputs exactly: the allowance is for field detections. Radii
        calibrated on field recordings already hold the field's input errors as they were when those
        recordings were made; of a calibration's clock drift, what it adds at a detection beyond its
        larger value at the two ends of ``calibration_times_s`` is added (in quadrature), nothing else.
        """
        stated = self.c.input_uncertainty
        field = events["is_field"].to_numpy(bool) if "is_field" in events else np.zeros(len(events), bool)
        out = Allowance(np.zeros(len(events)), np.zeros((len(events), len(self.c.levels))))
        if stated.is_zero or not field.any() or col.TEMPERATURE not in events:
            return out
        drifting = isinstance(stated, CorrelatedInputErrors) and stated.drifts and calibration_times_s is not None
        if calibrated_on_field and not drifting:
            return out
        source = np.column_stack([position_m, source_height_m(features, self.c.site)])[field]
        humidity = events[col.HUMIDITY].to_numpy(float) if col.HUMIDITY in events else np.zeros(len(events))
        weather = (events[col.TEMPERATURE].to_numpy(float)[field], humidity[field])
        times = event_time_s(events)[field]  # a calibration's drift grows its clocks' errors with it
        mics, levels = self.c.site.mic_positions_m, self.c.levels
        found = allowance_m(mics, source, *weather, stated, levels, time_s=times)
        if calibrated_on_field:
            ends = [allowance_m(mics, source, *weather, stated, levels, time_s=np.full(len(times), t)) for t in calibration_times_s]
            found = Allowance(
                _growth(found.sigma_m, np.maximum(ends[0].sigma_m, ends[1].sigma_m)),
                _growth(found.radius_m, np.maximum(ends[0].radius_m, ends[1].radius_m)),
            )
        out.sigma_m[field], out.radius_m[field] = found.sigma_m, found.radius_m
        return out

    def _calibration_domain(self, events: pd.DataFrame, train: np.ndarray, finite: np.ndarray) -> np.ndarray:
        """(train,) mask of the training rows whose out-of-fold errors calibrate conformal and selective localization.

        ``calibrate_on="all"``: every training row. ``"field"``: only field recordings with known
        positions (e.g. the other positions under leave-one-position-out, or calibration
        playbacks), exchangeable with field test events where simulation is not.
        ``"auto"``: the field rows where they span at least ``MIN_FIELD_CALIBRATION_POSITIONS``
        positions and enough events for the highest level (⌈1/(1 − level)⌉ − 1), else all.
        """
        mode = self.c.calibrate_on
        every = np.ones(train.size, dtype=bool)
        field = events["is_field"].to_numpy(bool)[train] if "is_field" in events else ~every
        if mode == "all" or (mode == "auto" and not field.any()):
            return every
        needed = int(np.ceil(1 / (1 - max(self.c.levels)))) - 1
        n_rows = int((field & finite).sum())
        n_positions = np.unique(events[col.POSITION_ID].to_numpy()[train][field & finite]).size
        if n_rows >= needed and n_positions >= MIN_FIELD_CALIBRATION_POSITIONS:
            log.info("conformal calibration on %d field events at %d positions", n_rows, n_positions)
            return field
        why = (
            f"{n_rows} field events with a known position and an estimate at {n_positions} positions in training; calibration "
            f"on the field needs at least {needed} events (level {max(self.c.levels)}) at {MIN_FIELD_CALIBRATION_POSITIONS} positions"
        )
        if mode == "field":
            raise DataError(f"conformal.calibrate_on=field: {why} (protocol=lopo, or localize with calibration playbacks, provide them)")
        log.info("conformal calibration on all %d training events (%s)", train.size, why)
        return every

    @staticmethod
    def _add_method(out: pd.DataFrame, method: str, position_m: np.ndarray, truth_m: np.ndarray) -> None:
        """A method's estimate and error columns in the predictions table."""
        for k, column in enumerate(col.estimate_xy(method)):
            out[column] = position_m[:, k]
        out[col.error_m(method)] = error_2d_m(position_m, truth_m)

    @staticmethod
    def _trust_summary(support: TrainingSupport | None, trusted: TrustedDecision) -> dict[str, Any]:
        """The training region and how often the trust check overrode the gate, for metrics.json."""
        if support is None:
            return {"enabled": False}
        reasons, counts = np.unique(trusted.reason[trusted.reason != ""].astype(str), return_counts=True)
        return {
            "enabled": True,
            "training_region": support.description(),
            "overridden": {str(r): int(n) for r, n in zip(reasons, counts, strict=True)},
            "n_novel": int((trusted.flags["novelty"] > 1).sum()),
            "n_solver_outside_support": int(trusted.flags["solver_outside_support"].sum()),
        }

    def _calibration_summary(self, domain: np.ndarray, cal: np.ndarray, train_groups: np.ndarray) -> dict[str, Any]:
        """Which rows calibrated, and which levels their number of positions can support.

        Events of one position share its propagation, so a guarantee for a *new position* rests
        on the number of positions n, not of events: split conformal over n exchangeable
        positions reaches level ℓ only when n ≥ ⌈1/(1 − ℓ)⌉ − 1 (19 positions for 0.95, 4 for
        0.8). Simulation gives hundreds; a few field playback spots do not, and the levels they
        cannot support are listed (and logged as a warning) instead of silently reported as met.
        """
        n_positions = int(np.unique(train_groups[cal]).size)
        on = "field" if domain.sum() < domain.size else "all"
        needed = {col.level_key(level): self._positions_needed(level, on == "field") for level in self.c.levels}
        unsupported = [level for level, n in needed.items() if n_positions < n]
        rescaled = unsupported if on == "field" and self.c.unsupported_levels == "rescaled" else []
        if unsupported:
            log.warning(
                "conformal calibration on %d %s positions cannot support level(s) %s for a new position (they need %s positions); "
                "those radii are %s",
                n_positions,
                "field" if on == "field" else "training",
                ", ".join(unsupported),
                ", ".join(str(needed[lv]) for lv in unsupported),
                "rescaled from the simulation's and labelled not guaranteed" if rescaled else "left empty (radius_note says why)",
            )
        return {
            "on": on,
            "n_events": int(cal.sum()),
            "n_positions": n_positions,
            "positions_needed_by_level": needed,
            "unsupported_levels": unsupported,
            # radii given anyway (conformal.unsupported_levels=rescaled): no guarantee, and labelled so
            "not_guaranteed_levels": rescaled,
            "not_guaranteed_method": NOT_GUARANTEED_METHOD if rescaled else None,
            "guarantee": self._field_guarantee() if on == "field" else GUARANTEE_SIMULATION,
            # with probability 0.9 over calibration sets of this many positions, each radius covers at least this (field only)
            "one_set": self._one_set_statement(n_positions) if on == "field" else None,
            # what one calibration set of this many positions gives with one event per position (position_method=subsample):
            # coverage ~ Beta(k, n + 1 − k), k = ⌈(n + 1)·level⌉; pooling every event (the default) scatters less
            "coverage_of_one_set": {
                col.level_key(level): [round(float(beta.ppf(q, k, n_positions + 1 - k)), 3) for q in (0.05, 0.95)]
                for level in self.c.levels
                if (k := int(np.ceil((n_positions + 1) * level))) <= n_positions
            },
        }

    def _positions_needed(self, level: float, on_field: bool) -> int:
        """Calibration positions a radius at ``level`` needs: ``positions_needed``, or on field spots the most any PAC scorer needs."""
        needed = [positions_needed(level)]
        if on_field:
            needed += [
                pac_positions_needed(level, declared(scorer, "pac_delta"), declared(scorer, "pac_epsilon"))
                for scorer in self.c.scorers.values()
                if declared(scorer, "position_method") == "pac"
            ]
        return max(needed)

    def _field_guarantee(self) -> str:
        """``GUARANTEE_FIELD``, with the PAC scorers' own sentence where there are any (one per δ, ε)."""
        pac: dict[tuple[float, float], list[str]] = {}
        for name, scorer in self.c.scorers.items():
            if declared(scorer, "position_method") == "pac":
                pac.setdefault((declared(scorer, "pac_delta"), declared(scorer, "pac_epsilon")), []).append(name)
        return GUARANTEE_FIELD + "".join(
            GUARANTEE_PAC.format(names=", ".join(names), epsilon=epsilon, confidence=1 - delta, delta=delta)
            for (delta, epsilon), names in pac.items()
        )

    def _one_set_at(self, n_positions: int, level: float) -> float | None:
        """The smallest ``one_set_coverage`` over the scorers at ``level``, each by its own rank rule (None: no scorer's is finite)."""
        found = [
            one_set_coverage(
                n_positions,
                level,
                method=declared(scorer, "position_method"),
                delta=declared(scorer, "pac_delta"),
                epsilon=declared(scorer, "pac_epsilon"),
            )
            for scorer in self.c.scorers.values()
        ]
        finite = [c for c in found if c is not None]
        return min(finite) if finite else None

    def _one_set_statement(self, n_positions: int) -> dict[str, Any]:
        """Per level, what one set of ``n_positions`` calibration spots gives its radius (``one_set_coverage``), logged once."""
        levels = {col.level_key(level): self._one_set_at(n_positions, level) for level in self.c.levels}
        stated = {level: c for level, c in levels.items() if c is not None}
        if stated:
            log.info(
                "with probability %.1f over your %d calibration spots, the radii cover at least %s of calls at a new spot "
                "(exact with conformal position_method=subsample or pac; a lower bound for pooled)",
                ONE_SET_PROBABILITY,
                n_positions,
                ", ".join(f"{c:.2f} at {level}" for level, c in stated.items()),
            )
        return {"probability": ONE_SET_PROBABILITY, "n_positions": n_positions, "covers_at_least": levels}

    def _out_of_fold_gate(
        self,
        folds: list[tuple[np.ndarray, np.ndarray]],
        train: np.ndarray,
        sim: np.ndarray,
        solver_xy: np.ndarray,
        oof_model: np.ndarray,
        features: pd.DataFrame,
        truth: np.ndarray,
        groups: np.ndarray,
        events: pd.DataFrame,
        mcols: list[str],
    ) -> GateDecision:
        """The gate's decisions on the training events, each from a gate fitted without that event's position.

        A gate fitted on all training positions and applied to them decides in-sample (the learned
        gate has seen their labels), so its calibration errors would be smaller than the test
        errors and the conformal radii too narrow. Each calibration fold gets its own gate, fitted
        on the other folds' simulated events, and is checked against the support of the point model
        that predicted the fold (fitted on the other folds).
        """
        position = np.full((train.size, 2), np.nan)
        substituted = np.zeros(train.size, dtype=bool)
        for fit_idx, held_idx in folds:
            fold_gate = self._fit_gate(self.c.gate, train[fit_idx], sim[fit_idx], solver_xy, oof_model[fit_idx], features, truth, groups)
            support = self._support(train[fit_idx], features, mcols, events, solver_xy, groups, oof_model[fit_idx], sim[fit_idx])
            cues = self._cues(train[held_idx], solver_xy, oof_model[held_idx], features, mcols, support)
            decision = self._decide(fold_gate, train[held_idx], solver_xy, oof_model[held_idx], features, cues).decision
            position[held_idx], substituted[held_idx] = decision.position_m, decision.substituted
        return GateDecision(position, substituted)

    def _error_inputs(
        self, x: pd.DataFrame, solver_xy: np.ndarray, model_xy: np.ndarray, decision: GateDecision, estimate_gdop: np.ndarray
    ) -> pd.DataFrame:
        """The error model's inputs: its feature columns plus, with ``error_model_gate_cues``, the gate's context.

        The context (columns ``gate__*``) is what the features cannot know: how far the solver's
        and the point model's estimates lie apart (m; NaN without a solver fix), whether the gate
        substituted the model's, and the GDOP and range from the array centre (m) at the gated
        estimate. Where solver and model disagree, one of them is wrong: the strongest single cue
        of a gross error.
        """
        if not self.c.error_model_gate_cues:
            return x
        centre = self.c.site.mic_positions_m[:, :2].mean(axis=0)
        context = pd.DataFrame(
            {
                col.GATE_SOLVER_MODEL_DISTANCE: np.sqrt(((solver_xy - model_xy) ** 2).sum(axis=1)),
                col.GATE_SUBSTITUTED: decision.substituted.astype(float),
                col.GATE_ESTIMATE_GDOP: estimate_gdop,
                col.GATE_ESTIMATE_RANGE: np.sqrt(((decision.position_m - centre) ** 2).sum(axis=1)),
            },
            index=x.index,
        )
        return pd.concat([x, context], axis=1)

    def _selective_threshold(self, oof_err: np.ndarray, oof_pred: np.ndarray, groups: np.ndarray) -> tuple[float, dict[str, Any]]:
        """The certified threshold on the predicted error (Learn then Test on the out-of-fold calibration events).

        Calibration events without a finite estimate count as gross errors. ``unit: position``
        (the default) takes source positions as the independent units (``groups``, the events'
        positions); ``unit: event`` counts detections as independent, which gross errors shared
        within a position violate.
        """
        sel = self.c.selective
        unit = sel.get("unit", "position")
        gross = ~(oof_err <= float(sel["gross_m"]))
        if unit == "position":
            threshold, path = selective_threshold_by_position(oof_pred, gross, groups, float(sel["delta"]), float(sel["epsilon"]))
        else:
            threshold, path = selective_threshold(oof_pred, gross, float(sel["delta"]), float(sel["epsilon"]))
        placed = oof_pred <= threshold
        info = {
            "unit": unit,
            "threshold_m": threshold,
            "delta": float(sel["delta"]),
            "epsilon": float(sel["epsilon"]),
            "gross_m": float(sel["gross_m"]),
            "calibration_share_placed": float(placed.mean()),
            "calibration_share_gross_placed": float(gross[placed].mean()) if placed.any() else float("nan"),
        }
        if not np.isfinite(threshold):
            log.warning(
                "selective localization: no threshold certifies share(error > %g m | placed) <= %g; nothing is placed",
                sel["gross_m"],
                sel["delta"],
            )
        return threshold, info


def _growth(now: np.ndarray, then: np.ndarray) -> np.ndarray:
    """What an allowance ``now`` adds to one ``then`` already held, in quadrature (0 where it is not larger)."""
    return np.sqrt(np.maximum(np.nan_to_num(now) ** 2 - np.nan_to_num(then) ** 2, 0.0))


def _time_span_s(times_s: np.ndarray) -> tuple[float, float] | None:
    """(earliest, latest) of the finite ``times_s``, s; None where none is finite."""
    finite = np.asarray(times_s, dtype=float)[np.isfinite(times_s)]
    return (float(finite.min()), float(finite.max())) if finite.size else None
