"""The per-event stages on simulated events, each timed alone: simulation, features, solvers.

Every case simulates its events once in ``setup`` (untimed) with the site's default simulator; the
timed call is the stage a run or a season calls on a batch. Divide by ``n_events`` for per-event
figures. A season's detections per second (``bench_season.py``) is the figure the project optimizes;
these say where its time goes.
"""

from __future__ import annotations

import numpy as np


def _simulated(site_name: str, n_events: int, overrides: list[str] | None = None):
    """The composed config, the site and a batch of ``n_events`` simulated events at ``n_events // 5`` positions."""
    from acoustlab.run.plugin_checks import compose_config
    from acoustlab.run.registry import build
    from acoustlab.stages.sites import site_from_config

    cfg = compose_config([f"+site={site_name}", *(overrides or [])])
    site = site_from_config(cfg.site)
    ids = np.arange(n_events)
    return cfg, site, build(cfg.simulator, "simulator").simulate(site, ids, ids // 5, 0)


class Simulate:
    """The outdoor simulator rendering a batch of events."""

    params = [["frozen_lake", "forest"], [64]]
    param_names = ["site", "n_events"]

    def setup(self, site_name: str, n_events: int) -> None:
        from acoustlab.run.registry import build

        self.cfg, self.site, _ = _simulated(site_name, 1)
        self.simulator = build(self.cfg.simulator, "simulator")
        self.ids = np.arange(n_events)

    def time_simulate(self, site_name: str, n_events: int) -> None:
        self.simulator.simulate(self.site, self.ids, self.ids // 5, 0)


class Features:
    """The feature stage with the default set, the lean set and the lean set with the coarse GCC search."""

    params = [["frozen_lake", "forest"], ["physics", "physics_lean", "physics_lean_coarse"], [64]]
    param_names = ["site", "features", "n_events"]

    def setup(self, site_name: str, features: str, n_events: int) -> None:
        from acoustlab.run.registry import build_feature_sets

        cfg, self.site, self.batch = _simulated(site_name, n_events, [f"features={features}"])
        self.sets = build_feature_sets(cfg.features)

    def time_extract(self, site_name: str, features: str, n_events: int) -> None:
        from acoustlab.core.types import RecordingBatch
        from acoustlab.stages.dataset import extract_features

        fresh = RecordingBatch(self.batch.audio, self.batch.sample_rate_hz, self.batch.events)  # nothing cached from the last call
        extract_features(fresh, self.site, self.sets)

    def peakmem_extract(self, site_name: str, features: str, n_events: int) -> None:
        self.time_extract(site_name, features, n_events)


class Solvers:
    """Each solver on the same events' TDOA candidates."""

    params = [["frozen_lake", "forest"], ["consistent_set", "hyperbolic", "least_squares", "baseline_per_reference_mic"], [256]]
    param_names = ["site", "solver", "n_events"]

    def setup(self, site_name: str, solver: str, n_events: int) -> None:
        from acoustlab.run.registry import build, build_feature_sets
        from acoustlab.stages.dataset import extract_features
        from acoustlab.stages.solver_columns import solver_inputs_for

        cfg, site, batch = _simulated(site_name, n_events, [f"solver={solver}"])
        features = extract_features(batch, site, {"tdoa": build_feature_sets(cfg.features)["tdoa"]})
        self.inputs = solver_inputs_for(features, batch.events, site)
        self.solver = build(cfg.solver, "solver")

    def time_solve(self, site_name: str, solver: str, n_events: int) -> None:
        self.solver.solve(self.inputs)


class FeaturesOnGpu:
    """The lean feature stage with the GCC on a CUDA GPU (``+features.gcc.device=cuda``) beside the same on the CPU."""

    params = [["frozen_lake", "forest"], ["cpu", "cuda"], [64]]
    param_names = ["site", "device", "n_events"]

    def setup(self, site_name: str, device: str, n_events: int) -> None:
        from acoustlab.run.registry import build_feature_sets

        if device == "cuda":
            try:
                import torch
            except ImportError as exc:
                raise NotImplementedError(f"torch is not installed ({exc})") from exc
            if not torch.cuda.is_available():
                raise NotImplementedError("no CUDA GPU")
        overrides = ["features=physics_lean", *([f"+features.gcc.device={device}"] if device == "cuda" else [])]
        cfg, self.site, self.batch = _simulated(site_name, n_events, overrides)
        self.sets = build_feature_sets(cfg.features)

    def time_extract(self, site_name: str, device: str, n_events: int) -> None:
        from acoustlab.core.types import RecordingBatch
        from acoustlab.stages.dataset import extract_features

        extract_features(RecordingBatch(self.batch.audio, self.batch.sample_rate_hz, self.batch.events), self.site, self.sets)
