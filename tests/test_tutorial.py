"""The notebook tutorial (docs/tutorial.md) runs as written: every Python block, in order, in a fresh folder."""

import re

import pytest

from acoustlab.core.resources import PROJECT_ROOT

TUTORIAL = PROJECT_ROOT / "docs" / "tutorial.md"


@pytest.mark.slow
def test_the_notebook_tutorial_runs_as_written(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", TUTORIAL.read_text(), flags=re.S)
    assert len(blocks) >= 4
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for k, block in enumerate(blocks):
        exec(compile(block, f"{TUTORIAL}:block{k + 1}", "exec"), namespace)  # noqa: S102 - the project's own documentation
    assert (tmp_path / "positions.png").stat().st_size > 1000
    assert (tmp_path / "runs" / "loca" / "positions.csv").is_file()
    assert len(namespace["positions"]) == 1 and namespace["errors"].max() < 1.0
