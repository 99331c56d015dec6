"""Checks of the command line before Hydra composes anything (one-line errors, exit code 2)."""

from __future__ import annotations

import dataclasses
import difflib
import os
import types
import typing
from pathlib import Path
from typing import Any

from acoustlab.core.errors import ConfigError
from acoustlab.run.registry import ALL_GROUPS, CONF_DIR, group_options
from acoustlab.run.schema import AcoustlabConfig

#: Flags that only inspect the app; they need no site.
INSPECT_FLAGS = ("--help", "-h", "--hydra-help", "--info", "-i", "--cfg", "-c", "--shell-completion", "-sc", "--version")


def _inspecting(argv: list[str]) -> bool:
    """True for a command line that only inspects the app (``--help``, ``--cfg`` …): it needs no site and writes nothing."""
    return any(a in INSPECT_FLAGS or a.split("=")[0] in INSPECT_FLAGS for a in argv)


def _values(value: str) -> list[str] | None:
    """Option names in a (possibly swept) override value; None where they cannot be read statically."""
    if any(ch in value for ch in "()[]{}$*"):
        return None
    return [v.strip() for v in value.split(",") if v.strip()]


def _typed_field(key: str) -> type | None:
    """The schema's type of a dotted key (``data.n_events`` → int), or None where the key is free-form or unknown."""
    node: Any = AcoustlabConfig
    for part in key.split("."):
        if not dataclasses.is_dataclass(node):
            return None
        hints = typing.get_type_hints(node)
        if part not in hints:
            return None
        node = hints[part]
        args = [a for a in typing.get_args(node) if a is not type(None)]
        if typing.get_origin(node) in (typing.Union, types.UnionType) and len(args) == 1:  # X | None, Optional[X]
            node = args[0]
    return node if node in (int, float) else None


def _check_typed_key(key: str) -> None:
    """A dotted key inside a typed node of the schema that the node lacks: one line, with the closest existing key."""
    node: Any = AcoustlabConfig
    parts = key.split(".")
    for depth, part in enumerate(parts):
        if not dataclasses.is_dataclass(node):
            return  # free-form below here (plugin nodes, dicts): their own checks name unknown settings
        hints = typing.get_type_hints(node)
        if part not in hints and depth == 0:
            return  # hydra.*, and root keys Hydra itself reports
        if part not in hints:
            where = ".".join(parts[:depth])
            near = difflib.get_close_matches(part, list(hints), n=1)
            hint = f"; did you mean {'.'.join([*parts[:depth], near[0]])}?" if near else f"; its keys: {', '.join(sorted(hints))}"
            raise ConfigError(f"{key}: {where or 'the config'} has no key {part!r}{hint}")
        node = hints[part]
        args = [a for a in typing.get_args(node) if a is not type(None)]
        if typing.get_origin(node) in (typing.Union, types.UnionType) and len(args) == 1:
            node = args[0]


def _check_typed_value(key: str, value: str) -> None:
    """A number-typed key given a value that is not one: the one-line error Hydra would give as several lines."""
    kind = _typed_field(key)
    for option in (_values(value) or []) if kind is not None else []:
        if option == "null":
            continue
        try:
            float(option) if kind is float else int(option)
        except ValueError:
            expected = "an integer" if kind is int else "a number"
            raise ConfigError(f"{key} must be {expected}; got {option!r}") from None


def _check_override_syntax(argv: list[str]) -> None:
    """Refuse, in one line that says how to quote it, a setting Hydra's override grammar cannot read.

    Hydra reads an unquoted value as its own grammar: letters beyond ASCII (a folder named
    ``Gärten``), quotes and brackets stop its lexer with no word of which setting, or how to write it.

    Raises
    ------
    ConfigError
        Naming the setting and its quoted form.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    for arg in argv:
        if arg.startswith("-") or "=" not in arg:
            continue
        try:
            parser.parse_overrides([arg])
        except HydraException:
            key, value = arg.split("=", 1)
            quoted = value.replace("\\", "\\\\").replace('"', '\\"')
            raise ConfigError(
                f"cannot read the setting {arg!r}: Hydra reads a value with commas, quotes, brackets or letters beyond ASCII "
                f'only in double quotes, as {key}="{quoted}" (the whole setting quoted once more for the shell)'
            ) from None


def check_argv(argv: list[str], conf_dir: Path = CONF_DIR) -> None:
    """Validate group overrides and the site choice in command-line arguments.

    Raises
    ------
    ConfigError
        For an unknown option of a group (listing the available ones), ``site=`` without ``+``,
        or no site at all.
    """
    if _inspecting(argv):
        return
    _check_override_syntax(argv)
    site_given = False
    for arg in argv:
        if arg.startswith("-") or "=" not in arg:
            continue
        key, value = arg.split("=", 1)
        prefix = key[: len(key) - len(key.lstrip("+~"))]
        name = key.lstrip("+~")
        if name not in ALL_GROUPS:
            if "." in name and name.split(".")[0] not in ALL_GROUPS:
                _check_typed_key(name)
            _check_typed_value(name, value)
            continue
        if name == "site":
            if prefix != "+":
                raise ConfigError(f"the site is chosen with a leading '+': use +site={value}")
            site_given = True
        options = group_options(name, conf_dir)
        for option in _values(value) or []:
            if option not in options:
                raise ConfigError(f"unknown option {option!r} for {name}; available: {', '.join(options)}")
    if not site_given:
        raise ConfigError(
            "no site chosen: pass one with +site=NAME (available: "
            f"{', '.join(group_options('site', conf_dir))}), e.g. python -m acoustlab +site=frozen_lake"
        )


#: Command-line keys naming folders a run writes into, and the default of the first.
OUTPUT_DIR_KEYS = ("paths.outputs_dir", "hydra.run.dir", "hydra.sweep.dir", "cache.dir", "protocol.output_dir")
DEFAULT_OUTPUTS_DIR = "outputs"


def check_output_dirs(argv: list[str]) -> None:
    """Every folder a run will write into is writable (or can be created), before Hydra makes the run directory.

    Raises
    ------
    ConfigError
        Naming the setting and the folder that cannot be written, instead of Hydra's traceback
        from inside its run-directory set-up.
    """
    if _inspecting(argv):
        return
    given = {}
    for arg in argv:
        key, _, value = arg.lstrip("+~").partition("=")
        if key in OUTPUT_DIR_KEYS and value and "${" not in value:
            given[key] = value
    given.setdefault("paths.outputs_dir", DEFAULT_OUTPUTS_DIR)
    for key, value in given.items():
        path = Path(value).expanduser().absolute()
        existing = next(p for p in (path, *path.parents) if p.exists())
        if not existing.is_dir():
            raise ConfigError(f"{key}={value}: {existing} is a file, not a folder; choose a folder for the run's outputs")
        if not os.access(existing, os.W_OK | os.X_OK):
            where = "it" if existing == path else f"its parent {existing}"
            raise ConfigError(
                f"{key}={value}: {where} is not writable by this user; choose a folder you can write, e.g. {key}=$HOME/acoustlab-outputs"
            )
