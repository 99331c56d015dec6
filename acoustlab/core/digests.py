"""SHA-256 digests of files and tables: what caches, saved methods, checkpoints and season manifests verify."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pandas as pd


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a file's contents, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(2**20), b""):
            digest.update(block)
    return digest.hexdigest()


def frame_sha256(frame: pd.DataFrame, with_dtypes: bool = False) -> str:
    """SHA-256 (hex) of a table's column names (and dtypes, if asked) and the exact values of every row, index ignored."""
    header = [(str(c), str(t)) for c, t in frame.dtypes.items()] if with_dtypes else [str(c) for c in frame.columns]
    digest = hashlib.sha256(json.dumps(header).encode())
    digest.update(pd.util.hash_pandas_object(frame, index=False).to_numpy().tobytes())
    return digest.hexdigest()
