"""What every stage module shares: the :class:`Stage` declaration, an input that must exist, a silent progress bar."""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from ..config import Flag, Param
from ..errors import InputError
from ..io.rig.cache import cache_limit, rig_cache_dir


@contextlib.contextmanager
def _no_progress(length, label):
    class _Bar:
        def update(self, n):
            pass

    yield _Bar()


def _require(path, what: str) -> Path:
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: {what} not found")
    return path


@dataclass
class Stage:
    """A pipeline stage: its parameters and the runner that executes it.

    :attr:`params` are the stage's own declarations plus those of its
    extensions (*more_params*: the settings registered trackers declare).
    """

    name: str
    help: str
    declared: list
    runner: Callable
    extra_inputs: Callable = field(default=lambda kw: [])
    #: Maps a declared input (param name, path) to the files it stands for (an image-sequence pattern).
    expand_input: Callable = field(default=lambda name, path: [path])
    uses_progress: bool = False
    uses_seed: bool = False
    uses_base_dir: bool = False
    #: The runner takes ``cache_dir`` (the user's rig cache, :func:`~retarget_cli.io.rig.cache.rig_cache_dir`).
    uses_cache: bool = False
    #: Declarations that extensions add, read at each use (a registry may grow after import).
    more_params: Callable = field(default=lambda: [])

    @property
    def params(self) -> list:
        return [*self.declared, *self.more_params()]

    def param(self, name: str) -> Param:
        return next(p for p in self.params if p.name == name)


#: ``--no-cache`` of the commands that read a rig.
NO_CACHE = Param("no_cache", "setting", bool, False,
                 "Read the rig's files every time instead of keeping them parsed in the user's rig cache "
                 "($RETARGET_CACHE_DIR, else ~/.cache/retarget; see `retarget cache`).")
NO_CACHE_FLAG = Flag("no_cache", decls=("--no-cache",), show_default=False)


def command_cache_dir(output, no_cache: bool, *, folder: bool = False) -> Path | None:
    """The rig cache of a command: the user's (:func:`~retarget_cli.io.rig.cache.rig_cache_dir`), shared by
    every run; None with *no_cache*. *output* and *folder* are kept for the callers (the cache no longer lives
    beside the output). ``$RETARGET_CACHE_SIZE`` is checked here, before any work."""
    if no_cache:
        return None
    cache_limit()
    return rig_cache_dir()


# --------------------------------------------------------------------------- what a stage found


_RESULTS: contextvars.ContextVar[dict | None] = contextvars.ContextVar("retarget_stage_results", default=None)


@contextlib.contextmanager
def collect_results() -> Iterator[dict]:
    """Collect what the stage run inside the block reports (:func:`report_result`) into the dict yielded.

    ``retarget run`` records it in the stage's manifest (``results``): facts a
    stage found that are no setting, such as the neutral frame ``auto`` chose.
    """
    found: dict = {}
    token = _RESULTS.set(found)
    try:
        yield found
    finally:
        _RESULTS.reset(token)


def report_result(key: str, value) -> None:
    """Record *value* (JSON-ready) under *key* for the stage's manifest; nothing happens outside
    :func:`collect_results`."""
    found = _RESULTS.get()
    if found is not None:
        found[key] = value
