"""Committed benchmark results name what made them, none was made by a different version of its script, and the benchmarks' own checks hold."""

import functools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"


def _benchmark_module(name: str):
    """A module of ``benchmarks/`` (they live beside the package, not in it)."""
    import importlib

    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(REPO / "benchmarks"))


def _check_results():
    """The benchmarks' staleness check."""
    return _benchmark_module("check_results")


def test_no_committed_result_was_made_by_another_version_of_its_script():
    proc = subprocess.run([sys.executable, "benchmarks/check_results.py", "--strict"], cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 0, "stale benchmark results:\n" + "\n".join(l for l in proc.stdout.splitlines() if "script changed" in l)


def test_results_name_their_commit_and_script():
    made_with = json.loads((RESULTS / "real_array.json").read_text())["provenance"]
    assert len(made_with["commit"]) == 40 and made_with["script"] == "benchmarks/bench_real_array.py"
    assert "Made with commit" in (RESULTS / "real_array.md").read_text()


def test_provenance_records_the_package_releases():
    """A result names the releases it was made with (two runs of one commit can differ where a release changed)."""
    import importlib.metadata

    made_with = _benchmark_module("common").provenance()
    assert made_with["packages"]["numpy"] == np.__version__ and made_with["packages"]["pandas"] == pd.__version__
    assert made_with["packages"]["scikit-learn"] == importlib.metadata.version("scikit-learn")
    assert "not-a-package" not in made_with["packages"]


def test_the_staleness_check_sees_a_changed_script(tmp_path, monkeypatch):
    check_results = _check_results()
    result = tmp_path / "x.json"
    result.write_text(json.dumps({"provenance": {"commit": "0" * 40, "script": "benchmarks/bench_real_array.py", "script_sha256": "f" * 64}}))
    assert check_results.status(result)[0] == "script changed"
    result.write_text(json.dumps({"value": 1}))
    assert check_results.status(result)[0] == "no provenance"


def test_a_docstring_or_comment_is_not_a_code_change():
    """The staleness check compares what code does: docstrings, comments and YAML formatting do not make a result stale."""
    check_results = _check_results()
    old = b'def f(x):\n    """Old words."""\n    return x + 1  # one\n'
    assert check_results.same_code(old, b'def f(x):\n    """New words, longer."""\n    # a comment\n    return x + 1\n', "m.py")
    assert not check_results.same_code(old, b'def f(x):\n    """Old words."""\n    return x + 2\n', "m.py")
    assert check_results.same_code(b"a: 1  # note\nb: [1, 2]\n", b"a: 1\nb:\n  - 1\n  - 2\n", "c.yaml")
    assert not check_results.same_code(b"a: 1\n", b"a: 2\n", "c.yaml")
    assert not check_results.same_code(b"x", b"y", "data.csv")


def test_what_plugins_import_is_a_dependency_of_every_result():
    """Plugins are built by name through Hydra, so a benchmark depends on the package modules they import
    (a change to the GCC toolkit once left results that compute features reading 'current')."""
    check_results = _check_results()
    deps = check_results.plugin_dependencies()
    assert {"acoustlab/toolkit/gcc_candidates.py", "acoustlab/toolkit/dsp.py", "acoustlab/toolkit/solve3d.py"} <= set(deps)
    assert all((REPO / d).is_file() for d in deps)


def test_identity_hashes_are_references_not_results():
    check_results = _check_results()
    for path in RESULTS.glob("identity_*.json"):
        assert check_results.status(path)[0] == "reference"


def test_gpu_only_results_say_so_and_name_their_command():
    """Results a lent GPU made cannot be re-run here: the check says so instead of a bare 'no provenance'."""
    check_results = _check_results()
    for name, command in check_results.GPU_ONLY.items():
        path = RESULTS / f"{name}.json"
        assert path.is_file(), name
        state, detail = check_results.status(path)
        if "provenance" not in json.loads(path.read_text()):
            assert state == "needs a GPU" and command in detail and "last written in" in detail


def _git(repo, *args: str) -> str:
    """Run git in a scratch repository; its output."""
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout.strip()


def _commit(repo, message: str) -> str:
    """Commit everything in a scratch repository; the new commit."""
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", message)
    return _git(repo, "rev-parse", "HEAD")


def test_a_file_added_since_a_result_is_not_a_change_but_an_edited_or_removed_one_is(tmp_path, monkeypatch):
    """A new module or config runs only where an existing file (or the script) names it, and that file's change is caught."""
    check_results = _check_results()

    git = functools.partial(_git, tmp_path)

    git("init", "-q")
    (tmp_path / "kept.py").write_text("X = 1\n")
    (tmp_path / "edited.py").write_text("Y = 1\n")
    (tmp_path / "removed.py").write_text("Z = 1\n")
    first = _commit(tmp_path, "first")
    (tmp_path / "added.yaml").write_text("lean: true\n")
    (tmp_path / "edited.py").write_text("Y = 2\n")
    (tmp_path / "removed.py").unlink()
    monkeypatch.setattr(check_results, "REPO", tmp_path)
    assert not check_results.changed_since(first, "added.yaml")
    assert not check_results.changed_since(first, "kept.py")
    assert check_results.changed_since(first, "edited.py")
    assert check_results.changed_since(first, "removed.py")


def test_a_change_shown_to_have_no_effect_is_waived_but_a_later_one_is_not(tmp_path, monkeypatch):
    """benchmarks/no_effect.yaml waives exactly the listed change of the listed files; anything beyond it still counts."""
    check_results = _check_results()

    git = functools.partial(_git, tmp_path)

    commit = functools.partial(_commit, tmp_path)

    git("init", "-q")
    (tmp_path / "gcc.py").write_text("def f(x):\n    return x\n")
    (tmp_path / "other.py").write_text("Y = 1\n")
    result_made = commit("the result's commit")
    (tmp_path / "gcc.py").write_text("def f(x, device='cpu'):\n    return x\n")
    (tmp_path / "other.py").write_text("Y = 2\n")
    after = commit("the change, shown to have no effect on gcc.py's callers")
    (tmp_path / "no_effect.yaml").write_text(f"- before: {result_made}\n  after: {after}\n  files: [gcc.py]\n  identity: [a, b]\n")
    monkeypatch.setattr(check_results, "REPO", tmp_path)
    monkeypatch.setattr(check_results, "NO_EFFECT", tmp_path / "no_effect.yaml")
    assert not check_results.changed_since(result_made, "gcc.py")
    assert check_results.changed_since(result_made, "other.py")  # changed in the same commit, but not listed
    (tmp_path / "gcc.py").write_text("def f(x, device='cpu', memory=4):\n    return x\n")
    assert check_results.changed_since(result_made, "gcc.py")  # a later change is a change
    later = commit("a second change, shown to have no effect either")
    check_results._no_effect_entries.cache_clear()
    (tmp_path / "no_effect.yaml").write_text(f"- before: {result_made}\n  after: {after}\n  files: [gcc.py]\n  identity: [a, b]\n"
                                             f"- before: {after}\n  after: {later}\n  files: [gcc.py]\n  identity: [c, d]\n")
    assert not check_results.changed_since(result_made, "gcc.py")  # the two listed changes chain
    assert not check_results.changed_since(after, "gcc.py")
    (tmp_path / "gcc.py").write_text("def f(x, device='cpu', memory=4):\n    return 2 * x\n")
    assert check_results.changed_since(result_made, "gcc.py") and check_results.changed_since(after, "gcc.py")


def test_a_faster_change_waives_answers_but_not_the_results_that_time_it(tmp_path, monkeypatch):
    """An entry's ``timed_by`` results are not waived: a change made to be faster re-runs what times it."""
    check_results = _check_results()

    git = functools.partial(_git, tmp_path)

    git("init", "-q")
    (tmp_path / "gcc.py").write_text("def f(x):\n    return x / 2\n")
    made = _commit(tmp_path, "result")
    (tmp_path / "gcc.py").write_text("def f(x):\n    return x * 0.5\n")
    _commit(tmp_path, "faster, same answers")
    (tmp_path / "no_effect.yaml").write_text(f"- before: {made}\n  after: {git('rev-parse', 'HEAD')}\n  files: [gcc.py]\n"
                                             "  identity: [a, b]\n  timed_by: [gcc_speed]\n")
    monkeypatch.setattr(check_results, "REPO", tmp_path)
    monkeypatch.setattr(check_results, "NO_EFFECT", tmp_path / "no_effect.yaml")
    check_results._no_effect_entries.cache_clear()
    assert not check_results.changed_since(made, "gcc.py", "accuracy")  # its answers are the same
    assert check_results.changed_since(made, "gcc.py", "gcc_speed")  # its timings are not
    check_results._no_effect_entries.cache_clear()


def test_every_waived_change_names_committed_identity_evidence():
    """Each no_effect.yaml entry names two committed bench_identity measurements (before and after the change)
    whose jobs gave the same predictions and metrics, hash for hash."""
    import yaml

    entries = yaml.safe_load((REPO / "benchmarks" / "no_effect.yaml").read_text()) or []
    assert entries
    for entry in entries:
        assert {"before", "after", "files", "identity", "why"} <= set(entry)
        machine_key = _benchmark_module("bench_identity").MACHINE_KEY  # where it was measured, not a job
        before, after = ({job: v for job, v in json.loads((RESULTS / f"identity_{label}.json").read_text()).items() if job != machine_key}
                         for label in entry["identity"])
        assert set(before) == set(after) and len(before) >= 3
        for job in before:
            assert before[job]["predictions_sha256"] == after[job]["predictions_sha256"], job
            assert before[job]["metrics_sha256"] == after[job]["metrics_sha256"], job
        assert all((REPO / f).is_file() for f in entry["files"])


def test_a_benchmark_helper_module_the_script_imports_is_a_dependency():
    check_results = _check_results()
    bench = REPO / "benchmarks"
    deps = check_results.dependencies(bench / "bench_lean_features.py")  # imports bench_season, which imports common
    assert {bench / "bench_season.py", bench / "common.py"} <= deps
    assert REPO / "acoustlab" / "season" / "synthetic.py" in deps  # what the helper imports, followed
    assert bench / "bench_lean_features.py" not in deps


def test_an_event_is_matched_to_its_own_call_even_when_its_source_is_next_to_a_recorder():
    bench = _benchmark_module("bench_season")
    mics = np.array([[0.0, 0.0, 1.5], [60.0, 0.0, 1.5], [30.0, 50.0, 1.5]])
    c, margin = 330.0, 0.17
    # the second call is 1 m from recorder 0 (3 ms of travel, less than the selections' 0.02-s pad)
    truth = pd.DataFrame({"emission_s": [10.0, 12.3, 14.6], "x_m": [30.0, 1.0, 45.0], "y_m": [20.0, 0.0, 10.0], "z_m": [1.5, 1.5, 1.5]})
    travel = np.sqrt(((truth[["x_m", "y_m", "z_m"]].to_numpy()[:, None] - mics[None]) ** 2).sum(-1)).min(1) / c
    first_arrival = truth["emission_s"].to_numpy() + travel
    events = pd.DataFrame({"start_s": first_arrival - bench.RAVEN_PAD_S - margin})
    radii = {f"radius_gdop_scaled_{level}_m": 0.5 for level in ("0.5", "0.8", "0.95")}
    positions = pd.DataFrame({"x_m": truth["x_m"] + 0.1, "y_m": truth["y_m"], "solver_x_m": truth["x_m"], "solver_y_m": truth["y_m"],
                              "placed": True, **radii})

    out = bench.truth_errors(positions, events, truth, margin)

    assert out["n_matched_calls"] == 3
    assert out["method"]["share_over_5m"] == 0.0 and out["solver"]["share_over_5m"] == 0.0
    assert out["coverage_gdop_scaled_0.95"] == 1.0


def test_the_process_benchmark_summarises_each_process_by_its_median_round():
    bench = _benchmark_module("bench_solver_processes")
    label = next(label for label in bench.SOLVERS if bench.GOALS[label] == 100)
    # three processes: the middle round of each is its figure (one slow round must not move it)
    processes = [{name: {"ratio": [90.0, 110.0, 400.0], "us": [5.0, 4.0, 1.0], "scipy_us": [450.0, 440.0, 400.0]}
                  for name in bench.SOLVERS} for _ in range(2)]
    processes.append({name: {"ratio": [60.0, 70.0, 80.0], "us": [7.0, 6.0, 5.0], "scipy_us": [420.0, 420.0, 420.0]} for name in bench.SOLVERS})

    summary = bench.summarise(processes)[label]

    assert summary["per_process"]["ratio"] == [110.0, 110.0, 70.0]
    assert (summary["ratio_median"], summary["ratio_min"], summary["ratio_max"]) == (110.0, 70.0, 110.0)
    assert summary["processes_meeting_goal"] == 2 and summary["goal"] == 100
    assert summary["us_median"] == 4.0 and summary["scipy_us_min"] == 420.0


def test_the_process_benchmark_times_the_code_it_imports():
    deps = _check_results().dependencies(REPO / "benchmarks" / "bench_solver_processes.py")
    assert REPO / "benchmarks" / "bench_solver_speed.py" in deps  # its detections, SciPy reference and goals
    assert REPO / "plugins" / "solvers" / "consistent_select.py" in deps


def test_an_identity_measurement_says_where_its_machine_differs_from_the_reference():
    bench = _benchmark_module("bench_identity")
    here = bench.machine_record()
    assert here["cpu"] and here["releases"]["numpy"] == np.__version__
    elsewhere = {**here, "cpu": "another CPU", "releases": {**here["releases"], "numpy": "0.0"}}
    assert bench.machine_differences(here, here) == []
    assert bench.machine_differences(here, elsewhere) == [f"cpu: another CPU → {here['cpu']}", f"numpy 0.0 → {np.__version__}"]
    assert bench.machine_differences(here, None) == ["unknown"]  # references made before machines were recorded
