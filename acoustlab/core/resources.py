"""Data shipped inside the package and the ``acoustlab://`` paths that point to it."""

from __future__ import annotations

from pathlib import Path

#: The project checkout: ``conf/`` and ``docs/`` live here, beside the package.
PROJECT_ROOT = Path(__file__).resolve().parents[2]
#: Hydra's config directory (one YAML per registered plugin option).
CONF_DIR = PROJECT_ROOT / "conf"
#: The package's data folder (calls, noise, sites, examples; see NOTICE.md for licences).
PACKAGE_DATA = Path(__file__).resolve().parents[1] / "data"
#: Prefix of config paths that point into ``PACKAGE_DATA``.
URI_PREFIX = "acoustlab://"


def resolve_path(path: str) -> Path:
    """Turn a config path (absolute, relative to the working directory, or ``acoustlab://``) into a Path."""
    if path.startswith(URI_PREFIX):
        return PACKAGE_DATA / path[len(URI_PREFIX) :]
    return Path(path).expanduser().resolve()
