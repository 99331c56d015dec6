"""TabPFN point model on CPU and GPU: the same code path, agreement and speed at the real model size.

Usage: python benchmarks/bench_tabpfn_device.py [--rows 1000] [--features 80] [--test 110] [--out DIR]

Real weights cannot be downloaded here, so the model is a randomly initialised checkpoint of the
published v2 regressor's size (``plugins.models.tabpfn_checkpoint.FULL_SIZE``): timings are those
of the real architecture, predictions are meaningless. Shapes default to the method's: 1,000
training rows (the cap), 80 feature columns (3 mics), 110 test events. For every available device
it times ``fit`` + ``predict`` + ``predict_quantiles`` (after one warm-up) and compares the devices'
predictions. Writes tabpfn_device.json and .md into ``--out`` (default benchmarks/results).
Needs only numpy, scipy, scikit-learn, torch and tabpfn (no Hydra), so it runs on a bare GPU box.
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from plugins.models.tabpfn_checkpoint import FULL_SIZE, build_random_checkpoint  # noqa: E402
from plugins.models.tabpfn_models import TabPFNPointModel  # noqa: E402

log = logging.getLogger("bench_tabpfn_device")


def synchronize(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def run(device: str, ckpt: Path, x_train: np.ndarray, y_train: np.ndarray, x_test: np.ndarray, repeats: int) -> dict:
    """Median seconds of fit, predict and quantiles on ``device``, and its predictions."""
    model = TabPFNPointModel(model_path=str(ckpt), n_estimators=4, device=device)
    model.fit(x_train, y_train).predict(x_test)  # warm-up: loads weights, compiles kernels
    fit_s, pred_s, quant_s = [], [], []
    for _ in range(repeats):
        synchronize(device)
        t0 = time.perf_counter()
        model.fit(x_train, y_train)
        synchronize(device)
        t1 = time.perf_counter()
        pred = model.predict(x_test)
        synchronize(device)
        t2 = time.perf_counter()
        quant = model.predict_quantiles(x_test, [0.5, 0.8, 0.95])
        synchronize(device)
        t3 = time.perf_counter()
        fit_s.append(t1 - t0), pred_s.append(t2 - t1), quant_s.append(t3 - t2)
    return {"fit_s": float(np.median(fit_s)), "predict_s": float(np.median(pred_s)), "quantiles_s": float(np.median(quant_s)),
            "prediction": pred, "quantiles": quant}


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rows", type=int, default=1000)
    parser.add_argument("--features", type=int, default=80)
    parser.add_argument("--test", type=int, default=110)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    opts = parser.parse_args()
    import tabpfn
    import torch

    rng = np.random.default_rng(0)
    x = rng.normal(size=(opts.rows + opts.test, opts.features)).astype(np.float32)
    y = (x[:, 0] * 3 + rng.normal(size=len(x))).astype(np.float32)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = build_random_checkpoint(Path(tmp) / "random-full-size-regressor.ckpt", FULL_SIZE)
        results = {d: run(d, ckpt, x[: opts.rows], y[: opts.rows], x[opts.rows :], opts.repeats) for d in devices}
    summary = {
        "python": platform.python_version(), "torch": torch.__version__, "tabpfn": getattr(tabpfn, "__version__", "?"),
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "shape": {"train_rows": opts.rows, "features": opts.features, "test_rows": opts.test, "n_estimators": 4},
        "architecture": FULL_SIZE, "repeats": opts.repeats,
        "timings_s": {d: {k: round(v, 4) for k, v in r.items() if k.endswith("_s")} for d, r in results.items()},
    }
    lines = ["# TabPFN point model, CPU vs GPU (random weights, published v2 size)", "",
             f"Measured with `python benchmarks/bench_tabpfn_device.py` (torch {summary['torch']}, GPU: {summary['gpu']}); "
             f"{opts.rows} training rows × {opts.features} features, {opts.test} test rows, n_estimators=4, median of {opts.repeats}.", "",
             "| device | fit (s) | predict (s) | quantiles (s) |", "|:--|--:|--:|--:|"]
    for d, r in results.items():
        lines.append(f"| {d} | {r['fit_s']:.3f} | {r['predict_s']:.3f} | {r['quantiles_s']:.3f} |")
    if "cuda" in results:
        cpu, gpu = results["cpu"], results["cuda"]
        spread = float(np.std(cpu["prediction"])) or 1.0
        summary["cuda_vs_cpu"] = {
            "max_abs_prediction_diff": float(np.max(np.abs(cpu["prediction"] - gpu["prediction"]))),
            "prediction_std": spread,
            "max_abs_quantile_diff": float(np.max(np.abs(cpu["quantiles"] - gpu["quantiles"]))),
            "speedup_predict": cpu["predict_s"] / gpu["predict_s"],
            "speedup_fit_plus_predict": (cpu["fit_s"] + cpu["predict_s"]) / (gpu["fit_s"] + gpu["predict_s"]),
        }
        c = summary["cuda_vs_cpu"]
        lines += ["", f"GPU vs CPU: predictions differ by at most {c['max_abs_prediction_diff']:.3g} (their spread: std "
                  f"{c['prediction_std']:.3g}); quantiles by at most {c['max_abs_quantile_diff']:.3g}; predict is "
                  f"{c['speedup_predict']:.1f}× faster on the GPU, fit + predict {c['speedup_fit_plus_predict']:.1f}×."]
    lines += ["", "With random weights the predictions are nearly constant, so the agreement figure checks that both devices run "
              "the same computation (the GPU runs in mixed precision), not accuracy; the published weights have the same size, "
              "so the timings carry over. On a lent GPU machine the CPU row is that machine's CPU."]
    try:  # what made the result (common needs Hydra, which a bare GPU box may lack: then the result names no commit)
        from common import provenance

        summary["provenance"] = made = provenance()
        lines += ["", f"Made with commit {made['commit'][:10]}{' plus uncommitted changes' if made['uncommitted_changes'] else ''} "
                  f"by {made['script']} (sha256 {made['script_sha256'][:12]})."]
    except ImportError as exc:
        log.warning("no provenance recorded (%s)", exc)
    opts.out.mkdir(parents=True, exist_ok=True)
    (opts.out / "tabpfn_device.json").write_text(json.dumps(summary, indent=2))
    (opts.out / "tabpfn_device.md").write_text("\n".join(lines) + "\n")
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
