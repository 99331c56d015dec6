"""Metrics, plots, the sweep report, the paper comparison and experiment logging."""
