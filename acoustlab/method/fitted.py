"""The method fitted once on training events (``FittedMethod``): predicts any number of new events, in any chunks.

``acoustlab.method.pipeline.LocalizationPipeline.fit`` makes it; ``acoustlab.method.localizer``
places field detections with it.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.contracts import (
    ConformalScorer,
    Gate,
    declared,
    hook,
)
from acoustlab.method.estimates import TestEstimates, crb_from_features, error_2d_m, hull_distance_extent
from acoustlab.method.trust import (
    REASON_BEYOND_RADIUS,
    REASON_GATE,
    REASON_MIC_DROPPED,
    TrainingSupport,
    TrustedDecision,
    beyond_radius,
    splice_trusted,
)
from acoustlab.toolkit.conformal import calibration_quantile, conformal_quantile
from acoustlab.toolkit.event_physics import source_height_m
from acoustlab.toolkit.regions import ellipse_axes, mahalanobis, shape_matrices

if TYPE_CHECKING:
    from acoustlab.method.pipeline import LocalizationPipeline

log = logging.getLogger(__name__)


@dataclass
class FittedMethod:
    """The method fitted once on training events; predicts any number of new events, in any chunks.

    A row's prediction depends on this object and that row alone, so a season predicted chunk by
    chunk (or shard by shard) gives the rows predicting it at once would give.
    """

    pipeline: LocalizationPipeline
    #: the point model's and the error model's input columns
    mcols: list[str]
    ecols: list[str]
    #: fitted point models for x and y (targets relative to ``LocalizationPipeline._offset``)
    point_models: tuple[Any, Any]
    support: TrainingSupport | None
    gate: Gate
    #: the error model's floor, m
    floor: float
    #: radii calibrated on field rows (then no input-error allowance is added)
    calibrated_on_field: bool
    calibration: dict[str, Any]
    error_model: Any = None
    scorers: dict[str, ConformalScorer] = field(default_factory=dict)
    #: final quantile model(s) of quantile scorers (CQR) with ``fit_quantiles``, by scorer name
    quantile_models: dict[str, Any] = field(default_factory=dict)
    #: (x, error) a quantile scorer with only ``fit_predict_quantiles`` fits its final model on when predicting
    quantile_training: tuple[pd.DataFrame, np.ndarray] | None = None
    #: (train,) out-of-fold predicted errors of the training events, m
    oof_predicted: np.ndarray | None = None
    extra_gates: dict[str, Gate] = field(default_factory=dict)
    #: (threshold_m, diagnostics) of selective localization, or None
    selective: tuple[float, dict[str, Any]] | None = None
    #: field calibration rows with radii calibrated without their own spot (``LocalizationPipeline._held_out_calibration``)
    held_out_calibration: pd.DataFrame | None = None
    #: scorers calibrated on the simulated training rows (``conformal.unsupported_levels=rescaled``), by name
    simulation_scorers: dict[str, ConformalScorer] = field(default_factory=dict)
    #: (error_xy, position, predicted error, source height) of the calibration events, for ellipses
    #: (error xy, position, predicted error, height, position ids or None): the calibration rows of the ellipses (groups: over positions)
    ellipse_calibration: tuple[Any, ...] | None = None
    #: (earliest, latest) time of the field rows that calibrated the radii, s (a calibration's drift grows after them)
    calibration_times_s: tuple[float, float] | None = None

    def split_info(self, trust: dict[str, Any]) -> dict[str, Any]:
        """What the fitted plugins report, for ``MethodResult.split_diagnostics``."""
        info: dict[str, Any] = {"gate": self.gate.diagnostics(), "trust": trust, "calibration": self.calibration}
        for name, gate in self.extra_gates.items():
            info.setdefault("extra_gates", {})[name] = gate.diagnostics()
        if self.selective is not None:
            info["selective"] = self.selective[1]
        return info

    def predict(self, features: pd.DataFrame, events: pd.DataFrame) -> tuple[pd.DataFrame, dict[str, Any]]:
        """Predictions of every row of ``features``/``events`` (same length, same order) and the trust check's summary.

        Truth columns of ``events`` (``x_m, y_m``) may be NaN (field detections): errors are then
        infinite and mean nothing; the localize protocols blank them. Where the hand-over check is on,
        a hand-over whose model estimate lies farther from the solver's fix than the row's widest
        radius (``trust.beyond_radius``) is decided again with the solver's fix kept, and that row's
        error model and radii are those of the fix: rows are predicted independently, so deciding a
        row again gives what deciding it so at once would.
        """
        if len(features) != len(events):
            raise ValueError(f"features ({len(features)} rows) and events ({len(events)} rows) must have the same rows")
        out, trusted = self._predict_rows(features, events)
        far = np.flatnonzero(self._beyond_radius(out, features))
        if far.size:
            again, decided = self._predict_rows(features.iloc[far], events.iloc[far], overrule=REASON_BEYOND_RADIUS)
            again.index = out.index[far]
            out = pd.concat([out.drop(index=out.index[far]), again]).sort_index()
            trusted = splice_trusted(trusted, far, decided)
        return out, self.pipeline._trust_summary(self.support, trusted)

    def _beyond_radius(self, out: pd.DataFrame, features: pd.DataFrame) -> np.ndarray:
        """(B,) the rows ``trust.beyond_radius`` overrules; none where the hand-over check is off or nothing has a radius."""
        radius_columns = [col.radius(name, level) for name in self.scorers for level in self.pipeline.c.levels]
        if self.support is None or not self.support.settings.handover_check or not radius_columns:
            return np.zeros(len(out), dtype=bool)
        return beyond_radius(
            out[col.SUBSTITUTED].to_numpy(bool),
            out[list(col.estimate_xy("gate"))].to_numpy(float),
            out[list(col.estimate_xy("solver"))].to_numpy(float),
            out[radius_columns].to_numpy(float),
            self.support.inconsistent(features),
        )

    def _predict_rows(
        self, features: pd.DataFrame, events: pd.DataFrame, overrule: str | None = None
    ) -> tuple[pd.DataFrame, TrustedDecision]:
        """``predict``'s table and the configured gate's decision; ``overrule``: why every hand-over of these rows is undone."""
        pipe = self.pipeline
        rows = np.arange(len(features))
        solver_xy = features[list(col.SOLVER_ESTIMATE_COLUMNS)].to_numpy(dtype=float)
        truth = events[[col.TRUE_X, col.TRUE_Y]].to_numpy(dtype=float)
        model_xy = pipe._predict_point(self.point_models, features[self.mcols], solver_xy)
        cues = pipe._cues(rows, solver_xy, model_xy, features, self.mcols, self.support)
        if col.MICS_DROPPED in events:  # solved without a bad mic: the point model saw that mic's clip, so its estimate is not used
            dropped = events[col.MICS_DROPPED].fillna("").astype(str).to_numpy() != ""
            cues = dataclasses.replace(cues, distrust=np.where(dropped, REASON_MIC_DROPPED, cues.distrust).astype(object))
        own = (
            cues
            if overrule is None
            else dataclasses.replace(cues, distrust=np.where(cues.distrust == REASON_GATE, overrule, cues.distrust).astype(object))
        )
        trusted = pipe._decide(self.gate, rows, solver_xy, model_xy, features, own)
        gdop_at_estimate = pipe._gdop_at(trusted.decision.position_m, features)
        estimate = TestEstimates(
            model_xy,
            self.support,
            own,
            trusted,
            gdop_at_estimate,
            pipe._error_inputs(features[self.ecols], solver_xy, model_xy, trusted.decision, gdop_at_estimate),
        )
        predicted = np.maximum(self.error_model.predict(estimate.x_error), self.floor)
        out = self._table(features, events, solver_xy, truth, estimate, predicted)
        if self.ellipse_calibration is not None:
            self._add_ellipses(out, trusted.decision.position_m, predicted, features)
        for name, gate in self.extra_gates.items():  # compared on the same predictions, each with the support's own cues
            position = pipe._decide(gate, rows, solver_xy, model_xy, features, cues).decision.position_m
            pipe._add_method(out, col.extra_gate_method(name), position, truth)
        if self.selective is not None:
            self._place_selectively(out, predicted, trusted)
        self._add_radii(out, features, events, estimate, predicted)
        return out, trusted

    def _table(
        self,
        features: pd.DataFrame,
        events: pd.DataFrame,
        solver_xy: np.ndarray,
        truth: np.ndarray,
        t: TestEstimates,
        predicted: np.ndarray,
    ) -> pd.DataFrame:
        """One row per event: truth, every estimate and its error, the oracle, the trust check's cues, GDOPs, predicted error."""
        decision = t.trusted.decision
        solver_gdop = features[col.SOLVER_GDOP].to_numpy(dtype=float) if col.SOLVER_GDOP in features else np.full(len(features), np.nan)
        out = pd.DataFrame(
            {
                col.EVENT_ID: events[col.EVENT_ID].to_numpy(),
                col.POSITION_ID: events[col.POSITION_ID].to_numpy(),
                **dict(zip(col.estimate_xy("true"), (truth[:, 0], truth[:, 1]), strict=True)),
                **{
                    name: xy[:, k]
                    for method, xy in zip(col.ESTIMATORS, (solver_xy, t.model_xy, decision.position_m), strict=True)
                    for k, name in enumerate(col.estimate_xy(method))
                },
                col.SUBSTITUTED: decision.substituted,
                col.TRUST_REASON: t.trusted.reason,
                **{col.trust_flag(name): values for name, values in t.trusted.flags.items()},
                "gdop": t.gdop,
                "solver_gdop": solver_gdop,
                col.PREDICTED_ERROR: predicted,
            }
        )
        crb = crb_from_features(features, events, self.pipeline.c.site)
        if crb is not None:
            out[col.CRB] = crb
        # where coverage is reported by condition (metrics.coverage_by_condition): the true source's distance outside the
        # mics' hull in units of the array extent (0 inside; NaN without truth) and the event's SNR where known
        out[col.HULL_DISTANCE] = hull_distance_extent(self.pipeline.c.site, truth)
        if col.SNR in events:
            out[col.SNR] = events[col.SNR].to_numpy(float)
        for method in col.ESTIMATORS:
            out[col.error_m(method)] = error_2d_m(out[list(col.estimate_xy(method))].to_numpy(), truth)
        # the oracle: the better of solver and model per event (what a perfect gate would reach)
        solver_better = out[col.error_m("solver")].to_numpy() <= out[col.error_m("model")].to_numpy()
        for k, name in enumerate(col.estimate_xy("oracle")):
            out[name] = np.where(solver_better, solver_xy[:, k], t.model_xy[:, k])
        out[col.error_m("oracle")] = np.minimum(out[col.error_m("solver")], out[col.error_m("model")])
        if t.support is not None:  # the configured gate as it decided before the trust check, side by side on the same predictions
            self.pipeline._add_method(out, col.extra_gate_method(col.GATE_WITHOUT_TRUST), t.trusted.gate_position_m, truth)
        return out

    def _place_selectively(self, out: pd.DataFrame, predicted: np.ndarray, trusted: TrustedDecision) -> None:
        """``placed`` and ``abstain_reason`` columns from the certified threshold."""
        threshold = self.selective[0]
        has_fix = np.isfinite(trusted.decision.position_m).all(axis=1)
        out[col.PLACED] = has_fix & (predicted <= threshold)
        out[col.ABSTAIN_REASON] = np.where(
            ~has_fix,
            np.where(trusted.reason != "", trusted.reason, "no estimate"),
            np.where(out[col.PLACED], "", "predicted error above the certified threshold"),
        )

    def _add_radii(self, out: pd.DataFrame, features: pd.DataFrame, events: pd.DataFrame, t: TestEstimates, predicted: np.ndarray) -> None:
        """``radius__<scorer>__<level>`` columns: conformal radii grown by the stated input errors where they apply."""
        c = self.pipeline.c
        found = self.pipeline._input_allowance(
            t.trusted.decision.position_m,
            features,
            events,
            calibrated_on_field=self.calibrated_on_field,
            calibration_times_s=self.calibration_times_s,  # a method saved before the field had none reads the class default
        )
        out[col.INPUT_SIGMA] = found.sigma_m
        allowance = found.radius_m
        row_notes: list[np.ndarray] = []
        for name, scorer in self.scorers.items():
            quantiles = None
            if name in self.quantile_models:
                quantiles = scorer.predict_quantiles(self.quantile_models[name], t.x_error, c.levels)
            elif declared(scorer, "needs_quantiles") and self.quantile_training is not None:
                x_fit, error_fit = self.quantile_training
                quantiles = scorer.fit_predict_quantiles(x_fit, error_fit, t.x_error, c.levels)
            region = self.pipeline._region(scorer, t.trusted.decision.position_m)
            if quantiles is None:
                radii = scorer.radius(predicted, t.gdop, **region)
                notes_of = hook(scorer, "radius_notes")  # a Mondrian bin without calibration events: why its radii are infinite
                if notes_of is not None:
                    row_notes.append(np.array([f"{name}: {n}" if n else "" for n in notes_of(predicted, t.gdop, **region)], dtype=object))
            else:
                radii = scorer.radius(predicted, t.gdop, quantiles=np.maximum(quantiles, self.floor))
            radii = self._rescale_unsupported(name, radii, predicted, t.gdop, region)
            radii = np.sqrt(radii**2 + np.nan_to_num(allowance) ** 2)  # independent error sources add in quadrature
            for k, level in enumerate(c.levels):
                out[col.radius(name, level)] = radii[:, k]
        needed, given = self.calibration.get("positions_needed_by_level", {}), self.calibration.get("n_positions")
        notes = [
            f"radius at {level} not guaranteed (rescaled from the simulation's): a guarantee needs {needed[level]} calibration positions, {given} given"
            if level in self.calibration.get("not_guaranteed_levels", []) and self.simulation_scorers
            else f"no radius at {level}: its guarantee needs {needed[level]} calibration positions, {given} given"
            for level in self.calibration.get("unsupported_levels", [])
        ]
        out[col.RADIUS_NOTE] = (
            ["; ".join([*notes, *(n for n in row if n)]) for row in zip(*row_notes, strict=True)] if row_notes else "; ".join(notes)
        )
        one_set = (self.calibration.get("one_set") or {}).get("covers_at_least", {})
        for level, covers in one_set.items():  # a field calibration: what the user's one set of spots gives each radius
            out[col.one_set_coverage(level)] = np.nan if covers is None else covers

    def _rescale_unsupported(
        self, name: str, radii: np.ndarray, predicted: np.ndarray, gdop: np.ndarray, region: dict[str, np.ndarray]
    ) -> np.ndarray:
        """(B, L) radii with the levels the calibration cannot guarantee empty (NaN), or rescaled from the simulation's.

        Too few calibration positions for a guarantee at a level: no radius (an infinite one says
        nothing), unless ``conformal.unsupported_levels=rescaled`` (``NOT_GUARANTEED_METHOD``).
        """
        keys = [col.level_key(level) for level in self.pipeline.c.levels]
        unsupported = np.array([key in self.calibration.get("unsupported_levels", []) for key in keys])
        if not unsupported.any():
            return radii
        out = radii.copy()
        out[:, unsupported] = np.nan
        simulation = self.simulation_scorers.get(name)
        if simulation is None or not self.calibration.get("not_guaranteed_levels"):
            return out
        sim = simulation.radius(predicted, gdop, **region)
        supported = np.flatnonzero(~unsupported)
        if supported.size:  # the field's scale at its highest supported level
            top = supported[np.argmax(np.asarray(self.pipeline.c.levels)[supported])]
            scalable = (sim[:, top] > 0) & np.isfinite(sim[:, top]) & np.isfinite(radii[:, top])
            ratio = np.where(scalable, radii[:, top] / np.where(scalable, sim[:, top], 1.0), 1.0)
            with np.errstate(invalid="ignore"):
                rescaled = np.maximum(sim[:, unsupported] * ratio[:, None], radii[:, top : top + 1])
            # an unbounded radius at the top supported level, or a simulation with no tail there (an empty Mondrian
            # bin), bounds nothing above it: infinite, never NaN (inf × 0)
            out[:, unsupported] = np.where(np.isnan(rescaled), np.inf, rescaled)
        else:
            out[:, unsupported] = sim[:, unsupported]
        return out

    def _add_ellipses(self, out: pd.DataFrame, position: np.ndarray, predicted: np.ndarray, features: pd.DataFrame) -> None:
        """Ellipse columns ``ellipse__<level>__a_m|b_m|angle_deg``: shape from the TDOA geometry, size from conformal on the calibration events."""
        site = self.pipeline.c.site
        cal_error_xy, cal_position, cal_pred, cal_height, *rest = self.ellipse_calibration  # a method saved before: no groups
        groups = rest[0] if rest else None
        ok = np.isfinite(cal_error_xy).all(axis=1)
        shape = shape_matrices(site.mic_positions_m, cal_position[ok], cal_height[ok])
        scores = mahalanobis(cal_error_xy[ok], shape) / cal_pred[ok]
        test_shape = shape_matrices(site.mic_positions_m, position, source_height_m(features, site))
        for level in self.pipeline.c.levels:
            q = conformal_quantile(scores, level) if groups is None else calibration_quantile(scores, level, "position", groups[ok])
            a, b, angle = ellipse_axes(test_shape, q * predicted)
            for name, values in (("a_m", a), ("b_m", b), ("angle_deg", angle)):
                out[col.ellipse(level, name)] = values
