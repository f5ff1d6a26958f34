"""Exception hierarchy.

Library code raises these (or ``ValueError``); the CLI turns them into a
one-line message and exit status 1.
"""


class RetargetError(Exception):
    """Base class for every error ``retarget`` reports to a user."""


class InputError(RetargetError):
    """An input file is missing, unreadable or does not follow its contract."""


class ConfigError(RetargetError):
    """A configuration file or option is invalid."""


class ShapeError(RetargetError, ValueError):
    """An array argument has the wrong shape, dtype or values."""
