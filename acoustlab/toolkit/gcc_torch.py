"""GCC peak candidates computed with torch, for a GPU: the CPU path's computation, batched over pairs.

``acoustlab.toolkit.gcc_candidates.pair_candidates`` with ``device="cuda"`` lands here. The
steps are those of ``acoustlab.toolkit.dsp.gcc`` and the CPU peak picking, written as whole-
batch tensor operations so that a GPU runs them without a Python loop over pairs:

1. one real FFT per mic over twice the signal length, (β-)PHAT weighted per mic (floor 10⁻⁶ of
   the mic's largest magnitude);
2. the cross-spectra of every pair, zero outside the band (one band, or one per event), inverse
   transformed at ``upsample`` × the sampling rate (or, ``band_limited``, at ``upsample`` × twice
   the band's upper edge), single precision throughout;
3. in each pair's lag window ±(d_ij / c_max + margin): the RMS (sidelobe level), local maxima
   (edges allowed, as on the CPU), the K highest, and parabolic refinement with the neighbours
   clipped to the window.

Only the peaks (K per pair) and the RMS travel back to the host. The numbers equal the CPU path's
up to single-precision rounding of a different FFT library (cuFFT): the chosen peaks agree where
the heights of two candidates are not within that rounding of each other. The
lags themselves are assembled on the host in double precision exactly as the CPU path does.

The events go through in passes of as many as fit ``memory_gb`` of GPU memory (an estimate of the
pass' largest tensors, ``events_per_pass``), so a large feature chunk does not run a small GPU
out of memory; a GPU that still runs out stops with a ``ConfigError`` naming the setting.

torch is an optional dependency (``pip install -e ".[tabpfn]"`` brings it); it is imported only
when this path is asked for.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.dsp import GccLengths, _band_selection, gcc_lengths


def check_device(device: str) -> str:
    """``device`` if the GCC can run there, else a ``ConfigError`` that says what is missing.

    ``cpu`` always works; ``cuda`` / ``cuda:N`` need torch with a visible CUDA GPU.
    """
    name = str(device)
    if name == "cpu":
        return name
    if not (name == "cuda" or (name.startswith("cuda:") and name[5:].isdigit())):
        raise ConfigError(f"features.gcc.device must be 'cpu', 'cuda' or 'cuda:N'; got {device!r}")
    try:
        import torch
    except ImportError as exc:
        raise ConfigError(
            f'features.gcc.device={name} needs torch (pip install -e ".[tabpfn]", or torch for your CUDA); '
            "it is not installed. Use features.gcc.device=cpu"
        ) from exc
    if not torch.cuda.is_available():
        raise ConfigError(
            f"features.gcc.device={name}: torch {torch.__version__} sees no CUDA GPU "
            "(a CPU-only build, or no driver). Use features.gcc.device=cpu"
        )
    index = int(name[5:]) if ":" in name else 0
    if index >= torch.cuda.device_count():
        raise ConfigError(f"features.gcc.device={name}: only {torch.cuda.device_count()} CUDA device(s) visible")
    return name


def check_memory_gb(memory_gb: float) -> float:
    """``memory_gb`` as a float if it is a usable bound (> 0 GiB), else a ``ConfigError`` naming ``features.gcc.device_memory_gb``."""
    value = float(memory_gb)
    if not value > 0:
        raise ConfigError(f"features.gcc.device_memory_gb must be > 0; got {memory_gb}")
    return value


def window_bounds(lags_s: np.ndarray, windows_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last index (P,) of each pair's run of lags with |lag| ≤ its window (as the CPU path cuts it)."""
    inside = np.abs(lags_s)[None, :] <= windows_s[:, None]
    first = inside.argmax(axis=1)
    last = inside.shape[1] - 1 - inside[:, ::-1].argmax(axis=1)
    return first, last


def pair_candidates_torch(
    audio: np.ndarray,
    pairs: list[tuple[int, int]],
    sample_rate_hz: float,
    windows_s: np.ndarray,
    n_candidates: int,
    weighting: str,
    band_hz: Any,
    upsample: int,
    beta: float,
    band_limited: bool = False,
    device: str = "cuda",
    memory_gb: float = 4.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K best GCC peaks of every pair (module docstring), computed on ``device``.

    Parameters
    ----------
    audio : numpy.ndarray
        (E, M, S) recordings.
    pairs : list of (int, int)
        Mic pairs; the peak of pair (i, j) lies at t_j − t_i.
    sample_rate_hz : float
        Sampling rate, Hz.
    windows_s : numpy.ndarray
        (P,) largest |lag| of each pair, s.
    n_candidates : int
        Peaks kept per pair (K).
    weighting, band_hz, upsample, beta, band_limited
        As ``acoustlab.toolkit.dsp.gcc``.
    device : str
        A torch device (``cuda``, ``cuda:1``; ``cpu`` runs this path on the CPU, for tests).
    memory_gb : float
        GPU memory, GiB, that one pass of events may take (see ``events_per_pass``).

    Returns
    -------
    lags_s : numpy.ndarray
        (E, P, K) candidate lags in s, best first (NaN where fewer peaks exist).
    heights : numpy.ndarray
        (E, P, K) interpolated GCC heights (NaN likewise).
    sidelobe : numpy.ndarray
        (E, P) RMS of the correlation within each pair's window.

    Raises
    ------
    ConfigError
        Where ``device`` is not available (a method fitted on a GPU, loaded on a machine without
        one), or where a pass runs the GPU out of memory.
    """
    import torch

    if weighting not in ("phat", "beta_phat", "none"):
        raise ValueError(f"gcc weighting must be 'phat', 'beta_phat' or 'none'; got {weighting!r}")
    if upsample < 1:
        raise ValueError(f"gcc upsample must be >= 1; got {upsample}")
    dev = torch.device(check_device(device) if device != "cpu" else device)
    windows_s = np.asarray(windows_s, dtype=float)
    size = gcc_lengths(audio.shape[-1], sample_rate_hz, upsample, float(windows_s.max()), band_hz, band_limited)
    lags_s = np.arange(-size.half, size.half + 1) / size.rate_hz
    first, last = window_bounds(lags_s, windows_s)
    per_pass = events_per_pass(memory_gb, audio.shape[1], len(pairs), size)
    banded = band_hz is not None and np.asarray(band_hz).ndim == 2  # one band per event: cut it with the events
    parts = []
    for start in range(0, audio.shape[0], per_pass):
        stop = start + per_pass
        parts.append(
            _one_pass(
                audio[start:stop],
                pairs,
                sample_rate_hz,
                size,
                weighting,
                band_hz[start:stop] if banded else band_hz,
                beta,
                first,
                last,
                n_candidates,
                dev,
                memory_gb,
            )
        )
    offset, height, order, valid, sidelobe = (np.concatenate(arrays) for arrays in zip(*parts, strict=True))
    step = lags_s[1] - lags_s[0]
    rel = order - first[None, :, None]
    out_lags = np.where(valid, lags_s[first][None, :, None] + (rel + offset) * step, np.nan)
    out_heights = np.where(valid, height.astype(float), np.nan)
    return out_lags, out_heights, sidelobe.astype(float)


def events_per_pass(memory_gb: float, n_mics: int, n_pairs: int, size: GccLengths) -> int:
    """Events whose GCC fits ``memory_gb`` GiB: the spectra, cross-spectra, correlations and peak-picking tensors of one event, summed.

    An estimate (bytes per event: 12 per mic and spectrum bin, 8 per pair and cross-spectrum bin,
    4 per pair and correlation sample, 28 per pair and lag for the peak picking); torch's caching
    allocator and cuFFT's work areas come on top. At least one event per pass.
    """
    check_memory_gb(memory_gb)
    bins = size.n_out // 2 + 1
    per_event = 12 * n_mics * min(size.n_fft // 2 + 1, bins) + n_pairs * (8 * bins + 4 * size.n_out + 28 * (2 * size.half + 1))
    return max(1, int(memory_gb * 2**30 // per_event))


def _one_pass(
    audio: np.ndarray,
    pairs: list[tuple[int, int]],
    sample_rate_hz: float,
    size: GccLengths,
    weighting: str,
    band_hz: Any,
    beta: float,
    first: np.ndarray,
    last: np.ndarray,
    n_candidates: int,
    dev: Any,
    memory_gb: float,
) -> tuple[np.ndarray, ...]:
    """Peaks of one pass of events on ``dev``, as host arrays: offsets, heights, indices, validity (E, P, K), RMS (E, P)."""
    import torch

    try:
        with torch.no_grad():
            cc = _correlation(
                torch.as_tensor(np.ascontiguousarray(audio, dtype=np.float32), device=dev),
                pairs,
                sample_rate_hz,
                size,
                weighting,
                band_hz,
                beta,
            )
            peaks = _peaks(cc, torch.as_tensor(first, device=dev), torch.as_tensor(last, device=dev), n_candidates)
            return tuple(t.cpu().numpy() for t in peaks)
    except torch.cuda.OutOfMemoryError as exc:  # torch.OutOfMemoryError from torch 2.5; the extra allows 2.3
        raise ConfigError(
            f"features.gcc.device={dev}: a pass of {audio.shape[0]} events ran the GPU out of memory; "
            f"lower features.gcc.device_memory_gb (now {memory_gb} GiB)"
        ) from exc


def _correlation(
    x: Any, pairs: list[tuple[int, int]], sample_rate_hz: float, size: GccLengths, weighting: str, band_hz: Any, beta: float
) -> Any:
    """(E, P, 2·half + 1) weighted cross-correlation of every pair over lags −half … +half (steps 1 and 2 of the module docstring)."""
    import torch

    n_kept = min(size.n_fft // 2 + 1, size.n_out // 2 + 1)
    spectra = torch.fft.rfft(x, n=size.n_fft, dim=-1)[..., :n_kept]  # (E, M, F) complex64
    if weighting != "none":
        magnitude = spectra.abs()
        magnitude = torch.maximum(magnitude, 1e-6 * magnitude.amax(dim=-1, keepdim=True) + 1e-30)
        if weighting != "phat":
            magnitude = magnitude.pow(float(beta))
        spectra = spectra / magnitude
        del magnitude
    i_idx = torch.as_tensor([p[0] for p in pairs], device=x.device)
    j_idx = torch.as_tensor([p[1] for p in pairs], device=x.device)
    cross = spectra[:, i_idx].conj() * spectra[:, j_idx]  # (E, P, F)
    del spectra
    cross = cross * _band_mask(band_hz, size.n_fft, n_kept, sample_rate_hz, x.device)
    full = torch.fft.irfft(cross, n=size.n_out, dim=-1)  # zero-padded to n_out // 2 + 1 bins by irfft
    del cross
    if size.scale is not None:
        full = full * np.float32(size.scale)
    return torch.cat([full[..., size.n_out - size.half :], full[..., : size.half + 1]], dim=-1)


def _band_mask(band_hz: Any, n_fft: int, n_kept: int, sample_rate_hz: float, dev: Any) -> Any:
    """(1, 1, F) or (E, 1, F) float mask of the bins in the band (the CPU path's ``acoustlab.toolkit.dsp._band_selection``)."""
    import torch

    selection = _band_selection(band_hz, n_fft, sample_rate_hz)
    if selection is None:
        return torch.ones((1, 1, n_kept), device=dev)
    if isinstance(selection, slice):
        mask = np.zeros((1, 1, n_kept), dtype=np.float32)
        mask[..., selection] = 1.0
    else:
        mask = selection[:, None, :n_kept].astype(np.float32)
    return torch.as_tensor(mask, device=dev)


def _peaks(cc: Any, first: Any, last: Any, k: int) -> tuple[Any, Any, Any, Any, Any]:
    """Peak picking inside each pair's window [first, last] of cc (E, P, L): offsets, heights, indices, validity (E, P, K), RMS (E, P)."""
    import torch

    length = cc.shape[-1]
    index = torch.arange(length, device=cc.device)
    inside = (index[None, :] >= first[:, None]) & (index[None, :] <= last[:, None])  # (P, L)
    count = inside.sum(-1).to(cc.dtype)
    sidelobe = torch.sqrt((torch.where(inside, cc, 0.0) ** 2).sum(-1) / count)
    outside = torch.tensor(-torch.inf, device=cc.device, dtype=cc.dtype)
    seg = torch.where(inside, cc, outside)
    # local maxima with the CPU path's rule: ≥ the left neighbour, > the right one; a neighbour outside the window is −inf
    left = torch.cat([torch.full_like(seg[..., :1], -torch.inf), seg[..., :-1]], dim=-1)
    right = torch.cat([seg[..., 1:], torch.full_like(seg[..., :1], -torch.inf)], dim=-1)
    is_peak = inside & (seg >= left) & (seg > right)
    masked = torch.where(is_peak, seg, outside)
    del left, right, is_peak
    top_values, order = torch.topk(masked, min(k, length), dim=-1)  # sorted, highest first
    valid = top_values > -torch.inf
    lo, hi = first[None, :, None], last[None, :, None]
    mid = torch.gather(cc, -1, order)
    left_v = torch.gather(cc, -1, torch.clamp(order - 1, min=lo, max=hi).expand_as(order))
    right_v = torch.gather(cc, -1, torch.clamp(order + 1, min=lo, max=hi).expand_as(order))
    denom = left_v - 2 * mid + right_v
    safe = denom.abs() > 1e-15
    offset = torch.where(safe, 0.5 * (left_v - right_v) / torch.where(safe, denom, torch.ones_like(denom)), torch.zeros_like(denom))
    offset = offset.clamp(-0.5, 0.5)
    height = mid - 0.25 * (left_v - right_v) * offset
    return offset, height, order, valid, sidelobe
