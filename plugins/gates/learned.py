"""Learned gate: a classifier of "the solver's fix is worse than the model's", trained on simulation.

The hybrid gate's energy residual separates gross solver fixes from good ones poorly (AUC ≈ 0.7
on the forest); the solver's own diagnostics do much better: the RMS TDOA residual, the
consistency of the chosen TDOA set and its margin over the runner-up, GDOP, conditioning, and the
distance between the solver's and the point model's estimates. This gate feeds those cues to a
gradient-boosted classifier (scikit-learn's ``HistGradientBoostingClassifier``, which takes NaN as
missing) whose label is "the solver's error exceeds the model's".

Training is on simulation only and out-of-fold by source position: the classifier's probabilities
on the training events come from fits that never saw that position, and the substitution
threshold is chosen on them: the one with the lowest p95 error whose median error stays within
``p50_tolerance`` of the box-gated solver's. A solver failure (no fix, or one outside the box) is
always substituted. With ``stakes_cap_m`` each training event weighs what a wrong choice costs
there (|solver error − model error|, capped): most events differ by centimetres either way, and
an unweighted classifier spends its capacity on them rather than on the few events that set the
gated p99 (frozen lake, cross-fitted: gate p99 ÷ oracle p99 1.24 unweighted, 1.12 with a 20 m cap).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pandas as pd
from sklearn.ensemble import HistGradientBoostingClassifier
from sklearn.metrics import roc_auc_score
from sklearn.model_selection import GroupKFold
from threadpoolctl import threadpool_limits

from acoustlab.core import columns as col
from acoustlab.core.contracts import GateDecision
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.types import Site
from acoustlab.toolkit.event_physics import source_height_m
from acoustlab.toolkit.geometry import bounding_box
from acoustlab.toolkit.quantile_bins import BinnedColumns
from acoustlab.toolkit.tdoa import energy_residual_db

log = logging.getLogger(__name__)


def gate_cues(solver_position_m: np.ndarray, model_position_m: np.ndarray, features: pd.DataFrame, site: Site) -> pd.DataFrame:
    """The classifier's inputs: the solver's diagnostics, solver–model distance, energy residuals, box and range cues.

    Returns
    -------
    pandas.DataFrame
        One row per event; NaN where a cue is unavailable (e.g. no solver fix).
    """
    cues = {
        name: features[name].to_numpy(float)
        for name in features.columns
        if col.group_of(name) == "solver" and name not in col.SOLVER_ESTIMATE_COLUMNS
    }
    cues[col.SOLVER_MODEL_DISTANCE] = np.sqrt(((solver_position_m - model_position_m) ** 2).sum(axis=1))
    centre = site.mic_positions_m[:, :2].mean(axis=0)
    cues["solver_range_from_centre_m"] = np.sqrt(((solver_position_m - centre) ** 2).sum(axis=1))
    cues["model_range_from_centre_m"] = np.sqrt(((model_position_m - centre) ** 2).sum(axis=1))
    levels = [col.level_db(m) for m in range(site.n_mics)]
    if all(c in features.columns for c in levels):
        height = source_height_m(features, site)
        lv = features[levels].to_numpy(float)
        solver_energy = energy_residual_db(lv, site.mic_positions_m, np.nan_to_num(solver_position_m), height)
        cues["energy_residual_solver_db"] = np.where(np.isfinite(solver_position_m).all(1), solver_energy, np.nan)
        cues["energy_residual_model_db"] = energy_residual_db(lv, site.mic_positions_m, np.nan_to_num(model_position_m), height)
        cues["energy_residual_difference_db"] = cues["energy_residual_solver_db"] - cues["energy_residual_model_db"]
    return pd.DataFrame(cues, index=features.index)


class LearnedGate:
    """Substitute the model's estimate where a classifier says the solver's is worse (module docstring).

    Parameters
    ----------
    margin_fraction : float
        Box of stage 1: a solver fix outside the mics' box grown by this fraction of the array
        extent is always substituted.
    p50_tolerance : float
        The threshold keeps the gated median within (1 + this) × the box-gated solver's median.
    n_folds : int
        Position-grouped folds for the out-of-fold probabilities.
    max_iter, learning_rate, max_leaf_nodes : int, float, int
        Settings of the gradient-boosted classifier.
    stakes_cap_m : float or None
        Weight each training event by what the choice costs there, ``|solver error − model error|``
        capped at this many metres (default 20 m, as ``conf/gate/learned.yaml``; None: every event weighs the same). Most events differ by
        centimetres either way; the events where a wrong choice costs metres are the ones that
        set the gated p95 and p99.
    min_auc : float
        Fall back to the box-gated solver (substitute failures only) where the classifier's
        out-of-fold AUC is below this: it cannot tell good fixes from bad ones.
    min_class_events : int
        … or where either class ("solver worse" / "model worse") has fewer training events than this.
    seed : int
        Seed of the classifier.
    n_threads : int
        OpenMP threads of the classifier (``${threads:}`` in the config: the free cores).

    Notes
    -----
    The gate is never worse than the box-gated solver on its own out-of-fold training
    predictions: where the chosen threshold's gated p95 or p99 exceeds that reference's, it falls
    back too. ``diagnostics()["fallback"]`` says why (None where the classifier decides).
    """

    required_feature_groups: tuple[str, ...] = ()

    def __init__(
        self,
        margin_fraction: float = 0.25,
        p50_tolerance: float = 0.05,
        n_folds: int = 5,
        max_iter: int = 200,
        learning_rate: float = 0.05,
        max_leaf_nodes: int = 15,
        stakes_cap_m: float | None = 20.0,
        min_auc: float = 0.6,
        min_class_events: int = 10,
        seed: int = 0,
        n_threads: int = 1,
    ) -> None:
        if n_folds < 2:
            raise ConfigError(f"gate.n_folds must be >= 2; got {n_folds}")
        if p50_tolerance < 0:
            raise ConfigError(f"gate.p50_tolerance must be >= 0; got {p50_tolerance}")
        self.margin_fraction = float(margin_fraction)
        self.p50_tolerance = float(p50_tolerance)
        self.n_folds = int(n_folds)
        self.max_iter = int(max_iter)
        self.learning_rate = float(learning_rate)
        self.max_leaf_nodes = int(max_leaf_nodes)
        if stakes_cap_m is not None and not stakes_cap_m > 0:
            raise ConfigError(f"gate.stakes_cap_m must be > 0 m or null; got {stakes_cap_m}")
        self.stakes_cap_m = None if stakes_cap_m is None else float(stakes_cap_m)
        if not 0 <= min_auc <= 1:
            raise ConfigError(f"gate.min_auc must lie in [0, 1]; got {min_auc}")
        self.min_auc = float(min_auc)
        self.min_class_events = max(1, int(min_class_events))
        self.seed = int(seed)
        self.n_threads = max(1, int(n_threads))

    def _classifier(self) -> HistGradientBoostingClassifier:
        return HistGradientBoostingClassifier(
            max_iter=self.max_iter, learning_rate=self.learning_rate, max_leaf_nodes=self.max_leaf_nodes, random_state=self.seed
        )

    def _fit_classifier(self, x: pd.DataFrame, y: np.ndarray, w: np.ndarray | None) -> tuple[BinnedColumns, HistGradientBoostingClassifier]:
        """The classifier fitted on the cues as bin numbers (each where that grows the same trees), and the bins.

        The bins are the classifier's own (``acoustlab.toolkit.quantile_bins``), found in one pass:
        with sample weights scikit-learn finds them one quantile at a time, most of a gate's fit.
        """
        bins = BinnedColumns().fit(x, w)
        return bins, self._classifier().fit(bins.transform(x), y, sample_weight=w)

    def _failed(self, solver_position_m: np.ndarray, site: Site) -> np.ndarray:
        low, high = bounding_box(site.mic_positions_m, self.margin_fraction)
        finite = np.isfinite(solver_position_m).all(axis=1)
        return ~finite | ~np.where(finite[:, None], (solver_position_m >= low) & (solver_position_m <= high), False).all(axis=1)

    def fit(
        self,
        solver_position_m: np.ndarray,
        model_position_m: np.ndarray,
        features: pd.DataFrame,
        site: Site,
        truth_m: np.ndarray,
        groups: np.ndarray | None = None,
    ) -> LearnedGate:
        """Train the classifier and choose the threshold on simulated events (out-of-fold by position)."""
        with threadpool_limits(limits=self.n_threads, user_api="openmp"):
            return self._fit(solver_position_m, model_position_m, features, site, truth_m, groups)

    def _fit(
        self,
        solver_position_m: np.ndarray,
        model_position_m: np.ndarray,
        features: pd.DataFrame,
        site: Site,
        truth_m: np.ndarray,
        groups: np.ndarray | None,
    ) -> LearnedGate:
        if groups is None:
            raise DataError("the learned gate needs the events' source positions (groups) to train out-of-fold")
        cues = gate_cues(solver_position_m, model_position_m, features, site)
        failed = self._failed(solver_position_m, site)
        err_solver = np.sqrt(((solver_position_m - truth_m[:, :2]) ** 2).sum(axis=1))
        err_model = np.sqrt(((model_position_m - truth_m[:, :2]) ** 2).sum(axis=1))
        err_solver = np.where(failed | ~np.isfinite(err_solver), np.inf, err_solver)
        label = (err_solver > err_model).astype(int)
        use = ~failed
        # cues that are missing for every training event (e.g. a 3-D diagnostic of a 2-D solver) carry nothing
        self.columns_ = [c for c in cues.columns if np.isfinite(cues[c].to_numpy(float)[use]).any()]
        cues = cues[self.columns_]
        smallest_class = int(min(label[use].sum(), (1 - label[use]).sum()))
        if use.sum() < 20 or smallest_class < self.min_class_events or np.unique(groups[use]).size < self.n_folds:
            return self._fall_back(
                f"too few usable training events ({int(use.sum())}) or positions, or a class with fewer than "
                f"{self.min_class_events} events ({smallest_class})"
            )
        x, y, g = cues[use], label[use], groups[use]
        w = self._weights(err_solver[use], err_model[use])
        oof = np.empty(use.sum())
        for fit_idx, held_idx in GroupKFold(n_splits=self.n_folds).split(x, y, g):
            # a cue missing for every event of this fold's training part is left out of this fold's classifier
            cols = [c for c in x.columns if np.isfinite(x[c].to_numpy(float)[fit_idx]).any()]
            if np.unique(y[fit_idx]).size > 1:
                bins, clf = self._fit_classifier(x.iloc[fit_idx][cols], y[fit_idx], None if w is None else w[fit_idx])
                oof[held_idx] = _probability(bins, clf, x.iloc[held_idx][cols])
            else:
                oof[held_idx] = float(y[fit_idx][0])
        auc = float(roc_auc_score(y, oof))
        if auc < self.min_auc:
            return self._fall_back(f"out-of-fold AUC {auc:.3f} is below gate.min_auc={self.min_auc:g}", auc)
        threshold, grid = self._choose_threshold(oof, err_solver[use], err_model[use], err_model[~use])
        chosen, reference = grid.loc[grid["threshold"] == threshold].iloc[0], grid.iloc[-1]  # the last row: never substitute (inf)
        if chosen["p95_m"] > reference["p95_m"] or chosen["p99_m"] > reference["p99_m"]:
            return self._fall_back(
                f"its out-of-fold p95/p99 ({chosen['p95_m']:.3g}/{chosen['p99_m']:.3g} m) would exceed the box-gated "
                f"solver's ({reference['p95_m']:.3g}/{reference['p99_m']:.3g} m)",
                auc,
                grid,
            )
        self.oof_auc_, self.threshold_, self.threshold_grid_, self.fallback_ = auc, threshold, _records(grid), None
        self.bins_, self.classifier_ = self._fit_classifier(x, y, w)
        log.info("learned gate: out-of-fold AUC %.3f, threshold %.3f", self.oof_auc_, self.threshold_)
        return self

    def _fall_back(self, why: str, auc: float | None = None, grid: pd.DataFrame | None = None) -> LearnedGate:
        """Decide as the box-gated solver (substitute failures only) and say why."""
        log.warning("learned gate falls back to the solver's fix (substituting failures only): %s", why)
        self.bins_, self.classifier_, self.threshold_, self.oof_auc_ = None, None, np.inf, auc
        self.threshold_grid_, self.fallback_ = _records(grid), why
        return self

    def _weights(self, err_solver: np.ndarray, err_model: np.ndarray) -> np.ndarray | None:
        """(N,) sample weights, the capped cost of the wrong choice (m; at least 1 mm so no event is ignored); None: equal weights.

        (None rather than ones: with any sample weights scikit-learn's gradient boosting bins by weighted quantiles.)
        """
        if self.stakes_cap_m is None:
            return None
        return np.clip(np.abs(err_solver - err_model), 1e-3, self.stakes_cap_m)

    def _choose_threshold(
        self, prob: np.ndarray, err_solver: np.ndarray, err_model: np.ndarray, err_failed: np.ndarray
    ) -> tuple[float, pd.DataFrame]:
        """Lowest gated p95 with the median within tolerance of the box-gated solver's (failures take the model)."""
        thresholds = np.unique(np.concatenate([np.quantile(prob, np.linspace(0, 1, 101)), [np.inf]]))
        reference_p50 = np.median(np.concatenate([err_solver, err_failed]))
        rows = []
        for t in thresholds:
            gated = np.concatenate([np.where(prob > t, err_model, err_solver), err_failed])
            rows.append(
                {
                    "threshold": float(t),
                    "p50_m": float(np.median(gated)),
                    "p95_m": float(np.percentile(gated, 95)),
                    "p99_m": float(np.percentile(gated, 99)),
                    "substitution_rate": float(np.mean(np.concatenate([prob > t, np.ones(err_failed.size, bool)]))),
                }
            )
        grid = pd.DataFrame(rows)
        ok = grid["p50_m"] <= (1 + self.p50_tolerance) * reference_p50
        if not ok.any():
            return float(grid.loc[grid["p50_m"].idxmin(), "threshold"]), grid
        # among thresholds tied at the lowest p95 the most permissive (fewest substitutions): the choice
        # is then stable across folds where the p95 curve is flat, and keeps the physical fix where it costs nothing
        best_p95 = grid.loc[ok, "p95_m"].min()
        tied = ok & (grid["p95_m"] <= best_p95 * (1 + 1e-9))
        return float(grid.loc[tied, "threshold"].max()), grid

    def probability(self, solver_position_m: np.ndarray, model_position_m: np.ndarray, features: pd.DataFrame, site: Site) -> np.ndarray:
        """(B,) the classifier's probability that the solver's fix is worse than the model's (1 for failures)."""
        if not hasattr(self, "threshold_"):
            raise DataError("the learned gate must be fitted on simulated events before it decides")
        failed = self._failed(solver_position_m, site)
        prob = np.ones(len(solver_position_m))
        if self.classifier_ is not None and (~failed).any():
            cues = gate_cues(solver_position_m, model_position_m, features, site)
            missing = [c for c in self.columns_ if c not in cues.columns]
            if missing:
                raise DataError(f"the learned gate was trained with cues {missing[:3]} that these events lack")
            with threadpool_limits(limits=self.n_threads, user_api="openmp"):
                # a gate saved before the bins were kept has none: its classifier reads the values
                prob[~failed] = _probability(getattr(self, "bins_", None), self.classifier_, cues.loc[cues.index[~failed], self.columns_])
        return prob

    def decide(self, solver_position_m: np.ndarray, model_position_m: np.ndarray, features: pd.DataFrame, site: Site) -> GateDecision:
        """See ``acoustlab.core.contracts.Gate``."""
        prob = self.probability(solver_position_m, model_position_m, features, site)
        substitute = self._failed(solver_position_m, site) | (prob > self.threshold_)
        return GateDecision(np.where(substitute[:, None], model_position_m, solver_position_m), substitute)

    def diagnostics(self) -> dict[str, Any]:
        """The threshold, the out-of-fold AUC and the threshold grid (records)."""
        if not hasattr(self, "threshold_"):
            return {}
        out: dict[str, Any] = {"threshold": float(self.threshold_), "oof_auc": self.oof_auc_, "fallback": getattr(self, "fallback_", None)}
        if getattr(self, "threshold_grid_", None) is not None:
            out["threshold_grid"] = self.threshold_grid_
        return out


def _probability(bins: BinnedColumns | None, classifier: HistGradientBoostingClassifier, x: pd.DataFrame) -> np.ndarray:
    """(B,) the classifier's probability of "solver worse" for cues ``x`` (as bin numbers where it was fitted on them)."""
    return classifier.predict_proba(x if bins is None else bins.transform(x))[:, 1]


def _records(grid: pd.DataFrame | None) -> list[dict[str, float]] | None:
    """The threshold grid as plain records: a fitted gate is saved without pandas objects (``acoustlab.method.saved``)."""
    return None if grid is None else [{str(k): float(v) for k, v in row.items()} for row in grid.to_dict(orient="records")]
