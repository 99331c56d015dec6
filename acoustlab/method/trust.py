"""Where the point model may be trusted: its training support, and a gate's decision checked against it.

A point model learned on simulation predicts positions inside the region it was trained on; asked
about a source outside it (a bird 100 m up where the site simulates 0–20 m, a speaker 15 m
outside the array), a tree ensemble returns a point near the edge of its training region with an
error radius calibrated on events it *did* know. A gate that hands over to the model there trades
a good physical fix for an extrapolated guess. This module gives the model an applicability
domain and checks every gate's decision against it:

* **Training support** (``TrainingSupport``): the convex hull of the training sources'
  horizontal positions and their height range, each grown by a margin, and a novelty score of
  the detection's feature row (distance to its nearest training rows in robustly standardised
  feature space, compared with the same distance among the training rows themselves).
* **Solver consistency**: a solver fix is physically consistent where its TDOA residual is no
  larger than (twice) the residuals of good fixes (error ≤ ``good_fix_m``) in the training simulation.
  An array without redundant measurements (3 mics in 2-D: the residual is always 0) cannot
  show consistency; there no fix counts as consistent, and neither does a fix from exactly as
  many mics as unknowns + 1 (``solver__n_mics_used`` < ``solver__dimensions_used`` + 2).
* **The measurements** (the hand-over check): the model's estimate must explain the measured
  time differences (the median over pairs of the nearest GCC candidate's misfit,
  ``candidate_misfit_m``, so that a few pairs whose candidates are all wrong cannot dominate it)
  at least as well as the solver's fix, within a tolerance in position metres: how much worse it
  explains them (m of range difference) times the GDOP at the estimate (m of position per m of
  range difference) may not exceed the ``handover_quantile`` of the same product for accurate
  (≤ ``handover_accurate_m``) out-of-fold model estimates on the simulated training rows. Outside
  an array the range differences change slowly with position, so a misfit in range metres admits
  estimates tens of metres off there; scaled by the GDOP it does not. It needs no training data
  of the site, so it holds where the simulation does not match the site.
* **The radius** (``beyond_radius``, part of the hand-over check): a model estimate farther from the
  solver's fix than the detection's own widest finite radius is not reported, unless the array's
  redundancy shows that fix inconsistent with its time differences (then the gate's hand-over stands). The radius states
  that the truth lies within it of the reported estimate; reporting a model estimate that far from
  a fix of the same measurements would state that the fix is off by more than the radius, which the
  gate cannot know. Where several GCC candidates of a 3-mic array happen to close the triangle
  (a ghost the measurements cannot tell from the source), this is the rule that keeps the fix.
* **The rule** (``support_cues`` once per rows, ``apply_trust`` per gate): where the gate substituted the model's estimate but the
  model is outside its support (its input is novel, its own estimate lies outside the training
  hull, or the solver's consistent fix lies outside it), the solver's fix is kept and the row
  says why. With no solver fix and the model outside its support, the method abstains (NaN).

Measured off the simulator by ``experiments/cross_simulator.py`` (``experiments/results/cross_simulator.md``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.contracts import GateDecision
from acoustlab.core.errors import ConfigError

log = logging.getLogger(__name__)

#: Why a row's estimate is what it is, after the trust check (``trust_reason`` in predictions and positions).
REASON_GATE = ""
REASON_SOLVER_OUTSIDE = "solver fix kept: consistent and outside the model's training region"
REASON_NOVEL = "solver fix kept: the detection is unlike the model's training data"
REASON_MODEL_OUTSIDE = "solver fix kept: the model's estimate lies outside its training region"
REASON_EXPLAINS_WORSE = "solver fix kept: the model's estimate explains the measured time differences worse"
REASON_MIC_DROPPED = "solver fix kept: a mic's clip was unusable and left out, and the model's features include it"
REASON_BEYOND_RADIUS = "solver fix kept: the model's estimate lies farther from it than the detection's widest radius"
REASON_ABSTAIN = "no estimate: no solver fix, and the model is outside its training support"
REASON_ABSTAIN_MISFIT = "no estimate: no solver fix, and the model's estimate does not explain the measured time differences"


@dataclass
class TrustSettings:
    """When the point model counts as outside its training support (``pipeline.trust`` in the config).

    Attributes
    ----------
    enabled : bool
        False: every gate decision stands as the gate made it.
    support_margin_m : float
        The training sources' horizontal convex hull is grown by this, m.
    height_margin_m : float
        The training sources' height range is grown by this, m (a 3-D fix outside it is outside the support).
    novelty_factor : float
        A detection is novel where its mean distance to its ``n_neighbors`` nearest training rows
        exceeds this × the ``novelty_quantile`` of the training rows' own such distances (0: no novelty check).
    novelty_quantile : float
        Quantile of the training rows' leave-self-out neighbour distances that sets the scale.
    n_neighbors : int
        Neighbours of the novelty score.
    good_fix_m : float
        Training fixes with a 2-D error at most this (m) define "consistent" residuals.
    residual_quantile, residual_factor : float
        A fix is consistent where its residual is at most ``residual_factor`` × this quantile of the
        good fixes' residuals (a gross fix's residual is typically orders of magnitude larger).
    handover_check : bool
        False: no hand-over is checked against the measured time differences.
    handover_accurate_m : float
        Out-of-fold model estimates within this 2-D error (m) of the truth set the tolerance.
    handover_quantile : float
        The tolerance is this quantile of their candidate misfits (m of range difference).
    """

    enabled: bool = True
    support_margin_m: float = 2.0
    height_margin_m: float = 2.0
    novelty_factor: float = 1.5
    novelty_quantile: float = 0.99
    n_neighbors: int = 5
    good_fix_m: float = 1.0
    residual_quantile: float = 0.99
    residual_factor: float = 2.0
    handover_check: bool = True
    handover_accurate_m: float = 2.0
    handover_quantile: float = 0.95

    def __post_init__(self) -> None:
        for name in ("support_margin_m", "height_margin_m", "novelty_factor", "good_fix_m", "residual_factor", "handover_accurate_m"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ConfigError(f"pipeline.trust.{name} must be a finite number >= 0; got {value}")
        for name in ("novelty_quantile", "residual_quantile", "handover_quantile"):
            if not 0 < getattr(self, name) <= 1:
                raise ConfigError(f"pipeline.trust.{name} must lie in (0, 1]; got {getattr(self, name)}")
        if self.n_neighbors < 1:
            raise ConfigError(f"pipeline.trust.n_neighbors must be >= 1; got {self.n_neighbors}")


def _hull_excess_m(hull_equations: np.ndarray, points_m: np.ndarray) -> np.ndarray:
    """(N,) how far each 2-D point lies outside a convex hull, m (≤ 0 inside; the largest facet-plane distance)."""
    return (points_m @ hull_equations[:, :2].T + hull_equations[:, 2]).max(axis=1)


class TrainingSupport:
    """The region and the feature rows a point model was trained on (module docstring).

    Parameters
    ----------
    settings : TrustSettings
        Margins, novelty and consistency settings.
    """

    def __init__(self, settings: TrustSettings) -> None:
        self.settings = settings

    def fit(
        self,
        features: pd.DataFrame,
        truth_m: np.ndarray,
        solver_error_m: np.ndarray,
        groups: np.ndarray,
        model_misfit_m: np.ndarray | None = None,
        model_error_m: np.ndarray | None = None,
    ) -> TrainingSupport:
        """Learn the support from training rows.

        Parameters
        ----------
        features : pandas.DataFrame
            The point model's input columns of the training rows.
        truth_m : numpy.ndarray
            (N, 3) true source positions, m (z may be NaN: the height check is then off).
        solver_error_m : numpy.ndarray
            (N,) the solver's 2-D error on those rows, m (inf without a fix).
        groups : numpy.ndarray
            (N,) source position of each row: a row's neighbours for the novelty scale come from
            other positions (events at one position are near-copies of each other, so their own
            distances would make every new position look novel).
        model_misfit_m, model_error_m : numpy.ndarray, optional
            (N,) out-of-fold model estimates' candidate misfits times the GDOP at each (m of position)
            and their 2-D errors, m: they set the hand-over tolerance (``handover_tolerance_m_``;
            None, and no hand-over check, without them).
        """
        from scipy.spatial import ConvexHull, QhullError  # imported when fitting: the config schema imports this module

        s = self.settings
        xy = np.asarray(truth_m, dtype=float)[:, :2]
        xy = xy[np.isfinite(xy).all(axis=1)]
        try:
            hull = ConvexHull(xy)
            self.hull_equations_, self.hull_vertices_m_ = hull.equations, xy[hull.vertices]
        except (QhullError, ValueError):  # collinear or too few sources: a box around them instead
            low, high = xy.min(axis=0), xy.max(axis=0)
            self.hull_equations_ = np.array([[-1, 0, low[0]], [1, 0, -high[0]], [0, -1, low[1]], [0, 1, -high[1]]], dtype=float)
            self.hull_vertices_m_ = np.array([[low[0], low[1]], [high[0], low[1]], [high[0], high[1]], [low[0], high[1]]])
        z = np.asarray(truth_m, dtype=float)[:, 2] if np.shape(truth_m)[1] > 2 else np.array([np.nan])
        z = z[np.isfinite(z)]
        self.height_range_m_ = (float(z.min()), float(z.max())) if z.size else None
        self._fit_novelty(features, np.asarray(groups))
        residual = features[col.solver_column("residual_s")].to_numpy(float) if col.solver_column("residual_s") in features else None
        good = np.asarray(solver_error_m) <= s.good_fix_m
        good_residuals = residual[good & np.isfinite(residual)] if residual is not None else np.array([])
        # an array without redundancy fits any fix exactly (residual ≈ 0): consistency cannot be shown there
        self.residual_limit_s_ = (
            float(s.residual_factor * np.quantile(good_residuals, s.residual_quantile)) if good_residuals.size >= 10 else None
        )
        if self.residual_limit_s_ is not None and self.residual_limit_s_ < 1e-9:
            self.residual_limit_s_ = None
        self.handover_tolerance_m_ = self._handover_tolerance(model_misfit_m, model_error_m)
        return self

    def _handover_tolerance(self, misfit_m: np.ndarray | None, error_m: np.ndarray | None) -> float | None:
        """The GDOP-scaled misfit (m of position) that accurate model estimates stay within on simulation; None: no check."""
        s = self.settings
        if not s.handover_check or misfit_m is None or error_m is None:
            return None
        misfit_m, error_m = np.asarray(misfit_m, dtype=float), np.asarray(error_m, dtype=float)
        accurate = np.isfinite(misfit_m) & (error_m <= s.handover_accurate_m)
        if accurate.sum() < 10:
            log.warning(
                "hand-over check off: only %d out-of-fold model estimates within %.3g m of the truth (10 needed to set its tolerance)",
                int(accurate.sum()),
                s.handover_accurate_m,
            )
            return None
        return float(np.quantile(misfit_m[accurate], s.handover_quantile))

    def _fit_novelty(self, features: pd.DataFrame, groups: np.ndarray) -> None:
        s = self.settings
        x = np.where(np.isfinite(features.to_numpy(float)), features.to_numpy(float), np.nan)
        self.columns_ = list(features.columns)
        present = np.isfinite(x).any(axis=0)  # a column missing in every training row carries nothing (centre 0, scale 1)
        self.centre_, self.scale_ = np.zeros(x.shape[1]), np.ones(x.shape[1])
        if present.any():
            low, centre, high = np.nanpercentile(x[:, present], [25, 50, 75], axis=0)
            self.centre_[present] = centre
            self.scale_[present] = np.where(high - low > 0, high - low, 1.0)
        if s.novelty_factor == 0 or len(x) <= s.n_neighbors + 1:
            self.neighbours_, self.novelty_limit_ = None, np.inf
            return
        from sklearn.neighbors import NearestNeighbors

        z = self._standardise(x)
        per_position = int(np.unique(groups, return_counts=True)[1].max())
        # a k-d tree sums each pair's squared differences itself; the brute-force path's matrix product rounds by how many
        # rows are asked at once, so a detection's novelty would depend on its batch (one ulp, but not bit for bit)
        self.neighbours_ = NearestNeighbors(n_neighbors=min(len(x), s.n_neighbors + per_position), algorithm="kd_tree").fit(z)
        distance, index = self.neighbours_.kneighbors(z)
        other = groups[index] != groups[:, None]  # leave the row's own position out
        own = np.array([d[o][: s.n_neighbors].mean() if o.any() else np.nan for d, o in zip(distance, other, strict=True)])
        own = own[np.isfinite(own)]
        if own.size == 0:
            self.neighbours_, self.novelty_limit_ = None, np.inf
            return
        self.novelty_limit_ = float(s.novelty_factor * np.quantile(own, s.novelty_quantile))

    def _standardise(self, x: np.ndarray) -> np.ndarray:
        z = (x - self.centre_) / self.scale_
        # a missing value sits at the centre; a huge one (a diverged diagnostic) counts, but bounded
        return np.clip(np.where(np.isfinite(z), z, 0.0), -50.0, 50.0)

    def novelty(self, features: pd.DataFrame) -> np.ndarray:
        """(B,) mean distance to the nearest training rows ÷ the novelty limit (> 1: novel; 0 without the check)."""
        if self.neighbours_ is None:
            return np.zeros(len(features))
        distance, _ = self.neighbours_.kneighbors(
            self._standardise(features[self.columns_].to_numpy(float)), n_neighbors=self.settings.n_neighbors
        )
        return distance.mean(axis=1) / self.novelty_limit_

    def outside_region(self, position_m: np.ndarray, height_m: np.ndarray | None = None) -> np.ndarray:
        """(B,) True where a finite position lies outside the grown hull (or a given height outside the grown height range)."""
        position_m = np.asarray(position_m, dtype=float)
        finite = np.isfinite(position_m).all(axis=1)
        outside = np.zeros(len(position_m), dtype=bool)
        outside[finite] = _hull_excess_m(self.hull_equations_, position_m[finite]) > self.settings.support_margin_m
        if height_m is not None and self.height_range_m_ is not None:
            low, high = self.height_range_m_
            h = np.asarray(height_m, dtype=float)
            margin = self.settings.height_margin_m
            outside |= finite & np.isfinite(h) & ((h < low - margin) | (h > high + margin))
        return outside

    def consistent(self, features: pd.DataFrame) -> np.ndarray:
        """(B,) True where the solver's fix fits its TDOAs as well as good training fixes did (False without redundancy)."""
        return self._residual_excess_s(features) <= 0  # NaN (cannot tell) compares False

    def inconsistent(self, features: pd.DataFrame) -> np.ndarray:
        """(B,) True where the array's redundancy shows the solver's fix does not fit its TDOAs (False where it cannot tell)."""
        return self._residual_excess_s(features) > 0

    def _residual_excess_s(self, features: pd.DataFrame) -> np.ndarray:
        """(B,) each fix's TDOA residual less the consistency limit, s; NaN where the residual cannot tell."""
        name = col.solver_column("residual_s")
        if self.residual_limit_s_ is None or name not in features:
            return np.full(len(features), np.nan)
        excess = features[name].to_numpy(float) - self.residual_limit_s_
        used, dims = col.solver_column("n_mics_used"), col.solver_column("dimensions_used")
        if used in features and dims in features:  # a fix from exactly as many mics as unknowns + 1 fits any TDOAs: no evidence
            n_used, n_dims = features[used].to_numpy(float), features[dims].to_numpy(float)
            known = np.isfinite(n_used) & np.isfinite(n_dims)
            excess[known & (n_used < n_dims + 2)] = np.nan
        return excess

    def description(self) -> dict[str, Any]:
        """The training region for metrics.json: hull vertices (m), height range (m), limits."""
        return {
            "hull_vertices_m": np.round(self.hull_vertices_m_, 3).tolist(),
            "height_range_m": None if self.height_range_m_ is None else [round(v, 3) for v in self.height_range_m_],
            "support_margin_m": self.settings.support_margin_m,
            "height_margin_m": self.settings.height_margin_m,
            "residual_limit_s": self.residual_limit_s_,
            "novelty_limit": None if not np.isfinite(self.novelty_limit_) else self.novelty_limit_,
            "handover_tolerance_m": self.handover_tolerance_m_,
        }


@dataclass
class TrustedDecision:
    """A gate's decision after the trust check.

    Attributes
    ----------
    decision : GateDecision
        The estimate each row reports (NaN where the method abstains) and whether it is the model's.
    reason : numpy.ndarray
        (B,) object: why the gate's choice was overridden ('' where it stands).
    flags : dict of str to numpy.ndarray
        ``novelty``, ``solver_outside_support``, ``model_outside_support``, ``solver_consistent`` per row.
    gate_position_m : numpy.ndarray
        (B, 2) what the gate chose before the check (for comparison).
    """

    decision: GateDecision
    reason: np.ndarray
    flags: dict[str, np.ndarray]
    gate_position_m: np.ndarray


def solver_height(features: pd.DataFrame) -> np.ndarray | None:
    """(B,) the solver's estimated source height where a 3-D fix was kept, NaN elsewhere; None for a 2-D solver."""
    if col.SOLVER_SOURCE_HEIGHT not in features or col.solver_column("dimensions_used") not in features:
        return None
    height = features[col.SOLVER_SOURCE_HEIGHT].to_numpy(float)
    return np.where(features[col.solver_column("dimensions_used")].to_numpy(float) == 3, height, np.nan)


@dataclass
class SupportCues:
    """Each row checked against the point model's training support: the same for every gate deciding on those rows.

    Attributes
    ----------
    flags : dict of str to numpy.ndarray
        ``novelty``, ``solver_outside_support``, ``model_outside_support``, ``solver_consistent`` per row.
    distrust : numpy.ndarray
        (B,) object: why the model's estimate must not be used there ('' where it may).
    """

    flags: dict[str, np.ndarray]
    distrust: np.ndarray


def support_cues(
    solver_xy: np.ndarray,
    model_xy: np.ndarray,
    features: pd.DataFrame,
    model_features: pd.DataFrame,
    support: TrainingSupport | None,
    misfit_m: tuple[np.ndarray, np.ndarray] | None = None,
    model_gdop: np.ndarray | None = None,
) -> SupportCues:
    """Check rows against the point model's training support (module docstring); no gate is involved yet.

    Parameters
    ----------
    solver_xy, model_xy : numpy.ndarray
        (B, 2) the solver's and the point model's estimates, m.
    features : pandas.DataFrame
        The rows' full feature table (solver columns included).
    model_features : pandas.DataFrame
        The point model's input columns of the rows.
    support : TrainingSupport or None
        None: nothing is distrusted.
    misfit_m : tuple of numpy.ndarray, optional
        (B,) candidate misfits (``candidate_misfit_m``) of the solver's fix and of the model's
        estimate, m of range difference; with the support's hand-over tolerance they decide the hand-over check.
    model_gdop : numpy.ndarray, optional
        (B,) GDOP at the model's estimates: turns the misfit's excess into position metres (1 where not given).
    """
    n = len(solver_xy)
    if support is None:
        empty = np.zeros(n, dtype=bool)
        return SupportCues(
            {
                "novelty": np.zeros(n),
                "solver_outside_support": empty,
                "model_outside_support": empty,
                "solver_consistent": empty,
                "model_misfit_excess_m": np.full(n, np.nan),
            },
            np.full(n, REASON_GATE, dtype=object),
        )
    novelty = support.novelty(model_features)
    solver_outside = support.outside_region(solver_xy, solver_height(features))
    model_outside = support.outside_region(model_xy)
    consistent = support.consistent(features)
    excess = misfit_excess_position_m(misfit_m, model_gdop, n)
    tolerance = support.handover_tolerance_m_
    explains_worse = np.zeros(n, dtype=bool) if tolerance is None else np.isfinite(excess) & (excess > tolerance)
    distrust = np.full(n, REASON_GATE, dtype=object)
    # the order sets which reason is reported where several apply: the measurements first, then the physical region
    for applies, why in (
        (explains_worse, REASON_EXPLAINS_WORSE),
        (model_outside, REASON_MODEL_OUTSIDE),
        (novelty > 1, REASON_NOVEL),
        (solver_outside & consistent, REASON_SOLVER_OUTSIDE),
    ):
        distrust = np.where(applies & (distrust == REASON_GATE), why, distrust)
    flags = {
        "novelty": novelty,
        "solver_outside_support": solver_outside,
        "model_outside_support": model_outside,
        "solver_consistent": consistent,
        "model_misfit_excess_m": excess,
    }
    return SupportCues(flags, distrust)


def misfit_excess_position_m(misfit_m: tuple[np.ndarray, np.ndarray] | None, model_gdop: np.ndarray | None, n: int) -> np.ndarray:
    """(B,) how much worse the model's estimate explains the time differences than the solver's fix, in position metres.

    The excess of the model's misfit over the solver's (m of range difference) times the GDOP at
    the model's estimate (1 where not given). Without a solver fix the model's misfit is compared
    with a perfect fit (0); NaN where the model's misfit is unknown (no candidates, no estimate).
    """
    if misfit_m is None:
        return np.full(n, np.nan)
    solver, model = (np.asarray(m, dtype=float) for m in misfit_m)
    scale = np.ones(n) if model_gdop is None else np.asarray(model_gdop, dtype=float)
    return (model - np.where(np.isfinite(solver), solver, 0.0)) * scale


def beyond_radius(
    substituted: np.ndarray, reported_xy: np.ndarray, solver_xy: np.ndarray, radii_m: np.ndarray, solver_wrong: np.ndarray | None = None
) -> np.ndarray:
    """(B,) the hand-overs whose model estimate lies farther from the solver's fix than the row's widest finite radius.

    A fix the array's redundancy shows wrong (``solver_wrong``: its residual above good fixes') is
    exactly where a gate should hand over, however far the model's estimate lies from it; such rows
    never count. Where the residual cannot tell (a 3-mic array fits every fix exactly), the fix is
    what the measurements give, and the rule holds.

    Parameters
    ----------
    substituted : numpy.ndarray
        (B,) bool: the reported estimate is the point model's.
    reported_xy, solver_xy : numpy.ndarray
        (B, 2) the reported estimates and the solver's fixes, m (a row without a fix never counts).
    radii_m : numpy.ndarray
        (B, R) every radius of each row, m (infinite or NaN ones, a level without a guarantee, are
        left out; a row without a finite radius never counts).
    solver_wrong : numpy.ndarray, optional
        (B,) bool: the fix is known inconsistent (``TrainingSupport.inconsistent``).
    """
    radii = np.where(np.isfinite(radii_m), radii_m, -np.inf)
    widest = radii.max(axis=1, initial=-np.inf)
    distance = np.hypot(*(np.asarray(reported_xy, dtype=float) - np.asarray(solver_xy, dtype=float)).T)
    wrong = np.zeros(len(widest), dtype=bool) if solver_wrong is None else np.asarray(solver_wrong, dtype=bool)
    return np.asarray(substituted, dtype=bool) & ~wrong & np.isfinite(widest) & np.isfinite(distance) & (distance > widest)


def splice_trusted(whole: TrustedDecision, rows: np.ndarray, part: TrustedDecision) -> TrustedDecision:
    """``whole`` with its ``rows`` replaced by ``part`` (the same rows decided again)."""

    def put(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        out = np.array(a, copy=True)
        out[rows] = b
        return out

    decision = GateDecision(
        put(whole.decision.position_m, part.decision.position_m), put(whole.decision.substituted, part.decision.substituted)
    )
    flags = {name: put(values, part.flags[name]) for name, values in whole.flags.items()}
    return TrustedDecision(decision, put(whole.reason, part.reason), flags, put(whole.gate_position_m, part.gate_position_m))


def apply_trust(decision: GateDecision, solver_xy: np.ndarray, cues: SupportCues) -> TrustedDecision:
    """A gate's decision with every hand-over to a distrusted model estimate undone (the solver's fix kept, or no estimate).

    Parameters
    ----------
    decision : GateDecision
        What the gate chose.
    solver_xy : numpy.ndarray
        (B, 2) the solver's estimates, m.
    cues : SupportCues
        The rows checked against the training support (``support_cues``).
    """
    distrusted = cues.distrust != REASON_GATE
    solver_fix = np.isfinite(solver_xy).all(axis=1)
    keep_solver = decision.substituted & distrusted & solver_fix
    abstain = decision.substituted & distrusted & ~solver_fix
    why_abstain = np.where(cues.distrust == REASON_EXPLAINS_WORSE, REASON_ABSTAIN_MISFIT, REASON_ABSTAIN)
    reason = np.where(keep_solver, cues.distrust, np.where(abstain, why_abstain, REASON_GATE))
    position = np.where(keep_solver[:, None], solver_xy, decision.position_m)
    position[abstain] = np.nan
    return TrustedDecision(GateDecision(position, decision.substituted & ~keep_solver & ~abstain), reason, cues.flags, decision.position_m)
