"""The Hydra app, the typed config schema, the registry, preflight, sweeps, upload, catalog and plugin checks."""
