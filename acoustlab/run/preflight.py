"""Checks of the command line before Hydra composes anything (one-line errors, exit code 2)."""

from __future__ import annotations

from pathlib import Path

from acoustlab.core.errors import ConfigError
from acoustlab.run.registry import ALL_GROUPS, CONF_DIR, group_options

#: Flags that only inspect the app; they need no site.
INSPECT_FLAGS = ("--help", "-h", "--hydra-help", "--info", "-i", "--cfg", "-c", "--shell-completion", "-sc", "--version")


def _values(value: str) -> list[str] | None:
    """Option names in a (possibly swept) override value; None where they cannot be read statically."""
    if any(ch in value for ch in "()[]{}$*"):
        return None
    return [v.strip() for v in value.split(",") if v.strip()]


def check_argv(argv: list[str], conf_dir: Path = CONF_DIR) -> None:
    """Validate group overrides and the site choice in command-line arguments.

    Raises
    ------
    ConfigError
        For an unknown option of a group (listing the available ones), ``site=`` without ``+``,
        or no site at all.
    """
    if any(a in INSPECT_FLAGS or a.split("=")[0] in INSPECT_FLAGS for a in argv):
        return
    site_given = False
    for arg in argv:
        if arg.startswith("-") or "=" not in arg:
            continue
        key, value = arg.split("=", 1)
        prefix = key[: len(key) - len(key.lstrip("+~"))]
        name = key.lstrip("+~")
        if name not in ALL_GROUPS:
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
