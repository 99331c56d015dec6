"""A fitted method saved once and loaded by every shard of a run, signed with this user's key.

The fitted method holds scikit-learn, XGBoost (and TabPFN) estimators, which have no safe
serialisation format of their own that keeps every plugin; it is written with ``joblib``
(pickle), and unpickling runs code from the file. So a method is loaded only when it carries an
HMAC-SHA-256 made with this user's secret key (``method_key_path``, created on first use, readable
by its owner only): a digest stored beside the file proves nothing, since whoever replaces the file
can replace the digest. A folder received from someone else, or edited, is refused before anything
is unpickled; fit again. Shards on other machines of a cluster share the key through the home folder
(or ``ACOUSTLAB_KEY_FILE``).
"""

from __future__ import annotations

import hashlib
import hmac
import io
import json
import os
import secrets
from pathlib import Path
from typing import Any

import joblib

from acoustlab.core.digests import file_sha256
from acoustlab.core.errors import DataError
from acoustlab.core.files import atomic_write_bytes

METHOD_FILE = "method.joblib"
DIGEST_FILE = "method.sha256.json"


def method_key_path() -> Path:
    """Where this user's signing key lives: ``$ACOUSTLAB_KEY_FILE``, else ``$XDG_CONFIG_HOME/acoustlab/method.key``
    (``~/.config/acoustlab/method.key``)."""
    given = os.environ.get("ACOUSTLAB_KEY_FILE")
    if given:
        return Path(given).expanduser()
    config = Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config")
    return config / "acoustlab" / "method.key"


def _signing_key() -> bytes:
    """This user's secret key, created (32 random bytes, mode 0600) the first time a method is saved or loaded.

    It is written to a private temporary file and linked into place, so a process that finds the key
    file always finds it whole, whichever of several processes made it.
    """
    path = method_key_path()
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        draft = path.with_name(f".{path.name}.{os.getpid()}.draft")
        descriptor = os.open(draft, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(descriptor, "wb") as handle:
            handle.write(secrets.token_bytes(32))
        try:
            os.link(draft, path)
        except FileExistsError:  # another process made it first: use theirs
            pass
        finally:
            draft.unlink()
    return path.read_bytes()


def _signature(path: Path) -> str:
    """HMAC-SHA-256 of a file's bytes under this user's key."""
    mac = hmac.new(_signing_key(), digestmod=hashlib.sha256)
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            mac.update(block)
    return mac.hexdigest()


def save_method(method: Any, directory: Path, key: str) -> str:
    """Write ``method`` to ``directory/method.joblib`` with its digest, its signature and ``key`` (what it was fitted from);
    return the digest."""
    directory.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    joblib.dump(method, buffer, compress=3)
    atomic_write_bytes(directory / METHOD_FILE, buffer.getvalue())
    digest = file_sha256(directory / METHOD_FILE)
    record = {"sha256": digest, "key": key, "hmac_sha256": _signature(directory / METHOD_FILE)}
    atomic_write_bytes(directory / DIGEST_FILE, json.dumps(record, indent=2).encode())
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
        record = json.loads((directory / DIGEST_FILE).read_text())
        recorded = record["sha256"]
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
    if not hmac.compare_digest(str(record.get("hmac_sha256", "")), _signature(path)):
        raise DataError(
            f"{path} was not written with this user's key ({method_key_path()}): loading a method runs code, so acoustlab "
            "loads only methods it saved itself; fit again (protocol.stage=fit), or give shards on other machines that key file"
        )
    return joblib.load(path)
