"""Where to play back: playback spots chosen so that ``calibrate`` determines the array best.

A calibration's accuracy depends on where its spots are far more than on how many playbacks each
spot gets: a spot's multipath biases its peaks alike in every playback, so only more spots, and
spots that pull on each unknown from different directions, average it out. Spots drawn at random
can leave a recorder's clock or position nearly undetermined (five random spots left three of a
forest array's six clocks at their prior in ``experiments/results/field_calibration.md``).

The plan is a greedy A-optimal design on the calibration's own linearised model
(``acoustlab.toolkit.array_calibration``, the stated array, every mic pair measured, timing noise
``timing_sigma_s`` for a pair whose mics stand half the array's extent from the spot, growing with
their distance as spherical spreading lowers their SNR): starting from the priors, each step adds the candidate spot that most lowers
the summed posterior variance of what a localization feels, in m² — each mic's two horizontal
coordinates, each clock offset times the speed of sound, and the thermometer's offset as the
path-length error it makes over the array's extent. Greedy selection is within a factor (1 − 1/e)
of the best set for the closely related log-det criterion and is what experimental-design practice
uses for sensor placement (Krause, Singh & Guestrin 2008, JMLR 9: 235–284). It is written here
because the criterion is this model's; NumPy does the algebra.

Candidates are a grid over the mics' hull grown by ``expansion`` × the array's extent (or the
user's own reachable spots), at least ``min_mic_distance_m`` from every stated mic and, once
chosen, at least ``min_separation_m`` from each other (two spots side by side share their
multipath). The distance from the mics defaults to five times the largest stated GPS error (at
least 3 m): the plan and the fit start from the stated array, and a spot within a few GPS errors
of a mic may stand on either side of the real one, so the direction the fit pulls that mic is
unknown (on the second simulator's 3-mic lake, five spots 3–4 m from the stated mics moved one
array's mics further off than stated).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.array_calibration import Playbacks, Priors, linearised_rows, speed_of_sound_slope, spots_for
from acoustlab.toolkit.geometry import distance_to_polygon_m, source_region
from acoustlab.toolkit.physics import speed_of_sound_m_s

log = logging.getLogger(__name__)

#: What a plan determines: drift needs playbacks spread over hours, which a plan of places does not choose.
PLANNED_KINDS = ("temperature", "clocks", "positions")


@dataclass
class PlaybackPlan:
    """Spots to play back from, in the order chosen, and what calibrating from them would leave uncertain.

    Attributes
    ----------
    spots_m : numpy.ndarray
        (K, 3) spot positions in m (x, y in the site's frame; z the speaker's height).
    predicted_sd_m : numpy.ndarray
        (K,) after the first k + 1 spots, the root-mean-square posterior standard deviation of the
        mics' horizontal coordinates, m (timing noise ``timing_sigma_s``, no multipath: a lower bound).
    prior_sd_m : float
        The same before any playback (the stated GPS error), m.
    """

    spots_m: np.ndarray
    predicted_sd_m: np.ndarray
    prior_sd_m: float


def grid_candidates(mic_positions_m: np.ndarray, expansion: float, spacing_m: float) -> np.ndarray:
    """(C, 2) grid points inside the mics' hull grown by ``expansion`` × the largest mic-to-mic distance, m."""
    polygon, buffer_m = source_region(mic_positions_m, expansion)
    low, high = polygon.min(axis=0) - buffer_m, polygon.max(axis=0) + buffer_m
    axes = [np.arange(lo, hi + spacing_m / 2, spacing_m) for lo, hi in zip(low, high, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 2)
    return grid[distance_to_polygon_m(grid, polygon) <= buffer_m]


def _usable_candidates(
    priors: Priors, candidates_xy_m: np.ndarray | None, expansion: float, min_mic_distance_m: float | None, n_spots: int, extent: float
) -> np.ndarray:
    """(C, 2) the candidates (the grid by default) at least the minimum distance from every stated mic, m (``extent``: the largest mic-to-mic distance)."""
    mics = np.asarray(priors.mic_positions_m, dtype=float)[:, :2]
    distance = max(3.0, 5.0 * float(np.max(priors.position_sigma_m))) if min_mic_distance_m is None else float(min_mic_distance_m)
    # a compact array's grid reaches at least twice that distance beyond its hull, so spots remain on every side
    reach = max(expansion, 2.0 * distance / extent)
    given = grid_candidates(mics, reach, extent / 25) if candidates_xy_m is None else np.asarray(candidates_xy_m, float).reshape(-1, 2)
    to_mic = np.sqrt(((given[:, None, :] - mics[None]) ** 2).sum(-1)).min(axis=1)
    usable = given[to_mic >= distance]
    if len(usable) < n_spots:
        raise ConfigError(
            f"plan_playbacks: {len(usable)} of {len(given)} candidate spots lie {distance:.1f} m or more from every mic, "
            f"{n_spots} spots asked for; give more candidates or a smaller min_mic_distance_m"
        )
    return usable


def _spreading_noise(source_m: np.ndarray, mics_m: np.ndarray, pairs: list[tuple[int, int]], reference_m: float) -> np.ndarray:
    """(C, P) each pair's timing noise relative to a pair whose mics stand ``reference_m`` from the spot.

    Spherical spreading lowers a mic's SNR as 1/d²; a time difference's variance grows as the sum of
    its two mics' 1/SNR (the cross-correlation's Cramér–Rao bound at moderate SNR), so its standard
    deviation as √((d_i² + d_j²) / 2) / ``reference_m``. Far spots pull on distant pairs only weakly.
    """
    distance = np.sqrt(((source_m[:, None, :] - mics_m[None]) ** 2).sum(-1))
    first, second = np.array([i for i, _ in pairs]), np.array([j for _, j in pairs])
    return np.sqrt((distance[:, first] ** 2 + distance[:, second] ** 2) / 2) / reference_m


def _metres_per_unit(names: list[str], sd: np.ndarray, speed_m_s: float, extent_m: float, dc_dt: float) -> np.ndarray:
    """Each normalised parameter's standard deviation as the path length it moves, m."""
    scale = np.ones(len(names))
    for k, name in enumerate(names):
        if name.startswith("clock_"):
            scale[k] = speed_m_s
        elif name == "temperature_offset_c":
            scale[k] = extent_m * dc_dt / speed_m_s
    return sd * scale


def plan_playbacks(
    priors: Priors,
    n_spots: int,
    *,
    candidates_xy_m: np.ndarray | None = None,
    source_height_m: float = 1.5,
    expansion: float = 0.3,
    min_mic_distance_m: float | None = None,
    min_separation_m: float | None = None,
    temperature_c: float = 15.0,
    humidity_pct: float = 60.0,
    timing_sigma_s: float = 1e-4,
) -> PlaybackPlan:
    """Choose ``n_spots`` playback spots for ``calibrate`` (module docstring).

    Parameters
    ----------
    priors : Priors
        The stated array and its standard deviations (``CalibrateProtocol.priors``).
    n_spots : int
        Spots to choose (≥ 3: mic positions need three spots not on a line).
    candidates_xy_m : numpy.ndarray, optional
        (C, 2) the spots a field team can reach, m; default a grid (``expansion``, spacing 1/25 of
        the array's extent).
    source_height_m : float
        The speaker's height above ground, m.
    expansion : float
        The default grid covers the mics' hull grown by this × the largest mic-to-mic distance (or
        by twice ``min_mic_distance_m``, where that is more).
    min_mic_distance_m : float, optional
        No spot nearer a stated mic than this, m (default 5 × the largest ``position_sigma_m``, at
        least 3 m: module docstring).
    min_separation_m : float, optional
        Chosen spots at least this far apart, m (default 1/10 of the array's extent).
    temperature_c, humidity_pct : float
        Weather the speed of sound is taken at, °C and %.
    timing_sigma_s : float
        Timing noise of one measured time difference, s.

    Raises
    ------
    ConfigError
        With fewer than 3 spots asked for, or fewer candidates than spots.
    """
    mics = np.asarray(priors.mic_positions_m, dtype=float)
    extent = float(np.sqrt(((mics[:, None, :2] - mics[None, :, :2]) ** 2).sum(-1)).max())
    if n_spots < 3:
        raise ConfigError(f"plan_playbacks: n_spots must be >= 3 (mic positions need 3 spots not on a line); got {n_spots}")
    candidates = _usable_candidates(priors, candidates_xy_m, expansion, min_mic_distance_m, n_spots, extent)
    separation = extent / 10 if min_separation_m is None else float(min_separation_m)
    source = np.column_stack([candidates, np.full(len(candidates), float(source_height_m))])
    pairs = [(i, j) for i in range(len(mics)) for j in range(i + 1, len(mics))]
    playbacks = Playbacks(
        source,
        np.zeros((len(source), len(pairs))),
        np.full(len(source), float(temperature_c)),
        np.full(len(source), float(humidity_pct)),
        np.zeros(len(source)),
        np.arange(len(source)),
        pairs,
    )
    rows, names, sd = linearised_rows(playbacks, priors, PLANNED_KINDS, timing_sigma_s)  # (C, P, p)
    needed = spots_for(len(names), len(mics) - 1)  # calibrate's unknowns; a spot gives M − 1 time differences
    if needed is not None and n_spots < needed:
        log.warning(
            "plan_playbacks: %d spots are too few for a calibration that can tell wrong GCC peaks from right ones on %d mics; "
            "plan %d or more (docs/calibrate.md)",
            n_spots,
            len(mics),
            needed,
        )
    rows = rows / _spreading_noise(source, mics, pairs, extent / 2)[:, :, None]
    speed = float(speed_of_sound_m_s(temperature_c, humidity_pct))
    dc_dt = float(speed_of_sound_slope(np.array([temperature_c]), np.array([humidity_pct]))[0])
    weight = _metres_per_unit(names, sd, speed, extent, dc_dt) ** 2
    position = np.array([n.startswith("mic_") for n in names])
    per_candidate = np.einsum("cpa,cpb->cab", rows, rows)  # each candidate's information, (C, p, p)
    information = np.eye(len(names))
    available = np.ones(len(candidates), dtype=bool)
    chosen, predicted = [], []
    for _ in range(n_spots):
        if not available.any():
            raise ConfigError(
                f"plan_playbacks: only {len(chosen)} of the candidate spots lie {separation:.1f} m apart, {n_spots} asked for; "
                "lower min_separation_m or give more candidates"
            )
        covariance = np.linalg.inv(information[None] + per_candidate[available])
        loss = np.einsum("ckk,k->c", covariance, weight)
        best = int(np.flatnonzero(available)[np.argmin(loss)])
        chosen.append(best)
        information = information + per_candidate[best]
        spread = np.diag(np.linalg.inv(information))[position] * sd[position] ** 2
        predicted.append(float(np.sqrt(spread.mean())) if spread.size else 0.0)
        available &= np.hypot(*(candidates - candidates[best]).T) >= separation
    prior = float(np.sqrt(np.mean(sd[position] ** 2))) if position.any() else 0.0
    return PlaybackPlan(source[chosen], np.asarray(predicted), prior)
