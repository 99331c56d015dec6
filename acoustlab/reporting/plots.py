"""The plots of a run: error CDF per method, site map with conformal circles, coverage calibration,
predicted against actual error. Written as PNG files with matplotlib's non-interactive Agg backend."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # no display on clusters and CI; must precede pyplot
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.collections import PatchCollection  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

from acoustlab.core import columns as col  # noqa: E402
from acoustlab.core.types import Site  # noqa: E402

log = logging.getLogger(__name__)

#: Events drawn on the site map (more make it unreadable); the first ones by event id.
MAP_EVENTS = 40


def radius_columns(predictions: pd.DataFrame) -> dict[tuple[str, float], str]:
    """Map (scorer, level) to the ``radius__<scorer>__<level>`` column of a predictions table."""
    out = {}
    for name in predictions.columns:
        parsed = col.parse_radius(name)
        if parsed is not None:
            out[(parsed[0], float(parsed[1]))] = name
    return out


def _finite(values: np.ndarray) -> np.ndarray:
    values = np.asarray(values, dtype=float)
    return values[np.isfinite(values)]


def error_cdf(ax: plt.Axes, errors_by_label: dict[str, np.ndarray]) -> None:
    """Empirical CDF of 2-D errors (m, log x axis), one curve per label."""
    styles = ("-", "--", ":", "-.")
    for i, (label, errors) in enumerate(errors_by_label.items()):
        e = np.sort(_finite(errors))
        if e.size == 0:
            continue
        # identical curves (the gate keeping every solver fix) stay visible through the line styles
        ax.step(
            np.maximum(e, 1e-3),
            np.arange(1, e.size + 1) / e.size,
            where="post",
            label=label,
            ls=styles[i % len(styles)],
            lw=2.2 if i == 0 else 1.4,
        )
    ax.set_xscale("log")
    ax.set_xlabel("2-D localization error (m)")
    ax.set_ylabel("fraction of detections")
    ax.set_ylim(0, 1.01)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)


def coverage_calibration(
    ax: plt.Axes,
    coverage_by_label: dict[str, dict[float, float]],
    intervals_by_label: dict[str, dict[float, tuple[float, float]]] | None = None,
    n_positions: int | None = None,
) -> None:
    """Empirical against nominal coverage, one line per label, with the diagonal.

    ``intervals_by_label`` draws each point's 95 % position-bootstrap interval (whole source
    positions resampled: detections at one position share its geometry and propagation, so a
    binomial band over detections would be too narrow); ``n_positions`` names how many positions.
    """
    ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="ideal")
    styles = ("-", "--", ":", "-.")
    for i, (label, by_level) in enumerate(coverage_by_label.items()):
        levels = sorted(by_level)
        line = ax.plot(levels, [by_level[lv] for lv in levels], marker="o", label=label, ls=styles[i % len(styles)])[0]
        interval = (intervals_by_label or {}).get(label)
        if interval:
            shown = [lv for lv in levels if lv in interval]
            low = [by_level[lv] - interval[lv][0] for lv in shown]
            high = [interval[lv][1] - by_level[lv] for lv in shown]
            ax.errorbar(shown, [by_level[lv] for lv in shown], yerr=[low, high], fmt="none", ecolor=line.get_color(), capsize=3)
    if intervals_by_label:
        ax.plot([], [], color="0.3", marker="|", ls="none", label=f"95 % position bootstrap ({n_positions or '?'} positions)")
    ax.set_xlabel("nominal coverage")
    ax.set_ylabel("empirical coverage")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)


def coverage_by_condition_plot(by_run: dict[str, dict[str, list[dict]]], path: Path, scorer: str | None = None) -> Path:
    """Small multiples of where the radii fail: a row per condition (GDOP, hull distance, SNR), a column per level.

    Each panel: coverage per detection against the condition's bin, one line per run, the nominal
    level dashed; bins of fewer than 20 detections hollow. ``by_run``: label → ``metrics.json``'s
    ``coverage_by_condition``; ``scorer``: whose radii (default ``gdop_scaled`` where present, else the first).
    """
    conditions = list(dict.fromkeys(c for m in by_run.values() for c in m))
    first = next(entry for m in by_run.values() for rows in m.values() for entry in rows)
    keys = [k for k in first if "@" in k]
    if scorer is None:
        names = list(dict.fromkeys(k.split("@")[0] for k in keys))
        scorer = "gdop_scaled" if "gdop_scaled" in names else names[0]
    levels = [k.split("@")[1] for k in keys if k.split("@")[0] == scorer]
    fig, axes = plt.subplots(len(conditions), len(levels), figsize=(3.2 * len(levels), 2.6 * len(conditions)), squeeze=False)
    styles = ("-", "--", ":", "-.")
    for row, condition in enumerate(conditions):
        # the bins any run has, by their lower edge ("(low, high]"), so every run's point of a bin is at one x
        bins = sorted({e["bin"] for m in by_run.values() for e in m.get(condition, [])}, key=lambda b: float(b[1:].split(",")[0]))
        for column, level in enumerate(levels):
            ax = axes[row, column]
            for i, (label, metrics) in enumerate(by_run.items()):
                rows = metrics.get(condition, [])
                x = np.array([bins.index(entry["bin"]) for entry in rows])
                y = np.array([entry.get(f"{scorer}@{level}", {}).get("detections", np.nan) for entry in rows])
                few = np.array([entry.get("too_few", False) for entry in rows], dtype=bool)
                line = ax.plot(x, y, ls=styles[i % len(styles)], label=label)[0]
                ax.scatter(x[~few], y[~few], color=line.get_color(), s=14)
                ax.scatter(x[few], y[few], facecolor="none", edgecolor=line.get_color(), s=14)
            ax.set_xticks(np.arange(len(bins)), bins, fontsize=6, rotation=30)
            ax.axhline(float(level), color="0.5", ls="--", lw=1)
            ax.set_ylim(0, 1.02)
            ax.grid(True, alpha=0.3)
            if row == 0:
                ax.set_title(f"{scorer} at {level}", fontsize=8)
            if column == 0:
                ax.set_ylabel(f"coverage by {condition}", fontsize=8)
    axes[0, 0].legend(fontsize=6, loc="lower left")
    fig.suptitle("where the radii fail (hollow: fewer than 20 detections)", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def predicted_vs_actual(ax: plt.Axes, predicted_m: np.ndarray, actual_m: np.ndarray, rho: float | None) -> None:
    """Scatter of the error model's prediction against the gate's actual error (log-log, m)."""
    ok = np.isfinite(predicted_m) & np.isfinite(actual_m)
    p, a = np.maximum(predicted_m[ok], 1e-3), np.maximum(actual_m[ok], 1e-3)
    ax.scatter(p, a, s=8, alpha=0.5)
    if p.size:
        lo, hi = min(p.min(), a.min()), max(p.max(), a.max())
        ax.plot([lo, hi], [lo, hi], color="0.6", lw=1, ls="--")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("predicted error (m)")
    ax.set_ylabel("actual error of the gated estimate (m)")
    ax.set_title("Spearman ρ = " + ("n/a (constant prediction)" if rho is None else f"{rho:.2f}"), fontsize=9)
    ax.grid(True, which="both", alpha=0.3)


#: Circles smaller than this fraction of a map's extent are drawn at that size, dashed (a true-scale inset shows one).
MIN_CIRCLE_FRACTION = 0.015


def site_map(ax: plt.Axes, site: Site, predictions: pd.DataFrame, radius_column: str | None) -> None:
    """Mics, trunks, true and gated positions of the first ``MAP_EVENTS`` events, with conformal circles.

    Circles below ``MIN_CIRCLE_FRACTION`` of the map are drawn at that size (dashed), and an
    inset shows the event with the median radius at true scale, so 0.3 m circles on a 70 m map are seen.
    """
    if len(site.tree_positions_m):
        trunks = [Circle((x, y), max(d / 2, 0.15)) for (x, y), d in zip(site.tree_positions_m, site.trunk_diameters_m)]
        ax.add_collection(PatchCollection(trunks, facecolor="tab:brown", edgecolor="none", alpha=0.5))
    shown = predictions.sort_values(col.EVENT_ID).head(MAP_EVENTS)
    (true_x, true_y), (gate_x, gate_y) = col.estimate_xy("true"), col.estimate_xy("gate")
    mics = site.mic_positions_m
    extent = max(np.ptp(np.concatenate([mics[:, 0], shown[true_x]])), np.ptp(np.concatenate([mics[:, 1], shown[true_y]])), 1.0)
    if radius_column is not None:
        radius = shown[radius_column].to_numpy(float)
        floor = MIN_CIRCLE_FRACTION * extent
        for enlarged, style in ((False, "solid"), (True, "dashed")):
            keep = np.isfinite(radius) & ((radius < floor) == enlarged)
            circles = [Circle((x, y), max(r, floor)) for x, y, r in zip(shown[gate_x][keep], shown[gate_y][keep], radius[keep])]
            ax.add_collection(PatchCollection(circles, facecolor="none", edgecolor="tab:orange", lw=0.6, alpha=0.6, linestyle=style))
    for _, row in shown.iterrows():
        ax.plot([row[true_x], row[gate_x]], [row[true_y], row[gate_y]], color="0.5", lw=0.5)
    ax.scatter(shown[true_x], shown[true_y], marker="x", color="tab:green", s=25, label="true source", zorder=3)
    ax.scatter(shown[gate_x], shown[gate_y], marker=".", color="tab:orange", s=30, label="estimate (gate)", zorder=3)
    ax.scatter(mics[:, 0], mics[:, 1], marker="^", color="k", s=60, label="microphones", zorder=4)
    # Frame the array and the true sources; wild estimates would shrink everything else to a dot.
    xs = np.concatenate([mics[:, 0], shown[true_x]])
    ys = np.concatenate([mics[:, 1], shown[true_y]])
    pad = 0.25 * max(np.ptp(xs), np.ptp(ys), 1.0)
    ax.set_xlim(xs.min() - pad, xs.max() + pad)
    ax.set_ylim(ys.min() - pad, ys.max() + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if radius_column is not None:  # after the limits: the inset goes to the corner that hides no mic
        _zoom_inset(ax, shown, radius, floor, mics[:, :2])
    n_positions = shown[[true_x, true_y]].round(6).drop_duplicates().shape[0]  # events at one position overlap on the map
    title = f"{site.name}: first {len(shown)} test events at {n_positions} source positions"
    if radius_column is not None:
        scorer, level = col.parse_radius(radius_column)
        title += f"; circles: {scorer} conformal, {float(level):.0%}"
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper right", fontsize=7)


#: Where an inset may go, in axes fractions (x, y, width, height): lower left, lower right, upper left (the legend is upper right).
INSET_CORNERS = ((0.02, 0.02, 0.32, 0.32), (0.66, 0.02, 0.32, 0.32), (0.02, 0.66, 0.32, 0.32))


def inset_corner(ax: plt.Axes, mics_xy: np.ndarray, points_xy: np.ndarray) -> tuple[float, float, float, float]:
    """The corner of ``INSET_CORNERS`` covering no microphone and the fewest other points (call after the limits are set)."""
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()

    def covered(xy: np.ndarray, box: tuple[float, float, float, float]) -> int:
        fx, fy = (xy[:, 0] - x0) / (x1 - x0), (xy[:, 1] - y0) / (y1 - y0)
        return int(((fx >= box[0]) & (fx <= box[0] + box[2]) & (fy >= box[1]) & (fy <= box[1] + box[3])).sum())

    return min(INSET_CORNERS, key=lambda box: (covered(mics_xy, box), covered(points_xy, box)))


def _zoom_inset(ax: plt.Axes, shown: pd.DataFrame, radius: np.ndarray, floor: float, mics_xy: np.ndarray) -> None:
    """Where the circles are smaller than ``floor`` (drawn enlarged, dashed), an inset at true scale around a typical one."""
    finite = np.flatnonzero(np.isfinite(radius))
    if finite.size == 0 or np.median(radius[finite]) >= floor:
        return
    k = finite[np.argsort(radius[finite])[finite.size // 2]]  # the event with the median radius
    (true_x, true_y), (gate_x, gate_y) = col.estimate_xy("true"), col.estimate_xy("gate")
    row = shown.iloc[k]
    half = 2.5 * max(radius[k], abs(row[true_x] - row[gate_x]), abs(row[true_y] - row[gate_y]), 1e-3)
    points = np.concatenate([shown[[true_x, true_y]].to_numpy(float), shown[[gate_x, gate_y]].to_numpy(float)])
    inset = ax.inset_axes(list(inset_corner(ax, mics_xy, points[np.isfinite(points).all(axis=1)])))
    inset.add_patch(Circle((row[gate_x], row[gate_y]), radius[k], facecolor="none", edgecolor="tab:orange", lw=1.0))
    inset.scatter([row[true_x]], [row[true_y]], marker="x", color="tab:green", s=25, zorder=3)
    inset.scatter([row[gate_x]], [row[gate_y]], marker=".", color="tab:orange", s=30, zorder=3)
    inset.set_xlim(row[gate_x] - half, row[gate_x] + half)
    inset.set_ylim(row[gate_y] - half, row[gate_y] + half)
    inset.set_aspect("equal")
    inset.set_xticks([])
    inset.set_yticks([])
    inset.set_title(f"true scale: event {int(row[col.EVENT_ID])}, r = {radius[k]:.2g} m, box {2 * half:.2g} m", fontsize=6)


def _save(fig: plt.Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def map_radius_column(predictions: pd.DataFrame) -> str | None:
    """The circles on the map: GDOP-scaled when present (else the first scorer), at the level nearest 0.8."""
    cols = radius_columns(predictions)
    if not cols:
        return None
    scorers = sorted({s for s, _ in cols}, key=lambda s: (s != "gdop_scaled", s))
    levels = sorted({lv for s, lv in cols if s == scorers[0]}, key=lambda lv: abs(lv - 0.8))
    return cols[(scorers[0], levels[0])]


def write_run_plots(predictions: pd.DataFrame, metrics: dict, site: Site | None, out_dir: Path) -> list[Path]:
    """Write the four plots of one run into ``out_dir`` and return their paths.

    Parameters
    ----------
    predictions : pandas.DataFrame
        The run's predictions table (``predictions.parquet``).
    metrics : dict
        The run's metrics (``metrics.json``).
    site : Site or None
        The site, for the map (skipped when None).
    out_dir : pathlib.Path
        Directory for the PNG files (created).
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    fig, ax = plt.subplots(figsize=(5.5, 4))
    error_cdf(ax, {m: predictions[col.error_m(m)].to_numpy(float) for m in col.methods_in(predictions.columns)})
    ax.set_title(f"{metrics.get('site', '')}: error CDF per method", fontsize=9)
    paths.append(_save(fig, out_dir / "error_cdf.png"))

    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    ci = metrics.get(col.METRICS_CI95, {})
    by_position = metrics.get(col.METRICS_COVERAGE_BY_POSITION, {})
    curves = {f"{s}, per detection": {float(lv): v for lv, v in by.items()} for s, by in metrics[col.METRICS_COVERAGE].items()}
    curves |= {f"{s}, per position": {float(lv): v["mean"] for lv, v in by.items()} for s, by in by_position.items()}
    intervals = {f"{s}, per detection": {float(lv): tuple(v) for lv, v in by.items()} for s, by in ci.get(col.METRICS_COVERAGE, {}).items()}
    coverage_calibration(ax, curves, intervals, ci.get("n_positions"))
    ax.set_title("coverage calibration (test detections; the guarantee's unit is the position)", fontsize=8)
    paths.append(_save(fig, out_dir / "coverage_calibration.png"))

    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    predicted_vs_actual(
        ax,
        predictions[col.PREDICTED_ERROR].to_numpy(float),
        predictions[col.error_m("gate")].to_numpy(float),
        metrics.get(col.METRICS_SPEARMAN, {}).get("error_model"),
    )
    paths.append(_save(fig, out_dir / "predicted_vs_actual_error.png"))

    if site is not None:
        fig, ax = plt.subplots(figsize=(6, 6))
        site_map(ax, site, predictions, map_radius_column(predictions))
        paths.append(_save(fig, out_dir / "site_map.png"))
    log.info("plots written to %s", out_dir)
    return paths


def _other_estimate(placed: pd.DataFrame) -> np.ndarray:
    """(N, 2) the estimate each placed row did not report (the model's where the solver's was kept, and the reverse)."""
    if not {"solver_x_m", "model_x_m", "source"} <= set(placed.columns):
        return np.full((len(placed), 2), np.nan)
    model = placed["source"].to_numpy() == "model"
    solver_xy = placed[["solver_x_m", "solver_y_m"]].to_numpy(float)
    model_xy = placed[["model_x_m", "model_y_m"]].to_numpy(float)
    return np.where(model[:, None], solver_xy, model_xy)


def _draw_disagreements(ax: plt.Axes, placed: pd.DataFrame, radius: np.ndarray | None) -> None:
    """Where the solver and the model disagree by more than the reported radius, draw the other estimate and a line to it."""
    other = _other_estimate(placed)
    reported = placed[[col.TRUE_X, col.TRUE_Y]].to_numpy(float)
    distance = np.sqrt(((other - reported) ** 2).sum(axis=1))
    far = np.isfinite(distance) & (distance > (radius if radius is not None else 0.0))
    if not far.any():
        return
    for (x0, y0), (x1, y1) in zip(reported[far], other[far], strict=True):
        ax.plot([x0, x1], [y0, y1], color="tab:gray", lw=0.6, ls=":", zorder=2)
    ax.scatter(
        other[far, 0],
        other[far, 1],
        marker="x",
        color="tab:gray",
        s=25,
        zorder=3,
        label="the other estimate (solver or model), farther than the radius",
    )


def write_positions_map(table: pd.DataFrame, site: Site, levels: list[float], scorers: list[str], out_dir: Path) -> Path:
    """``positions_map.png``: mics, trunks and every placed detection with its radius at the level nearest 0.8.

    Circles smaller than 1.5 % of the plot's extent are drawn at that size (dashed), so they stay visible.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    if len(site.tree_positions_m):
        trunks = [Circle((x, y), max(d / 2, 0.15)) for (x, y), d in zip(site.tree_positions_m, site.trunk_diameters_m)]
        ax.add_collection(PatchCollection(trunks, facecolor="tab:brown", edgecolor="none", alpha=0.5))
    mics = site.mic_positions_m
    placed = table[table[col.PLACED]]
    other = _other_estimate(placed)
    xs = np.concatenate([mics[:, 0], placed[col.TRUE_X].to_numpy(float), other[:, 0][np.isfinite(other[:, 0])]])
    ys = np.concatenate([mics[:, 1], placed[col.TRUE_Y].to_numpy(float), other[:, 1][np.isfinite(other[:, 1])]])
    extent = max(np.ptp(xs), np.ptp(ys), 1.0)
    scorer = "gdop_scaled" if "gdop_scaled" in scorers else (scorers[0] if scorers else None)
    title = f"{site.name}: {len(placed)} of {len(table)} detections placed"
    if scorer is not None and levels:
        level = min(levels, key=lambda lv: abs(lv - 0.8))
        radius = placed[f"radius_{scorer}_{col.level_key(level)}_m"].to_numpy(float)
        shown = np.maximum(radius, MIN_CIRCLE_FRACTION * extent)
        circles = [Circle((x, y), r) for x, y, r in zip(placed[col.TRUE_X], placed[col.TRUE_Y], shown) if np.isfinite(r)]
        ax.add_collection(PatchCollection(circles, facecolor="none", edgecolor="tab:orange", lw=0.8, alpha=0.7))
        title += f"; circles: {scorer} conformal, {level:.0%}"
    ax.scatter(placed[col.TRUE_X], placed[col.TRUE_Y], marker=".", color="tab:orange", s=30, label="estimate", zorder=3)
    _draw_disagreements(ax, placed, radius if scorer is not None and levels else None)
    ax.scatter(mics[:, 0], mics[:, 1], marker="^", color="k", s=60, label="microphones", zorder=4)
    pad = 0.2 * extent
    ax.set_xlim(xs.min() - pad, xs.max() + pad)
    ax.set_ylim(ys.min() - pad, ys.max() + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    return _save(fig, out_dir / "positions_map.png")


def write_calibration_plot(calibration: Any, residuals: pd.DataFrame, spots_m: np.ndarray, site: Site, path: Path) -> Path:
    """``calibration.png``: the stated and calibrated mics with the playback spots; time-difference residuals before and after.

    Parameters
    ----------
    calibration : acoustlab.toolkit.array_calibration.ArrayCalibration
        The calibration.
    residuals : pandas.DataFrame
        ``residual_before_s, residual_after_s`` per playback and mic pair.
    spots_m : numpy.ndarray
        (N, 3) playback positions, m.
    site : Site
        The site as stated (its mics are the "stated" ones).
    path : pathlib.Path
        Where the PNG goes.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, (ax, hist) = plt.subplots(1, 2, figsize=(10, 4.6))
    stated, calibrated = site.mic_positions_m, calibration.mic_positions_m
    ax.scatter(spots_m[:, 0], spots_m[:, 1], marker="*", color="tab:green", s=40, label="playback spots")
    ax.scatter(stated[:, 0], stated[:, 1], marker="^", facecolor="none", edgecolor="k", s=60, label="mics as stated")
    ax.scatter(calibrated[:, 0], calibrated[:, 1], marker="^", color="tab:red", s=40, label="mics calibrated")
    for (x0, y0, _), (x1, y1, _), name in zip(stated, calibrated, calibration.mic_ids, strict=True):
        ax.annotate("", (x1, y1), (x0, y0), arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 0.8})
        ax.text(x1, y1, f" {name}", fontsize=7)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"thermometer offset {calibration.temperature_offset_c:+.2f} °C; {calibration.n_spots} spots", fontsize=9)
    ax.legend(loc="best", fontsize=7)
    before = 1e3 * residuals["residual_before_s"].to_numpy(float)
    after = 1e3 * residuals["residual_after_s"].to_numpy(float)
    finite = np.concatenate([before[np.isfinite(before)], after[np.isfinite(after)]])
    limit = float(np.quantile(np.abs(finite), 0.99)) if finite.size else 1.0
    bins = np.linspace(-limit, limit, 41)
    hist.hist(np.clip(before[np.isfinite(before)], -limit, limit), bins=bins, alpha=0.5, label="stated array")
    hist.hist(np.clip(after[np.isfinite(after)], -limit, limit), bins=bins, alpha=0.5, label="calibrated")
    hist.set_xlabel("time-difference residual (ms)")
    hist.set_ylabel("playback × mic pair")
    hist.legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, path)
