"""A fitted method saved once and loaded by every shard of a run, without running code from the file.

The method is written with skops (``skops.io``), which stores objects as a tree of their types and
attributes and rebuilds only the types it is told to trust, where pickle would call whatever
function the file names. acoustlab trusts skops' defaults (scikit-learn's estimators, numpy, the
builtin containers), the classes of its own packages (``acoustlab``, ``plugins``) and the few
scikit-learn and XGBoost types a fitted method holds (``TRUSTED_TYPES``; XGBoost's boosters are
stored in XGBoost's own model format). A file naming any other type is refused before anything is
built, in one line naming the types, so a season folder received from someone else, or edited, is
safe to load whoever wrote it. Nothing needs a key. The SHA-256 beside the file (and in the
season's manifest) catches a file that changed after it was written (integrity, not authorship).

TabPFN's fitted state is its training rows: its models keep them and are fitted again on them
when first used after loading (``plugins.models.tabpfn_models``), from the checkpoint they were
fitted with (its SHA-256 checked).
"""

from __future__ import annotations

import hashlib
import importlib
import json
from pathlib import Path
from typing import Any

from acoustlab.core.errors import DataError
from acoustlab.core.files import atomic_write_bytes

METHOD_FILE = "method.skops"
DIGEST_FILE = "method.sha256.json"
#: Types outside skops' defaults and acoustlab's own packages that a fitted method holds.
TRUSTED_TYPES = frozenset(
    {
        "sklearn.ensemble._hist_gradient_boosting.predictor.TreePredictor",
        "sklearn.metrics._dist_metrics.EuclideanDistance64",
        "sklearn.neighbors._ball_tree.BallTree",
        "sklearn.neighbors._kd_tree.KDTree",
        "sklearn.tree._tree.Tree",
        "xgboost.core.Booster",
        "xgboost.sklearn.XGBRegressor",
        "xgboost.sklearn.XGBClassifier",
    }
)
#: Packages whose classes a saved method may hold (acoustlab's own).
OWN_PACKAGES = ("acoustlab", "plugins")


def save_method(method: Any, directory: Path, key: str) -> str:
    """Write ``method`` to ``directory/method.skops`` with its digest and ``key`` (what it was fitted from); return the digest.

    Raises
    ------
    DataError
        When the method holds a type ``load_method`` would refuse (a plugin holding an object
        skops cannot store): saved, it could not be loaded.
    """
    import skops.io as sio

    try:
        blob = sio.dumps(method)
    except (TypeError, ValueError, NotImplementedError) as exc:  # an object skops cannot take apart (a pandas table, a torch module)
        raise DataError(
            f"the fitted method cannot be saved without pickle ({type(exc).__name__}: {exc}): a plugin keeps an object "
            "skops cannot store; keep plain arrays, lists and dicts in fitted attributes"
        ) from None
    refused = _refused_types(sio.get_untrusted_types(data=blob))
    if refused:
        raise DataError(
            f"the fitted method holds {', '.join(refused)}, which a saved method may not hold (acoustlab.method.saved."
            "TRUSTED_TYPES): a plugin keeps an object that cannot be stored without running code on load"
        )
    directory.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(directory / METHOD_FILE, blob)
    digest = hashlib.sha256(blob).hexdigest()  # of the bytes just written, not read back
    atomic_write_bytes(directory / DIGEST_FILE, json.dumps({"sha256": digest, "key": key}, indent=2).encode())
    return digest


def saved_info(directory: Path) -> dict[str, str] | None:
    """``{"sha256", "key"}`` of the method saved in ``directory``, or None when there is none."""
    path = directory / DIGEST_FILE
    if not path.is_file() or not (directory / METHOD_FILE).is_file():
        return None
    try:
        info = json.loads(path.read_text())
        return {"sha256": str(info["sha256"]), "key": str(info["key"])}
    except (ValueError, KeyError, TypeError, RecursionError):
        return None


def load_method(directory: Path, expected_sha256: str | None = None) -> Any:
    """The method saved in ``directory``, after checking the file's SHA-256 against the recorded one (and ``expected_sha256``)
    and every type it names against the trusted ones.

    Raises
    ------
    DataError
        Naming the file, when it is missing, changed since it was written, names a type that is not
        trusted, or is not a saved method.
    """
    import skops.io as sio

    path = directory / METHOD_FILE
    if not path.is_file():
        raise DataError(f"no fitted method at {path}: run the fit stage first (protocol.stage=fit)")
    try:
        recorded = json.loads((directory / DIGEST_FILE).read_text())["sha256"]
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        raise DataError(
            f"{directory / DIGEST_FILE} is missing or unreadable: the fitted method {path} cannot be verified; fit again"
        ) from None
    blob = path.read_bytes()  # read once: the digest and the load are of the same bytes
    actual = hashlib.sha256(blob).hexdigest()
    for wanted in {recorded, expected_sha256} - {None}:
        if actual != wanted:
            raise DataError(
                f"{path}: SHA-256 {actual[:12]}… differs from the {'recorded' if wanted == recorded else 'expected'} "
                f"{wanted[:12]}…; the file changed after it was written, refusing to load it (fit again)"
            )
    try:
        untrusted = sio.get_untrusted_types(data=blob)
    except Exception as exc:  # skops raises what its zip and JSON readers raise on a file that is not its own
        raise DataError(f"{path}: not a saved acoustlab method ({type(exc).__name__}: {exc}); fit again") from None
    refused = _refused_types(untrusted)
    if refused:
        raise DataError(f"{path} names types a saved method never holds ({', '.join(refused)}): refusing to load it; fit again")
    try:
        return sio.loads(blob, trusted=untrusted)
    except Exception as exc:  # a trusted type whose stored state does not fit it: a file of another acoustlab version
        raise DataError(f"{path}: cannot be loaded by this version of acoustlab ({type(exc).__name__}: {exc}); fit again") from None


def _refused_types(names: list[str]) -> list[str]:
    """Of the type names skops does not trust by default, those a saved method may not hold (sorted)."""
    return sorted(name for name in names if name not in TRUSTED_TYPES and not _own_class(name))


def _own_class(name: str) -> bool:
    """Whether ``name`` is a class defined in acoustlab's own packages (a function or a foreign class is not)."""
    module, _, attribute = name.rpartition(".")
    if module.split(".")[0] not in OWN_PACKAGES:
        return False
    try:
        found = getattr(importlib.import_module(module), attribute, None)
    except ImportError:
        return False
    return isinstance(found, type) and found.__module__ == module
