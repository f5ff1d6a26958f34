"""Command-line interface: a click command built from each :class:`~retarget_cli.config.Command` declaration.

The commands are declared beside the code they run (a stage's in its
``stages/`` module, ``run`` in :mod:`retarget_cli.run.pipeline`, the pictures
in :mod:`retarget_cli.see.commands`, ...) and listed in :data:`DECLARED`; this
module only turns declarations into click options, prints, and turns errors
into one line and an exit status.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import logging
import os
import sys
from pathlib import Path

import click

from .. import __version__
from ..batch import command as batch_command
from ..config import UNSET, Command, Flag, Param, show_paths
from ..errors import RetargetError, UsageError, stop_cause, stop_message
from ..io.atomic import guard_writes, hash_memo, remove_stale_parts
from ..io.rig.cache import hash_memo_dir
from ..run import cache as cache_command
from ..run import pipeline
from ..see import commands as see_commands
from ..stages import annotate, apply, auto_pose, decompose, edit, map_landmarks, pose, select, solve_rig, track
from ..synth import take
from .types import VALUE_TYPES, NumberOrWord

log = logging.getLogger("retarget_cli")

#: Every command, by the module that declares it (``retarget --help`` lists them by name).
DECLARED: list[Command] = [
    *track.COMMANDS, annotate.COMMAND, select.COMMAND, decompose.COMMAND, pose.COMMAND, apply.COMMAND,
    edit.COMMAND, auto_pose.COMMAND, map_landmarks.COMMAND, solve_rig.COMMAND, pipeline.COMMAND, batch_command.COMMAND,
    *see_commands.COMMANDS, take.COMMAND, cache_command.COMMAND,
]

_TYPES = {int: click.INT, float: click.FLOAT, str: click.STRING}
_PATHS = {"file": dict(dir_okay=False), "folder": dict(file_okay=False), "path": {}, "out": dict(dir_okay=True),
          "existing": dict(exists=True)}


def declaration(name: str) -> Command:
    """The :class:`~retarget_cli.config.Command` named *name* (``pose-keys``)."""
    return next(c for c in DECLARED if c.name == name)


def command_params(name: str) -> list[Param]:
    """The declared parameters of the command *name*."""
    return declaration(name).params()


def flags_of(command: Command) -> list[Flag]:
    """*command*'s flags in ``--help`` order, each a :class:`~retarget_cli.config.Flag`."""
    flags = command.flags() if callable(command.flags) else command.flags
    return [Flag(f) if isinstance(f, str) else f for f in flags]


def _click_type(p: Param, f: Flag):
    if f.value is not None:
        return VALUE_TYPES[f.value](**dict(f.value_args))
    if f.path is not None:
        return click.Path(**_PATHS[f.path])
    if p.options:
        return click.Choice(p.options)
    number = _TYPES.get(p.type, click.STRING)
    if p.type in (int, float) and (p.min is not None or p.max is not None):
        rng = click.IntRange if p.type is int else click.FloatRange
        number = rng(p.min, p.max, min_open=p.min_open, max_open=p.max_open)
    if p.kind == "setting" and p.words and p.type in (int, float):
        return NumberOrWord(number, p.words)
    return number


def _option(p: Param, f: Flag) -> click.Option:
    """The click option of *p* as *f* shows it: its flag, help, type, range or choices, default."""
    flag = "--" + p.name.replace("_", "-")
    default = (None if p.required else p.default) if f.default is UNSET else f.default
    kw = dict(help=p.help if f.help is None else f.help, show_default=f.show_default, default=default)
    if p.type is bool and f.value is None:
        decls = f.decls or (f"{flag}/--no-{flag[2:]}",)
        kw["is_flag"] = True
    else:
        decls = f.decls or (flag,)
        kw.update(type=_click_type(p, f), multiple=f.multiple)
        if f.required:
            kw["required"] = True
    if f.metavar is not None:
        kw["metavar"] = f.metavar
    return click.Option([*decls, f.name], **kw)


def _argument(p: Param, f: Flag) -> click.Argument:
    kw = dict(type=_click_type(p, f), nargs=f.nargs, metavar=f.metavar)
    if f.required is not None:
        kw["required"] = f.required
    return click.Argument([f.name], **kw)


def click_params(command: Command) -> list[click.Parameter]:
    """The click arguments and options of *command*, from its declared parameters."""
    params = {p.name: p for p in command.params()}
    return [(_argument if f.argument else _option)(params[f.name], f) for f in flags_of(command)]


@contextlib.contextmanager
def progress(length, label):
    """A click progress bar on stderr (hidden when stderr is not a terminal or with -q)."""
    quiet = logging.getLogger("retarget_cli").getEffectiveLevel() > logging.WARNING
    if length is None or quiet:
        class _Null:
            def update(self, n):
                pass

        yield _Null()
        return
    with click.progressbar(length=length, label=label, file=sys.stderr) as bar:
        yield bar


def _drop_stdout() -> None:
    """Point stdout at the null device, so that what is buffered and the exit's flush do not fail again."""
    try:
        fd = sys.stdout.fileno()
    except (OSError, ValueError, AttributeError):
        return
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, fd)
    os.close(null)


class Console:
    """What a command's runner prints through (:class:`~retarget_cli.config.Command`'s *out*)."""

    progress = staticmethod(progress)

    def __init__(self):
        self.stdout_lost = False
        self.quiet = log.getEffectiveLevel() > logging.WARNING
        self.debug = log.isEnabledFor(logging.DEBUG)

    def echo(self, text) -> None:
        """*text* on stdout; once stdout failed (a closed pipe, a full disk) the rest is dropped and the work goes on."""
        if self.stdout_lost:
            return
        try:
            click.echo(text)
        except OSError as exc:
            if exc.errno not in (errno.EPIPE, errno.ENOSPC, errno.EIO):
                raise
            self.stdout_lost = True
            _drop_stdout()
            if exc.errno != errno.EPIPE:  # a reader that went away asked for nothing more; anything else is said
                click.echo(f"warning: stdout: {exc.strerror}; the rest of the output is not printed", err=True)

    def say(self, text) -> None:
        if not self.quiet:
            click.echo(text, err=True)


def one_line(exc: BaseException) -> str:
    """An exception as the one-line message the CLI prints.

    The tool's own errors (:class:`~retarget_cli.errors.RetargetError`), an
    ``OSError`` naming a file and running out of memory are the user's to fix and
    print their message; anything else is a bug and says so.
    """
    if isinstance(exc, OSError) and getattr(exc, "filename", None):
        return f"{exc.filename}: {exc.strerror or exc}"
    if isinstance(exc, MemoryError):
        return "out of memory" + (f" ({exc})" if str(exc) else "") + "; is an input far larger than expected?"
    msg = " ".join(str(exc).split())
    if isinstance(exc, RetargetError) and msg:
        return msg
    return (f"internal error ({type(exc).__name__}{': ' + msg[:300] if msg else ''}); "
            "rerun with -vv for the traceback")


def exit_status(exc: BaseException) -> int:
    """The exit status for *exc*: its own for the tool's errors, else 1."""
    return getattr(exc, "exit_status", 1) if isinstance(exc, RetargetError) else 1


def _input_files(value) -> list:
    """The files a path-valued argument stands for (a folder's files, a glob's matches, REGION=FILE's file)."""
    if isinstance(value, (tuple, list)):
        return [f for v in value for f in _input_files(v)]
    if not isinstance(value, str) or not value:
        return []
    if "=" in value and not Path(value).exists():
        value = value.partition("=")[2]
    p = Path(value)
    if p.is_dir():
        return sorted(f for f in p.iterdir() if f.is_file())[:100_000]
    if any(c in value for c in "*?["):
        return sorted(glob.glob(value))[:100_000]
    return [p]


class DeclaredCommand(click.Command):
    """A click command built from a :class:`~retarget_cli.config.Command`.

    A guarded command's writes pass the write guard
    (:func:`retarget_cli.io.atomic.guard_writes`): they may go inside the folder
    of each output the user named (or into the output folder itself) and never
    onto a file the command reads. Temporary files a killed run left there are
    removed first.
    """

    def __init__(self, declared: Command):
        self.declared = declared
        super().__init__(declared.name, params=click_params(declared), callback=self._run, help=declared.help)

    def _run(self, **values):
        out = Console()
        try:
            with hash_memo(None if values.get("no_cache") else hash_memo_dir()):
                result = self.declared.run(values, out)
            (self.declared.show or show_paths)(result, out)
        except UsageError as exc:
            if exc.bad_value:
                raise click.BadParameter(str(exc), param_hint=exc.param_hint) from None
            raise click.UsageError(str(exc)) from None

    def _outputs(self, ctx) -> tuple[list, list, list, list]:
        params = {p.name: p for p in self.declared.params()}
        roots, files, inputs, recursive = [], [], [], []
        for f in flags_of(self.declared):
            value = ctx.params.get(f.name)
            if value is None or isinstance(value, bool):
                continue
            if params[f.name].kind == "output":
                if not isinstance(value, str):
                    continue
                out = Path(value)
                folder = f.path == "folder" or (f.name == "output" and self.declared.folder_output)
                roots.append(out if folder else out.parent)
                recursive.append(folder)
                files.append(out)
            elif isinstance(value, (str, tuple, list)):
                inputs += _input_files(value)
        return roots, files, inputs, recursive

    def invoke(self, ctx):
        if not self.declared.guarded:  # run guards each run's output_dir; batch its batch folder
            return super().invoke(ctx)
        roots, files, inputs, recursive = self._outputs(ctx)
        with guard_writes(roots=roots, files=files, inputs=inputs,
                          label="the folders of the outputs given on the command line"):
            for root, rec in zip(roots, recursive):
                remove_stale_parts(root, recursive=rec)
            return super().invoke(ctx)


class RetargetGroup(click.Group):
    """Turns every error into a one-line message and a non-zero exit (``-vv`` adds the traceback).

    Errors: their own exit status (1, or 2 for usage and config errors); Ctrl-C: exit status 130; SIGTERM and
    SIGHUP (:class:`~retarget_cli.errors.Terminated`): 128 + the signal.
    """

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (click.exceptions.Exit, click.ClickException, click.exceptions.Abort):
            raise
        except KeyboardInterrupt as exc:
            log.debug("interrupted", exc_info=True)
            msg, code = stop_message(exc)
            click.echo(f"error: {msg}", err=True)
            ctx.exit(code)
        except Exception as exc:
            log.debug("traceback of the error below", exc_info=True)
            stop = stop_cause(exc)
            if stop is not None:  # a signal wrapped by the interpreter (a class being built when it landed)
                msg, code = stop_message(stop)
                click.echo(f"error: {msg}", err=True)
                ctx.exit(code)
            click.echo(f"error: {one_line(exc)}", err=True)
            ctx.exit(exit_status(exc))


@click.group(cls=RetargetGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="retarget")
@click.option("-v", "--verbose", count=True, help="More log output on stderr (-vv for debug).")
@click.option("-q", "--quiet", is_flag=True, help="Only errors on stderr.")
def main(verbose: int, quiet: bool):
    """Retarget a video of an actor's face onto a blendshape character.

    \b
    Stages:  track -> select -> decompose -> apply   (chained by `retarget run`)
    Example: retarget synth demo/ && retarget run demo/config.yaml
    """
    level = logging.ERROR if quiet else (logging.DEBUG if verbose > 1 else logging.INFO if verbose else logging.WARNING)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr, force=True)
    logging.getLogger("retarget_cli").setLevel(level)


for _declared in DECLARED:
    main.add_command(DeclaredCommand(_declared))


if __name__ == "__main__":  # pragma: no cover
    main()
