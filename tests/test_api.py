"""acoustlab from Python: the functions a notebook calls give the command line's answers as tables."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from acoustlab.api import localize, metrics, overrides_from, place, solve
from acoustlab.core.errors import ConfigError


def test_settings_become_the_command_line_s_overrides():
    given = {"field": {"audio_dir": "my audio/it's"}, "solver": {"dimensions": 3}, "features": {"gcc": {"band_hz": [6000, 10500.5]}}}
    assert overrides_from(given) == [
        "field.audio_dir='my audio/it\\'s'",
        "solver.dimensions=3",
        "features.gcc.band_hz=[6000,10500.5]",
    ]
    assert overrides_from({"a": None, "b": False}) == ["a=null", "b=false"]
    with pytest.raises(ConfigError, match="a setting must be a number, string"):
        overrides_from({"a": {1, 2}})


def test_solve_places_events_from_time_differences_with_their_diagnostics():
    mics = np.array([[0.0, 0.0, 1.0], [50.0, 0.0, 3.0], [0.0, 50.0, 2.0], [50.0, 50.0, 6.0], [25.0, 25.0, 10.0]])
    sources = np.array([[20.0, 30.0, 4.0], [12.0, 30.0, 8.0]])
    arrival = np.linalg.norm(mics[None] - sources[:, None], axis=-1) / 343.0
    table = solve(mics, arrival - arrival[:, :1], dimensions=3)
    np.testing.assert_allclose(table[["x_m", "y_m", "z_m"]].to_numpy(), sources, atol=1e-6)
    assert {"residual_m", "converged", "gdop", "height_gdop", "n_roots"} <= set(table.columns)
    flat = solve(mics[:, :2], (arrival - arrival[:, :1])[0], source_height_m=0.0, solver="least_squares")
    assert len(flat) == 1 and flat["z_m"].iloc[0] == 0.0
    with pytest.raises(ConfigError, match="hyperbolic or least_squares"):
        solve(mics, arrival, solver="consistent_set")


@pytest.mark.parametrize(
    "arguments, message",
    [
        ({"speed_of_sound_m_s": 0.0}, "speed_of_sound_m_s must lie in 200–450 m/s"),
        ({"speed_of_sound_m_s": -343.0}, "speed_of_sound_m_s must lie in 200–450 m/s"),
        ({"speed_of_sound_m_s": np.full(5, 343.0)}, "speed_of_sound_m_s must be one value or 2 \\(one per event\\); got shape \\(5,\\)"),
        ({"tdoa_s": np.zeros((2, 4))}, "tdoa_s must be \\(E, 5\\)"),
        ({"mic_positions_m": [[0.0, 0.0], [1.0, float("nan")], [0.0, 1.0]]}, "mic_positions_m must be .* finite"),
        ({"mic_positions_m": "mics.csv"}, "mic_positions_m must be numbers"),
    ],
)
def test_solve_names_the_argument_it_cannot_use(arguments, message):
    mics = np.array([[0.0, 0.0, 1.0], [50.0, 0.0, 3.0], [0.0, 50.0, 2.0], [50.0, 50.0, 6.0], [25.0, 25.0, 10.0]])
    given = {"mic_positions_m": mics, "tdoa_s": np.zeros((2, 5)), **arguments}
    with pytest.raises(ConfigError, match=message):
        solve(**given)


@pytest.mark.parametrize(
    "arguments, message",
    [
        ({"n_spots": "5"}, "n_spots must be a whole number >= 3; got '5'"),
        ({"n_spots": 2}, "n_spots must be a whole number >= 3"),
        ({"n_spots": 5, "candidates_xy_m": np.zeros((4, 3))}, "candidates_xy_m must be a \\(C, 2\\) array"),
        ({"n_spots": 5, "source_height_m": "1.5"}, "source_height_m must be a finite number"),
    ],
)
def test_plan_playbacks_names_the_argument_it_cannot_use(arguments, message):
    from acoustlab.api import plan_playbacks

    with pytest.raises(ConfigError, match=message):
        plan_playbacks("frozen_lake", **arguments)


@pytest.mark.slow
def test_localize_from_python_equals_the_command_line_s_positions(tmp_path, compose_cfg):
    from acoustlab.run.app import run_experiment

    quick = ["+experiment=smoke", "tracking=none", "plots=false", "model.n_estimators=20", f"paths.outputs_dir={tmp_path / 'outputs'}"]
    table = localize(
        "loca2021", overrides=quick, run_dir=tmp_path / "api", features={"gcc": {"band_hz": [6000, 10500]}}, solver={"dimensions": 3}
    )
    assert len(table) == 1 and table["source"].iloc[0] == "solver" and np.isfinite(table["radius_fixed_0.95_m"]).all()
    assert metrics(tmp_path / "api")["localization"]["n_detections"] == 1
    cfg = compose_cfg(
        ["+site=loca2021", "protocol=localize", "field=recordings", *quick, "features.gcc.band_hz=[6000,10500]", "solver.dimensions=3"]
    )
    run_experiment(cfg, tmp_path / "cli")
    pd.testing.assert_frame_equal(table, pd.read_parquet(tmp_path / "cli" / "positions.parquet"))


@pytest.mark.slow
def test_import_acoustlab_gives_the_notebook_functions_and_calibrate_feeds_localize(tmp_path):
    import acoustlab
    import acoustlab.season  # the subpackage keeps its name; its function is acoustlab.api.season
    from acoustlab import api

    assert all(getattr(acoustlab, name) is getattr(api, name) for name in ("localize", "calibrate", "solve", "metrics", "load_site"))
    site = acoustlab.load_site("recordings", field={"mics_csv": "acoustlab://examples/loca2021/mics.csv"})
    assert site.n_mics == 6 and acoustlab.load_site("forest").n_mics == 6 and len(acoustlab.load_site("frozen_lake").mic_pairs) == 3
    with pytest.raises(AttributeError, match="no attribute 'locate'"):
        acoustlab.locate  # noqa: B018
    cal = acoustlab.calibrate(
        "forest",
        run_dir=tmp_path / "cal",
        overrides=[f"paths.outputs_dir={tmp_path}", "tracking=none", "plots=false", "field=image_source"],
        field={"n_positions": 6, "events_per_position": 2, "outside_share": 0, "mic_position_error_m": 2.0, "clock_offset_max_s": 0.001},
    )
    assert Path(cal["path"]).is_file() and len(cal["mic_positions_m"]) == 6 and cal["n_spots"] == 6


@pytest.mark.slow
def test_the_fitted_method_localize_returns_places_more_recordings_as_one_run_would(tmp_path, compose_cfg):
    """``localize(..., return_method=True)``: the fitted method places another events table of the same array without fitting
    again, row for row what the first run gave those detections; only ``field`` settings may change."""
    from tests.test_localize import simulated_folder

    _, folder_overrides = simulated_folder(compose_cfg, tmp_path / "recordings", 6, rotation_deg=30.0)  # map coordinates too
    quick = ["+experiment=smoke", "tracking=none", "plots=false", "model.n_estimators=20", f"paths.outputs_dir={tmp_path / 'outputs'}"]
    table, method = localize("frozen_lake", overrides=[*folder_overrides[1:], *quick], run_dir=tmp_path / "api", return_method=True)
    events = pd.read_csv(tmp_path / "recordings" / "events.csv")
    events.iloc[2:].to_csv(tmp_path / "recordings" / "later.csv", index=False)
    again = place(method, field={"events_csv": tmp_path / "recordings" / "later.csv"})
    assert {"easting_m", "northing_m", "crs"} <= set(again.columns)
    pd.testing.assert_frame_equal(again, table.iloc[2:].reset_index(drop=True))
    with pytest.raises(ConfigError, match="only field.. settings may change; got 'solver.dimensions=3'"):
        place(method, solver={"dimensions": 3})


def test_the_api_shows_progress_on_stderr_unless_told_not_to(monkeypatch, capsys):
    """A notebook configures no logging: ``localize`` and the other calls show the run's INFO lines as the command line
    does; ``verbose=False`` keeps warnings only; a caller's own logging setup is left alone."""
    import logging

    from acoustlab.api import progress_shown

    root = logging.getLogger()
    monkeypatch.setattr(root, "handlers", [])  # as in a fresh notebook (pytest's capture handler set aside)
    stage = logging.getLogger("acoustlab.stages.dataset")
    with progress_shown():
        stage.info("simulating 1100 events")
    with progress_shown(verbose=False):
        stage.info("not shown")
        stage.warning("a warning still is")
    err = capsys.readouterr().err
    assert "INFO acoustlab.stages.dataset: simulating 1100 events" in err
    assert "not shown" not in err and "a warning still is" in err
    assert not logging.getLogger("acoustlab").handlers and logging.getLogger("acoustlab").level == logging.NOTSET  # restored
    mine = logging.StreamHandler()
    monkeypatch.setattr(root, "handlers", [mine])
    with progress_shown():
        assert not logging.getLogger("acoustlab").handlers  # the caller's setup is theirs
