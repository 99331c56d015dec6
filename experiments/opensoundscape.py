"""The released OpenSoundscape against acoustlab's first stage on the same forest detections, side by side in one run.

Usage::

    python experiments/opensoundscape.py --osl-python /path/to/venv/bin/python [--n-events 1000]

OpenSoundscape is not a dependency of acoustlab; ``--osl-python`` is an interpreter where
``import opensoundscape.localization`` works. Made here with a venv that sees this environment's
packages (``python -m venv --system-site-packages VENV``) and ``VENV/bin/pip install --no-deps
opensoundscape==0.13.2 librosa aru-metadata-parser noisereduce PyWavelets pytz lazy_loader audioread
soxr numba llvmlite msgpack pooch``. The package's
``__init__`` imports its machine-learning modules, whose torchvision and torchaudio have no build for
torch 2.13; the driver imports ``opensoundscape.localization`` (which needs none of them) from the
package's folder without running that ``__init__``.

Both read the same audio: ``--n-events`` forest events from acoustlab's default simulator (6 mics,
1.1 s at 24 kHz), laid end to end in one WAV per mic (float32) after 1 s of silence, so event k
is the window [1 + k·1.1, 1 + (k+1)·1.1) s of every file, and a detections table marks every window in every file, as a
detector would.

* **OpenSoundscape 0.13.2**, ``SynchronizedRecorderArray(file_coords (x, y), speed_of_sound).localize_detections(
  detections, max_receiver_dist=<array extent + 1 m>, min_n_receivers=3, cc_filter="phat", return_unlocalized=True)``: its
  defaults otherwise (least squares, no cc or residual threshold), once without band-pass (its
  default) and once with ``bandpass_ranges`` set to acoustlab's GCC band. It makes one candidate
  event per receiver that detected the call (each receiver in turn the reference), as its
  documentation says, so one call costs 6 localizations. The speed of sound is the one at the
  site's mean simulated temperature; torch is held to one thread. CPU time of the process
  (``time.process_time``) around that call, in a separate interpreter. For each call the table also
  gives the estimate with the lowest residual, the one a user filtering on its residual would keep.
* **acoustlab**, in this process on the same files: reading the 6 clips of each event
  (soundfile), features (``features=physics`` and ``features=physics_lean``, in batches of 16 events as
  a season run computes them), and the default solver
  (consistent set, 3-D) with its diagnostics; the lean set once more with ``+features.gcc.search=coarse``
  (the GCC's peaks searched on the 1/fs grid), solved again. The fitted method adds about 3 ms per detection
  (``python benchmarks/run.py season``) and is not run here: it needs a method fitted on
  simulation first.

Errors are horizontal distances to the simulated source; no position counts as an error.
Writes experiments/results/opensoundscape.md.
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.distance import pdist

#: The acoustlab side is imported in ``main`` only: the driver runs in OpenSoundscape's interpreter.
log = logging.getLogger("experiments.opensoundscape")
CLASS = "call"
#: Silence before the first and after the last event, s: OpenSoundscape reads each receiver's window widened by the largest delay.
PAD_S = 1.0
#: Events per feature batch on acoustlab's side, as a season run computes them (``protocol.batch_events``).
BATCH_EVENTS = 16


def driver(folder: Path, speed_of_sound: float, band_hz: list[float] | None) -> None:
    """Runs in OpenSoundscape's interpreter: localize every detection, print timings and positions as one JSON line."""
    import importlib.util

    import torch

    # the package's own __init__ imports its machine-learning modules (torchvision, torchaudio, lightning, wandb), which have no
    # builds for this torch; its localization subpackage needs none of them, so it is imported from the package's folder directly
    spec = importlib.util.find_spec("opensoundscape")
    package = types.ModuleType("opensoundscape")
    package.__path__ = list(spec.submodule_search_locations)
    sys.modules["opensoundscape"] = package

    torch.set_num_threads(1)
    start = time.process_time()
    from opensoundscape.localization import SynchronizedRecorderArray

    import_s = time.process_time() - start
    coords = pd.read_csv(folder / "file_coords.csv", index_col=0)
    detections = pd.read_csv(folder / "detections.csv").reset_index(drop=True)
    # every file starts at the same instant (its documented way of saying so: a timezone-aware start per detection)
    origin = datetime.datetime(2026, 1, 1, tzinfo=datetime.UTC)
    detections["start_timestamp"] = [origin + datetime.timedelta(seconds=float(t)) for t in detections["start_time"]]
    detections = detections.set_index(["file", "start_time", "end_time", "start_timestamp"])
    array = SynchronizedRecorderArray(coords, speed_of_sound=speed_of_sound)
    # every receiver of the array in each candidate event; its default max_delay is this distance over the speed of sound
    extent_m = float(pdist(coords[["x", "y"]].to_numpy()).max())
    start = time.process_time()
    wall = time.perf_counter()
    placed, unplaced = array.localize_detections(
        detections, max_receiver_dist=extent_m + 1.0, min_n_receivers=3, cc_filter="phat", bandpass_ranges=band_hz, return_unlocalized=True
    )
    cpu_s, wall_s = time.process_time() - start, time.perf_counter() - wall
    rows = []
    for estimate, kept in [*((e, True) for e in placed), *((e, False) for e in unplaced)]:
        location = estimate.location_estimate if kept and estimate.location_estimate is not None else [np.nan, np.nan]
        residual = float(estimate.residual_rms) if kept and estimate.location_estimate is not None else float("inf")
        rows.append(
            {
                "start_s": float(np.asarray(estimate.receiver_start_time_offsets, dtype=float)[0]),
                "x_m": float(location[0]),
                "y_m": float(location[1]),
                "residual_m": residual,
            }
        )
    print(json.dumps({"import_s": import_s, "cpu_s": cpu_s, "wall_s": wall_s, "candidates": rows}))


def opensoundscape_run(python: str, folder: Path, speed: float, band_hz: list[float] | None, truth: pd.DataFrame, clip_s: float) -> dict:
    """OpenSoundscape's localize_detections in its interpreter: CPU per call and the errors of every estimate and of each call's best."""
    from acoustlab.core import columns as col

    cmd = [python, __file__, "--driver", str(folder), str(speed), json.dumps(band_hz)]
    proc = subprocess.run(cmd, cwd=Path(__file__).resolve().parent.parent, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"OpenSoundscape's driver failed:\n{proc.stderr[-3000:]}")
    osl = json.loads(proc.stdout.strip().splitlines()[-1])
    n_events = len(truth)
    tx, ty, positions = (truth[c].to_numpy() for c in (col.TRUE_X, col.TRUE_Y, col.POSITION_ID))
    candidates = pd.DataFrame(osl["candidates"])
    event_of = np.clip(np.rint((candidates["start_s"].to_numpy() - PAD_S) / clip_s).astype(int), 0, n_events - 1)
    candidates["event"] = event_of
    candidates["error_m"] = errors_m(candidates["x_m"].to_numpy(), candidates["y_m"].to_numpy(), tx[event_of], ty[event_of])
    # per call the estimate a user filtering on OpenSoundscape's residual would keep: the lowest residual (none: no position)
    best = candidates.sort_values(["event", "residual_m"]).groupby("event").head(1).set_index("event").reindex(range(n_events))
    best_err = np.where(np.isfinite(best["residual_m"].to_numpy(float)), best["error_m"].to_numpy(float), np.inf)
    return {
        "band_hz": band_hz,
        "cpu_s": osl["cpu_s"],
        "wall_s": osl["wall_s"],
        "import_cpu_s": osl["import_s"],
        "ms_per_call": 1000 * osl["cpu_s"] / n_events,
        "estimates": len(candidates),
        "errors_every_estimate": summary(candidates["error_m"].to_numpy(float), positions[event_of]),
        "errors_lowest_residual_per_call": summary(best_err, positions),
    }


def write_inputs(batch, site, folder: Path) -> float:
    """One float32 WAV per mic with the events end to end, the coordinates and the detections table; the clip length in s."""
    import soundfile as sf

    folder.mkdir(parents=True, exist_ok=True)
    n_events, n_mics, n_samples = batch.audio.shape
    clip_s = n_samples / batch.sample_rate_hz
    files = []
    pad = np.zeros(int(round(PAD_S * batch.sample_rate_hz)), dtype=np.float32)
    for m in range(n_mics):
        path = folder / f"mic_{m}.wav"
        sf.write(path, np.concatenate([pad, batch.audio[:, m, :].reshape(-1), pad]), int(batch.sample_rate_hz), subtype="FLOAT")
        files.append(str(path))
    pd.DataFrame({"x": site.mic_positions_m[:, 0], "y": site.mic_positions_m[:, 1]}, index=pd.Index(files, name="file")).to_csv(
        folder / "file_coords.csv"
    )
    starts = len(pad) / batch.sample_rate_hz + np.arange(n_events) * clip_s
    index = pd.MultiIndex.from_tuples([(f, s, s + clip_s) for f in files for s in starts], names=["file", "start_time", "end_time"])
    pd.DataFrame({CLASS: 1}, index=index).to_csv(folder / "detections.csv")
    return clip_s


def read_clips(folder: Path, n_mics: int, n_events: int, n_samples: int) -> tuple[np.ndarray, float]:
    """The clips back from the WAVs, (E, M, S) float32, as a season run reads them (one read per mic and event)."""
    import soundfile as sf

    audio = np.empty((n_events, n_mics, n_samples), dtype=np.float32)
    rate = 0.0
    for k in range(n_events):
        for m in range(n_mics):
            with sf.SoundFile(folder / f"mic_{m}.wav") as f:
                f.seek(int(round(PAD_S * f.samplerate)) + k * n_samples)
                audio[k, m] = f.read(n_samples, dtype="float32")
                rate = f.samplerate
    return audio, float(rate)


def errors_m(x: np.ndarray, y: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """2-D errors in m, infinite where there is no position (it counts as an error)."""
    from acoustlab.method.pipeline import error_2d_m

    return error_2d_m(np.column_stack([x, y]), np.column_stack([tx, ty]))


def summary(err: np.ndarray, positions: np.ndarray) -> dict[str, float]:
    """Percentiles (failures as infinite errors), the share > 5 m with its 95 % interval by source position, the share unplaced."""
    from first_stage import share_ci

    from acoustlab.reporting.metrics import error_summary

    low, high = share_ci(err > 5, positions)
    stats = error_summary(err)  # a percentile among the failures is inf (np.quantile would give NaN between two infs)
    return {
        "n": stats["n"],
        "p50_m": stats["p50"],
        "p90_m": stats["p90"],
        "share_over_5m": stats["share_gt_5m"],
        "share_over_5m_ci": [low, high],
        "share_unplaced": stats["n_failed"] / stats["n"],
    }


def row(label: str, ms: float, ratio: str, n: str, e: dict[str, float]) -> str:
    low, high = e["share_over_5m_ci"]
    return (
        f"| {label} | {ms:.1f} | {ratio} | {n} | {e['p50_m']:.2f} | {e['p90_m']:.1f} | {e['share_over_5m']:.1%} "
        f"({low:.1%}–{high:.1%}) | {e['share_unplaced']:.1%} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--osl-python", help="an interpreter where opensoundscape imports (see the module docstring)")
    parser.add_argument("--n-events", type=int, default=1000)
    parser.add_argument("--driver", nargs=3, metavar=("FOLDER", "SPEED", "BAND"), help=argparse.SUPPRESS)  # internal: OpenSoundscape's side
    opts = parser.parse_args()
    if opts.driver:
        driver(Path(opts.driver[0]), float(opts.driver[1]), json.loads(opts.driver[2]))
        return
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if not opts.osl_python:
        raise SystemExit("--osl-python is required: an interpreter where `import opensoundscape.localization` works (see --help)")
    from common import REPO, compose_cfg, machine, write_results

    from acoustlab.core import columns as col
    from acoustlab.core.types import RecordingBatch
    from acoustlab.run.registry import build, build_feature_sets
    from acoustlab.stages.dataset import extract_features
    from acoustlab.stages.sites import site_from_config
    from acoustlab.stages.solver_columns import add_solver_columns
    from acoustlab.toolkit.physics import speed_of_sound_m_s

    cfg = compose_cfg(["+site=forest"])
    site = site_from_config(cfg.site)
    ids = np.arange(opts.n_events)
    batch = build(cfg.simulator, "simulator").simulate(site, ids, ids // 5, 0)
    folder = REPO / "outputs" / "experiments" / "opensoundscape"
    clip_s = write_inputs(batch, site, folder)
    speed = float(speed_of_sound_m_s(float(np.mean(site.temperature_range_c)), float(np.mean(site.relative_humidity_range_pct))))
    band = [float(b) for b in cfg.features.gcc.band_hz]
    osl = {
        name: opensoundscape_run(opts.osl_python, folder, speed, b, batch.events, clip_s)
        for name, b in (("no band-pass (its default)", None), (f"band-pass {band[0]:.0f}–{band[1]:.0f} Hz (acoustlab's band)", band))
    }
    version = subprocess.run(
        [opts.osl_python, "-c", "import importlib.metadata as m; print(m.version('opensoundscape'))"], capture_output=True, text=True
    ).stdout.strip()

    n_mics, n_samples = batch.audio.shape[1:]
    t = {}
    start = time.process_time()
    audio, rate = read_clips(folder, n_mics, opts.n_events, n_samples)
    t["read"] = time.process_time() - start
    ours = {}
    feature_configs = {
        "physics": ["features=physics"],
        "physics_lean": ["features=physics_lean"],
        "physics_lean, coarse search": ["features=physics_lean", "+features.gcc.search=coarse"],
    }
    for name, overrides in feature_configs.items():
        sets = build_feature_sets(compose_cfg(["+site=forest", *overrides]).features)
        start = time.process_time()
        parts = [
            extract_features(
                RecordingBatch(audio[k : k + BATCH_EVENTS], rate, batch.events.iloc[k : k + BATCH_EVENTS].reset_index(drop=True)),
                site,
                sets,
            )
            for k in range(0, opts.n_events, BATCH_EVENTS)
        ]
        ours[name] = pd.concat(parts, ignore_index=True)
        t[f"features ({name})"] = time.process_time() - start
    tx, ty = batch.events[col.TRUE_X].to_numpy(float), batch.events[col.TRUE_Y].to_numpy(float)
    errors = {}
    for name, solver_key in (("physics_lean", "solver"), ("physics_lean, coarse search", "solver (coarse search)")):
        start = time.process_time()
        table = add_solver_columns(
            ours[name], batch.events, site, build(cfg.solver, "solver"), float(cfg.pipeline.plausible_margin_fraction)
        )
        t[solver_key] = time.process_time() - start
        errors[name] = summary(
            errors_m(table[col.SOLVER_X].to_numpy(float), table[col.SOLVER_Y].to_numpy(float), tx, ty),
            batch.events[col.POSITION_ID].to_numpy(),
        )
    ms = {k: 1000 * v / opts.n_events for k, v in t.items()}
    ours_full = ms["read"] + ms["features (physics)"] + ms["solver"]
    ours_lean = ms["read"] + ms["features (physics_lean)"] + ms["solver"]
    ours_coarse = ms["read"] + ms["features (physics_lean, coarse search)"] + ms["solver (coarse search)"]
    a = errors["physics_lean"]
    result = {
        "machine": machine(),
        "n_events": opts.n_events,
        "opensoundscape_version": version,
        "speed_of_sound_m_s": speed,
        "opensoundscape": osl,
        "acoustlab_ms_per_call": ms,
        "acoustlab_first_stage_ms": {"physics": ours_full, "physics_lean": ours_lean, "physics_lean_coarse_search": ours_coarse},
        "acoustlab_solver_errors": a,
        "acoustlab_solver_errors_coarse_search": errors["physics_lean, coarse search"],
    }
    lines = [
        "# OpenSoundscape (released) against acoustlab's first stage, same forest detections",
        "",
        f"`python experiments/opensoundscape.py --osl-python PYTHON --n-events {opts.n_events}` (OpenSoundscape {version}; "
        f"{machine()['cpus']} CPUs, one run). {opts.n_events} simulated forest events at {opts.n_events // 5} source positions "
        f"(6 mics, {clip_s:.1f} s at {rate:.0f} Hz) in one WAV per mic; every window of every file marked as a detection. "
        "Process CPU time per call; OpenSoundscape in its own interpreter (torch on one thread, its import not counted), "
        "with the array's extent as max_receiver_dist and the speed of sound at the site's mean temperature. Errors: "
        "horizontal distance to the source; no position counts as an error.",
        "",
        "| | CPU ms per call | over acoustlab (lean) | estimates | p50 (m) | p90 (m) | > 5 m (95 % CI by position) | no position |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, o in osl.items():
        lines += [
            row(
                f"OpenSoundscape `localize_detections`, PHAT, least squares, {name}: every estimate",
                o["ms_per_call"],
                f"{o['ms_per_call'] / ours_lean:.1f}×",
                f"{o['estimates']} (one per reference receiver)",
                o["errors_every_estimate"],
            ),
            row(
                "… the lowest-residual estimate of each call",
                o["ms_per_call"],
                f"{o['ms_per_call'] / ours_lean:.1f}×",
                str(opts.n_events),
                o["errors_lowest_residual_per_call"],
            ),
        ]
    lines += [
        row(
            "acoustlab read + features=physics + solver (consistent set)", ours_full, f"{ours_full / ours_lean:.2f}×", str(opts.n_events), a
        ),
        row("acoustlab read + features=physics_lean + solver (consistent set)", ours_lean, "1.00×", str(opts.n_events), a),
        row(
            "acoustlab read + features=physics_lean with +features.gcc.search=coarse + solver",
            ours_coarse,
            f"{ours_coarse / ours_lean:.2f}×",
            str(opts.n_events),
            errors["physics_lean, coarse search"],
        ),
        "",
        "OpenSoundscape's CPU per call over acoustlab's lean first stage with the coarse search: "
        + ", ".join(f"{o['ms_per_call'] / ours_coarse:.1f}× ({name})" for name, o in osl.items())
        + ".",
        "",
        "acoustlab's stages, CPU ms per call: " + ", ".join(f"{k} {v:.1f}" for k, v in ms.items()) + ". The solver's fixes "
        "are the same with either feature set (it reads only the tdoa and xcorr main-band columns); the fitted method "
        "(gate, radii) adds about 3 ms per detection and is not run here. OpenSoundscape's import: "
        f"{next(iter(osl.values()))['import_cpu_s']:.1f} s of CPU.",
    ]
    write_results("opensoundscape", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
