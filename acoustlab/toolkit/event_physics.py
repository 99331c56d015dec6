"""Per-event physics every stage reads the same way: the speed of sound and the source height.

Before this module the speed of sound was derived in four places (one fell back to 343 m/s, 5–7 %
high on the frozen lake) and the mid-height rule for the source height was written out ten times.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import DataError
from acoustlab.core.types import Site
from acoustlab.toolkit.physics import speed_of_sound_m_s


def assumed_source_height_m(site: Site) -> float:
    """The height a 2-D solve assumes and a height-less estimate is placed at: the middle of the site's source-height range, m."""
    return float(np.mean(site.source_height_range_m))


def source_height_m(features: pd.DataFrame, site: Site) -> np.ndarray:
    """(E,) each event's source height, m: the solver's (estimated in 3-D, assumed in 2-D) where finite, else the assumed one."""
    assumed = assumed_source_height_m(site)
    if col.SOLVER_SOURCE_HEIGHT not in features:
        return np.full(len(features), assumed)
    height = features[col.SOLVER_SOURCE_HEIGHT].to_numpy(float)
    return np.where(np.isfinite(height), height, assumed)


def event_speed_of_sound_m_s(events: pd.DataFrame) -> np.ndarray:
    """(E,) each event's speed of sound, m/s: its ``speed_of_sound_m_s`` where given, else from its temperature and humidity.

    Raises
    ------
    DataError
        When the events carry neither.
    """
    if col.SPEED_OF_SOUND in events:
        return events[col.SPEED_OF_SOUND].to_numpy(dtype=float)
    if col.TEMPERATURE not in events:
        raise DataError("the events have neither speed_of_sound_m_s nor temperature_c; the speed of sound cannot be computed")
    humidity = events[col.HUMIDITY].to_numpy(float) if col.HUMIDITY in events else np.zeros(len(events))
    return np.asarray(speed_of_sound_m_s(events[col.TEMPERATURE].to_numpy(float), humidity), dtype=float)
