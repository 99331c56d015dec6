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


#: ``sampled_file_sha256``'s blocks per file and their size, bytes: enough that another recording of the same length
#: (a copy of another day, a re-export) differs in every block of audio, few enough to read for 10⁴ files at each resume.
SAMPLED_BLOCKS, SAMPLED_BLOCK_BYTES = 8, 4096


def sampled_file_sha256(path: str | Path, blocks: int = SAMPLED_BLOCKS, block_bytes: int = SAMPLED_BLOCK_BYTES) -> str:
    """SHA-256 (hex) of a file's size and ``blocks`` blocks of ``block_bytes`` spread evenly from its start to its end.

    A cheap fingerprint of a large file's content: it tells a file from another of the same size and
    modification time (``cp -p``, ``rsync -t`` of another copy) without reading all of it. An edit
    between the blocks is not seen; ``file_sha256`` reads everything.
    """
    with open(path, "rb") as fh:
        size = fh.seek(0, 2)
        digest = hashlib.sha256(str(size).encode())
        last = max(size - block_bytes, 0)
        for k in range(blocks):
            fh.seek(last * k // max(blocks - 1, 1))
            digest.update(fh.read(block_bytes))
    return digest.hexdigest()


def frame_sha256(frame: pd.DataFrame, with_dtypes: bool = False) -> str:
    """SHA-256 (hex) of a table's column names (and dtypes, if asked) and the exact values of every row, index ignored."""
    header = [(str(c), str(t)) for c, t in frame.dtypes.items()] if with_dtypes else [str(c) for c in frame.columns]
    digest = hashlib.sha256(json.dumps(header).encode())
    digest.update(pd.util.hash_pandas_object(frame, index=False).to_numpy().tobytes())
    return digest.hexdigest()
