"""Evaluation protocols: how events are split into training, calibration and test sets."""
