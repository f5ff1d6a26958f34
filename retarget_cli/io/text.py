"""Text data files read whole: size-capped, UTF-8, YAML through the tool's hardened loader."""

from __future__ import annotations

from pathlib import Path

from ..config import load_yaml
from ..errors import InputError

#: Largest JSON/YAML/text data file read whole (bytes).
MAX_TEXT_BYTES = 256 << 20


def read_text(path: Path, what: str) -> str:
    """A UTF-8 text file's content, or an InputError naming the file (missing, too large, not UTF-8)."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_TEXT_BYTES:
            raise InputError(f"{path}: larger than {MAX_TEXT_BYTES >> 20} MiB; not a {what} file")
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: {what} file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder; expected a {what} file") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text (byte {exc.start} is {data[exc.start:exc.start + 1]!r}); "
                         f"expected a {what} file") from None


def read_yaml_file(path: Path, what: str):
    """A YAML file's content (:func:`retarget_cli.config.load_yaml`'s limits), or an InputError naming the file."""
    return load_yaml(read_text(path, what), str(path), error=InputError)
