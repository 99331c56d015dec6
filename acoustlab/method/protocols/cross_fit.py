"""Cross-fit protocol: every simulated event gets exactly one out-of-sample prediction.

The sim-only split tests about 100 events, so its p99 is roughly the largest error and method
comparisons have little power. Here the source positions are dealt into K folds (grouped K-fold
after a seeded shuffle of the positions); each fold is predicted by a pipeline fitted on the other
folds' positions, capped at ``max_train_rows`` (whole positions, chosen at random), so every fit
stays inside the 1,000-row budget of the paper and no position is ever in both training and test.
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
from sklearn.model_selection import GroupKFold

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.method.pipeline import LocalizationPipeline, MethodResult
from acoustlab.method.splits import cap_rows
from acoustlab.stages.dataset import Dataset

log = logging.getLogger(__name__)


class CrossFitProtocol:
    """Grouped K-fold over source positions as the outer loop (module docstring).

    Parameters
    ----------
    n_folds : int
        Outer folds (each fold's positions are predicted by a fit on the others).
    max_train_rows : int
        Cap on each fit's training rows (whole positions kept together).
    seed : int
        Seed of the fold assignment and the caps.
    """

    def __init__(self, n_folds: int = 10, max_train_rows: int = 1000, seed: int = 0) -> None:
        if n_folds < 2:
            raise ConfigError(f"protocol.n_folds must be >= 2; got {n_folds}")
        if max_train_rows < 2:
            raise ConfigError(f"protocol.max_train_rows must be >= 2; got {max_train_rows}")
        self.n_folds = int(n_folds)
        self.max_train_rows = int(max_train_rows)
        self.seed = int(seed)

    def splits(self, events: pd.DataFrame) -> list[tuple[np.ndarray, np.ndarray]]:
        """(train, test) row indices per fold; the test rows of all folds partition every row."""
        groups = events[col.POSITION_ID].to_numpy()
        positions = np.unique(groups)
        if positions.size < self.n_folds:
            raise DataError(f"cross_fit with {self.n_folds} folds needs at least {self.n_folds} source positions; got {positions.size}")
        rng = np.random.default_rng([self.seed, 2])
        shuffled = dict(zip(positions, rng.permutation(positions.size), strict=True))  # seeded, so folds are not id ranges
        labels = np.array([shuffled[g] for g in groups])
        out = []
        for k, (train, test) in enumerate(GroupKFold(n_splits=self.n_folds).split(np.zeros(len(events)), groups=labels)):
            train = cap_rows(train, groups, self.max_train_rows, np.random.default_rng([self.seed, 3, k]))
            out.append((np.sort(train), np.sort(test)))
        return out

    def run(self, dataset: Dataset, pipeline: LocalizationPipeline, field_recordings: Dataset | None = None) -> MethodResult:
        """Pooled out-of-sample predictions of every simulated event (``field_recordings`` is not used)."""
        parts = []
        for k, (train, test) in enumerate(self.splits(dataset.events)):
            log.info("cross-fit fold %d/%d: %d training rows, %d test rows", k + 1, self.n_folds, train.size, test.size)
            result = pipeline.fit_predict(dataset.features, dataset.events, train, test)
            result.predictions[col.FOLD] = k
            parts.append(MethodResult(result.predictions, [{"split": f"fold {k}", **d} for d in result.split_diagnostics]))
        return MethodResult.concat(parts)
