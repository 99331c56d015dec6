"""Where the feature stage's time goes: CPU ms per event of each default feature group, per site, in one run.

Usage: python benchmarks/bench_feature_cost.py [--n-events 64] [--repeats 3]

On freshly simulated events of each site (default simulator and features), every group of
``features.groups`` transforms the same batch in the order a run uses, on a fresh
:class:`RecordingBatch` each repeat (so work shared through the batch's cache — the GCC of the
``tdoa``/``xcorr``/``uncertainty`` groups, the band-passed Hilbert magnitude of ``ir``/``envelope`` —
is charged to the first group that needs it). The smallest of ``--repeats`` is reported (process
CPU time, one process).

It also compares the band-passed Hilbert magnitude acoustlab computes (one transform: the
recording's spectrum times the Butterworth band-pass' squared magnitude response, one-sided, one
inverse transform, in single precision) with the textbook ``sosfiltfilt`` followed by
``scipy.signal.hilbert`` that it replaced: cost, and how far the envelopes and the
``ir``/``envelope`` features they give differ (the two pad the clip's first and last 50 ms differently).

Writes benchmarks/results/feature_cost.{json,md}.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
import scipy.signal as ss
from common import compose_cfg, machine, write_results

from acoustlab.core.types import RecordingBatch
from acoustlab.run.registry import build, build_feature_sets
from acoustlab.stages.sites import site_from_config
from plugins.features import waveform_groups

log = logging.getLogger("bench_feature_cost")
EDGE_S = 0.05


def textbook_envelope(audio: np.ndarray, sample_rate_hz: float, band_hz: tuple[float, float]) -> np.ndarray:
    """|analytic signal| of the recordings after the 4th-order Butterworth band-pass applied forward and backward, (E, M, S)."""
    nyq = sample_rate_hz / 2
    sos = ss.butter(4, [band_hz[0] / nyq, min(band_hz[1] / nyq, 0.99)], btype="bandpass", output="sos")
    return np.abs(ss.hilbert(ss.sosfiltfilt(sos, audio, axis=-1), axis=-1))


def cpu_ms_per_event(fn, n_events: int, repeats: int) -> float:
    """Smallest process CPU time of ``repeats`` calls of ``fn``, in ms per event."""
    best = np.inf
    for _ in range(repeats):
        start = time.process_time()
        fn()
        best = min(best, time.process_time() - start)
    return 1e3 * best / n_events


def group_costs(batch: RecordingBatch, site, groups: dict, repeats: int) -> dict[str, float]:
    """CPU ms per event of each group on a fresh batch, in the run's order (shared work charged to its first user)."""
    costs = {name: np.inf for name in groups}
    for _ in range(repeats):
        fresh = RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events)
        for name, group in groups.items():
            start = time.process_time()
            group.transform(fresh, site)
            costs[name] = min(costs[name], 1e3 * (time.process_time() - start) / len(batch.events))
    return costs


def envelope_against_textbook(batch: RecordingBatch, site, groups: dict, repeats: int) -> dict[str, float]:
    """acoustlab's band-passed Hilbert magnitude against the textbook one: cost, envelope and feature differences."""
    band = waveform_groups.BlindIrSummaries().band_hz if "ir" not in groups else groups["ir"].band_hz
    fs, audio, n = batch.sample_rate_hz, batch.audio, len(batch.events)
    ours = waveform_groups._hilbert_magnitude(audio, fs, band)
    textbook = textbook_envelope(audio, fs, band)
    edge = int(EDGE_S * fs)
    scale = textbook.max(axis=-1, keepdims=True)
    interior = np.abs(ours - textbook)[..., edge:-edge] / scale
    out = {"acoustlab_ms": cpu_ms_per_event(lambda: waveform_groups._hilbert_magnitude(audio, fs, band), n, repeats),
           "textbook_ms": cpu_ms_per_event(lambda: textbook_envelope(audio, fs, band), n, repeats),
           "interior_max_diff_of_peak": float(interior.max()), "median_diff_of_peak": float(np.median(np.abs(ours - textbook) / scale))}
    for name in ("ir", "envelope"):
        if name not in groups:
            continue
        features = groups[name].transform(RecordingBatch(audio, fs, batch.events), site)
        trial = RecordingBatch(audio, fs, batch.events)
        trial.derived(("hilbert_magnitude", band), lambda: textbook)  # what the groups read with the textbook envelope
        reference = groups[name].transform(trial, site)
        rel = (features - reference).abs().to_numpy() / np.maximum(reference.abs().to_numpy(), 1e-12)
        out[f"{name}_median_rel_diff"] = float(np.nanmedian(rel))
        out[f"{name}_share_within_1pct"] = float(np.mean(rel <= 0.01))
    return out


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-events", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=3)
    opts = parser.parse_args()
    result = {"machine": machine(), "n_events": opts.n_events, "sites": {}}
    lines = ["# Feature stage cost by group", "",
             f"`python benchmarks/bench_feature_cost.py --n-events {opts.n_events} --repeats {opts.repeats}`: process CPU ms per "
             f"event, the smallest of {opts.repeats} repeats on a fresh batch; work shared through the batch (the GCC, the Hilbert "
             "magnitude) is charged to the first group that needs it; one process.", ""]
    for site_name in ("forest", "frozen_lake"):
        cfg = compose_cfg([f"+site={site_name}"])
        site = site_from_config(cfg.site)
        ids = np.arange(opts.n_events)
        batch = build(cfg.simulator, "simulator").simulate(site, ids, ids // 5, 0)
        groups = build_feature_sets(cfg.features)
        costs = group_costs(batch, site, groups, opts.repeats)
        envelope = envelope_against_textbook(batch, site, groups, opts.repeats)
        result["sites"][site_name] = {"n_mics": site.n_mics, "samples_per_channel": int(batch.audio.shape[-1]),
                                      "sample_rate_hz": batch.sample_rate_hz, "ms_per_event": costs, "envelope_against_textbook": envelope}
        total = sum(costs.values())
        lines += [f"## {site_name}: {site.n_mics} mics, {batch.audio.shape[-1]} samples per channel at {batch.sample_rate_hz:.0f} Hz", "",
                  "| group | ms per event | share |", "|---|---|---|",
                  *[f"| {name} | {ms:.2f} | {100 * ms / total:.0f} % |" for name, ms in costs.items()],
                  f"| **all** | **{total:.1f}** | |", "",
                  f"The band-passed Hilbert magnitude (one transform, single precision): {envelope['acoustlab_ms']:.2f} ms per event "
                  f"against {envelope['textbook_ms']:.2f} ms for the textbook sosfiltfilt + hilbert, "
                  f"{envelope['textbook_ms'] / envelope['acoustlab_ms']:.1f}×; envelopes differ by at most "
                  f"{envelope['interior_max_diff_of_peak']:.1e} of the channel's peak away from the first and last {1e3 * EDGE_S:.0f} ms "
                  f"(median {envelope['median_diff_of_peak']:.1e} everywhere); "
                  + "; ".join(f"`{g}` features: median relative difference {envelope[f'{g}_median_rel_diff']:.1e}, "
                              f"{100 * envelope[f'{g}_share_within_1pct']:.1f} % within 1 %" for g in ("ir", "envelope")
                              if f"{g}_median_rel_diff" in envelope) + ".", ""]
    write_results("feature_cost", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
