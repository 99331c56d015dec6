"""The package's layers: no module imports from a layer above its own, and acoustlab never imports plugins."""

import subprocess
import sys
from pathlib import Path

import pytest

from acoustlab.core.imports import internal_imports

PACKAGE = Path(__file__).resolve().parent.parent / "acoustlab"
#: Layers from the bottom up; a module may import only from its own layer or the ones before it.
LAYERS = ("core", "toolkit", "stages", "method", "reporting", "season", "run")
#: Entry points at the top (``python -m acoustlab``, ``acoustlab.report``, ``acoustlab.upload``, ``acoustlab.catalog``,
#: ``acoustlab.synthetic_season``).
ENTRY = "entry"


def layer_of(module: str) -> str:
    parts = module.split(".")
    if parts[0] != "acoustlab":
        return parts[0]
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in LAYERS) else ENTRY


def all_modules() -> list[str]:
    modules = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules.append(".".join(parts))
    return modules


MODULES = all_modules()


def test_every_module_sits_in_a_known_layer():
    unknown = [m for m in MODULES if layer_of(m) not in (*LAYERS, ENTRY) and m != "acoustlab"]
    assert not unknown, f"modules outside the layers {LAYERS}: {unknown}"


@pytest.mark.parametrize("module", MODULES)
def test_no_upward_import(module):
    own = layer_of(module)
    if own == ENTRY or module == "acoustlab":
        allowed = set(LAYERS)
    else:
        allowed = set(LAYERS[: LAYERS.index(own) + 1])
    for imported in internal_imports(module):
        target = layer_of(imported)
        assert target != "plugins", f"{module} imports {imported}: acoustlab never imports plugins (Hydra builds them)"
        if imported == "acoustlab":
            continue  # the package root holds only metadata (__version__); see test_package_root_imports_nothing
        if target == ENTRY:
            assert own == ENTRY, f"{module} ({own}) imports the entry module {imported}"
            continue
        assert target in allowed, f"{module} (layer {own}) imports {imported} from the layer above, {target}"


PLUGINS = PACKAGE.parent / "plugins"
#: The layers a plugin may import: the data model and contracts, and the pure functions. A plugin that
#: needed a stage, the method or the app would be part of the pipeline, not a choice Hydra makes.
PLUGIN_LAYERS = ("core", "toolkit")


def plugin_modules() -> list[str]:
    modules = []
    for path in sorted(PLUGINS.rglob("*.py")):
        parts = list(path.relative_to(PLUGINS.parent).with_suffix("").parts)
        modules.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return modules


@pytest.mark.parametrize("module", plugin_modules())
def test_plugins_import_only_core_and_toolkit(module):
    for imported in internal_imports(module):
        if imported.split(".")[0] == "plugins":
            continue  # a plugin may build on another plugin (the consistent-set solver on the hyperbolic one)
        assert layer_of(imported) in PLUGIN_LAYERS, f"{module} imports {imported}: plugins import only acoustlab.core and acoustlab.toolkit"


def test_the_layer_test_sees_imports():
    """The walker finds real edges (a test that finds none would pass vacuously)."""
    assert "acoustlab.core.contracts" in internal_imports("acoustlab.method.pipeline")
    assert "acoustlab.stages.solver_columns" in internal_imports("acoustlab.run.app")
    assert layer_of("acoustlab.run.app") == "run" and layer_of("acoustlab.report") == ENTRY
    assert "acoustlab.toolkit.tdoa" in internal_imports("plugins.solvers.consistent_set")  # plugins are walked too


def test_package_root_imports_nothing():
    """The root is metadata at import time (every layer imports it); it reaches the notebook API only when asked for it."""
    assert internal_imports("acoustlab") <= {"acoustlab.api"}, "acoustlab/__init__.py must stay metadata only"
    loaded = subprocess.run(
        [sys.executable, "-c", "import sys, acoustlab; print(sorted(m for m in sys.modules if m.startswith('acoustlab')))"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert loaded.strip() == "['acoustlab']", loaded


def test_no_function_in_acoustlab_has_more_than_45_statements():
    """A function one reads in a sitting: at most 45 statements after its docstring, counted on the syntax tree
    (nested statements included), so the formatter's line breaks do not move the limit."""
    import ast

    long = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                statements = sum(isinstance(n, ast.stmt) for n in ast.walk(node)) - 1  # the def itself
                body = node.body
                if isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) and len(body) > 1:
                    statements -= 1  # the docstring
                if statements > 45:
                    long.append(f"{path.name}:{node.lineno} {node.name} ({statements} statements)")
    assert not long, "functions over 45 statements: " + ", ".join(long)


#: Literals that share a column's spelling but are something else: config keys and settings fields.
NOT_COLUMNS = {
    "acoustlab/stages/sites.py": {"temperature_c", "relative_humidity_pct", "snr_db"},  # site.* config keys
    "acoustlab/toolkit/input_uncertainty.py": {"temperature_c"},  # conformal.input_uncertainty field
    "plugins/gates/hybrid.py": {"substitution_rate"},  # a column of the gate's own τ grid
    "plugins/gates/learned.py": {"substitution_rate"},  # a key of the gate's own threshold path
}


#: Constants whose values are ordinary words used in many other senses (method names, config groups).
GENERIC_WORDS = {
    "ESTIMATORS",
    "METHODS",
    "TRUST_PREFIX",
    "RADIUS_PREFIX",
    "POSITION_SOURCE",
    "GROUP_SEPARATOR",
    "EXTRA_GATE_PREFIX",
    "GATE_WITHOUT_TRUST",
    "METRICS_GATE",
}


def _column_names() -> set[str]:
    """Every column name :mod:`acoustlab.core.columns` defines as a module constant."""
    from acoustlab.core import columns

    names = set()
    for name, value in vars(columns).items():
        if name.isupper() and name not in GENERIC_WORDS:
            values = value if isinstance(value, tuple) else (value,)
            names |= {v for v in values if isinstance(v, str) and len(v) >= 3}
    return names | {name for name, _, _ in columns.SOLVER_CATALOG}


def _literal_uses(path: Path, names: set[str]) -> list[tuple[int, str]]:
    """(line, literal) of every string constant in ``path`` spelled like a column, docstrings and f-string parts excluded."""
    import ast

    tree = ast.parse(path.read_text())
    skip = {
        id(n.body[0].value)
        for n in ast.walk(tree)
        if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
        and n.body
        and isinstance(n.body[0], ast.Expr)
        and isinstance(n.body[0].value, ast.Constant)
    }
    skip |= {id(v) for n in ast.walk(tree) if isinstance(n, ast.JoinedStr) for v in n.values}
    return [
        (n.lineno, n.value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value in names and id(n) not in skip
    ]


def test_column_names_are_written_only_through_the_columns_module():
    """A rename in core/columns.py reaches every writer and reader: no module spells a column or a metrics.json block itself."""
    root = PACKAGE.parent
    names = _column_names()
    assert {"snr_db", "crb_m", "x_m", "solver__gdop", "placed", "interval_width", "errors"} <= names  # the scan sees the constants
    spelled = []
    for path in sorted([*PACKAGE.rglob("*.py"), *(root / "plugins").rglob("*.py")]):
        rel = path.relative_to(root).as_posix()
        if rel == "acoustlab/core/columns.py":
            continue
        allowed = NOT_COLUMNS.get(rel, set())
        spelled += [f"{rel}:{line} {value!r}" for line, value in _literal_uses(path, names) if value not in allowed]
    assert not spelled, "column names spelled outside acoustlab/core/columns.py: " + ", ".join(spelled)


def test_the_column_scan_sees_a_spelled_column(tmp_path):
    """The scan above is not blind: a module that writes ``events["snr_db"]`` is found, a docstring is not."""
    module = tmp_path / "writer.py"
    module.write_text('"""Writes snr_db."""\ndef f(events):\n    events["snr_db"] = 1\n    return f"{events}_x_m"\n')
    assert _literal_uses(module, {"snr_db", "_x_m"}) == [(3, "snr_db")]
