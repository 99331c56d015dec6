"""Exceptions that carry a user-facing, one-line explanation."""


class AcoustlabError(Exception):
    """Base class of every error acoustlab reports to the user without a traceback."""


class ConfigError(AcoustlabError):
    """A configuration value is missing or invalid; the message names the field and what was expected."""


class DataError(AcoustlabError):
    """An input file or array is malformed; the message names the file or field and what was expected."""


def show(value: object) -> str:
    """A value as an error message shows it: numpy scalars as plain numbers (``24000``, not ``np.int64(24000)``), text quoted."""
    import numpy as np  # imported when a message is made: the errors module stays light

    return repr(value.item() if isinstance(value, np.generic) else value)
