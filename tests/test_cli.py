"""The command line as a user runs it (subprocesses)."""

import json

import pytest

from acoustlab.run.registry import ALL_GROUPS, group_options


@pytest.mark.slow
def test_help_lists_every_option_of_every_group(run_cli):
    proc = run_cli("--help")
    assert proc.returncode == 0, proc.stderr
    section = proc.stdout.split("== Configuration groups ==", 1)[1].split("== Config ==", 1)[0]
    listed: dict[str, list[str]] = {}
    for row in section.splitlines():
        if row and not row.startswith(" ") and row.endswith(":") and " " not in row:
            group = row[:-1]
            listed[group] = []
        elif row.startswith("  ") and listed:
            listed[group].append(row.split()[0])
    for group in ALL_GROUPS:
        assert group in listed, f"--help does not list group {group}"
        assert sorted(listed[group]) == group_options(group)


@pytest.mark.slow
def test_multirun_over_two_sites_runs_two_jobs(run_cli, tmp_path):
    out = tmp_path / "outputs"
    proc = run_cli("-m", "+site=frozen_lake,forest", "+experiment=smoke", "tracking=none", outputs=out)
    assert proc.returncode == 0, proc.stderr[-2000:]
    metrics = sorted(out.glob("multirun/*/*/*/metrics.json"))
    assert len(metrics) == 2
    sites = {json.loads(p.read_text())["site"] for p in metrics}
    assert sites == {"frozen_lake", "forest"}


def test_runs_are_named_by_what_they_vary():
    from acoustlab.__main__ import run_name_of

    assert (
        run_name_of(["+site=forest", "model=knn", "features.drop=[solver]", "paths.outputs_dir=/x", "tracking=none", "data.n_jobs=2"])
        == "forest model=knn features.drop=[solver]"
    )
    assert run_name_of(["+site=frozen_lake", "+experiment=smoke"]) == "frozen_lake experiment=smoke"
