"""The GCC's transforms with other FFT libraries: how much of the TDOA stage's floor is the FFT library's.

Usage: python benchmarks/bench_fft_backends.py [--n-events 16] [--repeats 5]

The TDOA stage of a 6-mic forest event spends most of its time in transforms: six forward real
transforms of 54,000 points (the spectra) and fifteen inverse real transforms of 108,000 points
(the pairs' correlations, upsampled ×2), single precision. On simulated forest events, the same
(β-)PHAT-weighted, band-limited cross-spectra that :func:`acoustlab.toolkit.dsp.gcc` inverts are
transformed with SciPy's pocketfft (what acoustlab uses) and, where installed, with pyFFTW
(FFTW 3; plans made once with FFTW_MEASURE, not timed) and mkl_fft (Intel MKL), each on one
thread. Reported: ms per event for the forward and the inverse transforms, the ratio to pocketfft,
and the largest difference of the correlations from pocketfft's relative to their peak (float32
rounding of a different algorithm). Neither library is an acoustlab dependency (FFTW is GPL, MKL
is Intel's licence and x86 only); this sizes what one would buy.

Writes benchmarks/results/fft_backends.{json,md}.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from collections.abc import Callable

import numpy as np
import scipy.fft as sfft
from common import compose_cfg, machine, write_results

from acoustlab.run.registry import build
from acoustlab.stages.sites import site_from_config
from acoustlab.toolkit.dsp import next_fast_len, weighted_spectra

log = logging.getLogger("bench_fft_backends")


def cross_spectra(spectra: np.ndarray, pairs: list[tuple[int, int]], band: tuple[float, float], n_fft: int, fs: float) -> np.ndarray:
    """(E, P, n_fft // 2 + 1) complex64 cross-spectra conj(X_i) X_j, zero outside ``band`` (as dsp.gcc builds them)."""
    freqs = sfft.rfftfreq(n_fft, d=1.0 / fs)
    keep = (freqs >= band[0]) & (freqs <= band[1])
    i_idx, j_idx = np.array(pairs).T
    return (np.conj(spectra[:, i_idx]) * spectra[:, j_idx] * keep).astype(np.complex64)


def backends(shape_in: tuple[int, ...], n_out: int, shape_fwd: tuple[int, ...], n_fft: int) -> dict[str, tuple[Callable, Callable, str]]:
    """name -> (inverse(x) for (…, n_out // 2 + 1) complex64 input, forward(x) for real float32 input, version)."""
    import scipy

    out = {"scipy (pocketfft)": (lambda x: sfft.irfft(x, n=n_out, axis=-1), lambda x: sfft.rfft(x, n=n_fft, axis=-1), scipy.__version__)}
    try:
        import pyfftw
        import pyfftw.builders as fb

        inverse = fb.irfft(pyfftw.empty_aligned(shape_in, dtype="complex64"), n=n_out, axis=-1, threads=1, planner_effort="FFTW_MEASURE")
        forward = fb.rfft(pyfftw.empty_aligned(shape_fwd, dtype="float32"), n=n_fft, axis=-1, threads=1, planner_effort="FFTW_MEASURE")
        out["pyFFTW (FFTW 3)"] = (lambda x: inverse(x), lambda x: forward(x), pyfftw.__version__)
    except ImportError:
        log.info("pyFFTW not installed: skipped")
    try:
        import mkl_fft

        out["mkl_fft (Intel MKL)"] = (lambda x: mkl_fft.irfft(x, n=n_out, axis=-1), lambda x: mkl_fft.rfft(x, n=n_fft, axis=-1),
                                      mkl_fft.__version__)
    except ImportError:
        log.info("mkl_fft not installed: skipped")
    return out


def best_seconds(fn: Callable, x: np.ndarray, repeats: int) -> tuple[float, np.ndarray]:
    """Smallest wall time of ``repeats`` calls (after one warm-up) and the last output."""
    result = fn(x)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn(x)
        times.append(time.perf_counter() - start)
    return min(times), np.asarray(result)


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-events", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=5)
    opts = parser.parse_args()
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    cfg = compose_cfg(["+site=forest"])
    site = site_from_config(cfg.site)
    ids = np.arange(opts.n_events)
    batch = build(cfg.simulator, "simulator").simulate(site, ids, ids // 5, 0)
    audio = batch.audio.astype(np.float32)
    fs, gcc_cfg = batch.sample_rate_hz, cfg.features.gcc
    n_fft = next_fast_len(2 * audio.shape[-1])
    n_out = n_fft * int(gcc_cfg.upsample)
    spectra = weighted_spectra(audio, str(gcc_cfg.weighting), float(gcc_cfg.beta))
    cross = cross_spectra(spectra, site.mic_pairs, tuple(gcc_cfg.band_hz), n_fft, fs)
    cross_in = np.zeros((*cross.shape[:2], n_out // 2 + 1), dtype=np.complex64)
    cross_in[..., : cross.shape[-1]] = cross
    rows, reference = {}, None
    for name, (inverse, forward, version) in backends(cross_in.shape, n_out, audio.shape, n_fft).items():
        t_inv, cc = best_seconds(inverse, cross_in, opts.repeats)
        t_fwd, _ = best_seconds(forward, audio, opts.repeats)
        if reference is None:
            reference = cc
        rows[name] = {"version": version, "inverse_ms_per_event": 1e3 * t_inv / opts.n_events, "forward_ms_per_event": 1e3 * t_fwd / opts.n_events,
                      "max_diff_relative_to_peak": float(np.max(np.abs(cc - reference)) / np.max(np.abs(reference)))}
        log.info("%s: %s", name, rows[name])
    base = rows["scipy (pocketfft)"]
    base_total = base["inverse_ms_per_event"] + base["forward_ms_per_event"]
    result = {"machine": machine(), "n_events": opts.n_events, "repeats": opts.repeats, "n_mics": site.n_mics, "n_pairs": len(site.mic_pairs),
              "forward_points": n_fft, "inverse_points": n_out, "backends": rows}
    lines = ["# The GCC's transforms with other FFT libraries (forest, 6 mics, one thread)", "",
             f"`python benchmarks/bench_fft_backends.py --n-events {opts.n_events} --repeats {opts.repeats}`: per event "
             f"{site.n_mics} forward real transforms of {n_fft:,} points and {len(site.mic_pairs)} inverse real transforms of "
             f"{n_out:,} points, float32, on the default GCC's band-limited (β-)PHAT cross-spectra of {opts.n_events} simulated "
             f"events; the best of {opts.repeats} repeats, one thread.", "",
             "| library | version | forward ms / event | inverse ms / event | both: speed-up over pocketfft | largest difference / peak |",
             "|---|---|---|---|---|---|"]
    for name, r in rows.items():
        total = r["inverse_ms_per_event"] + r["forward_ms_per_event"]
        lines.append(f"| {name} | {r['version']} | {r['forward_ms_per_event']:.2f} | {r['inverse_ms_per_event']:.2f} | "
                     f"{base_total / total:.2f}× | {r['max_diff_relative_to_peak']:.1e} |")
    lines += ["", "Neither pyFFTW (FFTW is GPL) nor mkl_fft (Intel's licence, x86 only) is an acoustlab dependency; the rows "
              "that are missing were not installed where this ran."]
    write_results("fft_backends", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
