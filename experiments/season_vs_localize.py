"""A season against ``localize`` on the same independent recordings: what the season's defaults and its clips cost.

Usage: python experiments/season_vs_localize.py [--site forest] [--n-positions 200]

``--n-positions`` × 5 events rendered by the second simulator (pyroomacoustics' image-source
method, ``field=image_source``: sources in and around the array, SNR 5–30 dB, real calls and
noise; acoustlab never trains on it) are evaluated three ways, each method fitted on 1,000 of the
site's own simulated events:

* as events: ``protocol=field_eval field=image_source`` (the simulator's clips as it rendered them,
  each at its own length), with the full feature set (the default) and with the season's lean set
  with the coarse GCC search (``features=physics_lean_coarse``);
* laid end to end in long files: 0.5 s between the clips of noise with each clip's own noise
  spectrum and level (its quietest quarter; ``--gap white``: white noise at that level, louder in
  a call's band; ``--gap zeros``: silence), one Raven selection per clip per recorder (its bounds)
  and a weather logger's table with one reading per clip (the temperature and humidity its events
  carry);
* ``localize`` on those recordings (one file per mic, an events table of the selections with their
  weather: what a user with the long files and a list of calls runs), lean and coarse;
* a season of them (600-s files per recorder), ``python -m acoustlab season`` with its defaults
  (the lean set, the coarse search) with the weather table, without it (one assumed temperature),
  and with ``features=physics``.

So features (lean vs full, coarse vs fine), the season's clip windows (read from long files) and its
weather are separated. Failures count as infinite errors; > 5 m
and p95 carry 95 % bootstrap intervals over source positions. Writes
experiments/results/season_vs_localize.md (``--gap white``: season_vs_localize_white.md, ``--gap zeros``:
season_vs_localize_silence.md).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import soundfile as sf
from common import compose_cfg, machine, time_cli, write_results

from acoustlab.run.registry import build
from acoustlab.stages.sites import site_from_config

log = logging.getLogger("experiments.season_vs_localize")
GAP_S = 0.5
FILE_S = 600.0
ORIGIN = pd.Timestamp("2026-05-01T05:00:00")
RUNS = {
    "localize, full features (default)": ("events", []),
    "localize, lean + coarse": ("events", ["features=physics_lean_coarse"]),
    "localize on the season's recordings, lean + coarse": ("recordings", ["features=physics_lean_coarse"]),
    "season, lean + coarse (default), weather table": ("season", ["WEATHER"]),
    "season, lean + coarse (default), one assumed temperature": ("season", []),
    "season, full features, weather table": ("season", ["features=physics", "WEATHER"]),
}
#: The weather logger's table of the laid-out season (one reading per clip, at its middle).
WEATHER_CSV = "weather.csv"


def field_settings(n_positions: int) -> list[str]:
    return ["field=image_source", f"field.n_positions={n_positions}"]


BLOCK = 1200  # samples: 50 ms at 24 kHz


def noise_like(clip: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) Gaussian noise with the spectrum and level of ``clip``'s quietest quarter (its own noise, where the call is not).

    What a recording holds around a call is the noise the call was recorded in; white noise at the
    same broadband level is 10–20 dB louder in a call's band where that noise is red (wind, rain,
    traffic), so it would make the clips' surroundings unlike any recording's.
    """
    blocks = clip[: (clip.size // BLOCK) * BLOCK].reshape(-1, BLOCK).astype(float)
    quiet = blocks[np.argsort(np.mean(blocks**2, axis=1))[: max(1, len(blocks) // 4)]]
    power = np.mean(np.abs(np.fft.rfft(quiet * np.hanning(BLOCK), axis=1)) ** 2, axis=0)
    spectrum = np.fft.rfft(rng.standard_normal(n))
    spectrum *= np.sqrt(np.interp(np.fft.rfftfreq(n), np.fft.rfftfreq(BLOCK), power))
    noise = np.fft.irfft(spectrum, n)
    return noise * np.sqrt(np.mean(quiet**2) / np.mean(noise**2))


def lay_out(site_name: str, n_positions: int, folder: Path, gap_fill: str = "shaped") -> pd.DataFrame:
    """Write the image-source events as a season in ``folder`` (audio/R<m>/, raven/); the events' truth and clip times, s."""
    cfg = compose_cfg([f"+site={site_name}", *field_settings(n_positions)])
    site = site_from_config(cfg.site)
    batch = build(cfg.field, "field").load(site)
    fs = batch.sample_rate_hz
    lengths = (
        batch.events["clip_samples"].to_numpy(int) if "clip_samples" in batch.events else np.full(batch.n_events, batch.audio.shape[-1])
    )
    rng = np.random.default_rng(0)
    gap = int(GAP_S * fs)
    pieces = [[] for _ in range(site.n_mics)]
    starts, cursor = [], 0
    for e in range(batch.n_events):
        clip = batch.audio[e, :, : lengths[e]]
        blocks = clip[:, : (lengths[e] // BLOCK) * BLOCK].reshape(site.n_mics, -1, BLOCK)
        floor = np.sqrt(np.min(np.mean(blocks**2, axis=-1), axis=-1))  # each mic's quietest 50 ms: its noise level
        for m in range(site.n_mics):
            if gap_fill == "shaped":
                noise = noise_like(clip[m], gap, rng)
            else:
                noise = rng.normal(0.0, floor[m], gap) if gap_fill == "white" else np.zeros(gap)
            pieces[m] += [noise.astype(np.float32), clip[m]]
        starts.append(cursor + gap)
        cursor += gap + lengths[e]
    n_file = int(FILE_S * fs)
    (folder / "whole").mkdir(parents=True, exist_ok=True)  # the same audio, one file per mic, for localize (field=recordings)
    for m in range(site.n_mics):
        signal = np.concatenate(pieces[m])
        sf.write(folder / "whole" / f"R{m}.wav", signal, int(fs), subtype="FLOAT")
        (folder / "audio" / f"R{m}").mkdir(parents=True, exist_ok=True)
        for k, first in enumerate(range(0, signal.size, n_file)):
            name = f"{ORIGIN + pd.Timedelta(seconds=k * FILE_S):%Y%m%d_%H%M%S}.wav"
            sf.write(folder / "audio" / f"R{m}" / name, signal[first : first + n_file], int(fs), subtype="FLOAT")
    begin = np.array(starts) / fs
    end = begin + lengths / fs
    pd.DataFrame(
        {
            "time": [(ORIGIN + pd.Timedelta(seconds=float(t))).isoformat() for t in (begin + end) / 2],
            "temperature_c": batch.events["temperature_c"].to_numpy(float),
            "relative_humidity_pct": batch.events["relative_humidity_pct"].to_numpy(float),
        }
    ).to_csv(folder / WEATHER_CSV, index=False)
    mics = site.mic_positions_m
    pd.DataFrame(
        {
            "mic_id": [f"R{m}" for m in range(site.n_mics)],
            "file": [f"R{m}.wav" for m in range(site.n_mics)],
            "x_m": mics[:, 0],
            "y_m": mics[:, 1],
            "z_m": mics[:, 2],
            "position_sigma_m": 0.0,  # the simulator's own mics, exact: the same inputs as the season's site
        }
    ).to_csv(folder / "whole" / "mics.csv", index=False)
    pd.DataFrame(
        {
            "event_id": np.arange(batch.n_events),
            "start_s": begin,  # each event's Raven box, as a user lists it for localize
            "end_s": end,
            "temperature_c": batch.events["temperature_c"].to_numpy(float),
            "relative_humidity_pct": batch.events["relative_humidity_pct"].to_numpy(float),
        }
    ).to_csv(folder / "whole" / "events.csv", index=False)
    (folder / "raven").mkdir(parents=True, exist_ok=True)
    index = (begin // FILE_S).astype(int)
    for m in range(site.n_mics):
        pd.DataFrame(
            {
                "Selection": np.arange(1, batch.n_events + 1),
                "Begin Time (s)": begin,
                "End Time (s)": end,
                "Begin File": [f"{ORIGIN + pd.Timedelta(seconds=k * FILE_S):%Y%m%d_%H%M%S}.wav" for k in index],
                "File Offset (s)": begin - index * FILE_S,
                "Species": "call",
            }
        ).to_csv(folder / "raven" / f"R{m}.Table.1.selections.txt", sep="\t", index=False)
    return batch.events.assign(begin_s=begin, end_s=end)


def acoustlab(args: list[str], run_dir: Path) -> None:
    time_cli([*args, "tracking=none", "plots=false", f"hydra.run.dir={run_dir}"])


def errors(kind: str, run_dir: Path, truth: pd.DataFrame) -> pd.DataFrame:
    """Per event: position id, solver and gate (reported position) errors, m (inf where not placed)."""
    xy = truth[["x_m", "y_m"]].to_numpy(float)
    if kind == "events":
        p = pd.read_parquet(run_dir / "predictions.parquet").sort_values("event_id")
        solver = p[["solver_x_m", "solver_y_m"]].to_numpy(float)
        gate = p[["gate_x_m", "gate_y_m"]].to_numpy(float)
    elif kind == "recordings":  # localize's positions table, one row per event of the events table, in its order
        p = pd.read_parquet(run_dir / "positions.parquet").sort_values("event_id")
        solver = p[["solver_x_m", "solver_y_m"]].to_numpy(float)
        gate = np.where(p[["placed"]].to_numpy(bool), p[["x_m", "y_m"]].to_numpy(float), np.nan)
    else:
        p = pd.read_parquet(run_dir / "positions.parquet")
        # each season event is the clip holding its start (the clips are 0.5 s apart, the widening shorter)
        centre = (p["start_s"].to_numpy(float) + p["end_s"].to_numpy(float)) / 2
        event = np.searchsorted(truth["begin_s"].to_numpy(float), centre) - 1
        solver = np.full((len(truth), 2), np.nan)
        gate = np.full((len(truth), 2), np.nan)
        solver[event] = p[["solver_x_m", "solver_y_m"]].to_numpy(float)
        placed = p["placed"].to_numpy(bool)
        gate[event] = np.where(placed[:, None], p[["x_m", "y_m"]].to_numpy(float), np.nan)
    out = pd.DataFrame({"position": truth["position_id"].to_numpy()})
    for name, est in (("solver", solver), ("gate", gate)):
        e = np.hypot(*(est - xy).T)
        out[name] = np.where(np.isfinite(e), e, np.inf)
    return out


def summary(err: pd.DataFrame, name: str, rng: np.random.Generator) -> dict[str, str]:
    """p50, p95 and > 5 m with 95 % bootstrap intervals over source positions."""
    groups = [g[name].to_numpy() for _, g in err.groupby("position")]
    stats = []
    for _ in range(1000):
        pick = np.concatenate([groups[k] for k in rng.integers(0, len(groups), len(groups))])
        stats.append((np.percentile(pick, 95), 100 * np.mean(pick > 5)))
    lo, hi = np.percentile(np.array(stats), [2.5, 97.5], axis=0)
    v = err[name].to_numpy()
    return {
        f"{name} p50 (m)": f"{np.median(v):.3f}",
        f"{name} p95 (m)": f"{np.percentile(v, 95):.2f} [{lo[0]:.2f}, {hi[0]:.2f}]",
        f"{name} > 5 m (%)": f"{100 * np.mean(v > 5):.1f} [{lo[1]:.1f}, {hi[1]:.1f}]",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", default="forest")
    parser.add_argument("--n-positions", type=int, default=200)
    parser.add_argument("--extra", nargs="*", default=[], help="overrides for every run (e.g. +experiment=smoke for a quick check)")
    parser.add_argument(
        "--gap", choices=["shaped", "white", "zeros"], default="shaped", help="what lies between the clips in the long files"
    )
    parser.add_argument("--runs", nargs="*", default=list(RUNS), help="which of the runs (default: all)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    rows, seconds = {}, {}
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        truth = lay_out(args.site, args.n_positions, folder, args.gap)
        log.info("laid out %d events as a season", len(truth))
        for name, (kind, extra) in ((n, RUNS[n]) for n in args.runs):
            run_dir = folder / f"run{len(seconds)}"
            started = time.perf_counter()
            if kind == "events":
                acoustlab([f"+site={args.site}", "protocol=field_eval", *field_settings(args.n_positions), *extra, *args.extra], run_dir)
            elif kind == "recordings":
                whole = folder / "whole"
                acoustlab(
                    [
                        "localize",
                        f"+site={args.site}",
                        "field=recordings",
                        f"field.audio_dir={whole}",
                        f"field.mics_csv={whole / 'mics.csv'}",
                        f"field.events_csv={whole / 'events.csv'}",
                        *extra,
                        *args.extra,
                    ],
                    run_dir,
                )
            else:
                acoustlab(
                    [
                        "season",
                        f"+site={args.site}",
                        f"protocol.recordings.audio_dir={folder / 'audio'}",
                        f"protocol.detections.paths=[{folder / 'raven'}]",
                        f"protocol.output_dir={folder / f'season{len(seconds)}'}",
                        *[f"protocol.weather_csv={folder / WEATHER_CSV}" if e == "WEATHER" else e for e in extra],
                        *args.extra,
                    ],
                    run_dir,
                )
            seconds[name] = time.perf_counter() - started
            err = errors(kind, run_dir, truth)
            rows[name] = {"events": str(len(err)), **summary(err, "solver", rng), **summary(err, "gate", rng)}
            log.info("%s (%.0f s): %s", name, seconds[name], rows[name])
    table = pd.DataFrame(rows).T
    markdown = [
        "# A season against localize on the same independent recordings",
        "",
        f"`python experiments/season_vs_localize.py --site {args.site} --n-positions {args.n_positions}"
        + (f" --extra {' '.join(args.extra)}" if args.extra else "")
        + (f" --gap {args.gap}" if args.gap != "shaped" else "")
        + "`: "
        f"{len(truth)} events of the second simulator (image-source, {args.n_positions} positions), "
        "as the simulator renders them (`protocol=field_eval`), and laid out as recordings (long files, one Raven selection per clip, "
        + {"shaped": "noise of each clip's own spectrum and level", "white": "white noise at each clip's noise level", "zeros": "silence"}[
            args.gap
        ]
        + " between the clips) placed by `localize` (one file per mic, the selections as its events table) and as a season. "
        "Failures are infinite errors; [95 % bootstrap over positions]. `gate` is the reported position.",
        "",
        table.to_markdown(),
        "",
        "Wall time per run (each fits its method): " + ", ".join(f"{k} {v:.0f} s" for k, v in seconds.items()) + f". Machine: {machine()}.",
    ]
    name = "season_vs_localize" + {"shaped": "", "white": "_white", "zeros": "_silence"}[args.gap]  # one result file per layout
    write_results(name, {"rows": rows, "seconds": seconds}, markdown)


if __name__ == "__main__":
    main()
