"""Content-addressed on-disk cache for the expensive stages (simulation, features).

A stage's entry lives in ``<root>/<stage>/<key>/`` where ``key`` is the SHA-256 of exactly the
config that determines the stage plus the version of the plugin code. Entries are built in
``<key>.partial/`` and renamed into place when complete (an atomic rename on POSIX), so a reader
never sees half an entry; chunk files inside ``.partial`` survive an interruption and are reused
when the stage is run again.
"""

from __future__ import annotations

import hashlib
import inspect
import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from acoustlab.data import stable_hash

log = logging.getLogger(__name__)


def plugin_version(obj: Any) -> str:
    """A version string for a plugin's code: its class path, ``cache_version`` and source hash.

    Editing the plugin's module therefore invalidates the entries it produced.
    """
    cls = obj if isinstance(obj, type) else type(obj)
    try:
        source = inspect.getsource(inspect.getmodule(cls))
    except (OSError, TypeError):
        source = ""
    digest = hashlib.sha256(source.encode()).hexdigest()[:16]
    return f"{cls.__module__}.{cls.__qualname__}:{getattr(cls, 'cache_version', '0')}:{digest}"


def atomic_save_npy(path: Path, array: np.ndarray) -> None:
    """Write an .npy file so that ``path`` either does not exist or is complete."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.save(fh, array)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write bytes so that ``path`` either does not exist or is complete."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


class StageCache:
    """Content-addressed directories for cached stages.

    Parameters
    ----------
    root : str or Path
        Cache root directory (created on demand).
    enabled : bool
        When False every lookup misses and finished entries are not kept (``cache.enabled=false``).
    """

    def __init__(self, root: str | Path, enabled: bool = True) -> None:
        self.root = Path(root)
        self.enabled = enabled
        self._scratch: list[Path] = []

    @staticmethod
    def key(spec: dict[str, Any]) -> str:
        """The content address of a stage spec."""
        return stable_hash(spec)

    def final_dir(self, stage: str, key: str) -> Path:
        """Where a finished entry lives."""
        return self.root / stage / key

    def lookup(self, stage: str, key: str) -> Path | None:
        """The finished entry's directory, or None on a miss; logs the hit or miss."""
        path = self.final_dir(stage, key)
        if self.enabled and path.is_dir():
            log.info("cache hit: %s %s", stage, key[:12])
            return path
        log.info("cache %s: %s %s", "miss" if self.enabled else "bypassed", stage, key[:12])
        return None

    def partial_dir(self, stage: str, key: str) -> Path:
        """A work directory for building an entry; reused after an interruption when caching is on."""
        if not self.enabled:
            path = Path(tempfile.mkdtemp(prefix=f"acoustlab-{stage}-"))
            self._scratch.append(path)
            return path
        path = self.root / stage / f"{key}.partial"
        path.mkdir(parents=True, exist_ok=True)
        return path

    def commit(self, stage: str, key: str, partial: Path) -> Path:
        """Move a completed work directory into place and return the entry's directory."""
        if not self.enabled:
            return partial
        final = self.final_dir(stage, key)
        if final.exists():  # another job finished the same entry first; keep theirs
            shutil.rmtree(partial, ignore_errors=True)
        else:
            os.replace(partial, final)
        log.info("cache stored: %s %s", stage, key[:12])
        return final

    def cleanup(self) -> None:
        """Remove scratch directories used while the cache was bypassed."""
        for path in self._scratch:
            shutil.rmtree(path, ignore_errors=True)
        self._scratch.clear()
