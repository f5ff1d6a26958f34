"""Atomic, deterministic, guarded file writing.

Every output is written to a temporary file in the destination directory and
renamed over the destination only once it is complete, so a crash or Ctrl-C
never leaves a half-written file that a rerun could mistake for finished work.
(Files are not fsync'ed: rename is atomic against crashes and signals; after a
power loss the stage manifests' sizes and hashes catch a truncated file.)

The write guard (:func:`guard_writes`, :func:`check_write`) is the one check
every written or deleted file passes: resolved, it must lie inside an output
folder (or be a file the user named), and it must not be an input of the run.
The output manifest of a folder (:func:`tracked_outputs`) lists the files a
command wrote there, so that clearing stale outputs removes only those.
Temporary ``.part`` files left by a killed run are removed by
:func:`remove_stale_parts` at the start of the next.
"""

from __future__ import annotations

import array
import contextlib
import contextvars
import hashlib
import io
import json
import logging
import os
import re
import secrets
import sys
import time
import zipfile
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np

from .._validate import check_name
from ..errors import InputError, ParameterError

log = logging.getLogger(__name__)

#: Fixed timestamp for zip members, so that NPZ files are byte-identical
#: across runs (``numpy.savez`` stamps the current time).
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


#: Name of a temporary file of :func:`atomic_open`: ``.<name>.<8 hex or mkstemp chars>.part``
#: (videos: ``.part.<suffix>``, as OpenCV picks the container by the suffix).
PART_RE = re.compile(r"^\..+\.[a-z0-9_]{8}\.part(\.[A-Za-z0-9]{1,5})?$")


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file next to *path*; rename it onto *path* on success.

    The destination passes :func:`check_write` first. The temporary file is
    named before it is created, inside the ``try``, so an exception (Ctrl-C
    included) at any moment removes it; a SIGKILL leaves a ``.part`` file that
    :func:`remove_stale_parts` removes at the start of the next run, because
    its name was written to this process's journal first (:func:`part_name`).

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
        raise ParameterError(f"mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    check_write(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = None
    try:
        while True:
            tmp = part_name(path)
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o644)
                break
            except FileExistsError:
                continue
        kwargs = {} if mode == "wb" else {"encoding": "utf-8", "newline": "\n"}
        with os.fdopen(fd, mode, **kwargs) as fh:
            yield fh
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        if isinstance(exc, OSError) and not exc.filename and exc.errno:  # a write or close (a full disk): name it
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Atomically write *data* to *path*; its sha256 is remembered for :func:`sha256_file` in this process
    (a stage's outputs are hashed for its manifests, and again as the next stage's inputs)."""
    with atomic_open(path, "wb") as fh:
        fh.write(data)
    digest = hashlib.sha256(data).hexdigest()
    with contextlib.suppress(OSError):
        _HASHES[_stat_key(os.stat(path))] = digest


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
    in the order given. The archive is streamed into the temporary file
    (:func:`atomic_open`), each member deflated as it is written: no copy of a
    member or of the archive is held in memory (a long take's ``landmarks.npz``
    is a few KB a frame).

    Parameters
    ----------
    path : path-like
        Destination ``.npz`` file.
    arrays : mapping of str to array_like
        Member name (without ``.npy``) to array. Strings become unicode arrays.
    compress : bool
        Deflate members (default) or store them.
    """
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    members = []
    for name, value in arrays.items():
        arr = value if isinstance(value, NpyChunks) else np.asanyarray(value)
        if arr.dtype == object:
            raise ParameterError(f"array {name!r} has dtype object; refusing to pickle")
        if isinstance(arr, np.ndarray) and arr.ndim and arr.flags.c_contiguous and arr.size and arr.dtype.itemsize:
            # written from the array itself ~1 MiB of rows at a time (write_array would copy up to 16 MiB)
            row = max(arr.nbytes // len(arr), 1)
            arr = NpyChunks(arr.shape, arr.dtype, lambda a, b, v=arr: v[a:b], max(1, (1 << 20) // row))
        members.append((name, arr))
    with atomic_open(path, "wb") as fh, zipfile.ZipFile(fh, "w", compression=method) as zf:
        for name, arr in members:
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
            info.compress_type = method
            info.external_attr = 0o644 << 16
            header = _npy_header(arr)
            # the member's size, known before it is written (as ``writestr`` knows it): zipfile picks the
            # header's format (ZIP64 or not) from it, so the bytes are those of writing the member whole
            info.file_size = len(header) + int(np.prod(arr.shape, dtype=np.int64)) * arr.dtype.itemsize
            with zf.open(info, "w") as dest:
                if isinstance(arr, NpyChunks):
                    dest.write(header)
                    for block in arr.blocks():
                        dest.write(block.reshape(-1).view(np.uint8))
                else:
                    np.lib.format.write_array(dest, arr, allow_pickle=False)


@dataclass(frozen=True)
class NpyChunks:
    """An array that :func:`savez` writes a block of rows at a time, never holding it whole.

    *rows* ``(a, b)`` gives rows ``a:b`` (any dtype: converted to *dtype* as ``numpy.asarray`` would); the
    member's bytes are those of the whole array (``rows(0, n)``) saved in the ``.npy`` format.
    """

    shape: tuple
    dtype: np.dtype
    rows: object
    block: int = 4096

    def __post_init__(self):
        object.__setattr__(self, "shape", tuple(int(n) for n in self.shape))
        object.__setattr__(self, "dtype", np.dtype(self.dtype))

    def blocks(self):
        """The rows in order, *block* at a time, as C-ordered arrays of :attr:`dtype`."""
        n = self.shape[0] if self.shape else 1
        for a in range(0, n, self.block):
            b = min(n, a + self.block)
            part = np.ascontiguousarray(self.rows(a, b), dtype=self.dtype)
            if part.shape != (b - a, *self.shape[1:]):
                raise ParameterError(f"rows {a}:{b}: expected shape {(b - a, *self.shape[1:])}, got {part.shape}")
            yield part


def _npy_header(arr) -> bytes:
    """The ``.npy`` header :func:`numpy.lib.format.write_array` writes for *arr* (an array or :class:`NpyChunks`)."""
    fmt = np.lib.format
    if isinstance(arr, NpyChunks):
        d = {"descr": fmt.dtype_to_descr(arr.dtype), "fortran_order": False, "shape": arr.shape}
    else:
        d = fmt.header_data_from_array_1_0(arr)
    header = io.BytesIO()
    try:
        fmt.write_array_header_1_0(header, d)
    except ValueError:  # a header too long for format 1.0: write_array moves to 2.0
        header = io.BytesIO()
        fmt.write_array_header_2_0(header, d)
    return header.getvalue()


class _PartFile:
    """A temporary file beside an output (``self.path``, open as ``self._fh``), removed on :meth:`close`; a
    context manager."""

    path = None
    _fh = None

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
        if self.path is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class RowSpill(_PartFile):
    """Rows of an array kept in a temporary file beside *path* instead of in memory: written once, in order
    (:meth:`write`), read back a block at a time (:meth:`chunks`, for :func:`savez`), removed on :meth:`close`.

    The file is a :func:`part_name` of *path* (a killed run's is removed by :func:`remove_stale_parts`) and
    passes the write guard like *path*. Use as a context manager.
    """

    def __init__(self, path, shape, dtype):
        path = Path(path)
        check_write(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.shape, self.dtype, self.n = tuple(int(n) for n in shape), np.dtype(dtype), 0
        self._row = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize
        self._fh, self.path = None, None
        self.path, self._fh = _new_part(path, ".npy")

    def write(self, rows) -> None:
        """Append *rows* (k, *shape[1:]), converted to the spill's dtype."""
        part = np.ascontiguousarray(rows, dtype=self.dtype)
        if part.shape[1:] != self.shape[1:] or self.n + len(part) > self.shape[0]:
            raise ParameterError(f"spill: rows of shape {part.shape} do not fit {self.shape} after {self.n} rows")
        self._fh.seek(self.n * self._row)
        self._fh.write(part.tobytes())
        self.n += len(part)

    def _read(self, a: int, b: int) -> np.ndarray:
        out = np.empty((b - a, *self.shape[1:]), self.dtype)
        self._fh.seek(a * self._row)
        if self._fh.readinto(memoryview(out).cast("B")) != out.nbytes:
            raise OSError(f"{self.path}: short read")
        return out

    def chunks(self, block: int = 4096) -> NpyChunks:
        """The spilled array as a :func:`savez` member (every row must have been written)."""
        if self.n != self.shape[0]:
            raise ParameterError(f"spill: {self.n} of {self.shape[0]} rows written")
        self._fh.flush()
        return NpyChunks(self.shape, self.dtype, self._read, block)



def _new_part(path: Path, suffix: str):
    """A new temporary file beside *path* (:func:`part_name`), created exclusively: ``(name, open file "w+b")``."""
    while True:
        tmp = part_name(path, suffix)
        try:
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o600)
            break
        except FileExistsError:
            continue
    return tmp, os.fdopen(fd, "w+b")


class CropSpill(_PartFile):
    """A rectangle of each frame of a take (gray ``uint8``) kept in a temporary file beside *path*: added in frame
    order (:meth:`add`), read back in order pasted into a frame-sized image (:meth:`frames`), removed on
    :meth:`close`. What is held in memory is four integers a frame (the rectangles).

    The file is a :func:`part_name` of *path* (a killed run's is removed by :func:`remove_stale_parts`) and
    passes the write guard like *path*. Use as a context manager.
    """

    def __init__(self, path):
        path = Path(path)
        check_write(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self._boxes = array.array("q")
        self._fh, self.path = None, None
        self.path, self._fh = _new_part(path, ".crops")
        self.nbytes = 0  # pixel bytes written so far

    def __len__(self) -> int:
        return len(self._boxes) // 4

    def discard(self) -> None:
        """Remove the file and forget every rectangle (the spill then holds no frame; :meth:`add` refuses)."""
        self.close()
        self._boxes = array.array("q")

    def add(self, image, box) -> None:
        """Append the rectangle *box* ``[x0, y0, x1, y1)`` (pixels, clipped to the image) of *image* (H, W), uint8."""
        image = np.asarray(image)
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ParameterError(f"crop spill: expected a gray uint8 image (H, W), got {image.dtype} {image.shape}")
        h, w = image.shape
        x0, y0, x1, y1 = (int(v) for v in box)
        x0, x1 = min(max(x0, 0), w), min(max(x1, 0), w)
        y0, y1 = min(max(y0, 0), h), min(max(y1, 0), h)
        x1, y1 = max(x1, x0), max(y1, y0)
        if self._fh is None:
            raise ValueError(f"crop spill {self.path}: closed")
        data = np.ascontiguousarray(image[y0:y1, x0:x1]).tobytes()
        self._fh.write(data)
        self.nbytes += len(data)
        self._boxes.extend((x0, y0, x1, y1))

    def boxes(self) -> np.ndarray:
        """The rectangles kept, clipped to the image: (n, 4) int64 ``[x0, y0, x1, y1)``."""
        return np.frombuffer(self._boxes, np.int64).reshape(-1, 4).copy() if len(self) else np.zeros((0, 4), np.int64)

    def frames(self, size, n: int | None = None):
        """The first *n* (default: all) frames, each its rectangle pasted into one image of *size* ``(W, H)``
        (yielded again for every frame: its pixels outside the frame's rectangle are those of earlier frames or
        0)."""
        W, H = (int(v) for v in size)
        canvas = np.zeros((H, W), np.uint8)
        self._fh.flush()
        self._fh.seek(0)
        boxes = self.boxes()
        for x0, y0, x1, y1 in boxes[:n]:
            part = np.empty((y1 - y0, x1 - x0), np.uint8)
            if part.size and self._fh.readinto(memoryview(part).cast("B")) != part.nbytes:
                raise OSError(f"{self.path}: short read")
            canvas[y0:y1, x0:x1] = part
            yield canvas



#: Largest array a data file may hold once loaded (bytes); guards against zip bombs and huge headers.
MAX_ARRAY_BYTES = int(os.environ.get("RETARGET_MAX_ARRAY_BYTES", 4 << 30))


#: :func:`load_npz` reads the members in parallel when at least two are this large (uncompressed bytes).
_PARALLEL_MIN_BYTES = 1 << 22


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path, limit: int) -> tuple[str, np.ndarray]:
    """(key, array) of one ``.npy`` member of an open archive; its header is checked before its data is read."""
    key = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
    where = f"{path}: member {key!r}"
    with zf.open(info) as fh:
        try:
            version = np.lib.format.read_magic(fh)
            reader = {(1, 0): np.lib.format.read_array_header_1_0,
                      (2, 0): np.lib.format.read_array_header_2_0}.get(version)
            if reader is None:
                raise ParameterError(f"unsupported .npy version {version}")
            shape, fortran, dtype = reader(fh)
        except Exception as exc:  # numpy raises ValueError, SyntaxError, TypeError...
            raise InputError(f"{where}: not valid .npy data ({' '.join(str(exc).split())[:200]})") from None
        if dtype.hasobject:
            raise InputError(f"{where}: holds Python objects (pickles are refused)")
        n = 1
        for d in shape:
            n *= int(d)
        if n * max(dtype.itemsize, 1) > limit:
            raise InputError(f"{where}: array of shape {shape} ({dtype}) is larger than the "
                             f"{limit / 2**30:.3g} GiB limit")
        return key, _read_data(fh, shape, fortran, dtype, where)


def _read_data(fh, shape, fortran: bool, dtype, where: str) -> np.ndarray:
    """The data of an ``.npy`` member after its header, read in one call.

    One read decompresses the whole member at once (numpy's reader takes
    256 KiB at a time, each a separate call into zlib that gives up and
    retakes the GIL, slow when another thread holds it).
    """
    arr = np.empty(shape[::-1] if fortran else shape, dtype=dtype)
    nbytes = arr.nbytes
    if nbytes:
        got = fh.readinto(memoryview(arr.reshape(-1).view(np.uint8)))
        if got != nbytes:
            raise InputError(f"{where}: not valid .npy data (truncated: {got} of {nbytes} bytes)")
    return arr.T if fortran else arr


def load_npz(path: str | os.PathLike, *, max_bytes: int | None = None) -> dict[str, np.ndarray]:
    """Read every member of an ``.npz`` file into a dict (no pickles).

    Each member's ``.npy`` header is checked before its data is read: a
    malformed header, an object dtype or an array larger than *max_bytes*
    (default :data:`MAX_ARRAY_BYTES`) is an error naming the file and member.

    Raises
    ------
    InputError
        If the file is missing or is not a readable ``.npz`` archive.
    """
    path = Path(path)
    limit = MAX_ARRAY_BYTES if max_bytes is None else max_bytes
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    with open(path, "rb") as fh:
        if fh.read(4) != b"PK\x03\x04":
            raise InputError(f"{path}: not an .npz archive (no zip header)")
    try:
        with zipfile.ZipFile(path) as zf:
            members = [info for info in zf.infolist() if not info.is_dir()]
            big = sum(info.file_size >= _PARALLEL_MIN_BYTES for info in members)
            if big >= 2 and (os.cpu_count() or 1) > 1:
                # zlib gives up the GIL while it inflates: large members decompress side by side
                from concurrent.futures import ThreadPoolExecutor

                with ThreadPoolExecutor(max_workers=min(big, 4, os.cpu_count() or 1)) as pool:
                    futures = [pool.submit(_read_member, zf, info, path, limit) for info in members]
                    # in member order, so that the error reported is the same as a serial read's
                    out = dict(f.result() for f in futures)
            else:
                out = dict(_read_member(zf, info, path, limit) for info in members)
    except InputError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, NotImplementedError, RuntimeError) as exc:
        raise InputError(f"{path}: not a readable .npz file ({' '.join(str(exc).split())[:200]})") from None
    return out


# --------------------------------------------------------------------------- file hashes, memoised

#: A file's hash is remembered only when its mtime and ctime are at least this much older than the moment it
#: was hashed: a file changed again within the file system's timestamp granularity would keep the same stat
#: (git's "racily clean" entries), so a file that young is hashed again each time.
RACY_NS = 2_000_000_000
#: Files smaller than this are not kept in the persistent memo (:class:`HashMemo`): hashing them costs about
#: what reading an entry does.
MEMO_MIN_BYTES = 256 << 10
#: At most this many entries in a persistent memo; past it, the older half (by last write) is removed.
MEMO_MAX_ENTRIES = 20_000

_MEMO_RE = re.compile(r"^[0-9a-f]{1,16}-[0-9a-f]{1,16}\.json$")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
#: This process's memo: stat key (device, inode, size, mtime_ns, ctime_ns) to hex sha256.
_HASHES: dict[tuple, str] = {}


def _stat_key(st: os.stat_result) -> tuple:
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _settled(st: os.stat_result, now_ns: int) -> bool:
    """Whether the file of *st* was last changed long enough before *now_ns* for its stat to vouch for it."""
    return now_ns - max(st.st_mtime_ns, st.st_ctime_ns) >= RACY_NS


class HashMemo:
    """A folder of file hashes kept between runs (``retarget cache``), one small JSON entry per file.

    An entry is named by the file's device and inode and holds the file's size, mtime_ns and ctime_ns and
    its sha256; it is used only while all four still match, as git's index and make trust a file's stat.
    The ctime is part of it because no user can set it back: a file rewritten with its size and mtime
    restored is hashed again. Entries are written atomically (another batch worker reads a whole entry or
    none; two writers of one file write the same bytes), and a missing, unreadable or stale entry is a
    miss, never an error.
    """

    def __init__(self, folder):
        self.folder = Path(folder)
        self._checked = False

    def _entry(self, key: tuple) -> Path:
        return self.folder / f"{key[0]:x}-{key[1]:x}.json"

    def get(self, key: tuple) -> str | None:
        """The remembered hex sha256 of the file with stat *key*, or None."""
        try:
            doc = json.loads(self._entry(key).read_bytes())
        except (OSError, ValueError):
            return None
        if not isinstance(doc, dict) or doc.get("stat") != list(key[2:]):
            return None
        digest = doc.get("sha256")
        return digest if isinstance(digest, str) and _HEX64.match(digest) else None

    def put(self, key: tuple, digest: str, path) -> None:
        """Remember *digest* for the file with stat *key* (*path*: recorded for a reader of the folder)."""
        try:
            with guard_writes(roots=[self.folder], label="the file hash memo"):
                if not self._checked:
                    self._checked = True
                    self._trim()
                write_json(self._entry(key), {"path": os.path.abspath(path), "sha256": digest,
                                              "stat": list(key[2:])})
        except (OSError, InputError) as exc:
            log.debug("file hash memo %s not written (%s)", self.folder, exc)

    def entries(self) -> list[Path]:
        """The memo's own entries (files named ``<device>-<inode>.json``)."""
        try:
            return [p for p in self.folder.iterdir() if _MEMO_RE.match(p.name) and p.is_file()]
        except OSError:
            return []

    def _trim(self) -> None:
        found = self.entries()
        if len(found) < MEMO_MAX_ENTRIES:
            return
        aged = []
        for p in found:
            with contextlib.suppress(OSError):
                aged.append((p.stat().st_mtime_ns, p.name, p))
        for _, _, p in sorted(aged)[: len(aged) // 2]:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(p)

    def clear(self) -> int:
        """Remove every entry (and temporary files of killed writers); returns how many entries."""
        found = self.entries()
        if self.folder.is_dir():
            with guard_writes(roots=[self.folder], label="the file hash memo"):
                remove_stale_parts(self.folder)
        n = 0
        for p in found:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(p)
                n += 1
        return n


_MEMO: contextvars.ContextVar[HashMemo | None] = contextvars.ContextVar("retarget_hash_memo", default=None)


@contextlib.contextmanager
def hash_memo(folder) -> Iterator[HashMemo | None]:
    """Keep the hashes :func:`sha256_file` computes inside the block in *folder* between runs (None: not)."""
    memo = None if folder is None else HashMemo(folder)
    token = _MEMO.set(memo)
    try:
        yield memo
    finally:
        _MEMO.reset(token)


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes, each unchanged file hashed once.

    A file whose stat (device, inode, size, mtime_ns, ctime_ns) is one already hashed in this process, or
    in the active :func:`hash_memo` (which keeps the files a run reads, not those inside the folders it may
    write), is not read again, as git's index and make trust a file's stat; a file
    changed within :data:`RACY_NS` of its hashing is not remembered, except a file this process just wrote
    with :func:`write_bytes` (its bytes were hashed as written; a stage's manifest trusts the size and mtime
    of its outputs the same way).
    """
    with open(path, "rb") as fh:
        st = os.fstat(fh.fileno())
        key = _stat_key(st)
        hit = _HASHES.get(key)
        if hit is not None:
            return hit
        memo = _MEMO.get() if st.st_size >= MEMO_MIN_BYTES else None
        if memo is not None and (hit := memo.get(key)) is not None:
            _HASHES[key] = hit
            return hit
        now = time.time_ns()
        h = hashlib.sha256()
        while block := fh.read(chunk):
            h.update(block)
        digest = h.hexdigest()
        after = os.fstat(fh.fileno())
    if _stat_key(after) == key and _settled(st, now):
        _HASHES[key] = digest
        if memo is not None and not _in_output(path):
            memo.put(key, digest, path)
    return digest


def _in_output(path) -> bool:
    """Whether *path* lies in a folder the active write guard lets this run write (an output a run rewrites:
    not kept in the persistent memo, whose worth is the files runs read again and again)."""
    guard = _GUARD.get()
    if guard is None or not guard.roots:
        return False
    p = _resolve(path)
    return any(p.is_relative_to(r) for r in guard.roots)


def digest_files(paths) -> str:
    """One sha256 over several files' names and contents."""
    h = hashlib.sha256()
    for p in sorted(map(str, paths)):
        h.update(p.encode())
        h.update(sha256_file(p).encode())
    return h.hexdigest()


def check_not_input(output: str | os.PathLike, inputs) -> None:
    """Refuse to write *output* if it is one of the *inputs* (never overwrite a user's input).

    Raises
    ------
    InputError
        If *output* resolves to the same file as any input, or the active
        :func:`guard_writes` forbids it; the inputs are added to that guard.
    """
    inputs = [i for i in inputs if i is not None]
    guard = _GUARD.get()
    if guard is not None:  # every later write of the run is checked against these inputs too
        guard.protect(i for i in inputs if os.path.exists(i) and _resolve(i) not in guard.files)
    out = Path(output).resolve()
    for inp in inputs:
        if Path(inp).resolve() == out:
            raise InputError(f"{output}: output would overwrite the input {inp}; choose another output path")
    check_write(output)


# --------------------------------------------------------------------------- the write guard


def _resolve(path) -> Path:
    return Path(os.path.abspath(Path(path).expanduser())).resolve()


def _file_id(path: Path):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


@dataclass
class WriteGuard:
    """Where a run may write: inside *roots* or onto *files*, never onto *inputs* (all resolved)."""

    roots: tuple = ()
    files: tuple = ()
    inputs: set = field(default_factory=set)
    input_ids: set = field(default_factory=set)
    #: Shown in errors: what the roots are (``output_dir of config.yaml``).
    label: str = "the output folder"
    #: Open journals of this guard's temporary files, by root (:func:`part_name`).
    journals: dict = field(default_factory=dict)

    def journal(self, tmp: Path) -> None:
        """Note *tmp* (a temporary file about to be created) in the journal of the root that holds it."""
        tmp = _resolve(tmp)
        root = max((r for r in self.roots if tmp.is_relative_to(r)), key=lambda r: len(r.parts), default=None)
        if root is None:
            return
        fh = self.journals.get(root)
        if fh is None:
            root.mkdir(parents=True, exist_ok=True)
            name = root / f"{JOURNAL_PREFIX}{os.getpid()}-{secrets.token_hex(4)}.txt"
            fh = self.journals[root] = open(name, "w", encoding="utf-8", newline="\n")  # noqa: SIM115
            fh.write(f"{os.getpid()} {_start_time(os.getpid())}\n")
        fh.write(tmp.relative_to(root).as_posix() + "\n")
        fh.flush()

    def close_journals(self) -> None:
        """Remove this guard's journals and any temporary file they list that is still there (none after a
        clean exit: each was renamed or removed)."""
        for root, fh in self.journals.items():
            fh.close()
            _clear_journal(Path(fh.name), root)
        self.journals.clear()

    def protect(self, paths) -> None:
        """Add *paths* to the inputs no write may touch."""
        for p in paths:
            if p is None:
                continue
            r = _resolve(p)
            self.inputs.add(r)
            fid = _file_id(r)
            if fid is not None:
                self.input_ids.add(fid)

    def check(self, path) -> Path:
        p = _resolve(path)
        fid = _file_id(p)
        if p in self.inputs or (fid is not None and fid in self.input_ids):
            raise InputError(f"{path}: refusing to write over an input of this run; choose another output path")
        if p in self.files or any(p == r or p.is_relative_to(r) for r in self.roots):
            return p
        where = ", ".join(str(r) for r in self.roots) or "the output paths given"
        raise InputError(f"{path}: refusing to write outside {self.label} ({where})")


_GUARD: contextvars.ContextVar[WriteGuard | None] = contextvars.ContextVar("retarget_write_guard", default=None)


@contextlib.contextmanager
def guard_writes(*, roots=(), files=(), inputs=(), label: str = "the output folder") -> Iterator[WriteGuard]:
    """Check every write and delete inside the block against the rules of :class:`WriteGuard`.

    Parameters
    ----------
    roots : iterable of path-like
        Folders (recursively) writes may go into.
    files : iterable of path-like
        Single files writes may go to wherever they are (paths the user named).
    inputs : iterable of path-like
        Files of the run that are never written or deleted.
    """
    guard = WriteGuard(tuple(_resolve(r) for r in roots if r is not None),
                       tuple(_resolve(f) for f in files if f is not None), label=label)
    guard.protect(inputs)
    token = _GUARD.set(guard)
    try:
        yield guard
    finally:
        _GUARD.reset(token)
        guard.close_journals()


@contextlib.contextmanager
def folder_lock(folder, what: str = "folder") -> Iterator[None]:
    """Hold an advisory lock on *folder* (``folder/.retarget/lock``) so that one run at a time writes into it.

    A second run into the same folder fails at once with one line naming the folder and the process that
    holds it. The lock is released when the block ends or the process dies (``flock``); where ``fcntl`` is
    missing (Windows) there is no lock.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    folder = Path(folder)
    lock = folder / ".retarget" / "lock"
    lock.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 1000).decode("utf-8", "replace").strip() or "another process"
            raise InputError(f"{folder}: another retarget run is writing into this {what} ({holder}); wait for it "
                             f"to finish or choose another {what}") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()}: {' '.join(os.path.basename(a) if i == 0 else a for i, a in enumerate(sys.argv))}"
                 .encode()[:900])
        yield
    finally:
        os.close(fd)


#: Name start of a journal of temporary files: ``.retarget-parts-<pid>-<8 hex>.txt`` in a guarded root.
JOURNAL_PREFIX = ".retarget-parts-"


def part_name(path, suffix: str = "") -> Path:
    """A temporary name beside *path* (``.<name>.<8 hex>.part<suffix>``), noted in the active guard's journal
    before the file is created, so that only what this tool created is ever cleaned up after a SIGKILL."""
    path = Path(path)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}.part{suffix}"
    guard = _GUARD.get()
    if guard is not None:
        guard.journal(tmp)
    return tmp


def _start_time(pid: int) -> str:
    """When process *pid* started (clock ticks since boot, from /proc), or '?' where that cannot be read."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return "?"


def _journal_owner_alive(first_line: str) -> bool:
    """Whether the process that wrote a journal (its first line: ``pid start``) still runs."""
    try:
        pid_text, start = first_line.split()
        pid = int(pid_text)
    except ValueError:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return start == "?" or _start_time(pid) in ("?", start)


def _clear_journal(journal: Path, root: Path) -> list[Path]:
    """Remove the temporary files *journal* lists (inside *root*, named like one, still there), then the journal."""
    removed = []
    try:
        names = journal.read_text(encoding="utf-8").splitlines()[1:]
    except (OSError, UnicodeDecodeError):
        names = []
    for rel in dict.fromkeys(names):
        p = root / rel
        if ".." in Path(rel).parts or Path(rel).is_absolute() or not PART_RE.match(p.name):
            continue
        if p.is_file() and not p.is_symlink():
            with contextlib.suppress(OSError):
                os.unlink(p)
                removed.append(p)
    with contextlib.suppress(OSError):
        os.unlink(journal)
    return removed


def check_write(path) -> None:
    """Raise :class:`InputError` if the active :func:`guard_writes` forbids writing or deleting *path*."""
    guard = _GUARD.get()
    if guard is not None:
        guard.check(path)


def remove_file(path) -> None:
    """Delete *path* (a file this tool wrote) after :func:`check_write`; a missing file is fine."""
    check_write(path)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)


def remove_stale_parts(folder, *, recursive: bool = True) -> list[Path]:
    """Remove the temporary files a killed run of this tool left under *folder*.

    Only files a journal in *folder* lists are removed (:func:`part_name` notes each temporary name before the
    file exists), and only when the process that wrote the journal is gone: a user's own file named like a
    temporary file, and the temporary files of another run still writing, are never touched. *recursive* is
    kept for callers: a journal lists paths at any depth below its folder.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = []
    for journal in sorted(folder.glob(JOURNAL_PREFIX + "*.txt")):
        if not journal.is_file() or journal.is_symlink():
            continue
        try:
            with open(journal, encoding="utf-8") as fh:
                first = fh.readline()
        except (OSError, UnicodeDecodeError):
            continue
        if _journal_owner_alive(first):
            continue
        check_write(journal)
        removed += _clear_journal(journal, _resolve(folder))
    if removed:
        log.info("removed %d temporary file(s) left by an interrupted run in %s", len(removed), folder)
    return removed


# --------------------------------------------------------------------------- output manifests


def _ledger_path(folder: Path, owner: str) -> Path:
    return folder / f".retarget-{check_name(owner, 'owner')}.json"


def read_output_manifest(folder, owner: str) -> dict[str, dict | None]:
    """Relative name to ``{"size", "sha256"}`` (or None: planned by a run that did not finish)."""
    path = _ledger_path(Path(folder), owner)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        files = data["files"]
        return {str(k): (v if isinstance(v, dict) else None) for k, v in files.items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


class TrackedOutputs:
    """Files one command writes into a folder; see :func:`tracked_outputs`."""

    def __init__(self, folder: Path, owner: str):
        self.folder, self.owner = Path(folder), owner
        self.before = read_output_manifest(self.folder, owner)
        self.written: list[Path] = []

    def _rel(self, p) -> str | None:
        try:
            return Path(os.path.abspath(p)).relative_to(Path(os.path.abspath(self.folder))).as_posix()
        except ValueError:
            return None

    def plan(self, paths: Iterable) -> None:
        """Record *paths* as about to be written (so a killed run's files are known to the next)."""
        files = dict(self.before)
        for p in paths:
            rel = self._rel(p)
            if rel is not None:
                files.setdefault(rel, None)
        self._save(files)

    def add(self, path) -> Path:
        self.written.append(Path(path))
        return Path(path)

    def _save(self, files: dict) -> None:
        write_json(_ledger_path(self.folder, self.owner), {"files": files})

    def _ours(self, rel: str, rec) -> bool:
        p = self.folder / rel
        try:
            st = p.lstat()
        except OSError:
            return False
        if not p.is_file() or p.is_symlink():
            return False
        return rec is None or (st.st_size == rec.get("size") and sha256_file(p) == rec.get("sha256"))

    def commit(self) -> list[Path]:
        """Remove files of earlier runs that this one did not write (if unchanged since); record this run's."""
        keep = {self._rel(p) for p in self.written}
        removed = []
        for rel, rec in sorted(self.before.items()):
            if rel in keep or ".." in Path(rel).parts or Path(rel).is_absolute():
                continue
            if self._ours(rel, rec):
                remove_file(self.folder / rel)
                removed.append(self.folder / rel)
            elif (self.folder / rel).exists():
                log.warning("%s: left in place (changed since retarget wrote it)", self.folder / rel)
        if removed:
            log.info("%s: removed %d output(s) of an earlier run", self.folder, len(removed))
        files = {}
        for p in self.written:
            rel = self._rel(p)
            if rel is not None and p.is_file():
                files[rel] = {"size": p.stat().st_size, "sha256": sha256_file(p)}
        self._save(dict(sorted(files.items())))
        return removed

    def rollback(self) -> None:
        """Remove the files this run wrote (a failed run leaves no partial set behind)."""
        for p in self.written:
            with contextlib.suppress(OSError, InputError):
                remove_file(p)
        with contextlib.suppress(OSError, InputError, ValueError):
            files = {k: v for k, v in self.before.items() if (self.folder / k).exists()}
            self._save(files)


@contextlib.contextmanager
def tracked_outputs(folder, owner: str, planned: Iterable = ()) -> Iterator[TrackedOutputs]:
    """Track the files a command writes into *folder* (call ``.add(path)`` after each write).

    On success, the files of earlier runs of *owner* that this run did not
    write, and that nobody changed since, are removed, and the folder's
    output manifest ``.retarget-<owner>.json`` lists this run's files. On an
    exception (Ctrl-C included) the files this run wrote are removed, so a
    failed run leaves no partial set (key OBJs without their targets.yaml).
    """
    rec = TrackedOutputs(Path(folder), owner)
    rec.plan(planned)
    try:
        yield rec
    except BaseException:
        rec.rollback()
        raise
    rec.commit()
