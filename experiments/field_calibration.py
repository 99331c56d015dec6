"""Does ``acoustlab calibrate`` recover the array? Playbacks at known spots, then calls localized with and without it.

Usage: python experiments/field_calibration.py [--sites frozen_lake forest] [--arrays 3] [--spots 5 10] [--n-positions 60]
[--designs random planned] [--signals calls sweep] [--field image_source]

Per site and per array draw (``field.array_seed``), recordings rendered by the second simulator
(pyroomacoustics' image-source method, ``field=image_source``; or with ``--field outdoor`` by
acoustlab's own simulator, the propagation the method learned from) with the errors a field study has:
the recorders stand off their stated positions by N(0, 2 m) per axis (consumer GPS), their clocks
are off by up to ±1 ms, the thermometer reads 3 °C high. Then:

* **playbacks**: ``--spots`` spots, 3 playbacks each (their own seed), calibrate from them
  (``protocol=calibrate``, defaults); the spots either drawn at random inside the array
  (``random``) or where ``acoustlab.api.plan_playbacks`` puts them for the stated array
  (``planned``); the speaker plays either bird calls drawn from the site's pool (``calls``) or the
  playback sweep ``calibrate`` asks for (``sweep``, ``field.signal=sweep``);
* **calls**: ``--n-positions`` × 3 other events, in and around the array (30 % outside), localized
  by the configured solver (consistent set) with the array as stated (uncalibrated), with each
  calibration (``calibration=PATH``), and with the true array known exactly (the same sources,
  calls and noise rendered with no errors: the bound).

Errors are the solver's 2-D errors (failures infinite); 95 % intervals by position bootstrap over
all arrays' positions. Writes experiments/results/field_calibration.md (``--field outdoor``:
field_calibration_outdoor.md).
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
from common import compose_cfg, fmt, machine, write_results

from acoustlab.core import columns as col
from acoustlab.reporting.metrics import error_summary, share_gross

log = logging.getLogger("experiments.field_calibration")
IMPAIRED = ["field.mic_position_error_m=2.0", "field.clock_offset_max_s=0.001", "field.temperature_error_c=3.0"]
#: the thermometer reads 3 °C high: the offset a calibration should find
TRUE_TEMPERATURE_OFFSET_C = -3.0
N_BOOT = 1000
#: what the speaker plays back (``field.signal``)
SIGNALS = {"calls": "calls", "sweep": "a sweep"}
#: the field sources the array's errors are rendered with
RENDERERS = {"image_source": "Second simulator (pyroomacoustics)", "outdoor": "acoustlab's own outdoor simulator"}
#: only the field recordings' solver fixes are measured: the method's training simulation is kept tiny
SMALL_TRAINING = ["data.n_events=8", "data.events_per_position=1", "data.chunk_size=8"]


def solver_errors(overrides: list[str]) -> tuple[np.ndarray, np.ndarray, pd.DataFrame]:
    """(E,) the solver's 2-D errors on the field events of a config, (E,) their position ids, and the events."""
    from acoustlab.run.app import build_run, prepare_data

    cfg = compose_cfg([*overrides, "tracking=none", "plots=false"])
    data = prepare_data(cfg, build_run(cfg))
    f, e = data.field_data.features, data.field_data.events
    err = np.hypot(
        f[col.SOLVER_X].to_numpy(float) - e[col.TRUE_X].to_numpy(float), f[col.SOLVER_Y].to_numpy(float) - e[col.TRUE_Y].to_numpy(float)
    )
    return np.where(np.isfinite(err), err, np.inf), e[col.POSITION_ID].to_numpy(), e


def allowance_check(path: Path, site: str, true_mics: np.ndarray, clock_error_s: np.ndarray, calls: pd.DataFrame) -> dict:
    """Does the input allowance a run carries from this calibration hold what its remaining errors do to the calls' fixes?

    Per call (``calls``: the true array's events, true positions and weather): the exact shift of the
    least-squares fix solved with the calibrated thermometer, clocks and mics instead of the true ones
    (the true air: the temperature at which the renderer's speed of sound is ours)
    (``fix_shift_m``), and the per-axis allowance σ with the calibration's covariance (what a run
    carries) and with its standard deviations as independent errors (an RMS per kind, as before).
    """
    from acoustlab.stages.field_calibration import load_calibration
    from acoustlab.stages.sites import site_from_config
    from acoustlab.toolkit.array_calibration import temperature_from_speed_c
    from acoustlab.toolkit.input_uncertainty import InputUncertainty, allowance_sigma_m, fix_shift_m

    site_obj = site_from_config(compose_cfg([f"+site={site}"]).site)
    calibration = load_calibration(str(path), site_obj)
    source = calls[[col.TRUE_X, col.TRUE_Y, col.TRUE_Z]].to_numpy(float)
    humidity = calls[col.HUMIDITY].to_numpy(float)
    # the air as the renderer propagated it (pyroomacoustics has its own formula for the speed of sound), and as a run
    # reads it: the thermometer 3 °C high plus the calibrated offset
    renderer = [temperature_from_speed_c(c, h) for c, h in zip(calls["simulator_speed_of_sound_m_s"], humidity, strict=True)]
    used = calls[col.TEMPERATURE].to_numpy(float) - TRUE_TEMPERATURE_OFFSET_C + calibration.temperature_offset_c
    weather = (np.asarray(renderer), humidity)
    errors = (
        (used - weather[0])[:, None],
        -clock_error_s[None, :],  # a clock estimated late leaves its corrected arrivals early
        (calibration.mic_positions_m - true_mics)[None, :, :2],
    )
    shift = np.hypot(*fix_shift_m(true_mics, source, *weather, *errors)[:, 0].T)
    thermometer = np.hypot(*fix_shift_m(true_mics, source, *weather, errors[0], 0 * errors[1], 0 * errors[2])[:, 0].T)
    independent = InputUncertainty(
        temperature_c=float(np.hypot(calibration.temperature_offset_sd_c, calibration.temperature_call_sd_c)),
        mic_position_m=float(np.sqrt(np.mean(calibration.mic_position_sd_m**2))),
        clock_offset_s=float(np.sqrt(np.mean(calibration.clock_offset_sd_s[1:] ** 2))),
    )
    return {
        "shift_m": np.where(np.isfinite(shift), shift, np.inf),
        "thermometer_shift_m": np.where(np.isfinite(thermometer), thermometer, np.inf),
        "thermometer_error_c": used - weather[0],
        # the thermometer error's spread from call to call about its mean: what the playbacks' spread estimates
        "call_spread_c": (calibration.temperature_call_sd_c, float(np.std(used - weather[0]))),
        "correlated": allowance_sigma_m(calibration.mic_positions_m, source, used, humidity, calibration.input_uncertainty()),
        "independent": allowance_sigma_m(calibration.mic_positions_m, source, used, humidity, independent),
    }


def spot_overrides(site: str, n_spots: int, design: str) -> list[str]:
    """The field's overrides that put ``n_spots`` playback spots: drawn at random inside the array, or planned."""
    if design == "random":
        return [f"field.n_positions={n_spots}", "field.outside_share=0"]
    from acoustlab.api import plan_playbacks

    spots = plan_playbacks(site, n_spots)[[col.TRUE_X, col.TRUE_Y, col.TRUE_Z]].to_numpy()
    return ["field.positions_m=[" + ",".join(f"[{x:.3f},{y:.3f},{z:.3f}]" for x, y, z in spots) + "]"]


def calibrate(
    site: str, array_seed: int, n_spots: int, design: str, out: Path, field: str = "image_source", per_spot: int = 3, signal: str = "calls"
) -> dict:
    """Run ``calibrate`` on ``n_spots`` playback spots (``design``, ``per_spot`` playbacks each of ``signal``) of the impaired
    array; return its calibration.json."""
    from acoustlab.run.app import run_experiment

    cfg = compose_cfg(
        [
            f"+site={site}",
            "protocol=calibrate",
            f"field={field}",
            *spot_overrides(site, n_spots, design),
            f"field.events_per_position={per_spot}",
            f"field.signal={signal}",
            f"field.array_seed={array_seed}",
            f"field.seed={9000 + array_seed}",
            *IMPAIRED,
            "tracking=none",
            "plots=false",
        ]
    )
    run_experiment(cfg, out, {})
    return json.loads((out / "calibration.json").read_text())


def true_array(site: str, array_seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) where the impaired array's recorders really stand, m, and (M,) their clocks' offsets, s."""
    from acoustlab.stages.sites import site_from_config
    from plugins.fields.image_source import ImageSourceField

    site_obj = site_from_config(compose_cfg([f"+site={site}"]).site)
    return ImageSourceField(mic_position_error_m=2.0, clock_offset_max_s=0.001, array_seed=array_seed).true_array(site_obj)


def allowance_summary(checks: list[dict]) -> dict:
    """The calls' fix shifts against the 0.5 and 0.95 allowance radii (σ · √(−2 ln(1 − level))), pooled and per calibration."""
    from acoustlab.toolkit.input_uncertainty import level_factor

    shift = np.concatenate([c["shift_m"] for c in checks])
    out: dict = {
        "n_calibrations": len(checks),
        "n_calls": int(shift.size),
        "median_shift_m": float(np.median(shift)),
        "median_thermometer_shift_m": float(np.median(np.concatenate([c["thermometer_shift_m"] for c in checks]))),
        "thermometer_error_c_range": [float(f(np.concatenate([c["thermometer_error_c"] for c in checks]))) for f in (np.min, np.max)],
        "call_spread_c_estimated": [c["call_spread_c"][0] for c in checks],
        "call_spread_c_true": [c["call_spread_c"][1] for c in checks],
    }
    for kind in ("correlated", "independent"):
        sigma = np.concatenate([c[kind] for c in checks])
        per_calibration = [float(np.mean(c["shift_m"] <= level_factor(0.95) * c[kind])) for c in checks]
        out[kind] = {
            "median_sigma_m": float(np.median(sigma)),
            **{f"within_{level}": float(np.mean(shift <= level_factor(level) * sigma)) for level in (0.5, 0.95)},
            "within_0.95_range_over_calibrations": [min(per_calibration), max(per_calibration)],
        }
    return out


def interval(errors: np.ndarray, groups: np.ndarray, stat) -> tuple[float, float]:
    codes, inverse = np.unique(groups, return_inverse=True)
    rows_of = [np.flatnonzero(inverse == k) for k in range(codes.size)]
    rng = np.random.default_rng(0)
    values = [stat(errors[np.concatenate([rows_of[k] for k in rng.integers(0, codes.size, codes.size)])]) for _ in range(N_BOOT)]
    return float(np.quantile(values, 0.025)), float(np.quantile(values, 0.975))


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["frozen_lake", "forest"])
    parser.add_argument("--arrays", type=int, default=3)
    parser.add_argument("--spots", nargs="+", type=int, default=[5, 10])
    parser.add_argument("--n-positions", type=int, default=60)
    parser.add_argument("--designs", nargs="+", choices=["random", "planned"], default=["random", "planned"])
    parser.add_argument("--signals", nargs="+", choices=list(SIGNALS), default=list(SIGNALS))
    parser.add_argument("--field", choices=list(RENDERERS), default="image_source")
    opts = parser.parse_args()
    raw: dict[str, dict] = {}
    lines = [
        f"# Field calibration: playbacks at known spots recover the array ({RENDERERS[opts.field]})",
        "",
        f"`python experiments/field_calibration.py --sites {' '.join(opts.sites)} --arrays {opts.arrays} --spots "
        f"{' '.join(map(str, opts.spots))} --n-positions {opts.n_positions} --designs {' '.join(opts.designs)} "
        f"--signals {' '.join(opts.signals)} --field {opts.field}`. {RENDERERS[opts.field]}, mics 2 m off "
        "per axis (σ), clocks within ±1 ms, thermometer 3 °C high; playbacks of bird calls or of the 1–8 kHz sweep; solver (consistent set) errors of calls at "
        f"{opts.n_positions} positions × 3 per array, pooled over {opts.arrays} arrays; failures infinite; 95 % position-bootstrap intervals.",
        "",
        "| site | array as | p50 (m) (95 % CI) | p95 (m) (95 % CI) | > 5 m % | p50 ÷ true | p95 ÷ true | p95 ÷ uncalibrated |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for site in opts.sites:
        calls = [
            f"+site={site}",
            "protocol=field_eval",
            f"field={opts.field}",
            f"field.n_positions={opts.n_positions}",
            "field.events_per_position=3",
            *SMALL_TRAINING,
        ]
        pooled: dict[str, list[np.ndarray]] = {}
        groups_all: list[np.ndarray] = []
        recovered: list[dict] = []
        allowance: dict[str, list[dict]] = {}
        for a in range(opts.arrays):
            seed = 100 + a
            array = [f"field.array_seed={seed}", f"field.seed={2000 + a}"]
            truth_err, groups, truth_events = solver_errors([*calls, *array])
            groups_all.append(groups + 10**6 * a)
            pooled.setdefault("true array", []).append(truth_err)
            pooled.setdefault("stated (uncalibrated)", []).append(solver_errors([*calls, *array, *IMPAIRED])[0])
            for signal, n_spots, design in ((s, n, d) for s in opts.signals for d in opts.designs for n in opts.spots):
                with tempfile.TemporaryDirectory() as tmp:
                    body = calibrate(site, seed, n_spots, design, Path(tmp) / "run", opts.field, signal=signal)
                    path = Path(tmp) / "run" / "calibration.json"
                    pooled.setdefault(f"calibrated from {SIGNALS[signal]}, {n_spots} {design} spots", []).append(
                        solver_errors([*calls, *array, *IMPAIRED, f"calibration={path}"])[0]
                    )
                    true_mics, true_clocks = true_array(site, seed)
                    # clocks are calibrated relative to mic 0's
                    clock_error = np.asarray(body["clock_offset_s"]) - body["clock_offset_s"][0] - (true_clocks - true_clocks[0])
                    allowance.setdefault(f"{n_spots} ({signal})", []).append(
                        allowance_check(path, site, true_mics, clock_error, truth_events)
                    )
                stated_mics = np.asarray(body["stated_mic_positions_m"])
                mic_errors = np.hypot(*(np.asarray(body["mic_positions_m"]) - true_mics)[:, :2].T)
                recovered.append(
                    {
                        "mic_errors_m": np.round(mic_errors, 4).tolist(),
                        "mic_error_stated_m": float(np.median(np.hypot(*(stated_mics - true_mics)[:, :2].T))),
                        "mic_error_calibrated_m": float(np.median(mic_errors)),
                        "array_seed": seed,
                        "n_spots": n_spots,
                        "design": design,
                        "signal": signal,
                        "temperature_offset_c": body["temperature_offset_c"],
                        "clock_error_us": np.round(1e6 * clock_error, 1).tolist(),
                        "mic_position_shift_m": body["mic_position_shift_m"],
                        "not_identified": body["not_identified"],
                        "held_out": body.get("held_out"),
                        # what the calibration says of its own mic positions (per axis): posterior, and jackknife over spots
                        "mic_position_sd_m": body["mic_position_sd_m"],
                        "jackknife_sd": body.get("jackknife_sd"),
                    }
                )
        groups = np.concatenate(groups_all)
        stats = {name: np.concatenate(v) for name, v in pooled.items()}
        base50, base95 = (np.quantile(stats["true array"], q) for q in (0.5, 0.95))
        unc95 = float(np.quantile(stats["stated (uncalibrated)"], 0.95))
        raw[site] = {
            "calibrations": recovered,
            "errors": {},
            "allowance": {n: allowance_summary(checks) for n, checks in allowance.items()},
        }
        for name, e in stats.items():
            s = error_summary(e)
            ci50, ci95 = interval(e, groups, np.median), interval(e, groups, lambda v: np.quantile(v, 0.95))
            raw[site]["errors"][name] = {**s, "p50_ci95": ci50, "p95_ci95": ci95}
            lines.append(
                f"| {site} | {name} | {fmt(s['p50'])} ({fmt(ci50[0])}–{fmt(ci50[1])}) | {fmt(s['p95'])} ({fmt(ci95[0])}–{fmt(ci95[1])}) | "
                f"{100 * share_gross(e):.1f} | {s['p50'] / base50:.2f} | {s['p95'] / base95:.2f} | {s['p95'] / unc95:.2f} |"
            )
    lines += [
        "",
        "Do the calibrations' own standard deviations hold? Each mic's 2-D error against 2 and 3 times its σ per axis, "
        "pooled over arrays and designs (a 2-D Gaussian exceeds them 13.5 % and 1.1 % of the time); a run carries the larger "
        "of the posterior and the jackknife σ into the radii:",
        "",
        "| site | playbacks | spots | mics | > 2 σ posterior | > 2 σ jackknife | > 2 σ larger | > 3 σ larger |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for site, r in raw.items():
        for signal, n_spots in ((s, n) for s in opts.signals for n in opts.spots):
            rows = [c for c in r["calibrations"] if c["n_spots"] == n_spots and c["signal"] == signal and c["jackknife_sd"]]
            if not rows:
                continue
            err = np.concatenate([c["mic_errors_m"] for c in rows])
            post = np.concatenate([c["mic_position_sd_m"] for c in rows])
            jack = np.concatenate([c["jackknife_sd"]["mic_position_sd_m"] for c in rows])
            larger = np.maximum(post, jack)
            lines.append(
                f"| {site} | {signal} | {n_spots} | {err.size} | {100 * np.mean(err > 2 * post):.0f} % | {100 * np.mean(err > 2 * jack):.0f} % | "
                f"{100 * np.mean(err > 2 * larger):.0f} % | {100 * np.mean(err > 3 * larger):.0f} % |"
            )
    lines += [
        "",
        "Does the input allowance a run carries from the calibration hold what the calibration's remaining errors do to a fix? "
        "Per call, the exact shift of the true array's least-squares fix solved with the calibrated thermometer, clocks and "
        "mics (and with the thermometer's error alone: the calibrated reading against the air the renderer propagated in; "
        "its spread over the calls, and the playbacks' estimate of it that the allowance carries, medians over calibrations), "
        "against the allowance radius at 0.5 and 0.95 (σ per axis × 1.18 and × 2.45), with the calibration's covariance "
        "(what a run carries) and with its standard deviations as independent errors (before); calls pooled over arrays and "
        "designs, the range over calibrations in brackets:",
        "",
        "| site | spots | calibrations | calls | median shift (m) | from the thermometer alone (m) | thermometer error (°C) "
        "| its SD over calls (°C): true | estimated "
        "| covariance: median σ (m) | ≤ 0.5 radius | ≤ 0.95 radius | independent: median σ (m) | ≤ 0.5 radius | ≤ 0.95 radius |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for site, r in raw.items():
        for n_spots, a in r["allowance"].items():
            cells = []
            for kind in ("correlated", "independent"):
                k = a[kind]
                low, high = k["within_0.95_range_over_calibrations"]
                cells.append(f"{k['median_sigma_m']:.3f} | {k['within_0.5']:.2f} | {k['within_0.95']:.2f} ({low:.2f}–{high:.2f})")
            low, high = a["thermometer_error_c_range"]
            lines.append(
                f"| {site} | {n_spots} | {a['n_calibrations']} | {a['n_calls']} | {a['median_shift_m']:.3f} | "
                f"{a['median_thermometer_shift_m']:.3f} | {low:+.2f} to {high:+.2f} | {np.median(a['call_spread_c_true']):.2f} | "
                f"{np.median(a['call_spread_c_estimated']):.2f} | " + " | ".join(cells) + " |"
            )
    lines += ["", "What each calibration said it could not determine (per site, array and number of spots):", ""]
    for site, r in raw.items():
        for c in r["calibrations"]:
            held = c["held_out"]
            held_text = (
                f"held-out playbacks p50 {fmt(held['stated']['p50_m'])} → {fmt(held['calibrated']['p50_m'])} m"
                if held
                else "no held-out measure"
            )
            jackknife = c["jackknife_sd"]["mic_position_sd_m"] if c["jackknife_sd"] else [float("nan")]
            lines.append(
                f"- {site}, array {c['array_seed']}, {c['n_spots']} {c['design']} spots, {c['signal']}: median mic error {c['mic_error_stated_m']:.2f} m as stated → "
                f"{c['mic_error_calibrated_m']:.2f} m calibrated (median σ per axis: posterior {np.median(c['mic_position_sd_m']):.3f} m, "
                f"jackknife {np.median(jackknife):.3f} m); clocks off by up to {np.max(np.abs(c['clock_error_us'])):.0f} µs "
                f"(median {np.median(np.abs(c['clock_error_us'][1:])):.0f} µs); thermometer offset {c['temperature_offset_c']:+.2f} °C "
                f"(truth −3); not identified: {c['not_identified'] or 'nothing'}; {held_text}"
            )
    name = "field_calibration" if opts.field == "image_source" else f"field_calibration_{opts.field}"
    write_results(name, {"machine": machine(), "sites": raw}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
