"""The paper's published figures beside this run's (``+experiment=paper_forest`` / ``paper_frozen_lake``)."""

from __future__ import annotations

from typing import Any

import numpy as np


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


def paper_comparison(reference: dict[str, Any], metrics: dict[str, Any]) -> tuple[list[dict[str, Any]], list[str]]:
    """Rows ``quantity, paper, ours, ratio`` for every figure of ``reference`` and the Markdown table.

    ``reference`` has ``source`` (what the paper measured it on), ``note`` (what differs here) and
    ``figures``: {dotted metrics path: the paper's value}.
    """
    rows = []
    for path, value in reference.get("figures", {}).items():
        ours = _ours(metrics, path)
        rows.append({"quantity": path, "paper": float(value), "ours": ours,
                     "ratio": ours / float(value) if np.isfinite(ours) and float(value) else float("nan")})

    def fmt(v: float) -> str:
        return "∞" if v == float("inf") else "—" if np.isnan(v) else f"{v:.3g}"

    lines = ["# This run beside the paper", "", f"Paper: {reference.get('source', '')}", "", f"Here: {reference.get('note', '')}", "",
             "| quantity (metrics.json) | paper | this run | this ÷ paper |", "|---|---|---|---|"]
    lines += [f"| `{r['quantity']}` | {fmt(r['paper'])} | {fmt(r['ours'])} | {fmt(r['ratio'])} |" for r in rows]
    return rows, lines
