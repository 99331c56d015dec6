"""Files written so that they are either absent or complete, and one clear error when the disk refuses a write.

Every file acoustlab writes (run folders, the stage cache, season parts, calibrations) goes
through ``atomic_write_bytes`` or ``atomic_save_npy``: a temporary file beside the target, renamed
into place, with the mode a plain ``open()`` would give it. A failed write raises ``StorageError``
naming the path and the free space.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from acoustlab.core.errors import AcoustlabError


class StorageError(AcoustlabError):
    """A file could not be written (disk full, quota, permissions); the message names the path and the free space."""


def storage_error(path: Path, exc: BaseException) -> StorageError:
    """A one-line ``StorageError`` for a failed write of ``path``: what failed, where, and how much space is free."""
    try:
        free = f"{shutil.disk_usage(_existing_parent(path)).free / 2**20:,.0f} MiB free"
    except OSError:
        free = "free space unknown"
    full = getattr(exc, "errno", None) in (errno.ENOSPC, errno.EDQUOT) or "requested and" in str(exc)  # numpy's short write
    what = "no space left on the device (or quota exceeded)" if full else f"{type(exc).__name__}: {exc}"
    return StorageError(
        f"cannot write {path}: {what}; {free} on {_existing_parent(path)}. Free some space or point "
        "cache.dir / paths.outputs_dir at a disk with room"
    )


def _existing_parent(path: Path) -> Path:
    path = Path(path)
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _default_file_mode() -> int:
    """The mode a plain ``open()`` would give a new file: 0666 less the process's umask (0644 under the usual 022)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


#: Read once at import (reading the umask briefly sets it, which is not safe while other threads create files).
NEW_FILE_MODE = _default_file_mode()


def _atomic_write(path: Path, write: Callable[[Any], None]) -> None:
    """Run ``write(handle)`` into a temporary file beside ``path`` and rename it into place; a failed write leaves no file.

    The file gets the mode a plain ``open()`` would give it (``tempfile.mkstemp`` makes 0600, which
    would hide results from the rest of a group sharing a project folder).
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        os.chmod(tmp, NEW_FILE_MODE)
        os.replace(tmp, path)
    except OSError as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise storage_error(path, exc) from None
    except BaseException:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise


def atomic_save_npy(path: Path, array: np.ndarray) -> None:
    """Write an .npy file so that ``path`` either does not exist or is complete (``StorageError`` when it cannot)."""
    _atomic_write(path, lambda fh: np.save(fh, array))


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write bytes so that ``path`` either does not exist or is complete (``StorageError`` when it cannot)."""
    _atomic_write(path, lambda fh: fh.write(data))
