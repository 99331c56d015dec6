"""The documentation: every command it shows is valid, the cheap ones are run, and the site builds strictly."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
#: Placeholders a reader replaces with their own paths: such commands are checked only as far as they can be.
PLACEHOLDERS = (
    "…",
    "...",
    "/data/",
    "NAME",
    "DIR",
    "outputs/runs/2026",
    "outputs/multirun/2026",
    "outputs/demo_season",
)  # written by the documented command before it (python -m acoustlab.synthetic_season)


def documented_commands() -> list[tuple[str, str]]:
    """(page, command) of every ``python -m acoustlab…`` line in a shell block of the README and the docs."""
    found = []
    for page in PAGES:
        for language, block in re.findall(r"```(\w*)\n(.*?)```", page.read_text(), flags=re.S):  # every fenced block, in pairs
            if language not in ("", "bash", "sh", "console"):
                continue
            for line in block.replace("\\\n", " ").split("\n"):
                line = re.split(r"\s+#\s", line)[0].strip()  # a trailing comment
                if "python -m acoustlab" in line:
                    found.append((page.name, line[line.index("python -m acoustlab") :]))
    return found


COMMANDS = documented_commands()


def test_the_docs_show_commands():
    assert len(COMMANDS) >= 20 and any("localize" in c for _, c in COMMANDS)


def _overrides(args: list[str]) -> list[str]:
    """The config overrides of one job: ``localize`` as its protocol, sweeps at their first value, launcher settings left out."""
    out = []
    for arg in args:
        if arg in ("-m", "--multirun"):
            continue
        if arg in ("localize", "season", "calibrate"):
            out.append(f"protocol={arg}")
            continue
        key, _, value = arg.partition("=")
        if key.startswith(("hydra/", "hydra.")):
            if key.startswith("hydra/launcher"):
                assert (REPO / "conf" / "hydra" / "launcher" / f"{value}.yaml").exists(), f"no launcher {value}"
            continue
        if value.startswith("range("):
            value = value[len("range(") :].split(",")[0]
        elif value.startswith("["):
            value = re.match(r"\[[^\]]*\]", value)[0]
        else:
            value = value.split(",")[0]
        out.append(f"{key}={value}")
    return out


@pytest.mark.slow
@pytest.mark.parametrize("page,command", COMMANDS, ids=[f"{p}:{c[:60]}" for p, c in COMMANDS])
def test_every_documented_command_is_valid(page, command, compose_cfg):
    """Main-job commands pass the command-line checks and the preflight (every plugin built and checked, nothing simulated);
    --help is run; report and upload commands exist."""
    from acoustlab.core.errors import ConfigError
    from acoustlab.run.app import build_run
    from acoustlab.run.preflight import check_argv

    words = shlex.split(command)
    module, args = words[2], words[3:]
    if module != "acoustlab":  # python -m acoustlab.report / .upload / .catalog
        proc = subprocess.run([sys.executable, "-m", module, "--help"], cwd=REPO, capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr[-2000:]
        return
    if "--help" in args:
        proc = subprocess.run([sys.executable, "-m", "acoustlab", *args], cwd=REPO, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0 and "Configuration groups" in proc.stdout, proc.stderr[-2000:]
        return
    # a reader puts their own value where the page writes … or <date>: the rest is checked as written
    check_argv([re.sub(r"<(\w+)>", r"\1", a.replace("…", "x")) for a in args if a not in ("-m", "localize", "season", "calibrate")])
    if any(p in command for p in PLACEHOLDERS):
        return  # a reader's own files: the options are checked, the files cannot be
    cfg = compose_cfg(_overrides(args))
    if "tabpfn" in command:  # without weights the preflight stops at once with the download command, as documented
        with pytest.raises(ConfigError, match="TabPFN weights not found|model=tabpfn needs the optional dependencies"):
            build_run(cfg)
        return
    build_run(cfg)


@pytest.mark.slow
def test_the_site_builds_strictly(tmp_path):
    pytest.importorskip("mkdocs", reason='the docs extra: pip install -e ".[docs]"')
    pytest.importorskip("mkdocstrings")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "site" / "api" / "index.html").exists()
