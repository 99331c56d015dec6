"""Do two versions give the same answers? Compare a branch with main, bit for bit, on the same machine.

Runs three jobs through the command line (so it works on any version of the package layout), hashes
``predictions.parquet`` (column names, dtypes and every value) and ``metrics.json`` (without the
timings and the code version, which legitimately change), and compares the hashes with a reference
written earlier by the same script. Each run gets a cold feature and simulation cache of its own.

Usage::

    git switch main   && python benchmarks/identity.py --label main            # the reference
    git switch BRANCH && python benchmarks/identity.py --label branch --compare main \
        --allow frozen_lake_lopo_standin:gate ...                              # JOB:KEY pairs allowed to differ

Writes the git-ignored ``benchmarks/.results/identity_<label>.json`` (and ``identity.md`` with
``--compare``); exit status 1 when a compared job differs in anything not listed in ``--allow``.
``--reuse`` compares an earlier measurement with the same label instead of running the jobs again.
Compare two measurements from one machine: the numerical packages and the CPU can move the last bits.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / ".results"
log = logging.getLogger("benchmarks.identity")

#: The jobs compared: frozen-lake sim-only (defaults), forest sim-only with the paper's method,
#: and the frozen-lake leave-one-position-out stand-in.
JOBS = {
    "frozen_lake_sim_only": ["+site=frozen_lake"],
    "forest_sim_only": ["+site=forest", "+experiment=paper_forest"],
    "frozen_lake_lopo_standin": ["+site=frozen_lake", "+experiment=paper_frozen_lake"],
}
#: metrics.json keys that are not results.
VOLATILE = ("timings_s", "code_version", "run_time")
#: The key of a measurement's machine record (every other top-level key is a job).
MACHINE_KEY = "_machine"


def machine_record() -> dict:
    """The CPU model (``/proc/cpuinfo``'s model name, else ``platform.processor``), Python's version and the releases of the
    numerical packages (two runs of one commit can differ where those differ)."""
    import platform
    from importlib import metadata

    def package_versions() -> dict[str, str]:
        found = {}
        for name in ("numpy", "scipy", "pandas", "scikit-learn", "xgboost", "xgboost-cpu", "torch", "tabpfn", "numba"):
            try:
                found[name] = metadata.version(name)
            except metadata.PackageNotFoundError:
                continue
        return found

    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        names = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines() if line.startswith("model name")]
        cpu = names[0] if names else cpu
    return {"cpu": cpu, "python": platform.python_version(), "releases": package_versions()}


def machine_differences(mine: dict | None, reference: dict | None) -> list[str]:
    """How the machines of two measurements differ, as short phrases (["unknown"] when the reference records none)."""
    if not mine or not reference:
        return ["unknown"]
    out = [f"{key}: {reference.get(key)} → {mine.get(key)}" for key in ("cpu", "python") if mine.get(key) != reference.get(key)]
    releases, old = mine.get("releases", {}), reference.get("releases", {})
    out += [
        f"{name} {old.get(name)} → {releases.get(name)}" for name in sorted(set(releases) | set(old)) if releases.get(name) != old.get(name)
    ]
    return out


def frame_digest(frame: pd.DataFrame) -> str:
    """SHA-256 over column names, dtypes and the exact bytes of every value.

    ``acoustlab.core.digests.frame_sha256(frame, with_dtypes=True)`` computes the same; this script
    keeps its own copy because it must run on old versions of the package to make a reference.
    """
    h = hashlib.sha256()
    h.update(json.dumps([(str(c), str(t)) for c, t in frame.dtypes.items()]).encode())
    h.update(pd.util.hash_pandas_object(frame, index=False).to_numpy().tobytes())
    return h.hexdigest()


def run_job(overrides: list[str], run_dir: Path) -> dict:
    """Run one job in a fresh process; return its metrics (volatile keys removed) and digests."""
    cmd = [sys.executable, "-m", "acoustlab", *overrides, "tracking=none", "plots=false", f"hydra.run.dir={run_dir}"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"job failed: {' '.join(overrides)}\n{proc.stderr[-3000:]}")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    for key in VOLATILE:
        metrics.pop(key, None)
    predictions = pd.read_parquet(run_dir / "predictions.parquet")
    return {
        "predictions_sha256": frame_digest(predictions),
        "metrics_sha256": hashlib.sha256(json.dumps(metrics, sort_keys=True).encode()).hexdigest(),
        "n_predictions": len(predictions),
        "metrics": metrics,
    }


def differing_keys(a: dict, b: dict) -> list[str]:
    """Top-level metrics keys whose values differ."""
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--label", required=True, help="name of this measurement (e.g. before, after)")
    parser.add_argument("--compare", help="label of a reference measurement to compare with")
    parser.add_argument(
        "--allow", nargs="*", default=[], help="JOB:KEY metrics keys allowed to differ in one job (e.g. frozen_lake_lopo_standin:tau_grid)"
    )
    parser.add_argument("--reuse", action="store_true", help="compare the stored identity_<label>.json instead of running")
    parser.add_argument("--jobs", nargs="*", default=list(JOBS), choices=list(JOBS))
    parser.add_argument(
        "--shared-cache",
        action="store_true",
        help="use the configured cache (outputs/cache) instead of a cold one per run: for package versions without cache.dir",
    )
    opts = parser.parse_args()
    if opts.reuse:
        result = json.loads((RESULTS / f"identity_{opts.label}.json").read_text())
    else:
        result = {}
        with tempfile.TemporaryDirectory() as tmp:
            for name in opts.jobs:
                log.info("running %s", name)
                # a cold cache of the run's own: with a warm outputs/cache a job measures what the cache holds
                cache = [] if opts.shared_cache else [f"cache.dir={Path(tmp) / 'cache'}"]
                result[name] = run_job([*JOBS[name], *cache], Path(tmp) / name)
        result[MACHINE_KEY] = machine_record()
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / f"identity_{opts.label}.json").write_text(json.dumps(result, indent=1, default=str))
    if not opts.compare:
        return
    reference = json.loads((RESULTS / f"identity_{opts.compare}.json").read_text())
    lines = [
        "# Bit-identity across a change",
        "",
        f"`python benchmarks/identity.py --label {opts.label} --compare {opts.compare}`",
        "",
        "| job | events | predictions.parquet | metrics.json | differing metrics keys |",
        "|---|---|---|---|---|",
    ]
    failed = False
    for name in opts.jobs:
        new, old = result[name], reference[name]
        same_pred = new["predictions_sha256"] == old["predictions_sha256"]
        keys = differing_keys(new["metrics"], old["metrics"])
        unexpected = [k for k in keys if f"{name}:{k}" not in opts.allow]
        failed |= not same_pred or bool(unexpected)
        lines.append(
            f"| {name} | {new['n_predictions']} | {'identical' if same_pred else 'DIFFERENT'} | "
            f"{'identical' if not keys else 'differs'} | {', '.join(keys) or '—'} |"
        )
    lines += ["", f"Allowed to differ (job:key): {', '.join(opts.allow) or 'nothing'}."]
    machines = machine_differences(result.get(MACHINE_KEY), reference.get(MACHINE_KEY))
    if machines == ["unknown"]:
        lines += [
            "",
            "One of the two measurements does not record its machine: the comparison holds only if both were made on one machine.",
        ]
    elif machines:
        lines += [
            "",
            f"Measured on different machines ({'; '.join(machines)}): answers can differ for that reason alone; "
            "measure both sides on one machine.",
        ]
    (RESULTS / "identity.md").write_text("\n".join(lines) + "\n")
    log.info("\n".join(lines))
    if failed:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
