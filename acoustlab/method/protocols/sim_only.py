"""Sim-only protocol: train and test on simulation, split by source position."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
from sklearn.model_selection import GroupShuffleSplit

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.method.pipeline import LocalizationPipeline, MethodResult
from acoustlab.method.splits import cap_rows
from acoustlab.stages.dataset import Dataset

log = logging.getLogger(__name__)


class SimOnlyProtocol:
    """≈90/10 split of simulated events by source position; training capped at ``max_train_rows``.

    Parameters
    ----------
    test_fraction : float
        Fraction of source positions withheld for testing.
    max_train_rows : int
        Training rows are subsampled (whole positions kept together) to at most this many.
    seed : int
        Seed of the split.
    """

    def __init__(self, test_fraction: float = 0.1, max_train_rows: int = 1000, seed: int = 0) -> None:
        if not 0 < test_fraction < 1:
            raise ConfigError(f"protocol.test_fraction must be in (0, 1); got {test_fraction}")
        if max_train_rows < 2:
            raise ConfigError(f"protocol.max_train_rows must be >= 2; got {max_train_rows}")
        self.test_fraction = float(test_fraction)
        self.max_train_rows = int(max_train_rows)
        self.seed = int(seed)

    def split(self, events: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
        """Row indices (train, test); no position appears in both."""
        groups = events[col.POSITION_ID].to_numpy()
        if np.unique(groups).size < 3:
            raise DataError(f"sim-only needs at least 3 source positions; got {np.unique(groups).size}")
        splitter = GroupShuffleSplit(n_splits=1, test_size=self.test_fraction, random_state=self.seed)
        train, test = next(splitter.split(np.zeros(len(events)), groups=groups))
        train = cap_rows(train, groups, self.max_train_rows, np.random.default_rng([self.seed, 1]))
        log.info("sim-only split: %d training rows, %d test rows", train.size, test.size)
        return np.sort(train), np.sort(test)

    def run(self, dataset: Dataset, pipeline: LocalizationPipeline, field_recordings: Dataset | None = None) -> MethodResult:
        """Per-event predictions on the withheld positions (``field_recordings`` is not used)."""
        train, test = self.split(dataset.events)
        return pipeline.fit_predict(dataset.features, dataset.events, train, test)
