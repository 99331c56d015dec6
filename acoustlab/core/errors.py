"""Exceptions that carry a user-facing, one-line explanation."""


class AcoustlabError(Exception):
    """Base class of every error acoustlab reports to the user without a traceback."""


class ConfigError(AcoustlabError):
    """A configuration value is missing or invalid; the message names the field and what was expected."""


class DataError(AcoustlabError):
    """An input file or array is malformed; the message names the file or field and what was expected."""
