"""Run a C++-backed character reader (usd-core, Assimp) in a child process, on an untrusted file.

Fuzzing showed usd-core aborting (``FATAL ERROR: Dereferenced an invalid SdfPrimSpec``) and allocating without
bound (23 GB before the kernel killed it) on mutated ``.usdc`` files: no check in Python can prevent that inside
the library. So :func:`read_isolated` runs the reader in ``python -m retarget_cli.io.rig._child`` with its address
space limited (:data:`MAX_CHILD_BYTES`) and a time limit (:data:`CHILD_TIMEOUT`): a crash, a runaway allocation or
a hang there is one :class:`~retarget_cli.errors.InputError` line here, and the reader's own errors come back as
they were raised. The result travels as ``.npy`` files and JSON in a temporary folder; the child's log records are
logged again here under their own logger names.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import resource
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from ...errors import InputError, MissingExtraError

log = logging.getLogger(__name__)

#: Address space the child may use (``RLIMIT_AS``); beyond it the reader fails, the process running ``retarget``
#: does not.
MAX_CHILD_BYTES = 8 << 30
#: Seconds the child may take.
CHILD_TIMEOUT = 900
#: Exit statuses of :mod:`._child`.
EXIT_INPUT, EXIT_EXTRA, EXIT_MEMORY = 3, 4, 5
_ARRAYS = ("neutral", "faces", "deltas")


def _limit():  # pragma: no cover - runs in the child before exec
    resource.setrlimit(resource.RLIMIT_AS, (MAX_CHILD_BYTES, MAX_CHILD_BYTES))


def _relog(records: list):
    for name, level, message in records:
        logging.getLogger(name).log(level, "%s", message)


def _crash(path: Path, library: str, code: int, stderr: str) -> InputError:
    if code < 0:
        try:
            what = f"signal {signal.Signals(-code).name}"
        except ValueError:
            what = f"signal {-code}"
    else:
        what = f"exit status {code}"
    lines = [line.strip() for line in stderr.splitlines() if line.strip() and not line.strip().startswith("---")]
    said = next((line for line in lines if "ERROR" in line or "Error" in line), lines[-1] if lines else "")
    tail = said[:160]
    log.debug("%s: the %s reader's child process: %s; %s", path, library, what, stderr[-2000:])
    return InputError(f"{path.name}: {library} stopped reading it ({what}{'; ' + tail if tail else ''}): a corrupt "
                      "or hostile file")


@contextlib.contextmanager
def run_isolated(kind: str, path: Path, library: str, request: dict, *, arrays: dict | None = None):
    """Run :mod:`._child`'s task *kind* on *path* in a child process; yield its output folder.

    *request* (JSON) goes to the task with ``path`` and ``out`` added; *arrays* are saved as ``NAME.npy`` in the
    folder first. The folder is removed when the ``with`` block ends.

    Raises
    ------
    InputError
        The task's own one-line error, or one line for a crash, a runaway allocation or a time-out.
    MissingExtraError
        As the task raised it.
    """
    package = Path(__file__).resolve().parents[3]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(package), *([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])])
    with tempfile.TemporaryDirectory(prefix="retarget-rig-") as out:
        for name, value in (arrays or {}).items():
            np.save(Path(out) / f"{name}.npy", value)
        message = json.dumps({**request, "path": str(path), "out": out})
        try:
            proc = subprocess.run([sys.executable, "-m", "retarget_cli.io.rig._child", kind, message],
                                  capture_output=True, text=True, errors="replace", timeout=CHILD_TIMEOUT, env=env,
                                  preexec_fn=_limit, stdin=subprocess.DEVNULL)
        except subprocess.TimeoutExpired:
            raise InputError(f"{path.name}: {library} took more than {CHILD_TIMEOUT} s to read it; stopped") from None
        meta_path = Path(out) / "result.json"
        meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
        _relog(meta.get("log", []))
        if proc.returncode == EXIT_INPUT:
            raise InputError(meta.get("error") or f"{path.name}: the {library} reader failed")
        if proc.returncode == EXIT_EXTRA:
            raise MissingExtraError(meta.get("error") or f"{path.name}: an optional extra is missing")
        if proc.returncode == EXIT_MEMORY:
            raise InputError(f"{path.name}: reading it needs more than {MAX_CHILD_BYTES >> 30} GiB of memory")
        if proc.returncode != 0 or not meta.get("done"):
            raise _crash(path, library, proc.returncode, proc.stderr)
        yield Path(out)


def read_isolated(kind: str, path: Path, library: str, rig_class, *, meshes=None, targets=None):
    """``rig_class`` read by :mod:`._child`'s reader *kind* (``"usd"``, ``"fbx"``) of *path*, in a child process.

    Raises
    ------
    InputError
        The reader's own one-line error, or one line for a crash, a runaway allocation or a time-out.
    MissingExtraError
        As the reader raised it.
    """
    with run_isolated(kind, path, library, {"meshes": meshes, "targets": targets}) as out:
        fields = dict(json.loads((out / "result.json").read_text())["rig"])
        fields.update({name: np.load(out / f"{name}.npy") for name in _ARRAYS})
    fields["mesh_ranges"] = [tuple(r) for r in fields["mesh_ranges"]]
    fields["target_refs"] = [tuple(r) for r in fields["target_refs"]]
    for key in ("groups", "raw_groups"):
        fields[key] = {k: [(int(j), float(w)) for j, w in v] for k, v in fields[key].items()}
    if "layers" in fields and fields["layers"] is not None:
        fields["layers"] = [Path(p) for p in fields["layers"]]
    return rig_class(**fields)


def write_result(rig, out: Path, records: list):
    """In the child: *rig*'s arrays as ``.npy`` and its other fields, with the log *records*, as JSON."""
    for name in _ARRAYS:
        np.save(out / f"{name}.npy", getattr(rig, name))
    fields = {k: v for k, v in vars(rig).items() if k not in _ARRAYS}
    if fields.get("layers") is not None:
        fields["layers"] = [str(p) for p in fields["layers"]]
    (out / "result.json").write_text(json.dumps({"rig": fields, "log": records, "done": True}))


__all__ = ["CHILD_TIMEOUT", "MAX_CHILD_BYTES", "read_isolated", "run_isolated", "write_result"]
