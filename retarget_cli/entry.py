"""The ``retarget`` console script: the CLI behind a handler that catches what the CLI cannot.

This module imports nothing heavy, so that a Ctrl-C while the CLI's modules load
(numpy, OpenCV, numba take a few tenths of a second) still gives one line and
exit status 130 instead of a traceback; any other exception that escapes the
CLI is one line and exit status 1 (``-vv`` shows its traceback).
"""

from __future__ import annotations

import sys


def _fail(exc: BaseException) -> int:
    from .errors import stop_cause, stop_message

    stop = stop_cause(exc)
    if stop is not None or type(exc).__name__ == "Abort":
        msg, code = stop_message(stop if stop is not None else exc)
        print(f"error: {msg}", file=sys.stderr)
        return code
    if "-vv" in sys.argv[1:3] or sys.argv[1:3].count("-v") >= 2 or "--verbose" in sys.argv[1:2]:
        import traceback

        traceback.print_exception(exc)
    try:
        from .cli.commands import one_line

        msg = one_line(exc)
    except BaseException:
        msg = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
    print(f"error: {msg}", file=sys.stderr)
    return 1


def _on_signal(signum, frame):
    from .errors import Terminated

    raise Terminated(signum)


def _stop_on_signals() -> None:
    """SIGTERM and SIGHUP unwind the run like Ctrl-C: temporary files are removed, one line, exit 128 + signal."""
    import signal

    for name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), _on_signal)


#: glibc's ``M_MMAP_THRESHOLD`` (mallopt parameter), and the value the console script fixes it at (1 MiB).
_M_MMAP_THRESHOLD, MMAP_THRESHOLD = -3, 1 << 20


def fix_mmap_threshold(nbytes: int = MMAP_THRESHOLD) -> bool:
    """Keep glibc's mmap threshold at *nbytes*: every larger block (a long take's per-frame arrays, a window's
    state) is mapped on its own and given back to the system when freed.

    Left to itself glibc raises the threshold to the largest block freed so far (up to 32 MB), so that a long
    take's arrays (a few MB each) come from the heap afterwards, where what is freed stays with the process
    and the heap fragments: ``track`` on the 3-minute synthetic take of ``bench/gaps.py --long`` peaked
    7.4 MB higher. A mapped block costs page faults each time it is made: at 128 KiB (glibc's starting value)
    every decoded 256x256 frame was one, 23 times the faults; at 1 MiB 10 times, for the same peak
    (docs/benchmarks.md). Returns whether it was set (False where the C library is not glibc).
    """
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, int(nbytes)))


def main(argv=None) -> None:
    """Run the CLI; exit with its status (130 on Ctrl-C, 143/129 on SIGTERM/SIGHUP, 1 or 2 on an error)."""
    _stop_on_signals()
    fix_mmap_threshold()
    try:
        import click

        from .cli.commands import main as cli

        try:
            code = cli.main(args=argv, prog_name="retarget", standalone_mode=False)
        except click.ClickException as exc:
            exc.show()
            code = exc.exit_code
        except click.exceptions.Exit as exc:
            code = exc.exit_code
    except SystemExit:
        raise
    except BaseException as exc:
        code = _fail(exc)
    sys.exit(code if isinstance(code, int) else 0)


if __name__ == "__main__":  # pragma: no cover
    main()
