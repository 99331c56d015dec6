"""Split conformal for the localization error, composable as in crepes: any normaliser × any binning.

For calibration errors e_i (m), the error model's predictions ê_i (m) and a per-event scale σ_i
(the *normaliser*), the score is

* ``signed`` (default): s_i = (e_i − ê_i) / σ_i — a one-sided upper bound on the error, the
  paper's "adjustment of the error model's quantile";
* ``absolute``: s_i = |e_i − ê_i| / σ_i — the two-sided normalised conformal regressor (crepes'
  ``ConformalRegressor``), whose upper end is the radius.

The radius at level 1 − α is max(0, ê + q̂ σ), with q̂ the ⌈(n+1)(1−α)⌉-th smallest score of the
event's Mondrian bin (one bin without ``binning``). Normalisers (σ):

* ``none``: σ = 1 — one additive adjustment for every event (``fixed`` in the paper);
* ``gdop``: σ = GDOP / median calibration GDOP — the adjustment scaled per detection by the
  geometry (``gdop_scaled`` in the paper; locally weighted conformal). The GDOP is first clipped
  to the central ``gdop_cap_quantile`` range of the calibration GDOPs (by default their 5th to
  95th percentile): near a singular geometry (a source on the mics' baseline extension) GDOP
  grows without bound, and an uncapped σ turned errors of centimetres into radii of 160 km on
  the 3-mic frozen lake (capped at the 99th percentile the largest 0.95 radius was still 7,900×
  the median there, because GDOP at a diverged estimate is itself extreme). Fit and predict use the same clipped σ, so the coverage guarantee holds;
* ``predicted_error``: σ = ê — multiplicative, e ≤ ê (1 + q̂) (``error_ratio``).

``use_error_model: false`` sets ê = 0: with ``normaliser: gdop`` the radius is q̂ × GDOP and
ignores the error model (``gdop_only``, what this project once called GDOP-scaled). Binning
(``gdop`` or ``predicted_error``) calibrates q̂ separately in ``n_bins`` quantile bins of that
quantity, so coverage holds within each geometry class, not only on average. ``region`` bins by
where the estimate lies: inside the mics' hull, near it (up to ``REGION_NEAR_EXTENT`` array
extents outside) or far; the errors of a call far outside a 3-mic array are not those of one
inside, and one quantile for both over-covers one and under-covers the other.
"""

from __future__ import annotations

import numpy as np

from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.conformal import calibration_quantile, check_calibration_unit, check_pac

NORMALISERS = ("none", "gdop", "predicted_error")
BINNINGS = ("none", "gdop", "predicted_error", "region")
#: ``binning: region``: an estimate up to this many array extents outside the mics' hull is "near", beyond it "far".
REGION_NEAR_EXTENT = 0.5
#: The three regions of ``binning="region"``, as a radius note names them.
REGION_NAMES = ("inside the array", f"within {REGION_NEAR_EXTENT:g} array extents outside it", "farther outside the array")


class SplitConformal:
    """Normalised, optionally Mondrian split conformal on the localization error (module docstring).

    Parameters
    ----------
    normaliser : {"none", "gdop", "predicted_error"}
        Per-event scale σ of the score.
    binning : {"none", "gdop", "predicted_error", "region"}
        Mondrian categories: quantile bins of this quantity, or ``region`` (inside / near / far
        from the mics' hull, by the estimate's ``hull_distance``).
    n_bins : int
        Number of bins (edges at calibration quantiles) for ``gdop`` and ``predicted_error``.
    score : {"signed", "absolute"}
        (e − ê)/σ for a one-sided bound, or |e − ê|/σ as crepes' two-sided regressor.
    use_error_model : bool
        False: ê = 0 (the radius ignores the error model).
    gdop_cap_quantile : float or None
        GDOP is clipped to the [1 − this, this] quantiles of the calibration GDOPs before it
        scales or bins anything (None: no clipping).
    calibration_unit : {"event", "position"}
        ``event``: the usual quantile over calibration events. ``position``: a guarantee over
        source positions, for calibration on field playback spots whose events are not
        exchangeable across spots (a calibration on the field is always position-level).
    position_method : {"pooled", "subsample", "pac"}
        How a position-level quantile is taken: the positions' empirical CDFs pooled, each
        position weighing the same, every event used (``grouped_conformal_quantile``, default);
        or one event per position drawn at random (``subsampled_position_quantile``). Both
        guarantee the level in finite samples for a random event of a new position, on average
        over calibration sets; pooling scatters less from one set to the next. ``pac``: the same
        draw at the PAC rank (``pac_rank``): coverage at least ``level − pac_epsilon`` with
        probability ``1 − pac_delta`` over calibration sets, for the one set you have.
    seed : int
        Seed of the ``subsample`` and ``pac`` draw.
    pac_delta, pac_epsilon : float
        δ and ε of ``position_method: pac`` (default 0.1 and 0.05: 9 positions for 0.8, 22 for 0.95).
    """

    def __init__(
        self,
        normaliser: str = "none",
        binning: str = "none",
        n_bins: int = 3,
        score: str = "signed",
        use_error_model: bool = True,
        gdop_cap_quantile: float | None = 0.95,
        calibration_unit: str = "event",
        position_method: str = "pooled",
        seed: int = 0,
        pac_delta: float = 0.1,
        pac_epsilon: float = 0.05,
    ) -> None:
        check_calibration_unit(calibration_unit, position_method)
        check_pac(pac_delta, pac_epsilon)
        self.calibration_unit = calibration_unit
        self.position_method = position_method
        self.pac_delta, self.pac_epsilon = float(pac_delta), float(pac_epsilon)
        self.seed = int(seed)
        if gdop_cap_quantile is not None and not 0.5 <= gdop_cap_quantile <= 1:
            raise ConfigError(f"conformal gdop_cap_quantile must lie in [0.5, 1] or be null; got {gdop_cap_quantile}")
        self.gdop_cap_quantile = None if gdop_cap_quantile is None else float(gdop_cap_quantile)
        if normaliser not in NORMALISERS:
            raise ConfigError(f"conformal normaliser must be one of {NORMALISERS}; got {normaliser!r}")
        if binning not in BINNINGS:
            raise ConfigError(f"conformal binning must be one of {BINNINGS}; got {binning!r}")
        if score not in ("signed", "absolute"):
            raise ConfigError(f"conformal score must be 'signed' or 'absolute'; got {score!r}")
        if n_bins < 1:
            raise ConfigError(f"conformal n_bins must be >= 1; got {n_bins}")
        self.normaliser = normaliser
        self.binning = binning
        self.n_bins = int(n_bins)
        self.score = score
        self.use_error_model = bool(use_error_model)

    @property
    def needs_hull_distance(self) -> bool:
        """``binning: region`` bins by the estimate's distance outside the mics' hull, which the pipeline passes."""
        return self.binning == "region"

    def _centre(self, predicted_m: np.ndarray) -> np.ndarray:
        return np.asarray(predicted_m, dtype=float) if self.use_error_model else np.zeros(len(predicted_m))

    def _clip_gdop(self, gdop: np.ndarray) -> np.ndarray:
        low, high = self.gdop_range_
        return np.clip(np.maximum(np.asarray(gdop, dtype=float), 1e-9), low, high)

    def _sigma(self, predicted_m: np.ndarray, gdop: np.ndarray) -> np.ndarray:
        if self.normaliser == "none":
            return np.ones(len(predicted_m))
        if self.normaliser == "gdop":
            return self._clip_gdop(gdop) / self.gdop_scale_
        return np.maximum(np.asarray(predicted_m, dtype=float), 1e-9)

    def _bins(self, predicted_m: np.ndarray, gdop: np.ndarray, hull_distance: np.ndarray | None = None) -> np.ndarray:
        if self.binning == "none":
            return np.zeros(len(predicted_m), dtype=int)
        if self.binning == "region":
            if hull_distance is None:
                raise ValueError("binning='region' needs hull_distance (the estimates' distance outside the mics' hull)")
            # no estimate (NaN) counts as far: nothing says it is near the array
            return np.searchsorted(self.edges_, np.nan_to_num(np.asarray(hull_distance, dtype=float), nan=np.inf), side="left")
        value = self._clip_gdop(gdop) if self.binning == "gdop" else np.asarray(predicted_m, dtype=float)
        return np.searchsorted(self.edges_, value, side="right")

    def fit(
        self,
        error_m: np.ndarray,
        predicted_m: np.ndarray,
        gdop: np.ndarray,
        levels: list[float],
        groups: np.ndarray | None = None,
        hull_distance: np.ndarray | None = None,
    ) -> SplitConformal:
        """Calibrate ``quantiles_`` (bins × levels) on calibration errors, predictions, GDOPs (positions ``groups``, ``hull_distance`` in array extents)."""
        error_m, predicted_m, gdop = (np.asarray(a, dtype=float) for a in (error_m, predicted_m, gdop))
        q = self.gdop_cap_quantile
        self.gdop_range_ = (1e-9, np.inf) if q is None else (float(np.quantile(gdop, 1 - q)), float(np.quantile(gdop, q)))
        self.gdop_scale_ = float(np.median(self._clip_gdop(gdop)))
        bins_of = self._clip_gdop(gdop) if self.binning == "gdop" else predicted_m
        if self.binning == "region":  # inside (≤ 0), near, far
            n_bins, self.edges_ = 3, np.array([0.0, REGION_NEAR_EXTENT])
        else:
            n_bins = self.n_bins if self.binning != "none" else 1
            self.edges_ = np.quantile(bins_of, np.linspace(0, 1, n_bins + 1)[1:-1]) if n_bins > 1 else np.array([])
        residual = error_m - self._centre(predicted_m)
        scores = (np.abs(residual) if self.score == "absolute" else residual) / self._sigma(predicted_m, gdop)
        bins = self._bins(predicted_m, gdop, hull_distance)
        self.levels_ = [float(v) for v in levels]

        def quantile(in_bin: np.ndarray, level: float) -> float:
            if not in_bin.any():
                return np.inf
            in_groups = None if groups is None else np.asarray(groups)[in_bin]
            return calibration_quantile(
                scores[in_bin], level, self.calibration_unit, in_groups, self.position_method, self.seed, (self.pac_delta, self.pac_epsilon)
            )

        self.quantiles_ = np.array([[quantile(bins == b, v) for v in self.levels_] for b in range(n_bins)])
        self.n_calibration_ = int(scores.size)
        self.n_calibration_by_bin_ = np.bincount(bins, minlength=n_bins).tolist()
        return self

    def radius_notes(self, predicted_m: np.ndarray, gdop: np.ndarray, hull_distance: np.ndarray | None = None) -> np.ndarray:
        """(B,) why a row's radii are infinite where its Mondrian bin held too few calibration events for a level ('' elsewhere)."""
        notes = np.full(len(predicted_m), "", dtype=object)
        if self.binning == "none":  # one bin: too few calibration positions is the calibration's own note
            return notes
        bins = self._bins(predicted_m, gdop, hull_distance)
        for b in np.flatnonzero(~np.isfinite(self.quantiles_).all(axis=1)):
            levels = ", ".join(f"{lv:g}" for lv, q in zip(self.levels_, self.quantiles_[b], strict=True) if not np.isfinite(q))
            where = REGION_NAMES[b] if self.binning == "region" else f"in {self.binning} bin {b + 1} of {len(self.quantiles_)}"
            notes[bins == b] = f"radius at {levels} infinite: {self.n_calibration_by_bin_[b]} calibration events {where}"
        return notes

    def radius(self, predicted_m: np.ndarray, gdop: np.ndarray, hull_distance: np.ndarray | None = None) -> np.ndarray:
        """(B, L) radii in m (≥ 0); infinite in a Mondrian bin the calibration left empty or too small for the level."""
        if not hasattr(self, "quantiles_"):
            raise RuntimeError("SplitConformal.radius called before fit")
        q = self.quantiles_[self._bins(predicted_m, gdop, hull_distance)]  # (B, L)
        return np.maximum(self._centre(predicted_m)[:, None] + q * self._sigma(predicted_m, gdop)[:, None], 0.0)
