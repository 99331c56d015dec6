"""Behavioural checks of plugins, one generator per contract (in the spirit of scikit-learn's ``check_estimator``).

``plugin_checks`` yields ``(group, option, check name, check)`` for every YAML option of every
plugin group under ``conf/``; each check builds the option as a run would and tests what it
*does*: a simulator's output does not depend on chunking, a feature set produces exactly the
columns its catalog names, a solver is exact on a noise-free scene, a gate only ever returns one
of its two inputs and learns on a copy, conformal radii grow with the level and cover on
exchangeable data, learned models survive ``clone()``. A new plugin is checked the moment its
YAML exists. A check raises ``AssertionError`` naming the plugin and what it got wrong, or
``CheckSkipped`` when it cannot run here (e.g. model weights are missing).

The checks use small, fast scenes on the embedded frozen-lake site (3 mics) and, where the
number of mics matters, the forest site (6 mics).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pandas as pd
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig
from sklearn.base import clone

from acoustlab.core import columns as col
from acoustlab.core.contracts import GateDecision, SolverInputs, declared, hook
from acoustlab.core.errors import ConfigError
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.run.registry import CONF_DIR, build, build_feature_sets, build_scorers, group_options
from acoustlab.stages.sites import site_from_config
from acoustlab.toolkit.event_physics import assumed_source_height_m
from acoustlab.toolkit.geometry import sample_in_expanded_hull
from acoustlab.toolkit.physics import speed_of_sound_m_s

Check = Callable[[], None]


class CheckSkipped(Exception):
    """A check that cannot run on this machine (the reason is the message)."""


def compose_config(overrides: list[str]) -> DictConfig:
    """The composed acoustlab config for ``overrides`` (as the command line would compose it)."""
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose(config_name="config", overrides=overrides)
    finally:
        GlobalHydra.instance().clear()


def _site_and_node(group: str, option: str, site: str = "frozen_lake", extra: tuple[str, ...] = ()) -> tuple[Site, DictConfig]:
    cfg = compose_config([f"+site={site}", f"{group}={option}", "paths.outputs_dir=/tmp/acoustlab-plugin-checks", *extra])
    return site_from_config(cfg.site), cfg


def _noise_free_batch(site_name: str = "frozen_lake", n_events: int = 4) -> tuple[Site, RecordingBatch]:
    """A small free-field batch with negligible noise (for feature checks)."""
    site, cfg = _site_and_node("simulator", "free_field", site_name, ("site.noise.snr_db=[60,60]", "simulator.duration_s=0.5"))
    sim = build(cfg.simulator, "simulator")
    return site, sim.simulate(site, np.arange(n_events), np.arange(n_events) // 2, seed=11)


def _exact_scene(site: Site, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Sources in the site's source region at its mid height: (E, 3) positions, (E, M) TDOAs to mic 0, (E, M) levels, c."""
    rng = np.random.default_rng(seed)
    xy = sample_in_expanded_hull(rng, site.mic_positions_m, site.hull_expansion, n)
    height = assumed_source_height_m(site)
    src = np.column_stack([xy, np.full(n, height)])
    dist = np.sqrt(((src[:, None, :] - site.mic_positions_m[None]) ** 2).sum(-1))
    c = float(speed_of_sound_m_s(np.mean(site.temperature_range_c), np.mean(site.relative_humidity_range_pct)))
    tdoa = (dist - dist[:, :1]) / c
    levels = 80.0 - 20 * np.log10(dist)
    return src, tdoa, levels, c


# --- simulators ---------------------------------------------------------------------------


def check_simulator_chunking(option: str) -> None:
    """Events rendered together or in separate chunks are identical, bit for bit."""
    site, cfg = _site_and_node("simulator", option)
    sim = build(cfg.simulator, "simulator")
    sim.validate(site)
    ids, positions = np.arange(4), np.array([0, 0, 1, 1])
    whole = sim.simulate(site, ids, positions, seed=5)
    parts = [sim.simulate(site, ids[k : k + 2], positions[k : k + 2], seed=5) for k in (0, 2)]
    audio = np.concatenate([p.audio for p in parts])
    assert np.array_equal(whole.audio, audio), f"simulator={option}: audio depends on how events are chunked"
    events = pd.concat([p.events for p in parts], ignore_index=True)
    pd.testing.assert_frame_equal(whole.events.reset_index(drop=True), events, check_exact=True, obj=f"simulator={option} events")
    assert whole.audio.shape[:2] == (4, site.n_mics), f"simulator={option}: audio shape {whole.audio.shape}"


# --- feature sets --------------------------------------------------------------------------


def check_feature_catalog(option: str) -> None:
    """Every group's ``transform`` returns exactly its catalog's columns, in order, one float row per event."""
    for site_name in ("frozen_lake", "forest"):
        site, batch = _noise_free_batch(site_name)
        cfg = compose_config([f"+site={site_name}", f"features={option}"])
        for name, fs in build_feature_sets(cfg.features).items():
            assert fs.group == name, f"features={option}: group {name!r} reports group {fs.group!r}"
            names = [row[0] for row in fs.catalog(site)]
            table = fs.transform(batch, site)
            assert list(table.columns) == names, f"features={option}, group {name} on {site_name}: columns differ from the catalog"
            assert len(table) == batch.n_events, f"features={option}, group {name}: {len(table)} rows for {batch.n_events} events"
            assert all(col.group_of(c) == name for c in names), f"features={option}, group {name}: a column is not named {name}__…"
            assert all(np.issubdtype(t, np.floating) for t in table.dtypes), f"features={option}, group {name}: non-float columns"


# --- solvers -------------------------------------------------------------------------------


def check_solver_exact(option: str) -> None:
    """Noise-free TDOAs (with consistent levels and candidates) are reproduced exactly.

    With 6 mics (forest) the position is unique, so the solver must return it within 1 mm. With 3
    mics (frozen lake) two positions can fit the same TDOAs; the solver must return one that
    reproduces them within 1 ns.
    """
    for site_name in ("frozen_lake", "forest"):
        site, cfg = _site_and_node("solver", option, site_name)
        solver = build(cfg.solver, "solver")
        assert "tdoa" in solver.required_feature_groups, f"solver={option} must declare the 'tdoa' feature group"
        src, tdoa, levels, c = _exact_scene(site, 200)
        pair_lags = np.stack([tdoa[:, j] - tdoa[:, i] for i, j in site.mic_pairs], axis=1)[..., None]
        height = assumed_source_height_m(site)
        inputs = SolverInputs(
            site.mic_positions_m, tdoa, c, received_level_db=levels, pair_lag_candidates_s=pair_lags, source_height_m=height
        )
        result = solver.solve(inputs)
        assert result.position_m.shape == (len(src), 2), f"solver={option}: position shape {result.position_m.shape}"
        if site.n_mics > 3:
            error = np.linalg.norm(result.position_m - src[:, :2], axis=1)
            assert np.all(error < 1e-3), f"solver={option} on {site_name}: max error {np.nanmax(error):.3g} m on noise-free TDOAs"
        else:
            fix = np.column_stack([result.position_m, np.full(len(src), height)])
            dist = np.sqrt(((fix[:, None, :] - site.mic_positions_m[None]) ** 2).sum(-1))
            mismatch = np.abs((dist - dist[:, :1]) / c - tdoa)
            assert np.all(mismatch < 1e-9), (
                f"solver={option} on {site_name}: fixes miss noise-free TDOAs by up to {np.nanmax(mismatch):.3g} s"
            )


# --- point and error models ----------------------------------------------------------------


def _weights_or_skip(model: Any, what: str) -> None:
    preflight = hook(model, "preflight")  # the optional hook of models that need weights
    if preflight is not None:
        try:
            preflight()
        except ConfigError as exc:
            raise CheckSkipped(f"{what}: {str(exc).split('.')[0]}") from None


def check_model_clone_and_fit(group: str, option: str) -> None:
    """``clone()`` gives an equal, unfitted copy; fitting it leaves the original unfitted; predictions have one value per row."""
    _, cfg = _site_and_node(group, option)
    model = build(cfg[group], group)
    copy = clone(model)
    assert repr(copy) == repr(model), f"{group}={option}: clone() changed the parameters"
    _weights_or_skip(model, f"{group}={option}")
    rng = np.random.default_rng(0)
    x = pd.DataFrame(rng.normal(size=(80, 4)), columns=[col.feature("g", f"f{k}") for k in range(3)] + [col.SOLVER_GDOP])
    x[col.SOLVER_GDOP] = np.abs(x[col.SOLVER_GDOP]) + 1.0
    y = np.abs(rng.normal(size=80)) + 0.1
    fitted = copy.fit(x, y)
    predicted = np.asarray(fitted.predict(x))
    assert predicted.shape == (80,), f"{group}={option}: predict gave shape {predicted.shape} for 80 rows"
    assert np.all(np.isfinite(predicted)), f"{group}={option}: non-finite predictions"
    if group == "error_model":
        assert np.all(predicted > 0), f"error_model={option}: predicted error scales must be positive"
    fitted_attrs = [a for a in vars(model) if a.endswith("_") and not a.startswith("_")]
    assert not fitted_attrs, f"{group}={option}: fitting a clone set {fitted_attrs} on the original"


# --- gates ---------------------------------------------------------------------------------


def _gate_scene(site: Site, n: int = 300) -> tuple[np.ndarray, np.ndarray, pd.DataFrame, np.ndarray]:
    src, _, levels, _ = _exact_scene(site, n, seed=1)
    solver = src[:, :2].copy()
    rng = np.random.default_rng(2)
    gross = rng.random(n) < 0.2
    solver[gross] += rng.normal(0, 400, size=(gross.sum(), 2))  # diverged fixes, far outside the box
    solver[:3] = np.nan  # no fix at all
    model = src[:, :2] + rng.normal(0, 1.0, size=(n, 2))
    features = pd.DataFrame(levels, columns=[col.level_db(m) for m in range(site.n_mics)])
    features[col.SOLVER_SOURCE_HEIGHT] = src[:, 2]
    return solver, model, features, src


def check_gate(option: str) -> None:
    """A gate returns, row by row, either the solver's or the model's estimate; it fills every missing fix;
    it learns on a copy (the configured gate stays unfitted); its diagnostics are JSON."""
    site, cfg = _site_and_node("gate", option)
    configured = build(cfg.gate, "gate")
    assert all(isinstance(g, str) for g in configured.required_feature_groups), f"gate={option}: required_feature_groups must be names"
    solver, model, features, src = _gate_scene(site)
    before = json.dumps(configured.diagnostics(), sort_keys=True, default=str)
    groups = np.arange(len(solver)) // 5  # five events per source position
    gate = clone(configured, safe=False).fit(solver, model, features, site, src, groups=groups)
    assert gate is not None, f"gate={option}: fit must return the gate"
    assert json.dumps(configured.diagnostics(), sort_keys=True, default=str) == before, (
        f"gate={option}: fitting a copy changed the original"
    )
    decision = gate.decide(solver, model, features, site)
    assert isinstance(decision, GateDecision), f"gate={option}: decide must return a GateDecision"
    chosen = np.where(decision.substituted[:, None], model, solver)
    assert np.array_equal(decision.position_m, chosen, equal_nan=True), f"gate={option}: position is not the estimate 'substituted' names"
    missing = ~np.isfinite(solver).all(axis=1)
    assert decision.substituted[missing].all(), f"gate={option}: kept a missing solver fix"
    json.dumps(gate.diagnostics())  # raises TypeError when not JSON-serialisable


# --- conformal scorers ---------------------------------------------------------------------


def check_conformal(option: str) -> None:
    """Radii are finite and non-decreasing in the level; on exchangeable data they cover at least the nominal level."""
    _, cfg = _site_and_node("conformal", option)
    levels = list(cfg.conformal.levels)
    rng = np.random.default_rng(3)
    n = 4000
    gdop = rng.uniform(1.0, 5.0, size=2 * n)
    predicted = rng.uniform(0.5, 3.0, size=2 * n)
    error = predicted * gdop * rng.exponential(1.0, size=2 * n)  # heteroscedastic, exchangeable
    positions = np.arange(2 * n) // 4  # four events per source position (for scorers calibrated over positions)
    hull = rng.uniform(-0.2, 1.5, size=2 * n)  # estimates inside, near and far from the hull (scorers binned by region)
    for name, scorer in build_scorers(cfg.conformal).items():
        if declared(scorer, "needs_quantiles"):  # CQR: a quantile model fitted on a third, independent sample
            x = pd.DataFrame({"predicted": predicted, "gdop": gdop})
            extra_gdop, extra_predicted = rng.uniform(1.0, 5.0, size=n), rng.uniform(0.5, 3.0, size=n)
            x_extra = pd.DataFrame({"predicted": extra_predicted, "gdop": extra_gdop})
            quantiles = scorer.fit_predict_quantiles(x_extra, extra_predicted * extra_gdop * rng.exponential(1.0, size=n), x, levels)
            fitted = clone(scorer, safe=False).fit(
                error[:n], predicted[:n], gdop[:n], levels, quantiles=quantiles[:n], groups=positions[:n]
            )
            radii = fitted.radius(predicted[n:], gdop[n:], quantiles=quantiles[n:])
        else:
            fit_region, test_region = (
                ({"hull_distance": hull[:n]}, {"hull_distance": hull[n:]}) if declared(scorer, "needs_hull_distance") else ({}, {})
            )
            fitted = clone(scorer, safe=False).fit(error[:n], predicted[:n], gdop[:n], levels, groups=positions[:n], **fit_region)
            radii = fitted.radius(predicted[n:], gdop[n:], **test_region)
        assert radii.shape == (n, len(levels)), f"conformal={option}, {name}: radius shape {radii.shape}"
        assert np.all(np.isfinite(radii)), f"conformal={option}, {name}: non-finite radii"
        assert np.all(np.diff(radii, axis=1) >= 0), f"conformal={option}, {name}: radii shrink as the level grows"
        for k, level in enumerate(levels):
            covered = float(np.mean(error[n:] <= radii[:, k]))
            tolerance = 3 * np.sqrt(level * (1 - level) / n)  # binomial noise of the test half
            assert covered >= level - tolerance, f"conformal={option}, {name}: coverage {covered:.3f} at nominal {level}"


#: The check of each plugin group (groups without behavioural checks are covered by their own tests).
CHECKS: dict[str, Callable[..., None]] = {
    "simulator": check_simulator_chunking,
    "features": check_feature_catalog,
    "solver": check_solver_exact,
    "model": lambda option: check_model_clone_and_fit("model", option),
    "error_model": lambda option: check_model_clone_and_fit("error_model", option),
    "gate": check_gate,
    "conformal": check_conformal,
}


def plugin_checks() -> Iterator[tuple[str, str, str, Check]]:
    """``(group, option, check name, check)`` for every registered option of every checked group."""
    for group, check in CHECKS.items():
        name = getattr(check, "__name__", "check")
        for option in group_options(group):
            yield group, option, name if name != "<lambda>" else "check_model_clone_and_fit", lambda c=check, o=option: c(o)
