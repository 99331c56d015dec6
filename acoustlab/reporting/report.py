"""Turn the runs of a sweep (or any run directories) into a Markdown and an HTML report.

``python -m acoustlab.report SWEEP_DIR [RUN_DIR ...] [--out DIR]`` (also ``acoustlab report``)
reads each run's ``metrics.json`` (and ``predictions.parquet`` for gross-error rates), labels runs by
the overrides that differ between them (from Hydra's ``.hydra/overrides.yaml``) and writes
``report.md`` and a self-contained ``report.html`` with tables shaped like the paper's — localization
error per method (mean, p50, p90, p95, p99), coverage and interval width per conformal scorer and
level, Spearman ρ of the error model next to GDOP alone — plus comparison plots and each run's own
plots. Sweeps write their report automatically into ``<sweep dir>/report/``.
"""

from __future__ import annotations

import argparse
import base64
import html
import json
import logging
import shutil
import sys
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from acoustlab.core import columns as col
from acoustlab.core.errors import DataError
from acoustlab.reporting.experiment_log import read_metrics
from acoustlab.reporting.metrics import GROSS_ERROR_M, gate_scalars, share_gross

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    """One run directory's results.

    Attributes
    ----------
    run_dir : pathlib.Path
        The run directory.
    metrics : dict
        Its ``metrics.json``.
    overrides : dict
        Its command-line overrides (``key -> value``), empty outside Hydra.
    label : str
        A short name: the overrides that differ between the reported runs.
    settings : dict
        Those overrides, ``key -> value``: the columns that tell the runs apart in every table.
    """

    run_dir: Path
    metrics: dict
    overrides: dict[str, str]
    label: str = ""
    settings: dict[str, str] = field(default_factory=dict)

    def identity(self) -> dict[str, str]:
        """The leading columns of this run's table rows: the settings that vary, or its label when none does."""
        return dict(self.settings) if self.settings else {"run": self.label}

    @cached_property
    def withheld_groups(self) -> str:
        """Feature groups withheld from the learned models (``features.drop``; ``pipeline.drop_from_*`` per model), from the run's config."""
        path = self.run_dir / "config_resolved.yaml"
        config = yaml.safe_load(path.read_text()) if path.exists() else {}
        config = config if isinstance(config, dict) else {}
        features = config.get("features") if isinstance(config.get("features"), dict) else {}
        pipeline = config.get("pipeline") if isinstance(config.get("pipeline"), dict) else {}
        parts = [", ".join(map(str, features.get("drop") or [])) or "none"]
        for key, who in (("drop_from_model", "point model"), ("drop_from_error_model", "error model")):
            if pipeline.get(key):
                parts.append(f"{who} also: {', '.join(map(str, pipeline[key]))}")
        return "; ".join(parts)

    @cached_property
    def predictions(self) -> pd.DataFrame | None:
        """The run's predictions table (read once), or None when absent."""
        path = self.run_dir / "predictions.parquet"
        return pd.read_parquet(path) if path.exists() else None


def _job_order(path: Path) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in path.parts)


def _overrides(run_dir: Path) -> dict[str, str]:
    path = run_dir / ".hydra" / "overrides.yaml"
    if not path.exists():
        return {}
    out = {}
    for item in yaml.safe_load(path.read_text()) or []:
        key, _, value = str(item).partition("=")
        key = key.lstrip("+~")
        if key != "paths.outputs_dir":
            out[key] = value
    return out


def collect_runs(paths: list[Path]) -> list[RunResult]:
    """Find run directories (with a complete ``metrics.json``) in ``paths`` and label them.

    Raises
    ------
    FileNotFoundError
        When a path does not exist.
    """
    dirs: list[Path] = []
    for path in map(Path, paths):
        if not path.exists():
            raise FileNotFoundError(f"{path} does not exist")
        found = [path] if (path / "metrics.json").exists() else sorted((p.parent for p in path.rglob("metrics.json")), key=_job_order)
        dirs += [d for d in found if d not in dirs]
    runs = []
    for d in dirs:
        try:
            metrics = read_metrics(d)
        except DataError as exc:  # a damaged or foreign folder: left out, named, never a traceback
            log.warning("left out of the report: %s", exc)
            continue
        if isinstance(metrics.get(col.METRICS_ERRORS), dict):  # shard-only jobs have no results
            runs.append(RunResult(d, metrics, _overrides(d)))
    keys = sorted({k for r in runs for k in r.overrides})
    varying = [k for k in keys if len({r.overrides.get(k) for r in runs}) > 1]
    for r in runs:
        r.settings = {k: r.overrides.get(k, "—") for k in varying}
        r.label = ", ".join(f"{k}={v}" for k, v in r.settings.items()) or f"{r.metrics.get('site', '')} {r.run_dir.name}".strip()
    return runs


#: What a sweep job that failed leaves in its folder: its overrides and the error's first line (``acoustlab.__main__``).
FAILED_FILE = "failed.json"


@dataclass
class FailedJob:
    """A sweep job that wrote no results: its folder, what it varied and why it failed (one line)."""

    run_dir: Path
    overrides: dict[str, str]
    error: str

    @property
    def label(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in self.overrides.items() if k != "paths.outputs_dir") or self.run_dir.name


def collect_failed(paths: list[Path]) -> list[FailedJob]:
    """The jobs under ``paths`` that failed (a ``failed.json`` and no ``metrics.json``), in job order."""
    failed = []
    for path in map(Path, paths):
        for marker in sorted(path.rglob(FAILED_FILE), key=lambda p: _job_order(p.parent)):
            if (marker.parent / "metrics.json").exists():
                continue  # run again since, and finished
            try:
                record = json.loads(marker.read_text())
                overrides = dict(str(o).lstrip("+~").partition("=")[::2] for o in record.get("overrides", []))
                failed.append(FailedJob(marker.parent, overrides, str(record.get("error", ""))))
            except (OSError, ValueError, AttributeError, TypeError) as exc:
                failed.append(FailedJob(marker.parent, {}, f"its {FAILED_FILE} is unreadable ({type(exc).__name__})"))
    return failed


def failed_rows(failed: list[FailedJob]) -> pd.DataFrame:
    """One row per failed job: its settings and its one-line reason."""
    return pd.DataFrame([{"job": f.run_dir.name, "settings": f.label, "error": f.error} for f in failed])


def error_rows(runs: list[RunResult]) -> pd.DataFrame:
    """Localization error per run and method (m): n, mean, p50, p90, p95, p99 and the gross-error rate."""
    rows = []
    for r in runs:
        predictions = r.predictions
        if predictions is not None and col.IN_SUMMARY in predictions:
            predictions = predictions[predictions[col.IN_SUMMARY].to_numpy(bool)]
        for method in r.metrics[col.METRICS_ERRORS]:  # solver, model, gate, oracle (newer runs) and any extra gates
            stats = r.metrics[col.METRICS_ERRORS][method]
            row = {
                **r.identity(),
                "method": method,
                "n (detections)": stats["n"],
                **{f"{k} (m)": stats[k] for k in ("mean", "p50", "p90", "p95", "p99")},
            }
            ci = r.metrics.get(col.METRICS_CI95, {}).get(col.METRICS_ERRORS, {}).get(method, {})
            for q in ("p95", "p99"):
                if q in ci:
                    row[f"{q} 95 % CI (m)"] = f"{ci[q][0]:.3g}–{ci[q][1]:.3g}"
            if predictions is not None:
                e = predictions[col.error_m(method)].to_numpy(float)
                row[f"> {GROSS_ERROR_M:g} m (%)"] = 100 * share_gross(e)
            rows.append(row)
    return pd.DataFrame(rows)


def default_title(runs: list[RunResult]) -> str:
    """A heading saying what was compared: the site(s) and the options that vary, e.g. ``forest: model = xgboost, knn``."""
    sites = ", ".join(dict.fromkeys(str(r.metrics.get("site", "")) for r in runs))
    keys = [k for k in dict.fromkeys(k for r in runs for k in r.overrides) if k != "site" and len({r.overrides.get(k) for r in runs}) > 1]
    varying = "; ".join(f"{k} = {', '.join(dict.fromkeys(str(r.overrides.get(k, '—')) for r in runs))}" for k in keys)
    return f"acoustlab: {sites}" + (f" — {varying}" if varying else f" — {len(runs)} run(s)")


def conclusion(runs: list[RunResult]) -> str:
    """One line: which run's gated estimate has the smallest p95 error, its gross-error share, and the spread across runs."""
    p95 = [(r.metrics[col.METRICS_ERRORS]["gate"]["p95"], r) for r in runs if "gate" in r.metrics.get(col.METRICS_ERRORS, {})]
    if not p95:
        return "No run has gated errors to compare."
    best_value, best = min(p95, key=lambda t: t[0])
    gross = best.metrics[col.METRICS_ERRORS]["gate"].get("share_gt_5m")
    gross_text = f", {100 * gross:.1f} % of detections > {GROSS_ERROR_M:g} m" if gross is not None else ""
    if len(p95) == 1:
        return f"The gated estimate's 95th-percentile error is {best_value:.3g} m{gross_text} ({best.label})."
    worst_value, worst = max(p95, key=lambda t: t[0])
    if f"{best_value:.3g}" == f"{worst_value:.3g}":
        return f"All {len(p95)} runs tie on the gated p95 error: {best_value:.3g} m (to 3 significant digits)."
    tied_best = [r.label for v, r in p95 if f"{v:.3g}" == f"{best_value:.3g}"]
    tied_worst = [r.label for v, r in p95 if f"{v:.3g}" == f"{worst_value:.3g}"]
    best_text = tied_best[0] if len(tied_best) == 1 else "a tie between " + " and ".join(tied_best)
    worst_text = tied_worst[0] if len(tied_worst) == 1 else "a tie between " + " and ".join(tied_worst)
    return (
        f"Smallest gated p95 error: {best_text} ({best_value:.3g} m{gross_text}); largest: {worst_text} ({worst_value:.3g} m); "
        f"see the relative table for paired 95 % intervals before calling a difference real."
    )


#: Below these a run's tail errors and coverage are too noisy to rank runs by: detections, and source positions.
FEW_DETECTIONS, FEW_POSITIONS = 200, 30


def too_few_warning(runs: list[RunResult]) -> str | None:
    """One line naming the runs whose p95, p99 and coverage rest on too few detections or positions to compare, or None."""
    few = []
    for r in runs:
        gate = r.metrics.get(col.METRICS_ERRORS, {}).get("gate")
        if not gate:
            continue
        n = int(gate.get("n", 0))
        positions = r.metrics.get(col.METRICS_CI95, {}).get("n_positions")
        if n < FEW_DETECTIONS or (positions is not None and positions < FEW_POSITIONS):
            few.append((r.label, n, positions))
    if not few:
        return None
    n_min = min(n for _, n, _ in few)
    half = 1.96 * np.sqrt(0.95 * 0.05 / max(n_min, 1))
    named = "; ".join(f"{label}: {n} detections" + (f" at {p} positions" if p is not None else "") for label, n, p in few)
    return (
        f"Too few to compare: {named}. At this size a coverage of 0.95 is known only to ±{half:.2f} (independent detections; "
        f"wider when they share positions) and a p99 error is one or two detections: run at least {FEW_DETECTIONS} detections "
        f"at {FEW_POSITIONS} positions before ranking runs."
    )


def paired_ratio_ci(
    first: pd.DataFrame, other: pd.DataFrame, q: float, n_boot: int = 1000, seed: int = 0, method: str = "gate"
) -> tuple[float, float] | None:
    """95 % interval of the ratio of ``method``'s ``q``-th error percentile (other / first), by a
    paired bootstrap over source positions (the exchangeable unit). Events without an estimate
    count as infinite errors.

    Returns None when the two runs were not evaluated on the same events.
    """
    a = first.set_index(col.EVENT_ID)
    b = other.set_index(col.EVENT_ID)
    if len(a) != len(b) or not a.index.sort_values().equals(b.index.sort_values()):
        return None
    b = b.loc[a.index]
    ea = np.nan_to_num(a[col.error_m(method)].to_numpy(float), nan=np.inf)
    eb = np.nan_to_num(b[col.error_m(method)].to_numpy(float), nan=np.inf)
    positions = a[col.POSITION_ID].to_numpy()
    members = [np.flatnonzero(positions == p) for p in np.unique(positions)]
    rng = np.random.default_rng(seed)
    ratios = np.empty(n_boot)
    with np.errstate(invalid="ignore"):  # inf / inf: both percentiles are failures, no ratio
        for k in range(n_boot):
            rows = np.concatenate([members[i] for i in rng.integers(0, len(members), len(members))])
            denominator = np.percentile(ea[rows], q)
            ratios[k] = np.percentile(eb[rows], q) / denominator if denominator > 0 else np.nan
    if np.isnan(ratios).all():
        return None
    # the ends are bootstrap ratios themselves (no interpolation), so an infinite ratio stays infinite
    low, high = np.nanpercentile(ratios, 2.5, method="lower"), np.nanpercentile(ratios, 97.5, method="higher")
    return float(low), float(high)


def relative_rows(runs: list[RunResult], method: str = "gate") -> pd.DataFrame:
    """``method``'s p50/p95/p99 error of every run and its ratio to the first run's (e.g. the full
    feature set at the head of an ablation sweep), with a 95 % interval from a paired bootstrap over
    source positions when the runs share their test events. Empty for a single run."""
    if len(runs) < 2 or any(method not in r.metrics[col.METRICS_ERRORS] for r in runs):
        return pd.DataFrame()
    first = runs[0].metrics[col.METRICS_ERRORS][method]
    first_predictions = runs[0].predictions
    rows = []
    for r in runs:
        errors = r.metrics[col.METRICS_ERRORS][method]
        predictions = r.predictions
        row = r.identity()
        for name, q in (("p50", 50), ("p95", 95), ("p99", 99)):
            row[f"{method} {name} (m)"] = errors[name]
            row[f"{name} / first"] = errors[name] / first[name] if first[name] > 0 else float("nan")
            ci = None
            if r is not runs[0] and first_predictions is not None and predictions is not None:
                ci = paired_ratio_ci(first_predictions, predictions, q, method=method)
            row[f"{name} / first, 95 % CI"] = "—" if ci is None else f"[{ci[0]:.2f}, {ci[1]:.2f}]"
        rows.append(row)
    return pd.DataFrame(rows)


def model_relative_rows(runs: list[RunResult]) -> pd.DataFrame:
    """``relative_rows`` for the point model: where feature groups show (the gate mostly keeps the solver's fix)."""
    return relative_rows(runs, method="model")


def _levels_without_guarantee(metrics: dict) -> str:
    """The levels some split's calibration could not guarantee, and what their radii are (none, or rescaled and not guaranteed)."""
    empty, rescaled = set(), set()
    for c in metrics.get("calibration_by_split", []):
        rescaled |= set(c.get("not_guaranteed_levels", []))
        empty |= set(c.get("unsupported_levels", [])) - set(c.get("not_guaranteed_levels", []))
    parts = [f"{lv}: no radius" for lv in sorted(empty)] + [f"{lv}: not guaranteed" for lv in sorted(rescaled)]
    return "; ".join(parts)


def coverage_rows(runs: list[RunResult]) -> pd.DataFrame:
    """Empirical coverage and median interval radius (m) per run, scorer and nominal level; levels without a guarantee named."""
    rows = []
    for r in runs:
        without = _levels_without_guarantee(r.metrics)
        for scorer, by_level in r.metrics[col.METRICS_COVERAGE].items():
            row = {**r.identity(), "scorer": scorer, **({"levels without a guarantee": without} if without else {})}
            for level, value in by_level.items():
                row[f"coverage@{level} (share)"] = value
            for level in by_level:
                row[f"median radius@{level} (m)"] = r.metrics[col.METRICS_WIDTH][scorer][level]["median_m"]
            for level, stats in r.metrics.get(col.METRICS_COVERAGE_BY_POSITION, {}).get(scorer, {}).items():
                row[f"coverage per position@{level} (share)"] = stats["mean"]  # the guarantee's unit
                row[f"worst position@{level} (share)"] = stats["min"]
            rows.append(row)
    return pd.DataFrame(rows)


def uncertainty_rows(runs: list[RunResult]) -> pd.DataFrame:
    """Spearman ρ of predicted vs actual error (error model and GDOP alone), substitution rate, the gate as fitted, timings."""
    rows = []
    for r in runs:
        m = r.metrics
        rho = m.get(col.METRICS_SPEARMAN, {})
        rows.append(
            {
                **r.identity(),
                "ρ error model (Spearman)": rho.get("error_model"),
                "ρ GDOP (Spearman)": rho.get("gdop"),
                "AUC error model, > 5 m": m.get(col.METRICS_GROSS_AUC, {}).get("error_model"),
                "substitution rate (%)": None if m.get(col.METRICS_SUBSTITUTION) is None else 100 * m[col.METRICS_SUBSTITUTION],
                "gate": _gate_summary(m),
                "CRB p50 (m)": m.get(col.CRB, {}).get("p50"),
                "feature groups withheld": r.withheld_groups,
                "models time (s)": m.get("timings_s", {}).get("models_s"),
            }
        )
    return pd.DataFrame(rows)


def format_cell(value: object) -> str:
    """A table cell as read: numbers to 3 significant digits, ∞ for a failure's infinite error, — where a run has no value."""
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "—"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return ("∞" if value > 0 else "−∞") if np.isinf(value) else f"{float(value):.3g}"
    return str(value)


def _gate_summary(metrics: dict) -> str | None:
    """``hybrid: tau_star_db 3.1`` — the configured gate's name and its numeric settings as fitted (median over splits)."""
    gate = metrics.get("gate")
    if not gate:
        return None
    settings = ", ".join(f"{k} {v:.3g}" for k, v in gate_scalars(metrics).items())
    return f"{gate.get('name', 'gate')}: {settings}" if settings else str(gate.get("name", "gate"))


def provenance_rows(runs: list[RunResult]) -> pd.DataFrame:
    """Where each run lives and what produced it: run dir, dataset hash, code version, choices."""
    return pd.DataFrame(
        [
            {
                **r.identity(),
                "run dir": str(r.run_dir),
                "dataset hash": r.metrics.get("dataset_hash", "")[:12],
                "code": r.metrics.get("code_version", ""),
                "choices": ", ".join(f"{k}={v}" for k, v in sorted(r.metrics.get("choices", {}).items())),
            }
            for r in runs
        ]
    )


def _comparison_plots(runs: list[RunResult], out_dir: Path) -> list[Path]:
    from acoustlab.reporting.plots import coverage_by_condition_plot, coverage_calibration, error_cdf, plt

    paths = []
    curves: dict[str, np.ndarray] = {}
    solver_seen = set()
    for r in runs:
        predictions = r.predictions
        if predictions is None:
            continue
        curves[f"gate: {r.label}"] = predictions[col.error_m("gate")].to_numpy(float)
        if r.metrics.get("dataset_hash") not in solver_seen:  # the solver is the same on the same data
            solver_seen.add(r.metrics.get("dataset_hash"))
            curves[f"solver: {r.label}"] = predictions[col.error_m("solver")].to_numpy(float)
    if curves:
        fig, ax = plt.subplots(figsize=(7, 4.5))
        error_cdf(ax, curves)
        ax.set_title("error CDF across runs", fontsize=9)
        fig.tight_layout()
        fig.savefig(out_dir / "sweep_error_cdf.png", dpi=110)
        plt.close(fig)
        paths.append(out_dir / "sweep_error_cdf.png")
    scorers = list(dict.fromkeys(s for r in runs for s in r.metrics[col.METRICS_COVERAGE]))
    columns = min(3, len(scorers))
    rows = -(-len(scorers) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(3.6 * columns, 3.8 * rows), squeeze=False)
    for ax, scorer in zip(axes.flat, scorers):  # one panel per scorer, one line per run: readable with conformal=all
        coverage_calibration(
            ax,
            {
                r.label: {float(lv): v for lv, v in r.metrics[col.METRICS_COVERAGE][scorer].items()}
                for r in runs
                if scorer in r.metrics[col.METRICS_COVERAGE]
            },
        )
        ax.set_title(scorer, fontsize=9)
    for ax in list(axes.flat)[len(scorers) :]:
        ax.set_visible(False)
    fig.suptitle("coverage calibration across runs", fontsize=10)
    fig.tight_layout()
    fig.savefig(out_dir / "sweep_coverage_calibration.png", dpi=110)
    plt.close(fig)
    paths.append(out_dir / "sweep_coverage_calibration.png")
    by_condition = {r.label: r.metrics[col.METRICS_COVERAGE_BY_CONDITION] for r in runs if r.metrics.get(col.METRICS_COVERAGE_BY_CONDITION)}
    if by_condition:
        paths.append(coverage_by_condition_plot(by_condition, out_dir / "sweep_coverage_by_condition.png"))
    return paths


_SECTIONS = (
    ("Localization error per detection (m)", error_rows),
    ("Gated error relative to the first run", relative_rows),
    ("Point-model error relative to the first run", model_relative_rows),
    ("Coverage and interval width of the conformal regions", coverage_rows),
    ("Ranking of errors and gating", uncertainty_rows),
    ("Provenance", provenance_rows),
)


def _img_tag(path: Path, alt: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode()
    return f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(alt)}"><figcaption>{html.escape(alt)}</figcaption></figure>'


def _copy_run_plots(runs: list[RunResult], out_dir: Path) -> list[tuple[str, list[Path]]]:
    """Each run's plots copied to ``out_dir/runs/<i>/``, with the run's label."""
    per_run = []
    for i, r in enumerate(runs):
        plots = sorted((r.run_dir / "plots").glob("*.png")) if (r.run_dir / "plots").exists() else []
        copied = []
        for p in plots:
            target = out_dir / "runs" / str(i) / p.name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(p, target)
            copied.append(target)
        per_run.append((r.label, copied))
    return per_run


def write_report(runs: list[RunResult], out_dir: Path, title: str | None = None, failed: list[FailedJob] | None = None) -> Path:
    """Write ``report.md`` (with images beside it) and a self-contained ``report.html``.

    Parameters
    ----------
    runs : list of RunResult
        The runs (from ``collect_runs``); must not be empty.
    out_dir : pathlib.Path
        Output directory (created).
    title : str, optional
        The report's heading (default: the site(s) and the options that vary, ``default_title``).
    failed : list of FailedJob, optional
        The sweep's jobs that failed (``collect_failed``): counted in the heading and listed with their reasons.

    Returns
    -------
    pathlib.Path
        The path of ``report.md``.
    """
    failed = list(failed or [])
    if not runs and not failed:
        raise ValueError("no runs to report")
    out_dir.mkdir(parents=True, exist_ok=True)
    tables = [(heading, build(runs)) for heading, build in _SECTIONS] if runs else []
    comparison = _comparison_plots(runs, out_dir) if runs else []
    per_run = _copy_run_plots(runs, out_dir)

    counted = f"{len(runs)} run(s)" + (f", {len(failed)} failed" if failed else "")
    title = title or (default_title(runs) if runs else "acoustlab") + (
        f" ({len(failed)} of {len(runs) + len(failed)} jobs failed)" if failed else ""
    )
    summary = conclusion(runs) if runs else "no job finished"
    warning = too_few_warning(runs) if runs else None
    md = [
        f"# {title}",
        "",
        f"**{summary}**",
        "",
        *([f"> {warning}", ""] if warning else []),
        f"{counted}. Errors are 2-D (m) over the detections in each run's summary; "
        f"gross = error above {GROSS_ERROR_M:g} m; — = not applicable to that run.",
        "",
    ]
    page = [
        f"<h1>{html.escape(title)}</h1>",
        f"<p><strong>{html.escape(summary)}</strong></p>",
        *([f"<p><em>{html.escape(warning)}</em></p>"] if warning else []),
        f"<p>{counted}. Errors are 2-D (m) over the detections in each run's summary; "
        f"gross = error above {GROSS_ERROR_M:g} m; — = not applicable to that run.</p>",
    ]
    if failed:
        tables = [("Failed jobs", failed_rows(failed)), *tables]
    for heading, table in tables:
        if table.empty:
            continue
        table = table.map(format_cell)  # every number to 3 significant digits, even in a column with gaps
        md += [f"## {heading}", "", table.to_markdown(index=False, disable_numparse=True), ""]
        page += [f"<h2>{html.escape(heading)}</h2>", table.to_html(index=False)]
    md += ["## Plots", ""]
    page += ["<h2>Plots</h2>"]
    for p in comparison:
        md += [f"![{p.stem}]({p.name})", ""]
        page.append(_img_tag(p, p.stem.replace("_", " ")))
    for i, (label, plots) in enumerate(per_run):
        if not plots:
            continue
        md += [f"### Run: {label}", ""] + [f"![{p.stem}](runs/{i}/{p.name})" for p in plots] + [""]
        page.append(f"<h3>Run: {html.escape(label)}</h3>")
        page += [_img_tag(p, f"{label}: {p.stem.replace('_', ' ')}") for p in plots]
    (out_dir / "report.md").write_text("\n".join(md))
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em}"
        "table{border-collapse:collapse;font-size:13px;margin-bottom:1em}td,th{border:1px solid #ccc;padding:3px 6px;text-align:right}"
        "figure{display:inline-block;margin:0.5em}img{max-width:520px}figcaption{font-size:12px;color:#555}"
    )
    (out_dir / "report.html").write_text(
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>{style}</style></head><body>"
        + "\n".join(page)
        + "</body></html>"
    )
    log.info("report written to %s and %s", out_dir / "report.md", out_dir / "report.html")
    return out_dir / "report.md"


def main(argv: list[str] | None = None) -> int:
    """``python -m acoustlab.report PATH ... [--out DIR] [--title TEXT]``."""
    parser = argparse.ArgumentParser(
        prog="python -m acoustlab.report", description="Summarise acoustlab runs (a sweep dir or run dirs) as Markdown and HTML."
    )
    parser.add_argument("paths", nargs="+", type=Path, help="a sweep directory (searched for metrics.json) or run directories")
    parser.add_argument("--out", type=Path, help="output directory (default: <first path>/report)")
    parser.add_argument("--title", default=None, help="report heading")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        runs = collect_runs(args.paths)
    except FileNotFoundError as exc:
        print(f"acoustlab.report: error: {exc}", file=sys.stderr)
        return 2
    failed = collect_failed(args.paths)
    if not runs and not failed:
        print(
            f"acoustlab.report: error: no finished runs (metrics.json with results) under {', '.join(map(str, args.paths))}",
            file=sys.stderr,
        )
        return 2
    out = args.out or args.paths[0] / "report"
    path = write_report(runs, out, title=args.title, failed=failed)
    print(path)
    print(path.with_suffix(".html"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
