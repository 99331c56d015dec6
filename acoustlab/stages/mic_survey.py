"""What a mics table says about how well its positions are known (``position_sigma_m``), read and checked once.

``calibrate`` takes it as each mic's prior; without a calibration it becomes the radii's mic-position
allowance (``conformal.input_uncertainty.mic_position_m``), so a GPS-surveyed array's radii carry
the survey's error instead of taking the positions as exact.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.contracts import FieldSource, hook
from acoustlab.core.errors import ConfigError, show
from acoustlab.stages.sites import site_mics_table
from acoustlab.toolkit.input_uncertainty import InputUncertainty

log = logging.getLogger(__name__)


def mic_position_sigmas(mics_table: pd.DataFrame | None, n_mics: int) -> np.ndarray | None:
    """(M,) each mic's stated horizontal error per axis from the mics table, m; None where it states none.

    Raises
    ------
    ConfigError
        Naming the line and the value, for a value that is not a number ≥ 0.
    """
    if mics_table is None or col.POSITION_SIGMA not in mics_table or len(mics_table) != n_mics:
        return None
    given = pd.to_numeric(mics_table[col.POSITION_SIGMA], errors="coerce").to_numpy(float)
    bad = ~np.isfinite(given) | (given < 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ConfigError(
            f"field.mics_csv, line {i + 2}, column '{col.POSITION_SIGMA}': {show(mics_table[col.POSITION_SIGMA].iloc[i])} "
            "is not a number >= 0 (m; 0 for a surveyed mic)"
        )
    return given


def mics_table_of(field_source: FieldSource | None, site_cfg: Mapping[str, Any] | None = None) -> pd.DataFrame | None:
    """The mics table the run's mics come from: the field source's (``tables()[0]``), else the site's ``mics_csv`` (a
    season's), or None where there is none (a simulated site and field)."""
    tables = hook(field_source, "tables") if field_source is not None else None
    if tables is not None:
        return tables()[0]
    return site_mics_table(site_cfg) if site_cfg is not None else None


def survey_allowance(stated: InputUncertainty, mics_table: pd.DataFrame | None, n_mics: int) -> InputUncertainty:
    """The radii's input allowance of an uncalibrated array: the mics table's survey error where the config states none.

    ``conformal.input_uncertainty.mic_position_m`` given (> 0) is kept; else the largest of the
    table's ``position_sigma_m`` (a mic's error moves every fix that uses it; the largest is the one
    a radius must carry). A table without the column is taken to be a consumer GPS's survey
    (``unsurveyed_mic_position_m``, 2 m per axis), said in one line with the figure: radii that take
    metres-off positions as exact are too small, and a surveyed array says so with 0s. Without a
    mics table (a simulated field) nothing changes.
    """
    if stated.mic_position_m > 0 or mics_table is None:
        return stated
    sigmas_m = mic_position_sigmas(mics_table, n_mics)
    if sigmas_m is None:
        assumed = float(stated.unsurveyed_mic_position_m)
        log.warning(
            "no %s in the mics table and no calibration: the radii assume the mics are where a consumer GPS puts them, "
            "%.2f m off per axis (conformal.input_uncertainty.unsurveyed_mic_position_m); give each mic's %s (0 for a "
            "surveyed mic), or calibrate the array with playbacks (docs/calibrate.md)",
            col.POSITION_SIGMA,
            assumed,
            col.POSITION_SIGMA,
        )
        return dataclasses.replace(stated, mic_position_m=assumed)
    largest = float(np.max(sigmas_m)) if sigmas_m.size else 0.0
    if largest > 0:
        log.info(
            "no calibration: the radii carry the mics table's survey error, %s up to %.2f m per axis "
            "(conformal.input_uncertainty.mic_position_m=%.2f; calibrate the array with playbacks to shrink it)",
            col.POSITION_SIGMA,
            largest,
            largest,
        )
    return dataclasses.replace(stated, mic_position_m=largest)
