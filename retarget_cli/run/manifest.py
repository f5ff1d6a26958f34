"""Stage manifests: what a stage ran with, so ``retarget run`` can skip it while nothing changed (as make and DVC do).

A manifest (``<output_dir>/.retarget/<stage>.json``) records the stage's
resolved settings, the sha256, size and mtime of every input and output, the
version and a fingerprint of the package's code, and the wall-clock time. It
is written last, so a run killed midway is rerun. (The output manifests of a
folder, which say which files a command wrote there, are
:class:`retarget_cli.io.atomic.TrackedOutputs`.)
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

from .. import __version__
from ..errors import InputError
from ..io.atomic import sha256_file, write_json


def code_fingerprint() -> str:
    """sha256 over the package's source files: a code change reruns every stage."""
    import hashlib

    h = hashlib.sha256(__version__.encode())
    root = Path(__file__).parents[1]  # the package (this module is in its run/ folder)
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def record(path: Path) -> dict:
    """A file's entry: sha256, size and modification time."""
    st = path.stat()
    return {"sha256": sha256_file(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def matches(path: Path, rec: dict) -> bool:
    """Whether *path* still is the file *rec* describes (size, then mtime, then the sha256)."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return False
    if st.st_size != rec.get("size"):
        return False
    if st.st_mtime_ns == rec.get("mtime_ns"):
        return True
    return sha256_file(path) == rec.get("sha256")


def record_inputs(inputs) -> dict:
    """Each input's :func:`record`, taken before a stage reads them (:func:`check_unchanged` after it)."""
    return {Path(p): record(Path(p)) for p in inputs}


def check_unchanged(records: dict, stage: str) -> None:
    """Raise if an input of *stage* differs from its record taken when the stage started.

    A file replaced or edited while the stage ran may have been read in either
    state, so the stage's outputs cannot be vouched for: the stage fails and
    no manifest is written (the next run reruns it).

    Raises
    ------
    InputError
        Naming the file and the stage.
    """
    for p, rec in records.items():
        if not matches(p, rec):
            raise InputError(f"{p}: changed while stage '{stage}' ran; its outputs may mix the old and the new "
                             "file, so no manifest is written: run again")


def write_manifest(path: Path, stage: str, *, settings: dict, inputs, outputs, base: Path, seconds: float,
                   results: dict | None = None) -> None:
    """Write a stage's manifest atomically; paths are recorded relative to *base* (the config's folder).

    *inputs*: paths, or the records of :func:`record_inputs` taken when the stage started (so the manifest
    vouches for the bytes the stage read, not for what lies there when it ends).
    *results*: what the stage found that is no setting (e.g. ``neutral``: the frame ``neutral_frame: auto``
    chose, and why); recorded for reports, not part of the up-to-date check.
    """
    recs = inputs if isinstance(inputs, dict) else record_inputs(inputs)
    doc = {
        "stage": stage,
        "version": __version__,
        "code": code_fingerprint(),
        "settings": settings,
        "base": os.path.abspath(base),  # where the relative paths start (preview/report find the video by it)
        "inputs": {os.path.relpath(p, base): rec for p, rec in recs.items()},
        "outputs": {os.path.relpath(p, base): record(p) for p in outputs},
        "seconds": seconds,
    }
    if results:
        doc["results"] = results
    write_json(path, doc)


def manifest_matches(path: Path, *, settings: dict, inputs: Callable, base: Path) -> tuple[bool, str]:
    """Whether the manifest at *path* still matches; returns (ok, reason).

    *inputs* is called only when the version, code and settings match (it may
    read files to list them).
    """
    if not path.is_file():
        return False, "never run"
    try:
        man = json.loads(path.read_text(encoding="utf-8"))
    except ValueError:  # invalid JSON or not UTF-8
        return False, "manifest unreadable"
    if not isinstance(man, dict):
        return False, "manifest unreadable"
    if man.get("version") != __version__ or man.get("code") != code_fingerprint():
        return False, "retarget version or code changed"
    if man.get("settings") != settings:
        return False, "settings changed"
    files = inputs()
    if sorted(man.get("inputs", {})) != sorted(os.path.relpath(p, base) for p in files):
        return False, "input files changed"
    for p in files:
        if not matches(p, man["inputs"][os.path.relpath(p, base)]):
            return False, f"{os.path.relpath(p, base)} changed"
    for rel, rec in man.get("outputs", {}).items():
        if not matches(base / rel, rec):
            return False, f"output {rel} missing or modified"
    return True, "up to date"
