"""The paper's published figures beside this run's (``+experiment=paper_forest`` / ``paper_frozen_lake``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from acoustlab.toolkit.input_uncertainty import InputUncertainty


def _ours(metrics: dict[str, Any], path: str) -> float:
    """A value of metrics.json by dotted path, e.g. ``errors.solver.p95`` or ``coverage.gdop_scaled.0.8``."""
    node: Any = metrics
    parts = path.split(".")
    k = 0
    while k < len(parts):
        # level keys contain a dot ("0.8"): try the longest key first
        for width in (2, 1):
            key = ".".join(parts[k : k + width])
            if isinstance(node, dict) and key in node:
                node, k = node[key], k + width
                break
        else:
            return float("nan")
    return float(node) if isinstance(node, (int, float)) and node is not None else float("nan")


def _get(config: dict[str, Any], path: str) -> Any:
    node: Any = config
    for part in path.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    return node


def deviations(config: dict[str, Any]) -> list[str]:
    """What this run's method does differently from the paper's method as written, read from its resolved config.

    ``+experiment=paper_*_as_written`` removes every one it can; what remains (the simulator, a
    point model other than TabPFN without weights) is listed all the same.
    """
    out = []
    solver = str(_get(config, "solver._target_") or "")
    if not solver.endswith("HyperbolicSolver"):
        out.append(f"first stage: {solver.rsplit('.', 1)[-1]} (the paper: the closed-form hyperbolic solver; solver=hyperbolic)")
    if _get(config, "features.gcc.weighting") not in (None, "phat"):
        out.append(f"GCC weighting {_get(config, 'features.gcc.weighting')} (the paper: PHAT; features.gcc.weighting=phat)")
    if "TabPFN" not in str(_get(config, "model._target_") or ""):
        out.append(
            f"point model {str(_get(config, 'model._target_')).rsplit('.', 1)[-1]} (the paper: TabPFN; model=tabpfn needs its weights)"
        )
    if _get(config, "pipeline.error_model_gate_cues"):
        out.append(
            "the error model also sees the gate's context (solver–model distance, GDOP and range of the chosen estimate); "
            "the paper's sees the features only (pipeline.error_model_gate_cues=false)"
        )
    folds = _get(config, "conformal.calibration_folds")
    if folds != -1:
        out.append(
            f"conformal calibrated over {folds} folds of training positions (the paper: leave one position out; conformal.calibration_folds=-1)"
        )
    gate = str(_get(config, "gate._target_") or "")
    if not gate.endswith("HybridGate"):
        out.append(f"gate {gate.rsplit('.', 1)[-1]} (the paper: the two-stage hybrid gate; gate=hybrid)")
    elif _get(config, "gate.tau_reference") != "solver":
        out.append(
            "τ* rule compared with the box-gated solver (the paper: with the bare solver; gate.tau_reference=solver), "
            "since against the bare solver the box alone meets the rule and the most permissive τ wins"
        )
    if _get(config, "pipeline.trust.enabled"):
        out.append(
            "the trust check keeps the solver's fix where the point model is outside its training support (the paper has none; "
            "pipeline.trust.enabled=false)"
        )
    scaled = (_get(config, "conformal.scorers") or {}).get("gdop_scaled")  # the paper's GDOP-scaled variant (others are ours)
    if isinstance(scaled, dict) and scaled.get("gdop_cap_quantile") is not None:
        out.append(
            f"GDOP-scaled conformal: GDOP clipped to its calibration {scaled['gdop_cap_quantile']:g} quantiles (the paper scales by "
            "GDOP as it is; conformal.scorers.gdop_scaled.gdop_cap_quantile=null)"
        )
    allowance = _get(config, "conformal.input_uncertainty") or {}
    if allowance and not InputUncertainty(**allowance).is_zero:
        out.append(
            "radii of field detections carry an allowance for the stated input errors (the paper has none; "
            "conformal.input_uncertainty.temperature_c=0)"
        )
    if _get(config, "calibration"):
        out.append("a field calibration (calibration=…) corrects the array before anything is solved (the paper has none)")
    out.append("the simulator and data are ours, not the paper's (see the note above)")
    return out


def paper_comparison(
    reference: dict[str, Any], metrics: dict[str, Any], config: dict[str, Any] | None = None
) -> tuple[list[dict[str, Any]], list[str]]:
    """Rows ``quantity, paper, ours, ratio`` for every figure of ``reference`` and the Markdown table.

    ``reference`` has ``source`` (what the paper measured it on), ``note`` (what differs here) and
    ``figures``: {dotted metrics path: the paper's value}. With the run's resolved ``config`` the
    page also lists every deviation from the paper's method as written (``deviations``).
    """
    rows = []
    for path, value in reference.get("figures", {}).items():
        ours = _ours(metrics, path)
        rows.append(
            {
                "quantity": path,
                "paper": float(value),
                "ours": ours,
                "ratio": ours / float(value) if np.isfinite(ours) and float(value) else float("nan"),
            }
        )

    def fmt(v: float) -> str:
        return "∞" if v == float("inf") else "—" if np.isnan(v) else f"{v:.3g}"

    lines = [
        "# This run beside the paper",
        "",
        f"Paper: {reference.get('source', '')}",
        "",
        f"Here: {reference.get('note', '')}",
        "",
        "| quantity (metrics.json) | paper | this run | this ÷ paper |",
        "|---|---|---|---|",
    ]
    lines += [f"| `{r['quantity']}` | {fmt(r['paper'])} | {fmt(r['ours'])} | {fmt(r['ratio'])} |" for r in rows]
    if config is not None:
        lines += ["", "## How this run's method differs from the paper's as written", ""] + [f"- {d}" for d in deviations(config)]
    return rows, lines
