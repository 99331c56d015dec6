"""The package's layers: no module imports from a layer above its own, and acoustlab never imports plugins."""

import subprocess
import sys
from pathlib import Path

import pytest

from acoustlab.core.imports import internal_imports

PACKAGE = Path(__file__).resolve().parent.parent / "acoustlab"
#: Layers from the bottom up; a module may import only from its own layer or the ones before it.
LAYERS = ("core", "toolkit", "reporting", "stages", "method", "season", "run")
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


def _functions(path: Path):
    import ast

    return [n for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]


def _module_of(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_no_layer_below_run_receives_the_config_or_the_built_run():
    """Jobs get a typed ``RunContext``: below ``run/`` no function takes a ``DictConfig``, a ``built`` run or a ``prepare``
    callback, and no ``context`` parameter is untyped (``core.contracts`` states the contracts loosely, below every type)."""
    import ast

    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if layer_of(_module_of(path)) in ("run", ENTRY):
            continue
        for fn in _functions(path):
            for arg in [*fn.args.args, *fn.args.kwonlyargs]:
                note = ast.unparse(arg.annotation) if arg.annotation is not None else ""
                where = f"{path.relative_to(PACKAGE.parent)}:{fn.lineno} {fn.name}({arg.arg}: {note})"
                if "DictConfig" in note or arg.arg in ("built", "prepare"):
                    found.append(where)
                if arg.arg == "context" and note in ("", "Any") and layer_of(_module_of(path)) != "core":
                    found.append(where)
    assert not found, "below run/: " + ", ".join(found)


def _callbacks_up(path: Path) -> list[str]:
    """Lambdas and nested functions of ``path`` passed to a function of a lower layer whose bodies use a name imported from
    a layer above that function's (a callback up a layer)."""
    import ast

    tree = ast.parse(path.read_text())
    imported: dict[str, str] = {}  # local name -> module it comes from
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in ("acoustlab", "plugins"):
            for alias in node.names:
                imported[alias.asname or alias.name] = node.module
    nested = {n.name: n for fn in _functions(path) for n in ast.walk(fn) if n is not fn and isinstance(n, ast.FunctionDef)}
    rank = {name: i for i, name in enumerate(LAYERS)}
    found = []
    for call in (n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in imported):
        callee = layer_of(imported[call.func.id])
        for arg in [*call.args, *(k.value for k in call.keywords)]:
            body = arg if isinstance(arg, ast.Lambda) else nested.get(arg.id) if isinstance(arg, ast.Name) else None
            if body is None or callee not in rank:
                continue
            used = {n.id for n in ast.walk(body) if isinstance(n, ast.Name)} | {
                n.value.id for n in ast.walk(body) if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)
            }
            above = sorted(u for u in used if u in imported and rank.get(layer_of(imported[u]), len(LAYERS)) > rank[callee])
            if above or (isinstance(arg, ast.Lambda) and {"self", "protocol", "built", "cfg"} & used and rank[callee] < rank["method"]):
                found.append(f"{path.name}:{call.lineno} {call.func.id}(…) gets a callback using {above or 'a higher object'}")
    return found


def test_no_callback_goes_up_a_layer():
    """A lower layer never calls back into a higher one through a lambda or a nested function it was handed."""
    found = [f for path in sorted(PACKAGE.rglob("*.py")) for f in _callbacks_up(path)]
    assert not found, ", ".join(found)


def test_the_callback_scan_sees_a_callback_up(tmp_path):
    """The scan is not blind: a run-layer module handing a stage a lambda that calls the app is found."""
    module = tmp_path / "app.py"
    module.write_text(
        "from acoustlab.stages.dataset import load\nfrom acoustlab.run.app import prepare_data\n"
        "def go(cfg):\n    return load(lambda: prepare_data(cfg))\n"
    )
    assert _callbacks_up(module) and "prepare_data" in _callbacks_up(module)[0]


def test_no_protocol_implements_a_contract_by_raising():
    """Every protocol and job method ``run`` / ``run_job`` does its work: none is a bare ``raise``."""
    import ast

    stubs = []
    for path in [*sorted((PACKAGE / "method" / "protocols").glob("*.py")), *sorted((PACKAGE / "season").glob("*.py"))]:
        for fn in _functions(path):
            body = [n for n in fn.body if not (isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant))]
            if fn.name in ("run", "run_job") and len(body) == 1 and isinstance(body[0], ast.Raise):
                stubs.append(f"{path.name}:{fn.lineno}")
    assert not stubs, "contract methods that only raise: " + ", ".join(stubs)


def test_the_app_dispatches_once_on_the_kind_of_job():
    """``run_experiment`` tells a job from an evaluation once, by its contract; ``run/app.py`` reads one other property
    of the protocol, before the context is built: whether it needs recordings (two branches on the kind of job in all)."""
    text = (PACKAGE / "run" / "app.py").read_text()
    assert text.count("isinstance(protocol, Job)") == 1
    assert __import__("re").findall(r'declared\(protocol, "(\w+)"\)', text) == ["needs_field"]


def test_positions_are_made_in_one_place():
    """What a positions row holds is defined once: only ``acoustlab.method.localizer`` turns predictions into positions."""
    import ast

    makers = {"positions_table", "without_truth"}
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.relative_to(PACKAGE).as_posix() in ("method/localizer.py", "reporting/positions.py"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                name = node.func.id if isinstance(node.func, ast.Name) else node.func.attr if isinstance(node.func, ast.Attribute) else ""
                if name in makers:
                    found.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {name}")
    assert not found, "positions made outside acoustlab/method/localizer.py: " + ", ".join(found)


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
