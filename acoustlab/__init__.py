"""acoustlab: physics-informed learning for robust acoustic localization with calibrated uncertainty.

The core package holds the typed data model, the plugin contracts, shared physics and
signal maths, caching, protocols, conformal maths, metrics and the Hydra entry point.
Plugins live in the top-level ``plugins`` package and are selected through Hydra config
groups; ``acoustlab`` never imports ``plugins``.
"""

__version__ = "0.1.0"
