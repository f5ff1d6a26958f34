"""``python -m retarget_cli.io.rig._child KIND REQUEST``: one character reader run here, for :mod:`._isolated`.

*KIND* is ``usd`` or ``fbx`` (a reader), or ``usd-copy`` (the animated copy of a USD character,
:mod:`._usd_copy`); *REQUEST* is JSON ``{"path", "meshes", "targets", "out", ...}``. A rig goes to *out*
(:func:`~retarget_cli.io.rig._isolated.write_result`), a copy to ``out/copy.<suffix>``; the one-line error to
``out/result.json`` with exit status 3 (4 for a missing extra, 5 for memory), the log records with either.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

from ...errors import InputError, MissingExtraError
from . import _usd_copy, fbx, usd
from ._isolated import EXIT_EXTRA, EXIT_INPUT, EXIT_MEMORY, write_result

READERS = {"usd": usd.read_usd_here, "fbx": fbx.read_fbx_here}


class _Keep(logging.Handler):
    """Keeps every record as (logger name, level, message)."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.records: list = []

    def emit(self, record):
        self.records.append((record.name, record.levelno, record.getMessage()))


def main(argv: list[str]) -> int:
    kind, request = argv[1], json.loads(argv[2])
    out = Path(request["out"])
    keep = _Keep()
    top = logging.getLogger("retarget_cli")
    top.addHandler(keep)
    top.setLevel(logging.DEBUG)
    top.propagate = False
    try:
        if kind == "usd-copy":
            _usd_copy.animate_here(request["path"], request, out)
            (out / "result.json").write_text(json.dumps({"done": True, "log": keep.records}))
            return 0
        rig = READERS[kind](request["path"], meshes=request["meshes"], targets=request["targets"])
    except (InputError, MissingExtraError, MemoryError) as exc:
        status = EXIT_MEMORY if isinstance(exc, MemoryError) else EXIT_EXTRA if isinstance(
            exc, MissingExtraError) else EXIT_INPUT
        (out / "result.json").write_text(json.dumps({"error": str(exc), "log": keep.records}))
        return status
    write_result(rig, out, keep.records)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
