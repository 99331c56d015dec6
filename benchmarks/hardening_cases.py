"""What a user sees for the bad inputs of the hardening issue: the command's last line, or the flags a clip gets.

Usage: python benchmarks/hardening_cases.py
Writes benchmarks/results/hardening_cases.json and .md. Config and table cases run the real
command line (``python -m acoustlab …``, fresh process; each stops in the preflight, before any
simulation, so each takes seconds); sample-level cases load a generated recordings folder and
report the ``quality_flags`` of its events. Not a speed benchmark: a record of behaviour.
"""

from __future__ import annotations

import logging
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import soundfile as sf
from common import REPO, machine, write_results

from acoustlab.stages.sites import site_from_config

log = logging.getLogger("hardening_cases")
RATE = 24000
SMOKE = ["+experiment=smoke", "tracking=none", "plots=false"]


def write_folder(root: Path, n_events: int = 4) -> pd.DataFrame:
    """Three-mic multichannel recordings (noise), a mics and an events table; returns the events."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for k in range(n_events):
        sf.write(root / f"ev{k}.wav", (0.01 * rng.standard_normal((2 * RATE, 3))).astype(np.float32), RATE, subtype="FLOAT")
    pd.DataFrame({"mic_id": ["a", "b", "c"], "x_m": [0.0, 40.0, 20.0], "y_m": [0.0, 0.0, 35.0], "z_m": 1.5}).to_csv(root / "mics.csv", index=False)
    events = pd.DataFrame({"event_id": range(n_events), "start_s": 0.5, "end_s": 1.0, "file": [f"ev{k}.wav" for k in range(n_events)]})
    events.to_csv(root / "events.csv", index=False)
    return events


def cli(args: list[str], outputs: Path) -> tuple[int, str]:
    """Exit code and last stderr line of one command."""
    proc = subprocess.run([sys.executable, "-m", "acoustlab", *args, f"paths.outputs_dir={outputs}"], cwd=REPO, capture_output=True, text=True)
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    return proc.returncode, lines[-1] if lines else ""


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        root = tmp / "rec"
        events = write_folder(root)
        site = ["+site=from_csv", f"site.mics_csv={root / 'mics.csv'}"]
        field = ["protocol=localize", "field=recordings", f"field.audio_dir={root}", f"field.mics_csv={root / 'mics.csv'}",
                 f"field.events_csv={root / 'events.csv'}", f"field.sample_rate_hz={RATE}", "simulator.sample_rate_hz=24000"]
        config_cases = {
            "data.n_events=abc": ["+site=frozen_lake", *SMOKE, "data.n_events=abc"],
            "data.n_jobs=0": ["+site=frozen_lake", *SMOKE, "data.n_jobs=0"],
            "site.relative_humidity_pct=[70,250]": ["+site=frozen_lake", *SMOKE, "site.relative_humidity_pct=[70,250]"],
            "seed=-1": ["+site=frozen_lake", *SMOKE, "seed=-1"],
            "protocol=field_eval without a field": ["+site=frozen_lake", *SMOKE, "protocol=field_eval", "field=none"],
            "pipeline.selective.delta=1.5": ["+site=frozen_lake", *SMOKE, "pipeline.selective.enabled=true", "pipeline.selective.delta=1.5"],
            "selective delta=0.0001 on 120 events": ["+site=frozen_lake", *SMOKE, "pipeline.selective.enabled=true", "pipeline.selective.delta=0.0001"],
            "run dir under a file": ["+site=frozen_lake", *SMOKE, f"hydra.run.dir={root / 'mics.csv' / 'run'}"],
        }
        for name, args in config_cases.items():
            code, line = cli(args, tmp / "out")
            rows.append({"case": name, "kind": "config", "exit": code, "user_sees": line.replace(str(tmp), "<tmp>")})
        received = tmp / "received"
        received.mkdir()
        (received / "config_resolved.yaml").write_text("paths: {outputs_dir: /somewhere/else}\n")
        (received / "metrics.json").write_text("{not json")
        for name, command in (("upload: malformed metrics.json", "upload"), ("report: malformed metrics.json", "report")):
            proc = subprocess.run([sys.executable, "-m", "acoustlab", command, str(received)], cwd=tmp, capture_output=True, text=True)
            lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip() and "Traceback" not in ln]
            rows.append({"case": name, "kind": "received folder", "exit": proc.returncode,
                         "user_sees": " / ".join(lines[-2:]).replace(str(tmp), "<tmp>")})
        table_cases = {
            "non-numeric mic coordinate": ("mics.csv", lambda t: t.assign(x_m=["0", "abc", "20"])),
            "events table with only a header": ("events.csv", lambda t: t.iloc[:0]),
            "duplicate event_id": ("events.csv", lambda t: t.assign(event_id=[0, 0, 1, 2])),
            "end_s=3600 on 2 s files": ("events.csv", lambda t: t.assign(end_s=[1.0, 3600.0, 1.0, 1.0])),
            "file=../../../../etc/passwd": ("events.csv", lambda t: t.assign(file=["ev0.wav", "../../../../etc/passwd", "ev2.wav", "ev3.wav"])),
            "start_s not a number": ("events.csv", lambda t: t.assign(start_s=["0.5", "x", "0.5", "0.5"])),
        }
        for name, (table, edit) in table_cases.items():
            original = (root / table).read_text()
            edit(pd.read_csv(root / table)).to_csv(root / table, index=False)
            code, line = cli([*site, *SMOKE, *field], tmp / "out")
            (root / table).write_text(original)
            rows.append({"case": name, "kind": "table", "exit": code, "user_sees": line.replace(str(tmp), "<tmp>")})

        from common import compose_cfg

        from plugins.fields.recordings import RecordingFolder

        site_obj = site_from_config(compose_cfg(site).site)
        damaged = {
            "dead (all-zero) channel": lambda a: a.__setitem__((slice(None), 2), 0.0),
            "NaN samples in one event": lambda a: a.__setitem__((slice(RATE // 2, RATE // 2 + 10), 0), np.nan),
            "±inf samples": lambda a: a.__setitem__((slice(RATE // 2, RATE // 2 + 10), 1), np.inf),
            "WAV truncated to a third": None,
        }
        for k, (name, damage) in enumerate(damaged.items()):
            write_folder(root)
            audio = sf.read(root / f"ev{k}.wav", dtype="float32")[0]
            if damage is None:
                audio = audio[: len(audio) // 3]
            else:
                damage(audio)
            sf.write(root / f"ev{k}.wav", audio, RATE, subtype="FLOAT")
            batch = RecordingFolder(str(root), str(root / "mics.csv"), str(root / "events.csv"), sample_rate_hz=RATE).load(site_obj)
            rows.append({"case": name, "kind": "samples", "exit": 0, "user_sees": f"quality_flags = {batch.events['quality_flags'].iloc[k]!r}"})
        write_folder(root)
        moved = events.assign(start_s=[0.5, 30.0, -3.0, 0.5], end_s=[1.0, 30.5, -2.5, 1.0])
        moved.to_csv(root / "events.csv", index=False)
        batch = RecordingFolder(str(root), str(root / "mics.csv"), str(root / "events.csv"), sample_rate_hz=RATE).load(site_obj)
        for k, name in ((1, "event past the end of its file"), (2, "event entirely before its file")):
            rows.append({"case": name, "kind": "samples", "exit": 0, "user_sees": f"quality_flags = {batch.events['quality_flags'].iloc[k]!r}"})
    lines = ["# Bad inputs: what a user sees", "", "`python benchmarks/hardening_cases.py`", "", "| case | exit | what the user sees |", "|---|---|---|"]
    lines += [f"| {r['case']} | {r['exit']} | {r['user_sees'].replace('|', '/')} |" for r in rows]
    write_results("hardening_cases", {"machine": machine(), "cases": rows}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
