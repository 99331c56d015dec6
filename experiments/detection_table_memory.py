"""Memory a season's detector tables take per row: read once, kept compact, extrapolated to 10⁷ rows.

Usage: python experiments/detection_table_memory.py --season DIR [--rows 1000000]

``DIR`` is a synthetic season (``python -m acoustlab.synthetic_season ... --out DIR``, or the
folder ``experiments/season_invariance.py --workdir`` keeps): its recordings are indexed, and Raven
tables of ``--rows`` selections in all (each recorder's table its share, selections drawn over its
files) are written and read with ``acoustlab.season.detections.read_detections``, as a season reads
them. Reported: the rows' size once read (pandas' deep memory usage), the peak of Python
allocations while reading (tracemalloc, the table's text excluded), both per row and for 10⁷ rows,
and the read time per row. Writes experiments/results/detection_table_memory.md.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pandas as pd
from common import machine, write_results

from acoustlab.season.detections import read_detections
from acoustlab.season.recorder_files import RecorderFiles

log = logging.getLogger("experiments.detection_table_memory")


def write_tables(recordings: RecorderFiles, n_rows: int, folder: Path) -> list[Path]:
    """Raven tables (one per recorder) with ``n_rows`` selections in all, at random times inside the recorders' files."""
    rng = np.random.default_rng(0)
    table = recordings.table
    paths = []
    for recorder in recordings.recorders:
        files = table[table["recorder_id"] == recorder]
        n = n_rows // len(recordings.recorders)
        pick = rng.integers(0, len(files), n)
        duration = (files["end_s"] - files["start_s"]).to_numpy(float)[pick]
        offset = rng.uniform(0, np.maximum(duration - 1.0, 0.0))
        path = folder / f"{recorder}.Table.1.selections.txt"
        pd.DataFrame(
            {
                "Selection": np.arange(1, n + 1),
                "View": "Spectrogram 1",
                "Channel": 1,
                "Begin Time (s)": offset,
                "End Time (s)": offset + 0.5,
                "Low Freq (Hz)": 2000.0,
                "High Freq (Hz)": 6000.0,
                "Begin File": [Path(p).name for p in files["path"].to_numpy()[pick]],
                "File Offset (s)": offset,
                "Species": rng.choice(["wren", "robin", "tit"], n),
            }
        ).to_csv(path, sep="\t", index=False)
        paths.append(path)
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--season", type=Path, required=True, help="a synthetic season's folder (its audio/)")
    parser.add_argument("--rows", type=int, default=1_000_000)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    recordings = RecorderFiles.from_file_names(args.season / "audio")
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_tables(recordings, args.rows, Path(tmp))
        tracemalloc.start()
        started = time.perf_counter()
        detections = read_detections(paths, "raven", recordings)
        seconds = time.perf_counter() - started
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    rows = len(detections)
    kept = int(detections.memory_usage(deep=True).sum())
    result = {
        "rows": rows,
        "bytes per row once read": kept / rows,
        "peak bytes per row while reading": peak / rows,
        "µs per row to read": 1e6 * seconds / rows,
        "GiB for 10⁷ rows once read": kept / rows * 1e7 / 2**30,
        "GiB for 10⁷ rows at the peak": peak / rows * 1e7 / 2**30,
    }
    log.info("%s", result)
    markdown = [
        "# Memory a season's detector tables take per row",
        "",
        f"`python experiments/detection_table_memory.py --season DIR --rows {args.rows}`: {rows:,} Raven selections over "
        f"{len(recordings.recorders)} recorders' tables, read as a season reads them (`read_detections`).",
        "",
        pd.DataFrame([result]).T.rename(columns={0: "value"}).to_markdown(floatfmt=".3g"),
        "",
        f"The peak counts Python allocations while reading (tracemalloc), the tables' text included. Machine: {machine()}.",
    ]
    write_results("detection_table_memory", result, markdown)


if __name__ == "__main__":
    main()
