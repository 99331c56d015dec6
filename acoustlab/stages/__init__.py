"""Data stages: sites from configs, the content-addressed cache, simulation and features, the solver columns."""
