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
not match, is logged and rebuilt; the cache only ever writes (atomically) and
replaces files named ``rig-*.npz`` in *cache_dir*.

A rig read from a character file (``source: char.glb``) is kept the same way
by :func:`cached_arrays`: the key is the sha256 of ``rig.yaml``, the file and
its external buffers, under another layout name, and the arrays are what
:mod:`retarget_cli.io.rig.load` builds from the file.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np

from ...errors import InputError, ParameterError
from ..atomic import savez
from ..obj import ObjMesh, check_coordinates, check_same_topology, count_vertices, read_obj

log = logging.getLogger(__name__)

#: Bump when the cache layout or the meaning of its arrays changes.
CACHE_VERSION = 1


def _file_sha256(path: Path) -> str:
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


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
    h.update(_file_sha256(rig_path).encode() + b"\n")
    for f in files:
        rel = os.path.relpath(Path(f).resolve(), rig_path.resolve().parent)
        h.update(f"{rel}\0{_file_sha256(Path(f))}\n".encode())
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
        try:
            savez(file, {"key": np.array(key), "version": np.array(CACHE_VERSION), "vertices": V,
                         **_template_arrays(template)}, compress=False)
            log.info("rig %s: cached %d meshes in %s", rig_path, len(paths), file)
        except OSError as exc:
            log.warning("rig cache %s not written (%s)", file, exc)
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
            log.info("rig %s: read from the cache %s", rig_path, file)
            return arrays
        except Exception as exc:  # noqa: BLE001  (any unreadable cache is rebuilt, never an error)
            log.warning("rig cache %s is unusable (%s); rebuilding it", file, exc)
    arrays = build()
    try:
        savez(file, {"key": np.array(key), "version": np.array(CACHE_VERSION), **arrays}, compress=False)
        log.info("rig %s: cached in %s", rig_path, file)
    except OSError as exc:
        log.warning("rig cache %s not written (%s)", file, exc)
    return arrays


__all__ = ["CACHE_VERSION", "cache_file", "cache_key", "cached_arrays", "check_vertex_counts", "load_rig_meshes"]
