"""Content-addressed on-disk cache for the expensive stages (simulation, features).

A stage's entry lives in ``<root>/<stage>/<key>/`` where ``key`` is the SHA-256 of exactly the
config that determines the stage plus the version of the code that produced it (the plugin and
every module of the project it imports). Entries are built in
``<key>.partial/`` and renamed into place when complete (an atomic rename on POSIX), so a reader
never sees half an entry; chunk files inside ``.partial`` survive an interruption and are reused
when the stage is run again. Jobs that need the same missing entry at the same time (a parallel
sweep on a cold cache) take turns through a lock file ``<key>.lock``: one builds, the others wait
and then read its entry.

Every entry's ``manifest.json`` lists the SHA-256 of each of its files; a lookup verifies them, so a
truncated, bit-flipped or half-deleted entry is logged, discarded and rebuilt, never read. Files
are made ``cache.file_mode`` (group-readable ``0644`` by default) when an entry is committed, so a
cluster group can share one cache. A write that fails (disk full, quota, permissions) raises
``StorageError`` naming the path and the free space.
"""

from __future__ import annotations

import ast
import contextlib
import fcntl
import functools
import hashlib
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from acoustlab.core.contracts import declared
from acoustlab.core.digests import file_sha256
from acoustlab.core.errors import ConfigError
from acoustlab.core.files import atomic_write_bytes
from acoustlab.core.imports import import_closure, module_source_path
from acoustlab.core.types import stable_hash

log = logging.getLogger(__name__)


def plugin_version(obj: Any) -> str:
    """A version string for a plugin's code: its class path, ``cache_version`` and a source digest.

    The digest covers the plugin's module and every acoustlab or plugins module it reaches through
    imports (``acoustlab.core.imports.import_closure``), so an edit to, say, the propagation
    physics a simulator uses invalidates the entries that simulator produced.
    """
    cls = obj if isinstance(obj, type) else type(obj)
    return f"{cls.__module__}.{cls.__qualname__}:{declared(cls, 'cache_version')}:{code_digest(cls.__module__)}"


def code_digest(module: str, follow_imports: bool = True) -> str:
    """SHA-256 (16 hex digits) of the code of ``module`` and, by default, of every own module it imports.

    The code is hashed as its syntax tree without docstrings, so editing a comment or a docstring
    keeps cache entries while any change to what the code does invalidates them.
    """
    digest = hashlib.sha256()
    for name in import_closure(module) if follow_imports else [module]:
        path = module_source_path(name)
        digest.update(name.encode() + b"\0" + (_code_text(path) if path is not None else b"") + b"\0")
    return digest.hexdigest()[:16]


def _code_text(path: Path) -> bytes:
    """The syntax tree of a module without docstrings or comments, as text (parsed once per content)."""
    return _code_text_of(path.read_bytes())


@functools.lru_cache(maxsize=512)
def _code_text_of(source: bytes) -> bytes:
    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body:
            first = body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree, annotate_fields=False).encode()


#: Manifest of a cache entry (and the list of its files' SHA-256 under ``"files"``).
MANIFEST = "manifest.json"
#: What a miss of a costly stage means for the user: the first run on a site pays it once.
FIRST_BUILD = {
    "simulation": " (the site's training events are simulated once; later runs with the same site and settings reuse them from {root})",
    "features": " (their features are computed once and reused likewise)",
}


def write_manifest(entry: Path, manifest: dict[str, Any]) -> None:
    """Write ``manifest.json`` with the SHA-256 of every other file of the entry (what a lookup verifies)."""
    files = sorted(p for p in Path(entry).iterdir() if p.is_file() and p.name != MANIFEST and not p.name.endswith(".tmp"))
    manifest = {**manifest, "files": {p.name: file_sha256(p) for p in files}}
    atomic_write_bytes(Path(entry) / MANIFEST, json.dumps(manifest, indent=2).encode())


def verify_entry(entry: Path) -> str | None:
    """Why a cache entry cannot be trusted (missing or unreadable manifest, missing, truncated or altered file), or None."""
    try:
        manifest = json.loads((entry / MANIFEST).read_text())
        files = manifest["files"]
    except FileNotFoundError:
        return "its manifest is missing"
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return f"its manifest is unreadable ({type(exc).__name__})"
    for name, expected in files.items():
        try:
            actual = file_sha256(entry / name)
        except OSError:
            return f"{name} is missing"
        if actual != expected:
            return f"{name} does not match its checksum"
    return None


class StageCache:
    """Content-addressed directories for cached stages.

    Parameters
    ----------
    root : str or Path
        Cache root directory (created on demand).
    enabled : bool
        When False every lookup misses and finished entries are not kept (``cache.enabled=false``).
    """

    def __init__(self, root: str | Path, enabled: bool = True, file_mode: int | str = 0o644) -> None:
        self.root = Path(root)
        self.enabled = enabled
        try:
            self.file_mode = int(file_mode, 8) if isinstance(file_mode, str) else int(file_mode)
        except ValueError:
            raise ConfigError(f"cache.file_mode must be an octal permission such as '0644'; got {file_mode!r}") from None
        if not 0 <= self.file_mode <= 0o777 or not self.file_mode & 0o600 == 0o600:
            raise ConfigError(
                f"cache.file_mode must be a permission in 0600..0777 that the owner can read and write; got {oct(self.file_mode)}"
            )
        self._scratch: list[Path] = []

    @staticmethod
    def key(spec: dict[str, Any]) -> str:
        """The content address of a stage spec."""
        return stable_hash(spec)

    def final_dir(self, stage: str, key: str) -> Path:
        """Where a finished entry lives."""
        return self.root / stage / key

    def lookup(self, stage: str, key: str, log_miss: bool = True, repair: bool = False) -> Path | None:
        """The finished, verified entry's directory, or None on a miss; logs the hit (and the miss unless ``log_miss`` is False).

        An entry that fails verification is a miss; with ``repair`` (only while holding the entry's
        build lock, or for a shard that owns its chunks) it is also discarded, so that a job never
        deletes an entry another job has just rebuilt.
        """
        path = self.final_dir(stage, key)
        if self.enabled and path.is_dir():
            problem = verify_entry(path)
            if problem is None:
                log.info("cache hit: %s %s", stage, key[:12])
                return path
            if not repair:
                log.info("cache entry %s %s failed verification (%s); it is rebuilt under the build lock", stage, key[:12], problem)
                return None
            self.discard(stage, key, problem)
        if log_miss:
            why = FIRST_BUILD.get(stage, "") if self.enabled else ""
            log.info("cache %s: %s %s%s", "miss" if self.enabled else "bypassed", stage, key[:12], why.format(root=self.root))
        return None

    @contextlib.contextmanager
    def building(self, stage: str, key: str) -> Iterator[None]:
        """Hold the entry's build lock (an exclusive POSIX lock on ``<key>.lock``; no-op when bypassed).

        POSIX record locks (``fcntl.lockf``) also work across nodes on NFS; on Lustre the file
        system must be mounted with ``flock``. ``get_or_build`` looks the entry up again inside:
        another job may have built it while this one waited.
        """
        if not self.enabled:
            yield
            return
        path = self.root / stage / f"{key}.lock"
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a+") as handle:
            try:
                fcntl.lockf(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                log.info("waiting for another job building %s %s", stage, key[:12])
                fcntl.lockf(handle, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.lockf(handle, fcntl.LOCK_UN)

    def get_or_build(self, stage: str, key: str, build: Callable[[], Path | None]) -> Path | None:
        """The entry's directory from the cache, or ``build()``'s under the entry's build lock.

        ``build`` writes and commits the entry (or returns None, e.g. for a shard that only renders
        its part). Jobs missing the same entry at once take turns: the first builds, the others find
        its entry when they get the lock.
        """
        found = self.lookup(stage, key)
        if found is not None:
            return found
        with self.building(stage, key):
            return self.lookup(stage, key, log_miss=False, repair=True) or build()

    def discard(self, stage: str, key: str, problem: str) -> None:
        """Remove a finished entry that cannot be trusted (logged with why); the next lookup misses and rebuilds it."""
        path = self.final_dir(stage, key)
        log.warning("cache entry %s %s is corrupt or incomplete (%s): discarded, rebuilding it", stage, key[:12], problem)
        doomed = path.with_name(f"{key}.corrupt-{os.getpid()}")
        try:
            os.replace(path, doomed)  # atomic: no reader sees half a deletion
        except OSError:
            doomed = path
        shutil.rmtree(doomed, ignore_errors=True)

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
        for path in partial.iterdir():
            path.chmod(self.file_mode)
        partial.chmod(self.file_mode | (self.file_mode & 0o444) >> 2)  # a readable directory can also be listed
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
