"""acoustlab: physics-informed learning for robust acoustic localization with calibrated uncertainty.

The package is layered; each subpackage imports only from the ones listed before it
(``tests/test_architecture.py`` enforces this):

- ``core``: typed data model, plugin contracts (``typing.Protocol``), errors, column names, resources;
- ``toolkit``: physics, propagation, DSP, geometry, TDOA and conformal maths (pure functions);
- ``reporting``: metrics, plots, the sweep report, the run folder's files, experiment logging (MLflow);
- ``stages``: the cached data stages (sites, simulation, features), the cache, the solver stage, field calibrations;
- ``method``: the localization pipeline, placing field detections (``FittedLocalizer``), the run context, the
  evaluation protocols and the ``localize`` and ``calibrate`` jobs;
- ``season``: the ``season`` job (streaming, resumable, sharded);
- ``run``: the Hydra app, typed config schema, registry, preflight, sweep callback, upload, plugin checks.

Plugins live in the top-level ``plugins`` package and are selected through Hydra config
groups; ``acoustlab`` never imports ``plugins``. Entry points: ``python -m acoustlab``,
``python -m acoustlab.report``, ``python -m acoustlab.upload``, ``python -m acoustlab.catalog``,
``python -m acoustlab.aligned_clips`` (its function: ``acoustlab.api.aligned_clips``).
"""

__version__ = "0.2.0"

#: The notebook API (``acoustlab.api``): ``import acoustlab; acoustlab.localize(...)``; imported on first use,
#: so ``import acoustlab`` stays cheap for the CLI. ``acoustlab.season`` is the season subpackage: its function is
#: ``acoustlab.api.season``.
_API = ("localize", "place", "calibrate", "plan_playbacks", "write_playback_sweep", "solve", "metrics", "overrides_from", "load_site")


def __getattr__(name: str):
    if name in _API:
        from acoustlab import api

        return getattr(api, name)
    raise AttributeError(f"module 'acoustlab' has no attribute {name!r}")
