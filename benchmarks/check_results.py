"""Which committed benchmark results still describe the code: ``python benchmarks/check_results.py [--strict]``.

Every result written by :func:`common.write_results` names the commit and the benchmark script
(with its SHA-256) that made it. For each ``results/*.json`` this prints one line:

- ``current``: the script is unchanged and no module it imports (``acoustlab``, followed through
  its own imports), no plugin and no config changed what it does since that commit (docstrings, comments and
  formatting do not count: Python files are compared as syntax trees without docstrings, YAML
  files by their parsed values; a file added since does not count, see :func:`changed_since`);
- ``code changed``: the script is the same but modules it depends on changed since (they are named:
  re-run it, or say in the results why the change does not matter); the benchmarks' helper modules
  it imports (``common.py``, ``bench_season.py``, …) are among them. A change listed in
  ``benchmarks/no_effect.yaml`` (its files' versions before and after, and a ``bench_identity.py``
  comparison showing that the same jobs give identical predictions and metrics) is not counted: see
  :func:`waived`;
- ``script changed``: the script differs from the one that made the result (stale: re-run it);
- ``no provenance``: written before results named their commit (re-run to find out); the detail
  names the commit that last wrote the file, from git history;
- ``reference``: hashes that ``bench_identity.py`` compares a later run against (``identity_*.json``),
  not a measurement of the code;
- ``needs a GPU``: made on a lent GPU machine before results named their commit; only a GPU can
  re-run it (the detail names the command and the commit that last wrote it; ``docs/tabpfn.md``
  says what changed since).

``--strict`` exits 1 when any result's script changed (what the test suite checks).
"""

from __future__ import annotations

import argparse
import functools
import json
import subprocess
import sys
from pathlib import Path

from common import REPO, RESULTS, script_sha256

from acoustlab.core.imports import import_closure, module_source_path
from acoustlab.stages.cache import _code_text_of  # what the cache keys hash: the syntax tree without docstrings


#: Results only a GPU can re-run, with the command that makes them.
GPU_ONLY = {"tabpfn_device": "python benchmarks/bench_tabpfn_device.py",
            "tabpfn_gpu_end_to_end": "python benchmarks/bench_tabpfn_gpu_end_to_end.py"}


def _imported_modules(script: Path) -> set[str]:
    """Names of the modules ``script`` imports (``from pkg import name`` gives pkg, and pkg.name in case it is a module)."""
    import ast

    tree = ast.parse(script.read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    for n in ast.walk(tree):
        if isinstance(n, ast.ImportFrom) and n.module:
            names |= {n.module, *(f"{n.module}.{a.name}" for a in n.names)}
    return names


def dependencies(script: Path) -> set[Path]:
    """Source files of the own modules ``script`` imports, followed transitively (:func:`import_closure`).

    The benchmarks' own helper modules it imports (``common``, ``bench_season``, …: files beside the
    script) count too, with what they import: a result made through a helper is stale when the helper
    changed, although the script's own hash is the same.
    """
    helpers: set[Path] = set()
    direct: set[str] = set()
    todo = [script]
    while todo:
        current = todo.pop()
        names = _imported_modules(current)
        direct |= names
        for name in names:
            helper = script.parent / f"{name}.py"
            if "." not in name and helper.is_file() and helper != script and helper not in helpers:
                helpers.add(helper)
                todo.append(helper)
    own = [m for m in direct if m.split(".")[0] in ("acoustlab", "plugins") and module_source_path(m) is not None]
    return helpers | {p for m in own for name in import_closure(m) if (p := module_source_path(name)) is not None}


@functools.cache  # the same for every result of one check
def plugin_dependencies() -> tuple[str, ...]:
    """Source files (relative to the repository) of the own modules that any plugin module imports, transitively."""
    modules = [".".join(p.relative_to(REPO).with_suffix("").parts) for p in sorted((REPO / "plugins").rglob("*.py"))]
    return tuple(sorted({path.relative_to(REPO).as_posix() for m in modules for name in import_closure(m)
                         if (path := module_source_path(name)) is not None and path.is_relative_to(REPO)}))


def same_code(old: bytes, new: bytes, name: str) -> bool:
    """Whether two versions of a file do the same: Python without docstrings and comments, YAML by value, else byte for byte."""
    import yaml

    try:
        if name.endswith(".py"):
            return _code_text_of(old) == _code_text_of(new)
        if name.endswith((".yaml", ".yml")):
            return yaml.safe_load(old) == yaml.safe_load(new)
    except (SyntaxError, ValueError, yaml.YAMLError):
        return False
    return old == new


#: Changes shown to leave results as they were (module docstring); read by :func:`waived`.
NO_EFFECT = Path(__file__).resolve().parent / "no_effect.yaml"


def _version(commit: str, path: str) -> bytes | None:
    """``path`` as it was at ``commit`` (None where it did not exist)."""
    proc = subprocess.run(["git", "show", f"{commit}:{path}"], cwd=REPO, capture_output=True)
    return proc.stdout if proc.returncode == 0 else None


@functools.cache  # the same file for every result of one check
def _no_effect_entries(listing: Path) -> tuple[dict, ...]:
    """The entries of a :data:`NO_EFFECT` listing (none where the file does not exist)."""
    import yaml

    return tuple(yaml.safe_load(listing.read_text()) or []) if listing.is_file() else ()


def waived(old: bytes, new: bytes, path: str, result: str | None = None) -> bool:
    """Whether going from ``old`` to ``new`` is a change listed in :data:`NO_EFFECT`, or a chain of listed changes.

    An entry names ``before`` and ``after`` commits, the ``files`` it covers and its evidence:
    ``identity``, the labels of two committed ``bench_identity.py`` measurements, one on each side,
    whose jobs gave the same predictions and metrics (the test suite checks their hashes). It
    covers ``path`` when the file did then what it does in ``old`` and ``new``: a result made before
    the change and a file not changed since are current; any other change to the file still counts.
    Entries chain: a result made before one listed change of a file is current after a later listed
    change too, as long as every step from ``old`` to ``new`` is a listed one.

    A change made to be faster leaves answers as they were but not timings: its entry lists the
    results that time the changed code under ``timed_by`` (result names, e.g. ``season_search``),
    and for those ``result`` the entry waives nothing (re-run them).
    """
    steps = []
    for entry in _no_effect_entries(NO_EFFECT):
        if path in entry["files"] and result not in entry.get("timed_by", ()):
            before, after = _version(entry["before"], path), _version(entry["after"], path)
            if before is not None and after is not None:
                steps.append((before, after))
    reached, todo = [old], [old]
    while todo:  # the versions a chain of listed changes leads to from ``old``
        current = todo.pop()
        for before, after in steps:
            if same_code(before, current, path) and not any(same_code(after, seen, path) for seen in reached):
                reached.append(after)
                todo.append(after)
    return any(same_code(version, new, path) for version in reached[1:])


def changed_since(commit: str, path: str, result: str | None = None) -> bool:
    """Whether ``path`` (relative to the repository) does something else now than at ``commit``, for ``result`` (see :func:`waived`).

    A file added since ``commit`` is not a change: a new module runs only when an existing one
    imports it, a new plugin or config only when a config or a benchmark's overrides name it,
    and each of those is an existing file that changed (or the script itself). Only listings
    of ``conf/`` read new files unasked: error messages and ``acoustlab.run.plugin_checks``,
    which no benchmark runs.
    """
    now = REPO / path
    if not now.is_file():
        return True  # removed since
    before = _version(commit, path)
    if before is None:
        return False  # added since
    current = now.read_bytes()
    return not same_code(before, current, path) and not waived(before, current, path, result)


def last_written(path: Path) -> str:
    """'last written in <commit> (<date>)' from git history, or 'not committed'."""
    path = path.resolve()
    if not path.is_relative_to(REPO):
        return "not committed"
    proc = subprocess.run(["git", "log", "-1", "--format=%h (%ad)", "--date=short", "--", path.relative_to(REPO).as_posix()],
                          cwd=REPO, capture_output=True, text=True)
    return f"last written in {proc.stdout.strip()}" if proc.returncode == 0 and proc.stdout.strip() else "not committed"


def status(result: Path) -> tuple[str, str]:
    """(status, detail) of one result file (see the module docstring)."""
    if result.name.startswith("identity_"):
        return "reference", "hashes bench_identity.py compares against, not a measurement"
    made_with = json.loads(result.read_text()).get("provenance")
    if not isinstance(made_with, dict):
        if result.stem in GPU_ONLY:
            return "needs a GPU", f"{last_written(result)}, before results named their commit: re-run on a GPU with `{GPU_ONLY[result.stem]}`"
        return "no provenance", f"{last_written(result)}: re-run its benchmark to record the commit"
    script = REPO / made_with["script"]
    if not script.is_file() or script_sha256(script) != made_with["script_sha256"]:
        return "script changed", f"{made_with['script']} differs from the version that made it: re-run it"
    files = [p.relative_to(REPO).as_posix() for p in dependencies(script) if p.is_relative_to(REPO)]
    # a script that runs the command line instead of importing the package, or whole jobs through
    # common.run_in_process, depends on all of acoustlab
    if not files or "run_in_process" in script.read_text():
        files.append("acoustlab")
    # plugins are built from the configs by name (Hydra), never imported: every benchmark may use any, and what they import
    files += ["plugins", "conf", *plugin_dependencies()]
    proc = subprocess.run(["git", "diff", "--name-only", made_with["commit"], "--", *files], cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        return "unknown commit", f"{made_with['commit'][:10]} is not in this repository's history"
    changed = [path for path in proc.stdout.split() if changed_since(made_with["commit"], path, result.stem)]
    return ("code changed", ", ".join(changed[:6]) + (" …" if len(changed) > 6 else "")) if changed else ("current", made_with["commit"][:10])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--strict", action="store_true", help="exit 1 when a result's benchmark script changed since it was made")
    opts = parser.parse_args()
    stale = 0
    for result in sorted(RESULTS.glob("*.json")):
        state, detail = status(result)
        stale += state == "script changed"
        print(f"{result.name:<40} {state:<15} {detail}")
    return 1 if opts.strict and stale else 0


if __name__ == "__main__":
    sys.exit(main())
