"""When a recording starts, read from the file itself: AudioMoth's comment, GUANO, Broadcast WAV, OpenSoundscape, or its name.

Recorders write their start time into the file, each its own way:

* **AudioMoth**: the comment (WAV ``ICMT``, read through libsndfile, which also gives a FLAC's
  comment): "Recorded at 05:30:00 01/05/2026 (UTC+1) by AudioMoth …" (day/month/year, the
  recorder's time zone in brackets);
* **GUANO** (Wildlife Acoustics, and others): a ``guan`` RIFF chunk of ``Key: Value`` lines whose
  ``Timestamp`` is ISO 8601;
* **Broadcast WAV**: a ``bext`` chunk with ``OriginationDate``, ``OriginationTime`` and the
  sample-accurate ``TimeReference`` (samples since midnight);
* **OpenSoundscape** (``Audio.save``): the comment, ``opso_metadata`` followed by a JSON object
  whose ``recording_start_time`` is ISO 8601 (``opso_metadata_version`` v0.1);
* and the file name, ``YYYYMMDD_HHMMSS`` and its variants, as the fallback.

Times with a zone are returned in UTC; times without one as written (an array's recorders share
a setting). libsndfile exposes neither ``guan`` nor ``bext``, so the RIFF chunks are walked here:
only chunk headers are read and the audio is skipped.
"""

from __future__ import annotations

import logging
import re
import struct
from pathlib import Path

import pandas as pd

from acoustlab.core.errors import DataError

log = logging.getLogger(__name__)

#: AudioMoth's comment: time, day/month/year, zone (UTC, UTC+1, UTC-5, UTC+5:30).
AUDIOMOTH_COMMENT = re.compile(r"Recorded at (\d{2}):(\d{2}):(\d{2}) (\d{2})/(\d{2})/(\d{4}) \(UTC(?:([+-])(\d{1,2})(?::(\d{2}))?)?\)")
#: Largest metadata chunk read, bytes (GUANO and bext are a few hundred).
MAX_CHUNK_BYTES = 1 << 16
#: A timestamp in a file name: date and time of day, separated by ``_``, ``-``, ``T`` or nothing.
TIMESTAMP_PATTERN = re.compile(r"(?<!\d)(\d{4})-?(\d{2})-?(\d{2})[_T-]?(\d{2})[-:]?(\d{2})[-:]?(\d{2})(?!\d)")


def timestamp_from_name(name: str) -> pd.Timestamp:
    """The start time written in a file name (``YYYYMMDD_HHMMSS`` and the usual variants).

    Raises
    ------
    DataError
        Naming the file, when its name holds no valid date and time.
    """
    match = TIMESTAMP_PATTERN.search(Path(name).stem)
    if match is None:
        raise DataError(
            f"recordings: file name {name!r} holds no start time; expected YYYYMMDD_HHMMSS (e.g. 20260501_053000.WAV) "
            "or give a files table with recorder_id, file, start_time"
        )
    try:
        return pd.Timestamp(*(int(g) for g in match.groups()))
    except ValueError as exc:
        raise DataError(f"recordings: file name {name!r}: {exc}") from None


def audiomoth_start(comment: str) -> pd.Timestamp | None:
    """The start time in an AudioMoth comment, in UTC (None when the comment is not AudioMoth's)."""
    match = AUDIOMOTH_COMMENT.search(comment or "")
    if match is None:
        return None
    hour, minute, second, day, month, year, sign, zone_h, zone_m = match.groups()
    local = pd.Timestamp(int(year), int(month), int(day), int(hour), int(minute), int(second))
    offset = pd.Timedelta(hours=int(zone_h or 0), minutes=int(zone_m or 0)) * (-1 if sign == "-" else 1)
    return local - offset


#: What OpenSoundscape's comment starts with, before its JSON.
OPSO_PREFIX = "opso_metadata"


def opso_start(comment: str) -> pd.Timestamp | None:
    """``recording_start_time`` of an OpenSoundscape comment, in UTC where it has a zone (None when it is not one, or has none).

    Raises
    ------
    DataError
        When the comment is OpenSoundscape's but its JSON or its time cannot be read (a file that
        claims a start time it does not give would otherwise be aligned with the others silently).
    """
    import json

    if not (comment or "").startswith(OPSO_PREFIX):
        return None
    try:
        body = json.loads(comment[len(OPSO_PREFIX) :])
    except ValueError as exc:
        raise DataError(f"an OpenSoundscape comment ({OPSO_PREFIX}…) holds no readable JSON: {exc}") from None
    value = body.get("recording_start_time") if isinstance(body, dict) else None
    if value in (None, ""):
        return None
    try:
        stamp = pd.Timestamp(value)
    except (TypeError, ValueError):
        raise DataError(f"an OpenSoundscape comment's recording_start_time {value!r} is not an ISO 8601 time") from None
    return stamp.tz_convert("UTC").tz_localize(None) if stamp.tzinfo is not None else stamp


def _riff_chunks(path: Path) -> dict[str, bytes]:
    """The ``guan`` and ``bext`` chunks of a RIFF/WAVE file (empty for any other file)."""
    found: dict[str, bytes] = {}
    with open(path, "rb") as handle:
        head = handle.read(12)
        if len(head) < 12 or head[:4] not in (b"RIFF", b"RF64") or head[8:12] != b"WAVE":
            return found
        while True:
            header = handle.read(8)
            if len(header) < 8:
                return found
            name, size = header[:4].decode("latin-1"), struct.unpack("<I", header[4:])[0]
            if name in ("guan", "bext") and size <= MAX_CHUNK_BYTES:
                found[name] = handle.read(size)
                handle.seek(size % 2, 1)
            else:
                handle.seek(size + size % 2, 1)


def guano_start(chunk: bytes) -> pd.Timestamp | None:
    """``Timestamp`` of a GUANO chunk, in UTC where it has a zone (None without one)."""
    for line in chunk.decode("utf-8", errors="replace").splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "Timestamp":
            stamp = pd.Timestamp(value.strip())
            return stamp.tz_convert("UTC").tz_localize(None) if stamp.tzinfo is not None else stamp
    return None


def bext_start(chunk: bytes, sample_rate_hz: float) -> pd.Timestamp | None:
    """A Broadcast WAV's start: its date plus ``TimeReference`` samples (or ``OriginationTime`` where that is 0)."""
    if len(chunk) < 346:
        return None
    date = chunk[320:330].decode("ascii", errors="replace").strip("\x00 ")
    time = chunk[330:338].decode("ascii", errors="replace").strip("\x00 ")
    low, high = struct.unpack("<II", chunk[338:346])
    try:
        midnight = pd.Timestamp(date.replace(":", "-").replace("/", "-"))
    except ValueError:
        return None
    reference = (high << 32) | low
    if reference:
        return midnight + pd.Timedelta(seconds=reference / sample_rate_hz)
    try:
        return pd.Timestamp(f"{midnight.date()} {time.replace('-', ':').replace('.', ':')}")
    except ValueError:
        return None


def start_from_metadata(path: str | Path) -> pd.Timestamp | None:
    """The start time a recorder or OpenSoundscape wrote into the file (GUANO, Broadcast WAV, AudioMoth, opso_metadata), or None.

    Raises
    ------
    DataError
        Naming the file, when its OpenSoundscape comment cannot be read.
    """
    import soundfile as sf

    path = Path(path)
    try:
        chunks = _riff_chunks(path)
        with sf.SoundFile(str(path)) as handle:
            comment, rate = handle.comment, float(handle.samplerate)
    except (OSError, RuntimeError, struct.error) as exc:
        log.debug("no start time read from %s: %s", path, exc)
        return None
    try:
        opso = opso_start(comment)
    except DataError as exc:
        raise DataError(f"{path}: {exc}") from None
    for start in (
        guano_start(chunks["guan"]) if "guan" in chunks else None,
        bext_start(chunks["bext"], rate) if "bext" in chunks else None,
        audiomoth_start(comment),
        opso,
    ):
        if start is not None:
            return start
    return None


def file_start_time(path: str | Path) -> pd.Timestamp | None:
    """When a file starts: its metadata, else the time in its name, else None."""
    start = start_from_metadata(path)
    if start is not None:
        return start
    return timestamp_from_name(Path(path).name) if TIMESTAMP_PATTERN.search(Path(path).stem) else None
