"""Row selection shared by the protocols: capping a training set while keeping source positions whole."""

from __future__ import annotations

import numpy as np
import pandas as pd


def cap_rows(rows: np.ndarray, groups: np.ndarray, max_rows: int, rng: np.random.Generator) -> np.ndarray:
    """At most ``max_rows`` of ``rows``, keeping whole groups (source positions), chosen at random.

    Groups are visited in a random order and kept while they fit; a group too large for the space
    left is skipped and a later, smaller one may still fill it.

    Parameters
    ----------
    rows : numpy.ndarray
        Candidate row indices.
    groups : numpy.ndarray
        Group (position) id of every row of the table ``rows`` index into.
    max_rows : int
        The cap.
    rng : numpy.random.Generator
        Source of the random order (consumed only when the cap applies).

    Returns
    -------
    numpy.ndarray
        The kept subset of ``rows``, in their original order.
    """
    if rows.size <= max_rows:
        return rows
    keep, total = [], 0
    sizes = pd.Series(groups[rows]).value_counts()
    for g in rng.permutation(np.unique(groups[rows])):
        if total + sizes[g] > max_rows:
            continue
        keep.append(g)
        total += sizes[g]
    return rows[np.isin(groups[rows], keep)]
