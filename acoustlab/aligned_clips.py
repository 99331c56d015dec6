"""``python -m acoustlab.aligned_clips RUN_DIR EVENT [EVENT ...]``: an event's clips aligned by its time differences.

To listen to a call and check its fix: for each event, ``aligned/event_<id>.wav`` holds one channel
per mic (the mics table's order), the clip the run placed it from, each channel shifted by that
mic's measured arrival after mic 0 (``tdoa_0_<m>_s``, whole samples, zeros where the shift leaves
no audio), so the call lines up across channels where the time differences are right; and
``aligned/event_<id>.csv`` gives per mic the shift, the residual at the solver's fix
(``residual_mic_<m>_m``: near 0 where the fix explains that mic) and whether the fix rests on it.

The clips are read again from the run's own inputs: a season's indexed files and events (its
``season.json``), or a ``localize`` run's field source (its ``config_resolved.yaml``): the clips
the run placed, as long as its recordings are where and as they were.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import soundfile as sf

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.types import RecordingBatch
from acoustlab.method.localizer import mic_residual_column
from acoustlab.toolkit.quality import dropped_mask

log = logging.getLogger("acoustlab.aligned_clips")

#: The folder of a run the aligned clips are written to.
ALIGNED = "aligned"


def shifted(clip: np.ndarray, shift_samples: int) -> np.ndarray:
    """``clip`` moved ``shift_samples`` earlier (later where negative), zeros where it leaves no audio."""
    out = np.zeros_like(clip)
    if shift_samples >= 0:
        out[: clip.size - shift_samples] = clip[shift_samples:]
    else:
        out[-shift_samples:] = clip[: clip.size + shift_samples]
    return out


def _season_clips(run_dir: Path, metrics: dict, rows: pd.DataFrame, sample_rate_hz: float) -> RecordingBatch:
    """The clips a season placed ``rows`` (its positions rows) from, read from its indexed files."""
    from acoustlab.season.recorder_files import RecorderFiles
    from acoustlab.season.stream import EVENTS, FILES, ChunkPlan, read_batch, read_manifest

    folder = Path(metrics["season"]["output_dir"])
    manifest = read_manifest(folder)
    events = pd.read_parquet(folder / EVENTS).set_index(col.EVENT_ID, drop=False)
    recordings = RecorderFiles.load(folder / FILES)
    try:
        chosen = events.loc[rows[col.EVENT_ID].to_numpy()].reset_index(drop=True)
        return read_batch(recordings, chosen, manifest["recorders"], sample_rate_hz, ChunkPlan.from_manifest(manifest))
    finally:
        recordings.close()


def _localize_clips(config: dict, rows: pd.DataFrame) -> RecordingBatch:
    """The clips a ``localize`` run placed ``rows`` from, cut again by its field source."""
    from omegaconf import OmegaConf

    from acoustlab.core.contracts import hook
    from acoustlab.run.registry import build
    from acoustlab.stages.sites import site_from_config

    cfg = OmegaConf.create(config)
    field = build(cfg.field, "field")
    load_events = hook(field, "load_events")
    if load_events is None:
        raise ConfigError(f"aligned clips: the run's field ({cfg.field.get('_target_')}) cannot cut clips by event")
    return load_events(site_from_config(cfg.site), [str(e) for e in rows[col.EVENT_ID]])


def write_aligned_clips(run_dir: str | Path, event_ids: Sequence[object], out_dir: str | Path | None = None) -> list[Path]:
    """Write ``event_<id>.wav`` and ``event_<id>.csv`` per event of ``event_ids`` (as ``positions.csv`` names them).

    Returns
    -------
    list of Path
        The WAV files written, in the order of ``event_ids``.

    Raises
    ------
    DataError
        For a run folder without positions or config, or an event id it does not have.
    """
    run_dir = Path(run_dir)
    for name in ("positions.parquet", "config_resolved.yaml", "metrics.json"):
        if not (run_dir / name).is_file():
            raise DataError(f"aligned clips: {run_dir} has no {name}; give the folder of a localize or season run")
    import yaml

    config = yaml.safe_load((run_dir / "config_resolved.yaml").read_text())
    metrics = json.loads((run_dir / "metrics.json").read_text())
    positions = pd.read_parquet(run_dir / "positions.parquet")
    names = positions[col.EVENT_ID].astype(str).to_numpy()
    wanted = [str(e) for e in event_ids]
    missing = [e for e in wanted if e not in set(names)]
    if missing:
        raise DataError(f"aligned clips: {run_dir / 'positions.parquet'} has no event {', '.join(missing[:5])}")
    rows = positions.iloc[[int(np.flatnonzero(names == e)[0]) for e in wanted]].reset_index(drop=True)
    rate = float(config["simulator"]["sample_rate_hz"])
    batch = _season_clips(run_dir, metrics, rows, rate) if "season" in metrics else _localize_clips(config, rows)
    out = Path(out_dir) if out_dir is not None else run_dir / ALIGNED
    out.mkdir(parents=True, exist_ok=True)
    n_mics = batch.audio.shape[1]
    uses = dropped_mask(rows.get(col.MICS_USED), len(rows), n_mics)  # the mics each fix rests on (the same ";"-list)
    written = []
    for k, row in rows.iterrows():
        arrival = np.array([0.0] + [float(row.get(f"tdoa_0_{m}_s", np.nan)) for m in range(1, n_mics)])
        n = int(batch.events[col.CLIP_SAMPLES].iloc[k]) if col.CLIP_SAMPLES in batch.events else batch.audio.shape[-1]
        shifts = np.where(np.isfinite(arrival), np.round(arrival * batch.sample_rate_hz), 0).astype(int)
        channels = np.stack([shifted(batch.audio[k, m, :n], int(shifts[m])) for m in range(n_mics)], axis=1)
        stem = f"event_{row[col.EVENT_ID]}"
        sf.write(out / f"{stem}.wav", channels, int(batch.sample_rate_hz), subtype="FLOAT")
        pd.DataFrame(
            {
                "mic": np.arange(n_mics),
                "arrival_after_mic0_s": arrival,
                "shift_samples": shifts,
                "residual_m": [float(row.get(mic_residual_column(m), np.nan)) for m in range(n_mics)],
                "fix_uses_mic": uses[k],
            }
        ).to_csv(out / f"{stem}.csv", index=False)
        written.append(out / f"{stem}.wav")
    log.info("aligned clips of %d event(s) in %s", len(written), out)
    return written


def main(argv: list[str] | None = None) -> int:
    """``python -m acoustlab.aligned_clips RUN_DIR EVENT [EVENT ...] [--out DIR]``."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m acoustlab.aligned_clips",
        description="Write an event's clips aligned by its time differences (one channel per mic) and each mic's residual.",
    )
    parser.add_argument("run_dir", help="the folder of a localize or season run (its positions.parquet)")
    parser.add_argument("events", nargs="+", help="event ids as positions.csv gives them")
    parser.add_argument("--out", default=None, help="folder to write into (default: RUN_DIR/aligned)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        write_aligned_clips(args.run_dir, args.events, args.out)
    except (DataError, ConfigError) as exc:
        log.error("%s", exc)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
