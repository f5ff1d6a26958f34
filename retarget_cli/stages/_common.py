"""Helpers every stage runner shares: an input that must exist, a progress bar that shows nothing."""

from __future__ import annotations

import contextlib
from pathlib import Path

from ..errors import InputError


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
