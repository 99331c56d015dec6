"""Every config composes; every YAML of every plugin group instantiates and meets its contract."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from acoustlab.core import contracts as interfaces
from acoustlab.run.registry import (
    CONF_DIR,
    PLUGIN_GROUPS,
    build,
    build_feature_sets,
    build_scorers,
    group_options,
)
from acoustlab.stages.sites import site_from_config

CONTRACTS = {
    "simulator": interfaces.Simulator,
    "solver": interfaces.Solver,
    "model": interfaces.PointModel,
    "gate": interfaces.Gate,
    "error_model": interfaces.ErrorModel,
    "field": interfaces.FieldSource,
    "tracking": interfaces.Tracker,
}
OPTIONS = [(g, o) for g in PLUGIN_GROUPS for o in group_options(g)]


def test_every_group_has_options():
    for group in ("site", *PLUGIN_GROUPS, "experiment"):
        assert group_options(group), f"conf/{group}/ has no options"


@pytest.mark.parametrize("site", group_options("site"))
@pytest.mark.parametrize("experiment", [None, *group_options("experiment")])
def test_each_site_and_experiment_composes(compose_cfg, site, experiment):
    overrides = [f"+site={site}"] + ([f"+experiment={experiment}"] if experiment else [])
    cfg = compose_cfg(overrides)
    OmegaConf.to_container(cfg, resolve=True)  # every interpolation resolves
    site_obj = site_from_config(cfg.site)
    assert site_obj.n_mics >= 3


def test_experiments_never_choose_a_site():
    for name in group_options("experiment"):
        cfg = OmegaConf.load(CONF_DIR / "experiment" / f"{name}.yaml")
        assert "site" not in cfg, f"experiment {name} sets a site"


def test_the_season_fast_preset_is_the_lean_set_with_the_coarse_search(compose_cfg):
    """``+experiment=season_fast`` composes to exactly ``features=physics_lean +features.gcc.search=coarse
    solver=consistent_set``, and a setting given on the command line still wins over it."""
    preset = compose_cfg(["+site=forest", "+experiment=season_fast", "protocol=season"])
    spelled_out = compose_cfg(
        ["+site=forest", "features=physics_lean", "+features.gcc.search=coarse", "solver=consistent_set", "protocol=season"]
    )
    assert OmegaConf.to_container(preset) == OmegaConf.to_container(spelled_out)
    assert preset.solver._target_.endswith(".ConsistentSetSolver") and preset.features.gcc.search == "coarse"
    assert set(preset.features.groups) == set(compose_cfg(["features=physics_lean"]).features.groups)
    mine = compose_cfg(["+site=forest", "+experiment=season_fast", "solver=consistent_set", "features.gcc.search=fine"])
    assert mine.solver._target_.endswith(".ConsistentSetSolver") and mine.features.gcc.search == "fine"


@pytest.mark.slow
def test_the_season_defaults_to_the_season_fast_settings_and_nothing_else_does(compose_cfg):
    """``protocol=season`` (``python -m acoustlab season``) composes the lean set, the coarse GCC search and the consistent-set solver,
    exactly ``+experiment=season_fast``'s features and solver; a features or solver given on the command line wins, and the
    other protocols keep ``features=physics`` and ``solver=consistent_set``."""
    season = compose_cfg(["+site=forest", "protocol=season"])
    preset = compose_cfg(["+site=forest", "+experiment=season_fast", "protocol=season"])
    for node in ("features", "solver"):
        assert OmegaConf.to_container(season[node]) == OmegaConf.to_container(preset[node]), node
    assert season.features.gcc.search == "coarse" and season.solver._target_.endswith(".ConsistentSetSolver")
    full = compose_cfg(["+site=forest", "protocol=season", "features=physics", "solver=consistent_set"])
    assert OmegaConf.to_container(full.features) == OmegaConf.to_container(compose_cfg(["+site=forest"]).features)
    assert full.solver._target_.endswith(".ConsistentSetSolver") and "search" not in full.features.gcc
    on_gpu = compose_cfg(["+site=forest", "protocol=season", "features.gcc.search=fine", "+features.gcc.device=cuda"])
    assert on_gpu.features.gcc.search == "fine" and "ir" not in on_gpu.features.groups
    for protocol in ("sim_only", "localize", "field_eval", "cross_fit"):
        cfg = compose_cfg(["+site=forest", f"protocol={protocol}"])
        assert "ir" in cfg.features.groups and "search" not in cfg.features.gcc, protocol
        assert cfg.solver._target_.endswith(".ConsistentSetSolver"), protocol


@pytest.mark.parametrize("group,option", OPTIONS)
def test_every_option_composes_and_instantiates_to_its_contract(compose_cfg, group, option):
    cfg = compose_cfg(["+site=frozen_lake", f"{group}={option}", "paths.outputs_dir=/tmp/acoustlab-contract"])
    node = cfg[group]
    if group == "features":
        sets = build_feature_sets(node)
        for name, fs in sets.items():
            assert isinstance(fs, interfaces.FeatureSet), name
            assert fs.group == name, f"feature group {name!r} reports group {fs.group!r}"
        return
    if group == "conformal":
        scorers = build_scorers(node)
        assert all(isinstance(s, interfaces.ConformalScorer) for s in scorers.values())
        assert all(0 < v < 1 for v in node.levels)
        return
    obj = build(node, group)
    if group == "field" and obj is None:
        return  # 'none': no field data
    if group == "protocol":
        # exactly one contract: an evaluation protocol (run) or a job (run_job), never both, never a stub of the other
        assert isinstance(obj, interfaces.EvaluationProtocol) != isinstance(obj, interfaces.Job), f"protocol={option}"
        assert isinstance(interfaces.declared(obj, "needs_field"), bool)
        return
    assert isinstance(obj, CONTRACTS[group]), f"{group}={option} does not satisfy {CONTRACTS[group].__name__}"
    if group in ("model", "error_model"):
        from sklearn.base import clone

        clone(obj)  # scikit-learn estimator contract


def test_point_models_fit_and_predict(compose_cfg):
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(60, 4)), rng.normal(size=60)
    for option in group_options("model"):
        if option == "tabpfn":
            continue  # needs weights; tested with a tiny checkpoint in test_tabpfn.py
        cfg = compose_cfg(["+site=frozen_lake", f"model={option}"])
        model = build(cfg.model, "model").fit(x, y)
        assert model.predict(x).shape == (60,)


@pytest.mark.parametrize(
    "override,reason",
    [
        ("data.n_event=5", "Could not override 'data.n_event'"),  # a typo in a key
        ("data.n_events=abc", "Error merging override data.n_events=abc"),  # a wrong type
        ("pipeline.model_target=sideways", "Error merging override pipeline.model_target=sideways"),  # not a choice
        ("site.tempreature_c=[1,2]", "Could not override 'site.tempreature_c'"),
        ("conformal.level=[0.9]", "Could not override 'conformal.level'"),
    ],
)
def test_typed_schema_rejects_mistakes_when_composing(compose_cfg, override, reason):
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match=reason.replace("[", r"\[")):
        compose_cfg(["+site=frozen_lake", override])


def test_a_gate_needing_a_missing_feature_group_fails_in_preflight(compose_cfg):
    from acoustlab.core.errors import ConfigError
    from acoustlab.run.app import build_run

    cfg = compose_cfg(["+site=frozen_lake", "features=baseline_gcc_phat", "gate=hybrid", "tracking=none"])
    with pytest.raises(ConfigError, match=r"gate HybridGate needs the feature groups \['environment'\]"):
        build_run(cfg)
    build_run(compose_cfg(["+site=frozen_lake", "features=baseline_gcc_phat", "gate=bounding_box", "tracking=none"]))


def test_shared_gcc_settings_reach_all_three_groups(compose_cfg):
    cfg = compose_cfg(["+site=frozen_lake", "features.gcc.band_hz=[6000,10500]", "features.gcc.upsample=3"])
    sets = build_feature_sets(cfg.features)
    for name in ("tdoa", "xcorr", "uncertainty"):
        assert sets[name].band_hz == (6000.0, 10500.0) and sets[name].upsample == 3, name


def test_physics_srp_extends_physics(compose_cfg):
    physics = compose_cfg(["+site=frozen_lake", "features=physics"]).features
    srp = compose_cfg(["+site=frozen_lake", "features=physics_srp"]).features
    assert list(srp.groups) == [*physics.groups, "srp"]
    assert OmegaConf.to_container(srp.groups, resolve=True)["tdoa"] == OmegaConf.to_container(physics.groups, resolve=True)["tdoa"]


def test_physics_lean_is_physics_without_the_waveform_groups(compose_cfg):
    """features=physics_lean is written out in full: its GCC settings and kept groups must not drift from physics'."""
    physics = OmegaConf.to_container(compose_cfg(["+site=frozen_lake", "features=physics"]).features, resolve=True)
    lean = OmegaConf.to_container(compose_cfg(["+site=frozen_lake", "features=physics_lean"]).features, resolve=True)
    assert lean["gcc"] == physics["gcc"]
    assert list(lean["groups"]) == [g for g in physics["groups"] if g not in ("ir", "spectral", "envelope")]
    assert lean["groups"]["xcorr"] == {**physics["groups"]["xcorr"], "extra_bands_hz": []}
    for name in ("tdoa", "uncertainty", "geometry", "environment"):
        assert lean["groups"][name] == physics["groups"][name], name


@pytest.mark.slow
def test_physics_lean_features_are_physics_features_minus_the_waveform_columns(compose_cfg):
    """On the same audio the lean set gives exactly the full set's GCC and context columns (so the solver's fixes are the same)."""
    from acoustlab.core.types import RecordingBatch
    from acoustlab.run.registry import build
    from acoustlab.stages.dataset import extract_features

    cfg = compose_cfg(["+site=forest"])
    site = site_from_config(cfg.site)
    ids = np.arange(4)
    batch = build(cfg.simulator, "simulator").simulate(site, ids, ids, 0)
    full = extract_features(batch, site, build_feature_sets(cfg.features))
    lean_sets = build_feature_sets(compose_cfg(["+site=forest", "features=physics_lean"]).features)
    lean = extract_features(RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events), site, lean_sets)
    assert not any(c.startswith(("ir__", "spectral__", "envelope__")) or c.endswith("hz") and c.startswith("xcorr__") for c in lean.columns)
    assert set(lean.columns) < set(full.columns)
    pd.testing.assert_frame_equal(lean, full[lean.columns], check_exact=True)


def test_cache_keys_cover_the_code_a_plugin_imports(tmp_path, monkeypatch):
    from acoustlab.core import imports
    from acoustlab.stages import cache

    closure = imports.import_closure("plugins.simulators.outdoor")
    assert "acoustlab.toolkit.propagation" in closure and "acoustlab.toolkit.physics" in closure
    before = cache.code_digest("plugins.simulators.outdoor")
    edited = tmp_path / "propagation.py"
    source = imports.module_source_path("acoustlab.toolkit.propagation").read_text()
    real = imports.module_source_path

    def patched(module):
        return edited if module == "acoustlab.toolkit.propagation" else real(module)

    monkeypatch.setattr(cache, "module_source_path", patched)
    edited.write_text(source + "\n# a comment only\n")
    assert cache.code_digest("plugins.simulators.outdoor") == before  # comments and docstrings do not count
    edited.write_text(source + "\nSPEED_FACTOR = 1.0\n")
    assert cache.code_digest("plugins.simulators.outdoor") != before  # code does


def test_a_foreign_plugins_package_is_refused(monkeypatch):
    import sys
    import types

    from acoustlab.core.errors import ConfigError
    from acoustlab.run import registry

    foreign = types.ModuleType("plugins")
    foreign.__file__ = "/site-packages/plugins/__init__.py"
    monkeypatch.setitem(sys.modules, "plugins", foreign)
    registry.check_plugins_package.cache_clear()
    try:
        with pytest.raises(ConfigError, match="is not acoustlab's"):
            registry.build(OmegaConf.create({"_target_": "plugins.gates.simple.SolverOnlyGate"}), "gate")
    finally:
        registry.check_plugins_package.cache_clear()


def test_batch_cache_computes_once_per_key():
    from acoustlab.core.types import EVENT_COLUMNS, RecordingBatch

    events = pd.DataFrame({c: [0.0] for c in EVENT_COLUMNS})
    batch = RecordingBatch(np.zeros((1, 3, 8), np.float32), 16000.0, events)
    calls = []
    assert batch.derived("k", lambda: calls.append(1) or 42) == 42
    assert batch.derived("k", lambda: calls.append(1) or 43) == 42
    assert len(calls) == 1


def test_a_mistyped_ablation_group_fails_in_preflight(compose_cfg):
    from acoustlab.core.errors import ConfigError
    from acoustlab.run.app import build_run

    with pytest.raises(ConfigError, match=r"features.drop names feature groups \['solvr'\]"):
        build_run(compose_cfg(["+site=frozen_lake", "features.drop=[solvr]", "tracking=none"]))
    with pytest.raises(ConfigError, match=r"pipeline.drop_from_model names feature groups \['xcor'\]"):
        build_run(compose_cfg(["+site=frozen_lake", "pipeline.drop_from_model=[xcor]", "tracking=none"]))
    build_run(compose_cfg(["+site=frozen_lake", "features.drop=[solver,xcorr]", "tracking=none"]))


#: Attribute names acoustlab reads by name from objects that are not plugins (the standard library,
#: numpy/AST nodes, plugin packages), each with why it is not a plugin property.
NOT_PLUGIN_ATTRIBUTES = {
    "sched_getaffinity": "os: free cores",
    "errno": "OSError: disk full",
    "body": "ast nodes: docstring-free source digests",
    "__len__": "iterables: progress totals",
    "__name__": "functions: plugin check names",
    "__file__": "packages: where a plugins package lives",
    "__path__": "packages: where a plugins package lives",
    "ACOUSTLAB_PLUGINS": "packages: the marker a plugins package must set",
}


def test_no_plugin_attribute_is_read_that_no_contract_declares():
    """Every getattr/hasattr/declared/hook with a literal name in acoustlab/ names a declared property, hook or contract attribute."""
    import ast
    import inspect
    from pathlib import Path

    import acoustlab

    contract_names = {
        name
        for obj in vars(interfaces).values()
        if inspect.isclass(obj) and getattr(obj, "_is_protocol", False)
        for name in (*getattr(obj, "__annotations__", {}), *(n for n in vars(obj) if not n.startswith("_")))
    }
    allowed = {
        "getattr": set(interfaces.OPTIONAL_PROPERTIES) | set(interfaces.OPTIONAL_HOOKS) | contract_names | set(NOT_PLUGIN_ATTRIBUTES),
        "declared": set(interfaces.OPTIONAL_PROPERTIES),
        "hook": set(interfaces.OPTIONAL_HOOKS),
    }
    allowed["hasattr"] = allowed["getattr"]
    offenders = []
    for path in Path(acoustlab.__file__).parent.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id in allowed
                and len(node.args) >= 2
                and isinstance(node.args[1], ast.Constant)
                and isinstance(node.args[1].value, str)
                and node.args[1].value not in allowed[node.func.id]
            ):
                offenders.append(f"{path.name}:{node.lineno} {node.func.id}(…, {node.args[1].value!r})")
    assert not offenders, (
        "attributes read by name that no contract declares (add them to OPTIONAL_PROPERTIES / OPTIONAL_HOOKS): " + ", ".join(offenders)
    )


def test_declared_refuses_an_undeclared_name():
    with pytest.raises(KeyError, match="not an optional plugin property"):
        interfaces.declared(object(), "needs_simulation")
    assert interfaces.declared(object(), "needs_field") is False and interfaces.hook(object(), "preflight") is None


def test_srp_phat_cross_correlates_in_the_shared_gcc_band(compose_cfg):
    """features.gcc.band_hz reaches SRP-PHAT too, so every group that cross-correlates uses one band."""
    cfg = compose_cfg(["+site=loca2021", "features=physics_srp", "features.gcc.band_hz=[6000,10500]"])
    sets = build_feature_sets(cfg.features)
    assert sets["srp"].band_hz == (6000.0, 10500.0)


#: Options that are deliberate variants of a plugin (its name says how), by (group, option, plugin label) → the settings that make the variant.
YAML_VARIANTS: dict[tuple[str, str, str], set[str]] = {
    # every conformal scorer is one SplitConformal variant: what it scales by, whether it uses the error model, its bins, its unit,
    # how a position-level quantile is taken
    **{
        ("conformal", option, label): {"normaliser", "use_error_model", "binning", "n_bins", "calibration_unit", "position_method"}
        for option in group_options("conformal")
        for label in ("fixed", "gdop_scaled", "gdop_only", "error_ratio", "mondrian_gdop", "gdop_by_region")
    },
    ("field", "recordings", "field"): {"mics_csv", "events_csv"},  # the shipped LOCA 2021 example; a user's own files have no default
    ("features", "physics_lean", "xcorr"): {"extra_bands_hz"},  # the lean set's xcorr: main band only
    ("features", "physics_lean_coarse", "xcorr"): {"extra_bands_hz"},  # the season's default: the lean set with the coarse GCC search
}


def _same(a, b) -> bool:
    """Equal plugin settings: numbers, strings, sequences and mappings compared by value, arrays elementwise."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple, np.ndarray)) and isinstance(b, (list, tuple, np.ndarray)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if hasattr(a, "__dict__") and type(a) is type(b) and not isinstance(a, type):
        return _same(vars(a), vars(b))
    return a == b or (isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b))


def _plugin_nodes(cfg, group):
    """(label, node) of every project plugin the option configures (feature groups one by one)."""
    node = cfg[group]
    nodes = node.groups.items() if group == "features" else node.scorers.items() if group == "conformal" else [(group, node)]
    return [(label, n) for label, n in nodes if n is not None and str(n.get("_target_", "")).startswith("plugins.")]


@pytest.mark.parametrize("group,option", OPTIONS)
def test_python_defaults_equal_the_yaml_defaults(compose_cfg, group, option):
    """A plugin built in a notebook with no arguments behaves as the command line's option: every setting the YAML
    states that is not wired to the run (``${seed}``, ``${threads:}``, the site's or the shared GCC's values) equals the
    Python default, compared on the built objects (nested defaults included)."""
    import importlib
    import inspect

    from hydra.utils import instantiate

    cfg = compose_cfg(["+site=frozen_lake", f"{group}={option}", "paths.outputs_dir=/tmp/acoustlab-contract"])
    for label, node in _plugin_nodes(cfg, group):
        module, name = str(node._target_).rsplit(".", 1)
        cls = getattr(importlib.import_module(module), name)
        params = inspect.signature(cls).parameters
        raw = OmegaConf.to_container(node, resolve=False)
        wired = {k for k, v in raw.items() if isinstance(v, str) and "${" in v} | YAML_VARIANTS.get((group, option, label), set())
        needed = {k for k in raw if k != "_target_" and (k in wired or (k in params and params[k].default is inspect.Parameter.empty))}
        from_yaml = instantiate(node, _convert_="all")
        resolved = OmegaConf.to_container(node, resolve=True)
        from_python = instantiate({"_target_": resolved["_target_"], **{k: resolved[k] for k in needed}}, _convert_="all")
        differing = [k for k in vars(from_yaml) if not _same(vars(from_yaml)[k], vars(from_python).get(k))]
        assert not differing, f"conf/{group}/{option}.yaml ({label}, {node._target_}) differs from the Python defaults in " + ", ".join(
            f"{k}: YAML {vars(from_yaml)[k]!r} vs Python {vars(from_python).get(k)!r}" for k in differing
        )


@pytest.mark.parametrize(
    "override,message",
    [
        ("pipeline.selective.delta=1.5", "pipeline.selective.delta must lie in (0, 1); got 1.5"),
        ("pipeline.selective.epsilon=0", "pipeline.selective.epsilon must lie in (0, 1); got 0.0"),
        ("pipeline.selective.gross_m=-1", "pipeline.selective.gross_m must be a positive number"),
        ("pipeline.selective.delta=0.0001", "need at least 23025 calibration events to certify anything, but data.n_events=120"),
    ],
)
def test_impossible_selective_settings_stop_in_the_preflight(compose_cfg, override, message):
    from acoustlab.core.errors import ConfigError
    from acoustlab.run.app import build_run

    cfg = compose_cfg(["+site=frozen_lake", "+experiment=smoke", "pipeline.selective.enabled=true", override])
    with pytest.raises(ConfigError) as caught:
        build_run(cfg)
    assert message in str(caught.value)


def test_an_unwritable_outputs_dir_is_named_before_hydra_starts(tmp_path, monkeypatch):
    import os

    from acoustlab.core.errors import ConfigError
    from acoustlab.run import preflight

    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(preflight.os, "access", lambda p, mode: False if Path(p) == locked else real_access(p, mode))
    with pytest.raises(ConfigError, match=r"paths.outputs_dir=.*locked/outputs: its parent .*locked is not writable"):
        preflight.check_output_dirs(["+site=forest", f"paths.outputs_dir={locked / 'outputs'}"])
    with pytest.raises(ConfigError, match=r"hydra.run.dir=.*: it is not writable"):
        preflight.check_output_dirs(["+site=forest", f"paths.outputs_dir={tmp_path}", f"hydra.run.dir={locked}"])
    with pytest.raises(ConfigError, match=r"protocol.output_dir=.*locked/season: its parent .*locked is not writable"):  # a season's folder
        preflight.check_output_dirs(["protocol=season", f"paths.outputs_dir={tmp_path}", f"protocol.output_dir={locked / 'season'}"])
    (tmp_path / "a_file").write_text("")
    with pytest.raises(ConfigError, match="is a file, not a folder"):
        preflight.check_output_dirs([f"paths.outputs_dir={tmp_path / 'a_file' / 'x'}"])
    preflight.check_output_dirs([f"paths.outputs_dir={tmp_path / 'new' / 'deeper'}"])  # creatable: fine
    preflight.check_output_dirs(["--help", f"paths.outputs_dir={locked}"])  # inspecting writes nothing


def test_help_names_every_protocol_and_the_localize_command(compose_cfg):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        header = str(compose(config_name="config", return_hydra_config=True).hydra.help.header)
    GlobalHydra.instance().clear()
    assert "python -m acoustlab localize" in header
    import re

    assert all(re.search(rf"\b{protocol}\s+\(", header) for protocol in group_options("protocol")), header


def test_help_gives_every_option_of_every_group_a_description():
    from acoustlab.run.schema import option_descriptions

    described: dict[str, dict[str, str]] = {}
    for row in option_descriptions().splitlines():
        if not row.startswith(" "):
            group = row.rstrip(":")
            continue
        option, _, text = row.strip().partition(" ")
        described.setdefault(group, {})[option] = text.strip()
    for group in ("model", "error_model", "gate", "solver", "conformal", "protocol", "site", "field", "experiment", "features"):
        for option in group_options(group):
            text = described[group][option]
            assert text and "@package" not in text, f"{group}={option} has no description in --help"


@pytest.mark.parametrize("experiment", ["ablate_features", "cross_fit_gates"])
def test_long_experiments_say_what_they_cost_before_starting(compose_cfg, experiment):
    cfg = compose_cfg(["+site=forest", f"+experiment={experiment}"])
    assert "min" in cfg.expected_duration and "2 cores" in cfg.expected_duration


@pytest.mark.slow
def test_running_out_of_memory_is_one_line_not_a_traceback(tmp_path):
    """A MemoryError deep in a run (numpy's ``_ArrayMemoryError``) ends the command with one line saying what to lower."""
    import subprocess
    import sys

    code = (
        "import runpy, sys\n"
        "import acoustlab.run.app as app\n"
        "def boom(*a, **k):\n"
        "    raise MemoryError('Unable to allocate 7.2 GiB for an array with shape (60, 6, 2832000)')\n"
        "app.run_experiment = boom\n"
        f"sys.argv = ['acoustlab', '+site=frozen_lake', 'paths.outputs_dir={tmp_path}', 'hydra.run.dir={tmp_path / 'run'}']\n"
        "runpy.run_module('acoustlab', run_name='__main__')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    (line,) = [row for row in proc.stderr.splitlines() if row.strip()]
    assert line.startswith("acoustlab: error: ran out of memory (Unable to allocate 7.2 GiB") and "split the events table" in line
