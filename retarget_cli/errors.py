"""Every error class of ``retarget``, each knowing its exit status.

Library code raises these; the CLI (:class:`retarget_cli.cli.commands.RetargetGroup`)
turns a :class:`RetargetError` into one line on stderr and exits with its
:attr:`~RetargetError.exit_status`. Any other exception is a bug: the CLI says
so in one line (``internal error ...``) and ``-vv`` shows its traceback.

The classes that report a bad value also derive from :class:`ValueError`, so
callers of the Python API may catch either.
"""

from __future__ import annotations


class RetargetError(Exception):
    """Base class for every error ``retarget`` reports to a user."""

    #: The process exit status the CLI uses for this error.
    exit_status = 1


class InputError(RetargetError, ValueError):
    """An input file is missing, unreadable or does not follow its contract."""


class OutputError(RetargetError, OSError):
    """A file could not be written (a full disk, no permission); the message names the file and the stage."""


class ConfigError(RetargetError, ValueError):
    """A configuration file or option is invalid: a usage error, exit status 2 as for a bad command-line value."""

    exit_status = 2


class UsageError(RetargetError, ValueError):
    """A command-line value the command cannot use (exit status 2, shown as the CLI shows its own usage errors).

    Attributes
    ----------
    param_hint : str or None
        The option it concerns (``"--region"``); None for a clash between options.
    bad_value : bool
        The value of one option is wrong (``Invalid value for '--region': ...``), rather than the usage.
    """

    exit_status = 2

    def __init__(self, message, param_hint: str | None = None, bad_value: bool = True):
        super().__init__(message)
        self.param_hint, self.bad_value = param_hint, bad_value


class ParameterError(RetargetError, ValueError):
    """An argument of a library function is outside what the function accepts."""


class ShapeError(RetargetError, ValueError):
    """An array argument has the wrong shape, dtype or values."""


class TruncatedInputError(InputError):
    """Decoding stopped early; ``last_frame`` is the last frame read (-1 if none)."""

    def __init__(self, message, last_frame):
        super().__init__(message)
        self.last_frame = last_frame


class FaceLostError(InputError):
    """The face was lost: too few landmarks tracked for several frames.

    Attributes
    ----------
    frame : int
        Index (in the frames given) of the first frame of the lost run.
    points, confidence : ndarray
        What was tracked before the face was lost, shapes (frame, L, 2) and (frame, L).
    """

    def __init__(self, message, frame, points, confidence):
        super().__init__(message)
        self.frame, self.points, self.confidence = frame, points, confidence


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP: the run unwinds as on Ctrl-C (temporary files removed) and exits with 128 + the signal."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = int(signum)

    @property
    def exit_status(self) -> int:
        return 128 + self.signum

    @property
    def message(self) -> str:
        import signal

        return f"terminated ({signal.Signals(self.signum).name})"


def stop_cause(exc: BaseException) -> BaseException | None:
    """The Ctrl-C or :class:`Terminated` behind *exc*, if any: a signal that lands while Python 3.11 builds a class
    (``__set_name__``) comes out wrapped in a RuntimeError whose cause it is."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def stop_message(exc: BaseException) -> tuple[str, int]:
    """The one line and exit status of a stop: Ctrl-C (``interrupted``, 130) or :class:`Terminated`."""
    if isinstance(exc, Terminated):
        return exc.message, exc.exit_status
    return "interrupted", INTERRUPTED_EXIT_STATUS


class MissingExtraError(RetargetError):
    """An optional extra (``pip install 'retarget[NAME]'``) is needed and not installed."""


#: Exit status of Ctrl-C (128 + SIGINT), as shells report it.
INTERRUPTED_EXIT_STATUS = 130
