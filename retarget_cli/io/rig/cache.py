"""Reading a rig's OBJs once: vertex counts checked before parsing, parsed meshes cached.

:func:`load_rig_meshes` reads the OBJs a ``rig.yaml`` lists (neutral first)
into one array and the neutral's :class:`~retarget_cli.io.obj.ObjMesh`
template. Before parsing any of them it counts every file's ``v`` lines, so a
shape of another vertex count is reported (by its ``rig.yaml`` entry) before
the parse of a production rig begins.

With a *cache_dir*, the parsed meshes are kept in ``cache_dir/rig-<key16>.npz``
(uncompressed, :data:`CACHE_VERSION`), where the key is the sha256 of the
``rig.yaml`` bytes and of every file it references. The cache holds the
float64 vertices as stored, so they round-trip bit for bit, and the
template's non-coordinate bytes, so written OBJs are byte-identical to those
of a cold load. A cache file that cannot be read, or whose key or shapes do
not match, is logged and rebuilt.

A rig read from a character file (``source: char.glb``) is kept the same way
by :func:`cached_arrays`: the key is the sha256 of ``rig.yaml``, the file and
its external buffers, under another layout name, and the arrays are what
:mod:`retarget_cli.io.rig.load` builds from the file.

The commands use one cache folder per user, shared by every run and every batch worker
(:func:`rig_cache_dir`: ``$RETARGET_CACHE_DIR/rigs``, else ``$XDG_CACHE_HOME/retarget/rigs``, else
``~/.cache/retarget/rigs``), so that a studio's hundreds of clips onto one rig parse it once:

- an entry is written under a temporary name and renamed into place (:mod:`retarget_cli.io.atomic`), so a
  reader sees a whole entry or none; two workers that write the same key write the same bytes; an entry
  removed between the look-up and the read is a miss (rebuilt), never an error;
- a hit sets the entry's modification time (the LRU clock); after a write, the least recently used entries
  are removed until the folder holds at most :func:`cache_limit` bytes (``$RETARGET_CACHE_SIZE``, default
  2 GiB; ``0`` keeps nothing);
- only the cache's own entries are ever removed: files named ``rig-<16 hex>.npz`` whose ``key`` member
  begins with those 16 hex digits, and temporary files a killed writer's journal lists.
  :func:`cache_info` and :func:`clear_cache` serve ``retarget cache``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
from pathlib import Path

import numpy as np

from ...errors import InputError, ParameterError
from ..atomic import guard_writes, remove_stale_parts, savez, sha256_file
from ..obj import ObjMesh, check_coordinates, check_same_topology, count_vertices, read_obj

log = logging.getLogger(__name__)

#: Bump when the cache layout or the meaning of its arrays changes.
CACHE_VERSION = 1


#: The environment variable naming the user cache folder (the rig entries go in its ``rigs/``).
CACHE_DIR_ENV = "RETARGET_CACHE_DIR"
#: The environment variable with the cache's size limit: bytes, or with a suffix ``K``, ``M``, ``G`` (powers of 1024).
CACHE_SIZE_ENV = "RETARGET_CACHE_SIZE"
#: The size limit without :data:`CACHE_SIZE_ENV`: 2 GiB (the ICT FaceKit's entry is 36 MB).
DEFAULT_CACHE_BYTES = 2 << 30

_ENTRY_RE = re.compile(r"^rig-([0-9a-f]{16})\.npz$")
_UNITS = {"": 1, "B": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


def user_cache_dir(environ=None) -> Path:
    """The user's cache folder of ``retarget``.

    ``$RETARGET_CACHE_DIR`` when set, else ``$XDG_CACHE_HOME/retarget``, else ``~/.cache/retarget``.

    Parameters
    ----------
    environ : mapping, optional
        The environment (default ``os.environ``).
    """
    env = os.environ if environ is None else environ
    if env.get(CACHE_DIR_ENV):
        return Path(env[CACHE_DIR_ENV]).expanduser()
    xdg = env.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg and Path(xdg).is_absolute() else Path.home() / ".cache"
    return base / "retarget"


def rig_cache_dir(environ=None) -> Path:
    """Where the commands keep parsed rigs: ``rigs/`` in :func:`user_cache_dir`."""
    return user_cache_dir(environ) / "rigs"


def hash_memo_dir(environ=None) -> Path:
    """Where the commands keep the sha256 of the files they read (a rig's OBJs, a video) between runs:
    ``hashes/`` in :func:`user_cache_dir` (:class:`~retarget_cli.io.atomic.HashMemo`)."""
    return user_cache_dir(environ) / "hashes"


def cache_limit(environ=None) -> int:
    """The cache's size limit in bytes: ``$RETARGET_CACHE_SIZE`` (``500M``, ``2G``, ``0``) or 2 GiB.

    Raises
    ------
    ParameterError
        ``RETARGET_CACHE_SIZE: expected bytes such as 500M or 2G, got 'lots'``.
    """
    env = os.environ if environ is None else environ
    text = str(env.get(CACHE_SIZE_ENV, "")).strip()
    if not text:
        return DEFAULT_CACHE_BYTES
    m = re.fullmatch(r"(\d+(?:\.\d+)?)\s*([BKMGT]?)(?:I?B)?", text.upper())
    if m is None:
        raise ParameterError(f"{CACHE_SIZE_ENV}: expected bytes such as 500M or 2G, got {text!r}")
    return int(float(m.group(1)) * _UNITS[m.group(2)])


def _entry_key(file: Path) -> str | None:
    """The ``key`` member of a cache entry, or None when the file is no readable entry."""
    try:
        with np.load(file, allow_pickle=False) as z:
            return str(z["key"])
    except Exception:  # noqa: BLE001  (anything unreadable is no entry of ours)
        return None


def cache_entries(cache_dir) -> list[tuple[Path, int, float]]:
    """The cache's own entries in *cache_dir*: (path, bytes, last use), least recently used first.

    An entry is a file named ``rig-<16 hex>.npz`` whose ``key`` member begins with those 16 hex digits
    (what this module writes); any other file is not listed, so never removed.
    """
    cache_dir = Path(cache_dir)
    if not cache_dir.is_dir():
        return []
    found = []
    for p in cache_dir.iterdir():
        m = _ENTRY_RE.match(p.name)
        if m is None or p.is_symlink() or not p.is_file():
            continue
        key = _entry_key(p)
        if key is None or not key.startswith(m.group(1)):
            continue
        with contextlib.suppress(FileNotFoundError):
            st = p.stat()
            found.append((p, st.st_size, st.st_mtime))
    return sorted(found, key=lambda e: (e[2], e[0].name))


def _remove(paths) -> int:
    removed = 0
    for p in paths:
        try:
            os.unlink(p)
            removed += 1
        except FileNotFoundError:  # another worker removed it first
            pass
    return removed


def evict(cache_dir, limit: int, *, keep=None) -> list[Path]:
    """Remove the least recently used entries of *cache_dir* until they total at most *limit* bytes.

    *keep* (an entry just written or read) goes last. Only :func:`cache_entries` are removed, and the
    temporary files of writers that were killed (:func:`~retarget_cli.io.atomic.remove_stale_parts`).

    Returns
    -------
    list of Path
        The entries removed.
    """
    entries = cache_entries(cache_dir)
    keep = None if keep is None else Path(keep).resolve()
    entries.sort(key=lambda e: e[0].resolve() == keep)  # stable: LRU order, *keep* last
    total = sum(e[1] for e in entries)
    gone = []
    for p, size, _ in entries:
        if total <= limit:
            break
        gone.append(p)
        total -= size
    with guard_writes(roots=[cache_dir], label="the rig cache"):
        remove_stale_parts(cache_dir)
    _remove(gone)
    if gone:
        log.info("rig cache %s: removed %d least recently used entr%s (limit %d bytes)", cache_dir, len(gone),
                 "y" if len(gone) == 1 else "ies", limit)
    return gone


def cache_info(cache_dir=None) -> dict:
    """``folder``, ``entries``, ``bytes`` and ``limit`` of the rig cache (default :func:`rig_cache_dir`)."""
    cache_dir = rig_cache_dir() if cache_dir is None else Path(cache_dir)
    entries = cache_entries(cache_dir)
    return {"folder": cache_dir, "entries": len(entries), "bytes": sum(e[1] for e in entries),
            "limit": cache_limit()}


def clear_cache(cache_dir=None) -> tuple[int, int]:
    """Remove every entry of the rig cache (default :func:`rig_cache_dir`); returns (entries, bytes) removed."""
    cache_dir = rig_cache_dir() if cache_dir is None else Path(cache_dir)
    entries = cache_entries(cache_dir)
    if Path(cache_dir).is_dir():
        with guard_writes(roots=[cache_dir], label="the rig cache"):
            remove_stale_parts(cache_dir)
    n = _remove(p for p, _, _ in entries)
    return n, sum(e[1] for e in entries)


def _touch(file: Path) -> None:
    """Mark *file* as just used (its modification time is the LRU clock)."""
    with contextlib.suppress(OSError):
        os.utime(file)


def _store(file: Path, arrays: dict, what) -> None:
    """Write one entry atomically (only inside its folder), then keep the folder within :func:`cache_limit`."""
    limit = cache_limit()
    size = sum(np.asarray(a).nbytes for a in arrays.values())
    if size > limit:
        log.info("rig %s: not cached (%d bytes, more than the cache's limit of %d)", what, size, limit)
        return
    try:
        with guard_writes(roots=[file.parent], label="the rig cache"):
            savez(file, arrays, compress=False)
        log.info("rig %s: cached in %s", what, file)
    except OSError as exc:
        log.warning("rig cache %s not written (%s)", file, exc)
        return
    with contextlib.suppress(OSError):
        evict(file.parent, limit, keep=file)


def cache_key(rig_path: str | os.PathLike, files, *, kind: str = "") -> str:
    """sha256 over the cache version, ``rig.yaml``'s bytes and each referenced file (name and bytes).

    Parameters
    ----------
    rig_path : path-like
        The ``rig.yaml``.
    files : sequence of path-like
        Every file the rig references, in a fixed order (names are taken
        relative to the ``rig.yaml``'s folder, so the cache survives moving
        the whole rig).
    kind : str
        What the cache file holds (``""``: a rig's OBJs; ``"source"``: a rig read from a character file),
        so that two layouts never share a key.
    """
    rig_path = Path(rig_path)
    h = hashlib.sha256(f"retarget rig cache v{CACHE_VERSION}{' ' + kind if kind else ''}\n".encode())
    h.update(sha256_file(rig_path).encode() + b"\n")
    for f in files:
        rel = os.path.relpath(Path(f).resolve(), rig_path.resolve().parent)
        h.update(f"{rel}\0{sha256_file(Path(f))}\n".encode())
    return h.hexdigest()


def cache_file(cache_dir: str | os.PathLike, key: str) -> Path:
    """Where the cache of *key* lives: ``cache_dir/rig-<first 16 hex digits>.npz``."""
    return Path(cache_dir) / f"rig-{key[:16]}.npz"


def check_vertex_counts(rig_path, entries) -> int:
    """Count the ``v`` lines of every OBJ (no parse) and compare each with the first (the neutral).

    Parameters
    ----------
    rig_path : path-like
        The ``rig.yaml``, named in the error.
    entries : sequence of (str, Path)
        ``rig.yaml`` entry (``"neutral"``, ``"shapes.jawOpen"``, ...) and OBJ
        path, the neutral first.

    Returns
    -------
    int
        The neutral's vertex count.

    Raises
    ------
    InputError
        ``rig.yaml: shapes.jawOpen (jawOpen.obj): 26718 vertices, the neutral
        neutral.obj has 26719``.
    """
    (_, neutral), *rest = entries
    n0 = count_vertices(neutral)
    if n0 == 0:
        raise InputError(f"{rig_path}: neutral ({Path(neutral).name}): OBJ has no 'v' lines")
    for label, p in rest:
        n = count_vertices(p)
        if n != n0:
            raise InputError(f"{rig_path}: {label} ({Path(p).name}): {n} vertices, "
                             f"the neutral {Path(neutral).name} has {n0}")
    return n0


def _template_arrays(mesh: ObjMesh) -> dict:
    uniq: dict[bytes, int] = {}
    index = np.fromiter((uniq.setdefault(t, len(uniq)) for t in mesh.tails), np.int32, len(mesh.tails))
    tails = list(uniq)
    return {
        "segments": np.frombuffer(b"".join(mesh.segments), np.uint8),
        "segment_lengths": np.array([len(s) for s in mesh.segments], np.int64),
        "runs": np.array(mesh.runs, np.int64).reshape(-1, 2),
        "tails": np.frombuffer(b"".join(tails), np.uint8),
        "tail_lengths": np.array([len(t) for t in tails], np.int64),
        "tail_index": index,
        "meta": np.array(json.dumps({"topology": mesh.topology, "n_faces": mesh.n_faces})),
    }


def _split(blob: np.ndarray, lengths: np.ndarray) -> list[bytes]:
    data = blob.tobytes()
    ends = np.cumsum(lengths).tolist()
    return [data[a:b] for a, b in zip([0, *ends[:-1]], ends)]


def _template_from(arrays: dict, path: Path, vertices: np.ndarray) -> ObjMesh:
    segments = _split(arrays["segments"], arrays["segment_lengths"])
    uniq = _split(arrays["tails"], arrays["tail_lengths"])
    index = arrays["tail_index"]
    if len(index) != len(vertices) or (len(index) and int(index.max()) >= len(uniq)):
        raise ParameterError("tail index does not match the vertices")
    tails = [uniq[i] for i in index.tolist()]
    runs = [tuple(r) for r in arrays["runs"].tolist()]
    if len(segments) != len(runs) + 1 or (runs and runs[-1][1] != len(vertices)):
        raise ParameterError("segments and runs do not match")
    meta = json.loads(str(arrays["meta"]))
    return ObjMesh(path, vertices, segments, runs, tails, str(meta["topology"]), int(meta["n_faces"]))


def _read_cache(file: Path, key: str, n_meshes: int, neutral: Path):
    """The cached (template, vertices), or None (logged) when the file is unusable."""
    try:
        with np.load(file, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        if str(arrays["key"]) != key or int(arrays["version"]) != CACHE_VERSION:
            raise ParameterError("key or version differs")
        V = arrays["vertices"]
        if V.dtype != np.float64 or V.ndim != 3 or V.shape[0] != n_meshes or V.shape[2] != 3:
            raise ParameterError(f"vertices have shape {V.shape}")
        return _template_from(arrays, neutral, V[0]), V
    except FileNotFoundError:  # removed by another worker since the look-up: a miss
        return None
    except Exception as exc:  # noqa: BLE001  (any unreadable cache is rebuilt, never an error)
        log.warning("rig cache %s is unusable (%s); rebuilding it", file, exc)
        return None


def load_rig_meshes(rig_path, entries, *, extra_files=(), cache_dir=None, check=None):
    """Vertices of every OBJ of a rig and the neutral's template, through the cache when given.

    Parameters
    ----------
    rig_path : path-like
        The ``rig.yaml``.
    entries : sequence of (str, Path)
        ``rig.yaml`` entry and OBJ path of each mesh, the neutral first
        (see :func:`check_vertex_counts`). Every file must exist.
    extra_files : sequence of path-like
        Other files the rig references (a landmark map): part of the key only.
    cache_dir : path-like, optional
        Folder of the cache (created when written); None reads the OBJs.
    check : callable, optional
        Called with the neutral's vertex count before any OBJ is parsed (and
        on a cache hit), e.g. to check landmark vertex ids.

    Returns
    -------
    template : ObjMesh
        The neutral OBJ.
    vertices : ndarray, shape (M, N, 3), float64
        ``v`` positions of each mesh in *entries* order.

    Raises
    ------
    InputError
        A vertex count that differs from the neutral's (naming the entry and
        both counts, before any parse), an OBJ error, or meshes of different
        connectivity.
    """
    rig_path = Path(rig_path)
    paths = [Path(p) for _, p in entries]
    key = file = None
    if cache_dir is not None:
        key = cache_key(rig_path, [*paths, *extra_files])
        file = cache_file(cache_dir, key)
        if file.is_file():
            hit = _read_cache(file, key, len(paths), paths[0])
            if hit is not None:
                for p, v in zip(paths, hit[1]):  # a cache written before the coordinate check
                    check_coordinates(p, v)
                if check is not None:
                    check(hit[1].shape[1])
                _touch(file)
                log.info("rig %s: %d meshes from the cache %s", rig_path, len(paths), file)
                return hit
    n_vertices = check_vertex_counts(rig_path, entries)
    if check is not None:
        check(n_vertices)
    meshes = [read_obj(p) for p in paths]
    check_same_topology(meshes)
    V = np.stack([m.vertices for m in meshes])
    template = meshes[0]
    if file is not None:
        _store(file, {"key": np.array(key), "version": np.array(CACHE_VERSION), "vertices": V,
                      **_template_arrays(template)}, rig_path)
    return template, V


def cached_arrays(rig_path, files, build, *, cache_dir=None, kind: str, check=None) -> dict:
    """Arrays that *build* computes from a rig's files, kept in the cache between runs.

    The key is :func:`cache_key` of *rig_path*, *files* and *kind*; the file is
    ``cache_dir/rig-<key16>.npz`` (uncompressed), as for the OBJs.

    Parameters
    ----------
    rig_path : path-like
        The ``rig.yaml`` (or the character file given as the rig).
    files : sequence of path-like
        The other files the result depends on.
    build : callable
        ``build()`` -> dict of name to ndarray (no object arrays), called on a miss.
    cache_dir : path-like, optional
        None: *build* is called and nothing is kept.
    kind : str
        The layout's name (part of the key).
    check : callable, optional
        ``check(arrays)`` raises when cached arrays do not have the expected shapes: then they are
        logged and rebuilt.

    Returns
    -------
    dict of str to ndarray
    """
    if cache_dir is None:
        return build()
    key = cache_key(rig_path, files, kind=kind)
    file = cache_file(cache_dir, key)
    if file.is_file():
        try:
            with np.load(file, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
            if str(arrays.pop("key")) != key or int(arrays.pop("version")) != CACHE_VERSION:
                raise ParameterError("key or version differs")
            if check is not None:
                check(arrays)
            _touch(file)
            log.info("rig %s: read from the cache %s", rig_path, file)
            return arrays
        except FileNotFoundError:  # removed by another worker since the look-up: a miss
            pass
        except Exception as exc:  # noqa: BLE001  (any unreadable cache is rebuilt, never an error)
            log.warning("rig cache %s is unusable (%s); rebuilding it", file, exc)
    arrays = build()
    _store(file, {"key": np.array(key), "version": np.array(CACHE_VERSION), **arrays}, rig_path)
    return arrays


__all__ = ["CACHE_DIR_ENV", "CACHE_SIZE_ENV", "CACHE_VERSION", "DEFAULT_CACHE_BYTES", "cache_entries", "cache_file",
           "cache_info", "cache_key", "cache_limit", "cached_arrays", "check_vertex_counts", "clear_cache", "evict",
           "hash_memo_dir",
           "load_rig_meshes", "rig_cache_dir", "user_cache_dir"]
