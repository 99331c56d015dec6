"""Randomly initialised TabPFN v2 regressor checkpoints of the real architecture.

Real weights cannot be downloaded everywhere (CI, air-gapped clusters). A checkpoint built here
loads through exactly the same code path as the published one, so tests exercise loading, fitting,
batching and quantiles, and benchmarks can time a full-size model; its predictions are meaningless.
The recipe follows TabPFN's own checkpoint layout (state dict with the bar-distribution criterion,
architecture config and inference config).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

#: The published v2 regressor's size (emsize 192, 12 layers, 6 heads, 5,000 output buckets).
FULL_SIZE = dict(emsize=192, nlayers=12, nhead=6, features_per_group=2, num_buckets=5000, max_num_classes=0)
#: A tiny model for tests (seconds on a CPU).
TINY = dict(emsize=32, nlayers=2, nhead=2, features_per_group=2, num_buckets=100, max_num_classes=0)


def build_random_checkpoint(path: str | Path, size: dict | None = None, seed: int = 0) -> Path:
    """Write a randomly initialised TabPFN v2 regressor checkpoint to ``path`` and return it.

    Parameters
    ----------
    path : str or pathlib.Path
        Target ``.ckpt`` file; keep version strings out of the name (it is then read as v2).
    size : dict, optional
        Architecture sizes (``TINY`` by default, ``FULL_SIZE`` for timing).
    seed : int
        torch seed of the random weights.
    """
    import torch
    from scipy.stats import norm
    from tabpfn.architectures import tabpfn_v2
    from tabpfn.architectures.shared.bar_distribution import FullSupportBarDistribution
    from tabpfn.constants import ModelVersion
    from tabpfn.inference_config import InferenceConfig

    cfg, _ = tabpfn_v2.parse_config(dict(size or TINY))
    torch.manual_seed(seed)
    model = tabpfn_v2.get_architecture(cfg)
    n_buckets = int((size or TINY)["num_buckets"])
    borders = torch.tensor(norm.ppf(np.linspace(0.001, 0.999, n_buckets + 1)), dtype=torch.float32)
    state = dict(model.state_dict())
    state.update({f"criterion.{k}": v for k, v in FullSupportBarDistribution(borders).state_dict().items()})
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "state_dict": state,
            "config": dataclasses.asdict(cfg),
            "architecture_name": "tabpfn_v2",
            "inference_config": dataclasses.asdict(InferenceConfig.get_default("regression", ModelVersion.V2)),
        },
        path,
    )
    return path
