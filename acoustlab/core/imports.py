"""Static import graph of acoustlab's own code (from the source, nothing is imported).

Used to version cache entries by all the code that produced them (a plugin and every acoustlab or
plugins module it reaches through imports) and by the test that keeps the layers in order.
"""

from __future__ import annotations

import ast
import functools
import importlib.util
from pathlib import Path

#: Top-level packages whose modules count as the project's own code.
OWN_PACKAGES = ("acoustlab", "plugins")


@functools.cache
def module_source_path(module: str) -> Path | None:
    """The ``.py`` file of an own module (a package's ``__init__.py``); None when it is not one."""
    if module.split(".")[0] not in OWN_PACKAGES:
        return None
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        return None
    if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin)


def _resolve_relative(module: str, level: int, target: str | None, is_package: bool) -> str:
    parts = module.split(".")
    base = parts if is_package else parts[:-1]
    base = base[: len(base) - (level - 1)] if level > 1 else base
    return ".".join(base + ([target] if target else []))


@functools.cache
def internal_imports(module: str) -> frozenset[str]:
    """The own modules ``module`` imports anywhere in its source (function-level imports included).

    ``from pkg import name`` counts as ``pkg.name`` where that is a module, else as ``pkg``.
    """
    path = module_source_path(module)
    if path is None:
        return frozenset()
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve_relative(module, node.level, node.module, is_package) if node.level else (node.module or "")
            names = []
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                names.append(sub if module_source_path(sub) is not None else base)
        else:
            continue
        found.update(n for n in names if module_source_path(n) is not None)
    found.discard(module)
    return frozenset(found)


def import_closure(module: str) -> list[str]:
    """``module`` and every own module it reaches through imports, sorted."""
    seen: set[str] = set()
    todo = [module]
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        seen.add(current)
        todo.extend(internal_imports(current) - seen)
    return sorted(m for m in seen if module_source_path(m) is not None)
