"""A fitted method saved once and loaded by every shard of a run, verified by its SHA-256.

The fitted method holds scikit-learn, XGBoost (and TabPFN) estimators, which have no safe
serialisation format of their own that keeps every plugin; it is written with ``joblib``
(pickle). Unpickling runs code from the file, so ``load_method`` refuses a file whose SHA-256
differs from the digest recorded when it was written, and the file is only ever read from the run
directory that wrote it: never load a fitted method someone sent you; fit your own.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import joblib

from acoustlab.core.digests import file_sha256
from acoustlab.core.errors import DataError
from acoustlab.stages.cache import atomic_write_bytes

METHOD_FILE = "method.joblib"
DIGEST_FILE = "method.sha256.json"


def save_method(method: Any, directory: Path, key: str) -> str:
    """Write ``method`` to ``directory/method.joblib`` and its digest and ``key`` (what it was fitted from); return the digest."""
    directory.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    joblib.dump(method, buffer, compress=3)
    atomic_write_bytes(directory / METHOD_FILE, buffer.getvalue())
    digest = file_sha256(directory / METHOD_FILE)
    atomic_write_bytes(directory / DIGEST_FILE, json.dumps({"sha256": digest, "key": key}, indent=2).encode())
    return digest


def saved_info(directory: Path) -> dict[str, str] | None:
    """``{"sha256", "key"}`` of the method saved in ``directory``, or None when there is none."""
    path = directory / DIGEST_FILE
    if not path.is_file() or not (directory / METHOD_FILE).is_file():
        return None
    try:
        info = json.loads(path.read_text())
        return {"sha256": str(info["sha256"]), "key": str(info["key"])}
    except (ValueError, KeyError, TypeError):
        return None


def load_method(directory: Path, expected_sha256: str | None = None) -> Any:
    """The method saved in ``directory``, after checking the file's SHA-256 against the recorded one (and ``expected_sha256``).

    Raises
    ------
    DataError
        Naming the file, when it is missing or its digest differs (changed since it was written).
    """
    path = directory / METHOD_FILE
    if not path.is_file():
        raise DataError(f"no fitted method at {path}: run the fit stage first (protocol.stage=fit)")
    try:
        recorded = json.loads((directory / DIGEST_FILE).read_text())["sha256"]
    except (OSError, ValueError, KeyError, TypeError):
        raise DataError(
            f"{directory / DIGEST_FILE} is missing or unreadable: the fitted method {path} cannot be verified; fit again"
        ) from None
    actual = file_sha256(path)
    for wanted in {recorded, expected_sha256} - {None}:
        if actual != wanted:
            raise DataError(
                f"{path}: SHA-256 {actual[:12]}… differs from the {'recorded' if wanted == recorded else 'expected'} "
                f"{wanted[:12]}…; the file changed after it was written, refusing to load it (fit again)"
            )
    return joblib.load(path)
