"""Atomic, deterministic file writing.

Every output is written to a temporary file in the destination directory and
renamed over the destination only once it is complete, so a crash or Ctrl-C
never leaves a half-written file that a rerun could mistake for finished work.
(Files are not fsync'ed: rename is atomic against crashes and signals; after a
power loss the stage manifests' sizes and hashes catch a truncated file.)
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import tempfile
import zipfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import IO

import numpy as np

from ..errors import InputError

#: Fixed timestamp for zip members, so that NPZ files are byte-identical
#: across runs (``numpy.savez`` stamps the current time).
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file next to *path*; rename it onto *path* on success.

    Parameters
    ----------
    path : path-like
        Final destination. Its parent directory is created if needed.
    mode : {"wb", "w"}
        Binary or text (UTF-8, ``\\n`` newlines) mode.

    Yields
    ------
    file object
        Write to it; on an exception the temporary file is removed and
        *path* is left untouched.
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        kwargs = {} if mode == "wb" else {"encoding": "utf-8", "newline": "\n"}
        with os.fdopen(fd, mode, **kwargs) as fh:
            yield fh
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Atomically write *data* to *path*."""
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Atomically write UTF-8 *text* to *path*."""
    write_bytes(path, text.encode("utf-8"))


def dumps_json(obj) -> str:
    """Deterministic JSON: sorted keys, two-space indent, trailing newline."""
    return json.dumps(obj, indent=2, sort_keys=True, allow_nan=False) + "\n"


def write_json(path: str | os.PathLike, obj) -> None:
    """Atomically write *obj* as deterministic JSON."""
    write_text(path, dumps_json(obj))


def savez(path: str | os.PathLike, arrays: Mapping[str, np.ndarray], compress: bool = True) -> None:
    """Atomically write an ``.npz`` archive with byte-identical output.

    Same layout as :func:`numpy.savez_compressed` (readable by
    :func:`numpy.load`), but members carry a fixed timestamp and are written
    in the order given.

    Parameters
    ----------
    path : path-like
        Destination ``.npz`` file.
    arrays : mapping of str to array_like
        Member name (without ``.npy``) to array. Strings become unicode arrays.
    compress : bool
        Deflate members (default) or store them.
    """
    buf = io.BytesIO()
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(buf, "w", compression=method) as zf:
        for name, value in arrays.items():
            arr = np.asanyarray(value)
            if arr.dtype == object:
                raise ValueError(f"array {name!r} has dtype object; refusing to pickle")
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
            info.compress_type = method
            info.external_attr = 0o644 << 16
            member = io.BytesIO()
            np.lib.format.write_array(member, arr, allow_pickle=False)
            zf.writestr(info, member.getvalue())
    write_bytes(path, buf.getvalue())


def load_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read every member of an ``.npz`` file into a dict (no pickles).

    Raises
    ------
    InputError
        If the file is missing or is not a readable ``.npz`` archive.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    with open(path, "rb") as fh:
        if fh.read(4) != b"PK\x03\x04":
            raise InputError(f"{path}: not an .npz archive (no zip header)")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from exc


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def check_not_input(output: str | os.PathLike, inputs) -> None:
    """Refuse to write *output* if it is one of the *inputs* (never overwrite a user's input).

    Raises
    ------
    InputError
        If *output* resolves to the same file as any input.
    """
    out = Path(output).resolve()
    for inp in inputs:
        if inp is not None and Path(inp).resolve() == out:
            raise InputError(f"{output}: output would overwrite the input {inp}; choose another output path")
