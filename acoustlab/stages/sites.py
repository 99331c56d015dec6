"""Build and validate ``Site`` objects from configs and CSV files.

A site config holds either inline mic coordinates (``mics``) or a CSV (``mics_csv``) with
columns ``x_m, y_m, z_m`` (``mic_id`` optional), and optionally a tree CSV (``trees_csv``) with
columns ``x_m, y_m, diameter_m``. Paths may be absolute, relative to the directory the command
runs in, or ``acoustlab://…`` for data shipped inside the package.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError, DataError, show
from acoustlab.core.resources import resolve_path
from acoustlab.core.types import NoiseRegime, Site, require_range
from acoustlab.toolkit.geometry import collinearity_ratio
from acoustlab.toolkit.map_frame import map_projection, with_map_coordinates
from acoustlab.toolkit.peer_tables import recorder_positions_m, recorders_of, without_heightless

NOISE_KINDS = ("recorded", "white", "pink", "band")
#: Mics whose centred 2-D coordinates have a smaller/larger singular value below this are collinear.
COLLINEAR_TOLERANCE = 1e-3


def _read_csv(path_text: str, field: str, required: tuple[str, ...]) -> pd.DataFrame:
    path = resolve_path(path_text)
    if not path.is_file():
        raise DataError(f"site.{field}: file {path} does not exist")
    try:
        table = pd.read_csv(path, comment="#")
    except Exception as exc:  # pandas raises many types for malformed CSVs
        raise DataError(f"site.{field}: cannot read {path} as CSV ({exc})") from None
    if field == "mics_csv":  # mics given by latitude/longitude: their local frame and map coordinates
        table = with_map_coordinates(table, f"site.{field}: {path}")
    missing = [c for c in required if c not in table.columns]
    if missing:
        raise DataError(f"site.{field}: {path} lacks columns {missing}; expected columns {list(required)}, found {list(table.columns)}")
    values = table[list(required)]
    bad = ~np.isfinite(values.apply(pd.to_numeric, errors="coerce").to_numpy(dtype=float))
    if bad.any():
        row, position = np.argwhere(bad)[0]
        raise DataError(
            f"site.{field}: {path} row {row + 2} column {required[position]!r} is not a finite number ({show(values.iloc[row, position])})"
        )
    return table


def _opensoundscape_mics(coords_csv: str, detections_csv: str | None) -> np.ndarray:
    """(R, 3) the recorders of OpenSoundscape's coordinates table that the detections use (``acoustlab.toolkit.peer_tables``), m."""
    path = resolve_path(coords_csv)
    if not path.is_file():
        raise DataError(f"site.coords_csv: file {path} does not exist")
    try:
        coords = pd.read_csv(path, skipinitialspace=True)
        used = None
        if detections_csv:
            used = set(pd.read_csv(resolve_path(detections_csv), usecols=["file"], skipinitialspace=True)["file"].astype(str).str.strip())
    except (ValueError, OSError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DataError(f"site: cannot read {coords_csv} / {detections_csv} as OpenSoundscape tables: {str(exc).splitlines()[0]}") from None
    coords.columns = [str(c).strip() for c in coords.columns]
    if "file" not in coords.columns and coords.columns[0].startswith("Unnamed: 0"):
        coords = coords.rename(columns={coords.columns[0]: "file"})  # the index pandas wrote
    missing = [c for c in ("file", "x", "y") if c not in coords.columns]
    if missing:
        raise DataError(f"site.coords_csv: {path} lacks columns {missing}; found {list(coords.columns)}")
    coords["file"] = coords["file"].astype(str).str.strip()
    if used is not None and coords["file"].isin(used).any():
        coords = coords[coords["file"].isin(used)]
    coords = without_heightless(coords, f"site.coords_csv: {path}")
    xyz = coords[[c for c in ("x", "y", "z") if c in coords]].apply(pd.to_numeric, errors="coerce").to_numpy(float)
    if not np.isfinite(xyz).all():
        row = int(np.flatnonzero(~np.isfinite(xyz).all(axis=1))[0])
        raise DataError(f"site.coords_csv: {path}, file {coords['file'].iloc[row]!r}: its coordinates are not finite numbers")
    return recorder_positions_m(recorders_of(coords, None))


def site_mics_table(cfg: Mapping[str, Any]) -> pd.DataFrame | None:
    """The site's ``mics_csv`` as read (its local frame made from latitude/longitude where given), or None without one."""
    if not cfg.get("mics_csv") or cfg.get("coords_csv"):
        return None
    return _read_csv(str(cfg["mics_csv"]), "mics_csv", col.MIC_XYZ)


def site_map_projection(cfg: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray, str, bool] | None:
    """The map of a site whose ``mics_csv`` places its mics on the map (``acoustlab.toolkit.map_frame``), else None."""
    table = site_mics_table(cfg)
    return None if table is None else map_projection(table, f"site.mics_csv: {resolve_path(str(cfg['mics_csv']))}")


def load_mics(cfg: Mapping[str, Any]) -> np.ndarray:
    """Microphone positions (M, 3) in m from ``coords_csv`` (OpenSoundscape's table, one row per file), ``mics_csv`` or ``mics``."""
    if cfg.get("coords_csv"):
        return _opensoundscape_mics(str(cfg["coords_csv"]), cfg.get("detections_csv"))
    if cfg.get("mics_csv"):
        table = _read_csv(str(cfg["mics_csv"]), "mics_csv", col.MIC_XYZ)
        return table[list(col.MIC_XYZ)].to_numpy(dtype=float)
    mics = cfg.get("mics")
    if not mics:
        raise ConfigError(
            "site: give microphone positions as 'mics' ([[x, y, z], ...] in m) or 'mics_csv' "
            "(+site=recordings takes them from field.mics_csv: add field=recordings field.mics_csv=PATH)"
        )
    try:
        arr = np.asarray([[float(v) for v in row] for row in mics], dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"site.mics must be a list of [x, y, z] in m; got {mics!r}") from None
    if arr.ndim != 2 or arr.shape[1] != 3 or not np.isfinite(arr).all():
        raise ConfigError(f"site.mics must be a list of finite [x, y, z] in m; got shape {arr.shape}")
    return arr


def load_trees(cfg: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Tree positions (T, 2) and trunk diameters (T,) in m from ``trees_csv`` (none if absent)."""
    if not cfg.get("trees_csv"):
        return np.zeros((0, 2)), np.zeros(0)
    table = _read_csv(str(cfg["trees_csv"]), "trees_csv", (col.TREE_X, col.TREE_Y, col.TREE_DIAMETER))
    diam = table[col.TREE_DIAMETER].to_numpy(dtype=float)
    if (diam <= 0).any():
        row = int(np.argmax(diam <= 0))
        raise DataError(f"site.trees_csv: row {row + 2} has diameter_m={diam[row]}; expected > 0 m")
    return table[[col.TREE_X, col.TREE_Y]].to_numpy(dtype=float), diam


def _noise_regimes(noise_cfg: Mapping[str, Any]) -> tuple[NoiseRegime, ...]:
    regimes = []
    for i, r in enumerate(noise_cfg.get("regimes") or []):
        kind = str(r.get("kind"))
        if kind not in NOISE_KINDS:
            raise ConfigError(f"site.noise.regimes[{i}].kind={kind!r}; expected one of {list(NOISE_KINDS)}")
        files = tuple(str(f) for f in (r.get("files") or []))
        if kind == "recorded":
            if not files:
                raise ConfigError(f"site.noise.regimes[{i}] is 'recorded' but lists no files")
            for f in files:
                if not resolve_path(f).is_file():
                    raise DataError(f"site.noise.regimes[{i}].files: {f} does not exist")
        band = r.get("band_hz")
        if kind == "band":
            low, high = require_range(f"site.noise.regimes[{i}].band_hz", band, lower=0.0)
            band = (low, high)
        else:
            band = None
        regimes.append(NoiseRegime(kind=kind, files=files, band_hz=band))
    if not regimes:
        raise ConfigError("site.noise.regimes is empty; the noise pool needs at least one regime")
    return tuple(regimes)


def site_from_config(cfg: Mapping[str, Any]) -> Site:
    """Build and validate a Site from its config mapping.

    Raises
    ------
    ConfigError
        For fewer than 3 mics, collinear mics, empty noise or species pools, or malformed ranges.
    DataError
        For unreadable or malformed CSV files.
    """
    name = str(cfg.get("name") or "")
    if not name:
        raise ConfigError("site.name is missing")
    mics = load_mics(cfg)
    if mics.shape[0] < 3:
        raise ConfigError(f"site {name!r} has {mics.shape[0]} microphones; 2-D TDOA localization needs at least 3")
    if collinearity_ratio(mics[:, :2]) < COLLINEAR_TOLERANCE:
        raise ConfigError(f"site {name!r}: the microphones are collinear in x-y; 2-D localization needs a non-degenerate array")
    trees, diameters = load_trees(cfg)
    ground = cfg.get("ground") or {}
    noise = cfg.get("noise") or {}
    species = tuple(str(s) for s in (cfg.get("species_pool") or []))
    if not species:
        raise ConfigError(f"site {name!r}: species_pool is empty; list at least one species or 'synthetic'")
    sigma = float(ground.get("flow_resistivity_kpa_s_m2", 2e4))
    if sigma <= 0:
        raise ConfigError(f"site.ground.flow_resistivity_kpa_s_m2 must be > 0; got {sigma}")
    impedance_model = str(ground.get("model", "miki"))
    if impedance_model not in ("miki", "delany_bazley", "rigid"):
        raise ConfigError(f"site.ground.model={impedance_model!r}; expected miki, delany_bazley or rigid")
    layer = ground.get("layer_thickness_m")
    if layer is not None and not float(layer) > 0:
        raise ConfigError(f"site.ground.layer_thickness_m must be > 0 m or null; got {layer}")
    foliage = cfg.get("foliage_db_per_m")
    if foliage is not None:
        try:
            foliage = tuple(float(v) for v in foliage)
        except (TypeError, ValueError):
            raise ConfigError(f"site.foliage_db_per_m must be 8 numbers (dB/m, octaves 63 Hz–8 kHz); got {foliage!r}") from None
        if len(foliage) != 8 or min(foliage) < 0:
            raise ConfigError(f"site.foliage_db_per_m must be 8 non-negative numbers (dB/m, octaves 63 Hz–8 kHz); got {foliage!r}")
    hull_expansion = float(cfg.get("hull_expansion", 0.0))
    if hull_expansion < 0:
        raise ConfigError(f"site.hull_expansion must be >= 0; got {hull_expansion}")
    return Site(
        name=name,
        mic_positions_m=mics,
        tree_positions_m=trees,
        trunk_diameters_m=diameters,
        temperature_range_c=require_range("site.temperature_c", cfg.get("temperature_c"), lower=-80.0, upper=60.0),
        relative_humidity_range_pct=require_range("site.relative_humidity_pct", cfg.get("relative_humidity_pct"), lower=0.0, upper=100.0),
        ground_type=str(ground.get("type", "unspecified")),
        ground_flow_resistivity_kpa_s_m2=sigma,
        ground_impedance_model=impedance_model,
        ground_layer_thickness_m=None if layer is None else float(layer),
        noise_regimes=_noise_regimes(noise),
        snr_range_db=require_range("site.noise.snr_db", noise.get("snr_db")),
        species_pool=species,
        source_height_range_m=require_range("site.source_height_m", cfg.get("source_height_m"), lower=0.0),
        hull_expansion=hull_expansion,
        foliage_db_per_m=foliage,
    )
